"""The three-stage trainer: the loss falls, checkpoints resume bit-identically, files."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
from _model_data import make_dataset

from seqshape.data.windows import WindowDataset, batch_for_step, stream_indices
from seqshape.errors import ConfigError
from seqshape.model import Estimator
from seqshape.train import TrainConfig, Trainer, get_train_config
from seqshape.train.checkpoint import load_checkpoint


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("tracks") / "ds")


def _weights(path):
    return torch.load(path, weights_only=True)["state_dict"]


def test_loss_falls_and_files(dataset, tmp_path):
    cfg = get_train_config("smoke")
    tr = Trainer(dataset.path, tmp_path / "run", "sequential", cfg)
    before = tr.validate(0)
    path = tr.run()
    after = tr.metrics
    assert after["val_cd_m"] < 0.8 * before["val_cd_m"]
    rows = list(csv.DictReader(open(tmp_path / "run" / "log.csv")))
    stage1 = [float(r["loss"]) for r in rows if r["kind"] == "train" and r["stage"] == "1"]
    assert stage1[-1] < stage1[0]
    assert {r["stage"] for r in rows} == {"1", "2", "3"}
    conf = json.loads((tmp_path / "run" / "config.json").read_text())
    assert conf["kind"] == "sequential" and conf["model_config"]["num_complete"] == 128
    payload = torch.load(path, weights_only=True)
    assert payload["format"] == "seqshape-checkpoint" and "training" not in payload
    assert TrainConfig.from_dict(payload["train_config"]) == cfg
    for k in ("stage1.pt", "stage2.pt", "stage3.pt", "last.pt"):
        assert load_checkpoint(tmp_path / "run" / k)["training"]["stage"] == int(k[5]) \
            if k != "last.pt" else True
    est = Estimator.from_checkpoint(path)
    assert est.recurrent and est.config.num_complete == 128


def test_stage2_trains_only_the_pose_decoder(dataset, tmp_path):
    cfg = get_train_config("smoke")
    run = tmp_path / "run"
    Trainer(dataset.path, run, "baseline", cfg).run()
    s1 = load_checkpoint(run / "stage1.pt")["state_dict"]
    s2 = load_checkpoint(run / "stage2.pt")["state_dict"]
    for k in s1:
        same = torch.equal(s1[k], s2[k])
        assert same != k.startswith("pose_decoder."), k


class _Kill(Exception):
    pass


def _run_until(dataset, out, cfg, kill_at=None, resume=False):
    tr = Trainer(dataset.path, out, "sequential", cfg, resume=resume)
    if kill_at is not None:
        orig = tr._train_step

        def step(*a, **k):
            if tr.state["global_step"] == kill_at:
                raise _Kill
            return orig(*a, **k)

        tr._train_step = step
    try:
        return tr.run()
    except _Kill:
        tr.runlog.close()
        return None


def test_resume_is_bit_identical(dataset, tmp_path):
    cfg = get_train_config("smoke")
    ref = _run_until(dataset, tmp_path / "ref", cfg)
    out = tmp_path / "killed"
    assert _run_until(dataset, out, cfg, kill_at=8) is None          # mid stage 1 (ckpt at 5)
    assert _run_until(dataset, out, cfg, kill_at=21, resume=True) is None  # mid stage 3
    ck = load_checkpoint(out / "last.pt")["training"]
    assert (ck["stage"], ck["step"], ck["sigma_init"]) == (2, 5, True)
    got = _run_until(dataset, out, cfg, resume=True)
    a, b = _weights(ref), _weights(got)
    assert all(torch.equal(a[k], b[k]) for k in a)
    rows_ref = [r["global_step"] for r in csv.DictReader(open(tmp_path / "ref" / "log.csv"))]
    rows_got = [r["global_step"] for r in csv.DictReader(open(out / "log.csv"))]
    assert rows_ref == rows_got


def test_stage3_sigmas_start_at_the_val_optimum(dataset, tmp_path):
    # s^2 = L on the fixed val windows; without val windows, on the step's own batch
    cfg = get_train_config("smoke")
    tr = Trainer(dataset.path, tmp_path / "run", "sequential", cfg)
    batch = tr._val_batches[0]
    v = tr.validate(1)
    tr._init_sigmas(batch)
    s_cd, s_p = tr.joint.sigmas
    assert s_cd**2 == pytest.approx(v["val_cd_m"], rel=1e-5)
    assert s_p**2 == pytest.approx(v["val_pose_m2"], rel=1e-5)
    tr.runlog.close()
    no_val = Trainer(dataset.path, tmp_path / "run2", "sequential",
                     dataclasses.replace(cfg, val_windows=0))
    with torch.no_grad():
        res = no_val._losses(batch, None)
    no_val._init_sigmas(batch)
    b_cd, b_p = no_val.joint.sigmas
    assert b_cd**2 == pytest.approx(float(res["cd"]), rel=1e-5)
    assert b_p**2 == pytest.approx(float(res["pose"]), rel=1e-5)
    assert abs(b_p - s_p) > 1e-3 * s_p  # one batch is not the val set
    no_val.runlog.close()


def test_existing_run_needs_resume(dataset, tmp_path):
    cfg = dataclasses.replace(get_train_config("smoke"),
                              stages=get_train_config("smoke").with_stage_steps((5, 0, 0)).stages)
    Trainer(dataset.path, tmp_path / "r", "baseline", cfg).run()
    with pytest.raises(ConfigError, match="--resume"):
        Trainer(dataset.path, tmp_path / "r", "baseline", cfg)
    with pytest.raises(ConfigError, match="baseline"):
        Trainer(dataset.path, tmp_path / "r", "sequential", cfg, resume=True)


def test_windows_deterministic_and_sharded(dataset):
    tracks = dataset.split("train")
    a = WindowDataset(tracks, window=5, num_points=32, num_complete=64, seed=3, key=1)
    b = WindowDataset(tracks, window=5, num_points=32, num_complete=64, seed=3, key=1)
    wa, wb = a.window_at(4, 2), b.window_at(4, 2)
    assert all(np.array_equal(wa[k], wb[k]) for k in wa)
    assert wa["points"].shape == (5, 32, 3) and wa["complete"].shape == (64, 3)
    assert np.all(wa["lengths"] <= 32)
    # the two ranks of a 2-process step take the two halves of the 1-process double batch
    one = stream_indices(len(a), 3, 1, 2 * 8, 8)
    two = [p for r in range(2) for p in stream_indices(len(a), 3, 1, 2 * 4 * 2 + r * 4, 4)]
    assert one == two
    epoch0 = [i for _, i in stream_indices(len(a), 3, 1, 0, len(a))]
    assert sorted(epoch0) == list(range(len(a)))  # each epoch is a permutation
    full = batch_for_step(a, 2, 4, 0, 1)
    assert full["points"].shape == (4, 5, 32, 3)
    starts = [a.window_at(i, 0)["start"] for i in range(len(a))]
    assert 0 in starts and max(starts) > 0


def test_cli_train_and_resume(dataset, tmp_path):
    from seqshape.cli import main

    out = tmp_path / "cli"
    args = ["train", "--data", str(dataset.path), "--out", str(out), "--preset", "smoke",
            "--model", "baseline", "--stage-steps", "4,2,2", "--seed", "5"]
    assert main(args) == 0
    assert main(args) == 1  # exists without --resume
    assert main(args + ["--resume"]) == 0
    assert json.loads((out / "config.json").read_text())["train_config"]["seed"] == 5


@pytest.mark.slow
def test_torchrun_two_processes(dataset, tmp_path):
    torchrun = shutil.which("torchrun") or os.path.join(os.path.dirname(sys.executable),
                                                        "torchrun")
    out = tmp_path / "ddp"
    cmd = [torchrun, "--nproc_per_node", "2", "--master_port", "29531", "-m", "seqshape.cli",
           "train", "--data", str(dataset.path), "--out", str(out), "--preset", "smoke",
           "--stage-steps", "4,2,3"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300,
                         env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert res.returncode == 0, res.stderr[-3000:]
    conf = json.loads((out / "config.json").read_text())
    assert conf["world_size"] == 2
    assert Estimator.from_checkpoint(out / "model.pt").recurrent


def test_real_tracks_without_a_reference_are_left_out_of_training(tmp_path):
    from seqshape.data import Track, TrackDataset, write_dataset
    from seqshape.errors import DataError
    from seqshape.train.trainer import _trainable

    def track(tid, complete):
        return Track(tid, [np.zeros((5, 3), np.float32)], np.zeros((1, 4)), complete,
                     np.array([4.0, 1.8, 1.5]), np.zeros(1), {"split": "train"})

    ds = write_dataset(tmp_path / "d", [track("a", np.zeros((8, 3))), track("b", None)])
    entries = [dict(e, has_complete=e["track_id"] == "a") for e in ds.entries]
    keep = _trainable(TrackDataset(ds.path, _entries=entries), "train")
    assert keep.track_ids == ["a"]
    with pytest.raises(DataError, match="no train track has a complete shape"):
        _trainable(TrackDataset(ds.path, _entries=entries[1:]), "train")


def test_window_lengths_for_the_input_scale(dataset):
    """Without the option the windows are unchanged (no extra draws, no ``length``); with it,
    deterministic lengths: a tracker's noisy box length, or the points' running extent."""
    from seqshape.data.windows import points_length, running_lengths

    tracks = dataset.split("train")
    kw = {"window": 5, "num_points": 32, "num_complete": 64, "seed": 3, "key": 1}
    plain = WindowDataset(tracks, **kw).window_at(2, 1)
    assert "length" not in plain
    hint = WindowDataset(tracks, length_hint_noise=0.08, **kw)
    w = hint.window_at(2, 1)
    assert all(np.array_equal(w[k], plain[k]) for k in plain)
    assert np.array_equal(w["length"], hint.window_at(2, 1)["length"])
    true_length = tracks[2 // hint.windows_per_track].size[0]
    assert w["length"].shape == (5,) and np.all(np.abs(np.log(w["length"] / true_length)) < 0.5)
    pts = WindowDataset(tracks, length_hint_noise=0.08, length_points_prob=1.0, **kw)
    w = pts.window_at(2, 1)
    per_frame = [points_length(w["points"][k, :w["lengths"][k]]) for k in range(5)]
    np.testing.assert_allclose(w["length"], running_lengths(per_frame, True), rtol=1e-6)
    assert np.all(np.diff(w["length"]) >= 0)
    np.testing.assert_array_equal(running_lengths([0, 3, 0, 2, 5], True), [0, 3, 3, 3, 5])
    np.testing.assert_array_equal(running_lengths([0, 3, 0, 2, 5], False), [0, 3, 3, 2, 5])


@pytest.mark.parametrize("kind", ["sequential", "baseline"])
def test_train_with_input_scale(dataset, tmp_path, kind):
    cfg = get_train_config("smoke").with_stage_steps((3, 2, 3))
    cfg = dataclasses.replace(cfg, model_overrides={**cfg.model_overrides,
                                                    "scale_norm": "length", "scale_ref": 2.0},
                              length_points_prob=0.5)
    tr = Trainer(dataset.path, tmp_path / "run", kind, cfg)
    batch = tr._val_batches[0]
    scale = tr._scale(batch)
    assert scale.shape == batch["lengths"].shape and float(scale.min()) >= 1.0
    assert float(scale.max()) > 1.0  # 3.5-5 m boxes against scale_ref 2 m
    path = tr.run()
    payload = torch.load(path, weights_only=True)
    assert payload["model_config"]["scale_norm"] == "length"
    assert payload["model_config"]["scale_ref"] == 2.0
    assert TrainConfig.from_dict(payload["train_config"]).length_points_prob == 0.5
    est = Estimator.from_checkpoint(path)
    assert est.config.scale_norm == "length"
    out = est.step(["t"], [np.random.default_rng(0).normal(size=(40, 3)) * [2, 1, 0.5]])[0]
    assert out.scale > 1.0 and np.all(np.isfinite(out.complete))
