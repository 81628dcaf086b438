"""Checkpoints (resumable training state) and exported weights, written atomically.

Both are plain dicts of tensors, numbers, strings and lists, readable with
``torch.load(weights_only=True)`` (format in :mod:`seqshape.model.estimator`). A checkpoint
adds ``"training"``: stage, step, stage clock, optimiser, schedule, loss sigmas, and the
torch / numpy / python RNG states, so that a resumed run continues exactly as an
uninterrupted one would.
"""

from __future__ import annotations

import io
import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

from seqshape._io import atomic_open
from seqshape.errors import DataError
from seqshape.model.estimator import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, read_model_file
from seqshape.model.network import ShapePoseNet


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
