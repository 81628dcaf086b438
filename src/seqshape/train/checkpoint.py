"""Checkpoints (resumable training state) and exported weights, written atomically.

Both are plain dicts of tensors, numbers, strings and lists, readable with
``torch.load(weights_only=True)`` (format in :mod:`seqshape.model.estimator`). A checkpoint
adds ``"training"``: stage, step, stage clock, optimiser, schedule, loss sigmas, and the
torch / numpy / python RNG states, so that a resumed run continues exactly as an
uninterrupted one would.

:func:`load_init` reads the weights a run starts from (``seqshape train --init``): an exported
``model.pt``, a training checkpoint (only its weights), or ``"pretrained"`` (the shipped
``seqshape/pretrained/<kind>.pt``; resolved by :func:`seqshape.model.estimator.resolve_weights`),
checking that kind and model configuration match the run
(except the parameter-free fields :data:`~seqshape.model.config.PARAMETER_FREE_FIELDS`: the
input scale can be switched on when fine-tuning from weights trained without it, and the
points a frame is cut to changed (``--model-set num_points=128``); and the
zero-initialised extensions ``frame_skip`` and ``motion_input`` can be switched on: the new
parameters start at zero, so the run starts from exactly the source's function).
"""

from __future__ import annotations

import hashlib
import io
import json
import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

from seqshape._io import atomic_open
from seqshape.errors import ConfigError, DataError
from seqshape.model.config import PARAMETER_FREE_FIELDS, ModelConfig
from seqshape.model.estimator import (
    CHECKPOINT_FORMAT,
    CHECKPOINT_VERSION,
    read_model_file,
    resolve_weights,
)
from seqshape.model.estimator import PRETRAINED as PRETRAINED  # re-exported (--init pretrained)
from seqshape.model.network import ShapePoseNet, add_motion_columns


def rng_state() -> dict[str, Any]:
    """The torch, numpy (legacy global) and python RNG states, as weights-only-safe values."""
    np_state = np.random.get_state(legacy=True)  # noqa: NPY002 - the global state is saved on purpose
    py_state = random.getstate()
    return {"torch": torch.get_rng_state(),
            "numpy": {"key": torch.from_numpy(np_state[1].astype(np.int64)),
                      "pos": int(np_state[2]), "has_gauss": int(np_state[3]),
                      "cached_gaussian": float(np_state[4])},
            "python": [int(py_state[0]), list(py_state[1]), py_state[2]]}


def set_rng_state(state: dict[str, Any]) -> None:
    """Inverse of :func:`rng_state`."""
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    legacy = ("MT19937", n["key"].numpy().astype(np.uint32), n["pos"], n["has_gauss"],
              n["cached_gaussian"])
    np.random.set_state(legacy)  # noqa: NPY002
    p = state["python"]
    random.setstate((p[0], tuple(p[1]), p[2]))


def model_payload(model: ShapePoseNet, train_config: dict, metrics: dict) -> dict[str, Any]:
    """The exported-weights dict (no training state)."""
    return {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "kind": model.kind,
            "model_config": model.cfg.to_dict(), "train_config": train_config,
            "state_dict": {k: v.detach().clone() for k, v in model.state_dict().items()},
            "metrics": dict(metrics)}


def save_payload(path: str | Path, payload: dict[str, Any]) -> None:
    """``torch.save`` to ``path`` atomically (temp file + rename)."""
    buf = io.BytesIO()
    torch.save(payload, buf)
    with atomic_open(path, "wb") as fh:
        fh.write(buf.getbuffer())


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """A training checkpoint (validated); a weights-only export is a :class:`DataError`."""
    payload = read_model_file(path)
    training = payload.get("training")
    if not isinstance(training, dict) or "stage" not in training:
        raise DataError(path, "holds weights only, not a resumable training checkpoint")
    return payload


def resolve_init(spec: str | Path, kind: str) -> Path:
    """The weights file named by ``--init``: a path, ``"pretrained"`` = the shipped
    ``seqshape/pretrained/<kind>.pt``, or a shipped name
    (:func:`seqshape.model.estimator.resolve_weights`, the one resolver)."""
    return resolve_weights(spec, kind)


def load_init(spec: str | Path, kind: str, model_cfg: ModelConfig
              ) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Weights to start a run from, checked against the run's ``kind`` and ``model_cfg``.

    Returns ``(state_dict, record)``; ``record`` (JSON-able: source, resolved path, sha256,
    kind, whether the file was a training checkpoint and at which stage/step, its numeric
    metrics) goes into ``config.json`` and every file the run writes. A checkpoint's optimiser,
    sigmas and RNG states are not used: the new run starts its stages afresh.
    """
    path = resolve_init(spec, kind)
    payload = read_model_file(path)
    if payload["kind"] != kind:
        raise ConfigError(f"--init {path}: holds {payload['kind']} weights but this run trains "
                          f"a {kind} model; pass --model {payload['kind']} or {kind} weights")
    try:
        src_cfg = ModelConfig.from_dict(payload["model_config"]).to_dict()
    except (ConfigError, TypeError, ValueError) as exc:
        raise DataError(path, f"invalid model_config ({exc})") from None
    run_cfg = model_cfg.to_dict()
    # parameter-free options (the input scale, the points per frame) may differ: the weights
    # fit either way; with s = 1 (every car), or a frame within both point counts, the network
    # computes exactly what it did
    diff = [k for k in run_cfg
            if src_cfg.get(k) != run_cfg[k] and k not in PARAMETER_FREE_FIELDS]
    state_dict = payload["state_dict"]
    if "frame_skip" in diff and run_cfg["frame_skip"] and kind == "sequential":
        # adding the zero-initialised frame skip keeps the function: start from the weights
        # and a zero projection
        h, f = int(run_cfg["hidden"]), int(run_cfg["encoder2"][-1])
        state_dict = dict(state_dict)
        state_dict.setdefault("skip.weight", torch.zeros(h, f))
        state_dict.setdefault("skip.bias", torch.zeros(h))
        diff.remove("frame_skip")
    if "motion_input" in diff and model_cfg.motion_input:
        # zero GRU columns for the motion inputs keep the function (the baseline has none)
        if kind == "sequential":
            state_dict = add_motion_columns(state_dict, model_cfg)
        diff.remove("motion_input")
    if diff:
        what = ", ".join(f"{k} {src_cfg.get(k)!r} (run: {run_cfg[k]!r})" for k in diff)
        fix = " ".join(f"--model-set {k}={json.dumps(src_cfg.get(k))}" for k in diff)
        raise ConfigError(f"--init {path}: the weights' model configuration differs from this "
                          f"run's: {what}; train with the preset the weights came from or "
                          f"add: {fix}")
    training = payload.get("training")
    record: dict[str, Any] = {
        "source": str(spec), "path": str(path.resolve()), "sha256": _sha256(path),
        "kind": kind, "file": "checkpoint" if isinstance(training, dict) else "model",
        "metrics": {k: v for k, v in payload.get("metrics", {}).items()
                    if isinstance(v, (int, float, str)) and not isinstance(v, bool)}}
    if isinstance(training, dict):
        record.update(stage=int(training.get("stage", 0)),
                      global_step=int(training.get("global_step", 0)))
    return state_dict, record


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
