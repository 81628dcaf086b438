"""``seqshape train --init``: start from existing weights, skipped stages, fine-tuning on
tracks exported by the amodal labeller (``export_tracks``)."""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import json
import shutil
import zlib

import numpy as np
import pytest
import torch
from _kitti_fixture import TWO_CARS, write_box_kitti
from _model_data import make_dataset

from seqshape.amodal.accumulate import export_tracks
from seqshape.data import Track
from seqshape.errors import ConfigError, DataError
from seqshape.geometry import canonical_to_sensor
from seqshape.model import Estimator
from seqshape.model import weights as weights_module
from seqshape.testing import box_shell
from seqshape.train import Trainer, get_train_config

SMOKE = get_train_config("smoke")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("tracks") / "ds", n_train=4, n_val=2)


@pytest.fixture(scope="module")
def source(dataset, tmp_path_factory):
    """A short smoke-preset sequential run: its folder (model.pt, last.pt, ...)."""
    run = tmp_path_factory.mktemp("src") / "run"
    Trainer(dataset.path, run, "sequential", SMOKE.with_stage_steps((3, 2, 3))).run()
    return run


def _weights(path):
    return torch.load(path, weights_only=True)["state_dict"]


def _assert_same(a, b):
    assert set(a) == set(b)
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_zero_steps_reproduces_the_source(dataset, source, tmp_path):
    src = source / "model.pt"
    tr = Trainer(dataset.path, tmp_path / "run", "sequential", SMOKE.with_stage_steps((0, 0, 0)),
                 init=src)
    _assert_same(tr.model.state_dict(), _weights(src))  # before any step
    out = tr.run()
    _assert_same(_weights(out), _weights(src))
    assert not any((tmp_path / "run" / f"stage{i}.pt").exists() for i in (1, 2, 3))
    conf = json.loads((tmp_path / "run" / "config.json").read_text())
    init = conf["init"]
    assert init["source"] == str(src) and init["file"] == "model"
    assert init["sha256"] == hashlib.sha256(src.read_bytes()).hexdigest()
    assert torch.load(out, weights_only=True)["init"]["sha256"] == init["sha256"]
    # same val windows (same config and seed) and same weights as at the source's final
    # validation: the initial score equals the source's final one
    src_metrics = torch.load(src, weights_only=True)["metrics"]
    assert tr.metrics["init_val_cd_m"] == pytest.approx(src_metrics["val_cd_m"], rel=1e-5)
    assert tr.metrics["init_val_pose_m2"] == pytest.approx(src_metrics["val_pose_m2"], rel=1e-5)


def test_init_from_training_checkpoint(dataset, source, tmp_path):
    tr = Trainer(dataset.path, tmp_path / "run", "sequential", SMOKE.with_stage_steps((0, 0, 0)),
                 init=source / "stage2.pt")
    _assert_same(_weights(tr.run()), _weights(source / "stage2.pt"))
    assert tr.init["file"] == "checkpoint" and tr.init["stage"] == 2
    assert tr.init["global_step"] == 5


def test_kind_and_config_mismatch_are_clear_errors(dataset, source, tmp_path):
    with pytest.raises(ConfigError, match=r"holds sequential weights.*--model sequential"):
        Trainer(dataset.path, tmp_path / "a", "baseline", SMOKE, init=source / "model.pt")
    cfg = dataclasses.replace(SMOKE, model_overrides={**SMOKE.model_overrides, "hidden": 32})
    with pytest.raises(ConfigError, match=r"hidden 64 \(run: 32\).*--model-set hidden=64"):
        Trainer(dataset.path, tmp_path / "b", "sequential", cfg, init=source / "model.pt")
    with pytest.raises(DataError, match="weights file not found"):
        Trainer(dataset.path, tmp_path / "c", "sequential", SMOKE, init=tmp_path / "none.pt")


def test_pretrained(dataset, source, tmp_path, monkeypatch):
    shipped = tmp_path / "pretrained"
    shipped.mkdir()
    monkeypatch.setattr(weights_module, "PRETRAINED_DIR", shipped)
    with pytest.raises(DataError, match=r"sequential\.pt: shipped sequential weights are"):
        Trainer(dataset.path, tmp_path / "a", "sequential", SMOKE, init="pretrained")
    shutil.copy(source / "model.pt", shipped / "sequential.pt")
    tr = Trainer(dataset.path, tmp_path / "b", "sequential", SMOKE.with_stage_steps((0, 0, 0)),
                 init="pretrained")
    _assert_same(_weights(tr.run()), _weights(source / "model.pt"))
    assert tr.init["source"] == "pretrained"
    assert tr.init["path"] == str((shipped / "sequential.pt").resolve())


def test_joint_only_fine_tune(dataset, source, tmp_path):
    run = tmp_path / "run"
    tr = Trainer(dataset.path, run, "sequential", SMOKE.with_stage_steps((0, 0, 3)),
                 init=source / "model.pt")
    out = tr.run()
    assert not (run / "stage1.pt").exists() and not (run / "stage2.pt").exists()
    assert torch.load(run / "stage3.pt", weights_only=True)["training"]["global_step"] == 3
    rows = list(csv.DictReader(open(run / "log.csv")))
    assert rows and {r["stage"] for r in rows} == {"3"}
    before, after = _weights(source / "model.pt"), _weights(out)
    changed = {k.split(".")[0] for k in after if not torch.equal(before[k], after[k])}
    assert {"pose_decoder", "shape_decoder"} <= changed and len(changed) >= 3, changed
    assert Estimator.from_checkpoint(out).recurrent
    # resuming the finished run does not reload the init weights
    again = Trainer(dataset.path, run, "sequential", SMOKE.with_stage_steps((0, 0, 3)),
                    resume=True, init=source / "model.pt")
    _assert_same(again.model.state_dict(), after)
    assert again.init["sha256"] == tr.init["sha256"]


# --------------------------------------------------------------------------- export -> train
SIZE = np.array([4.2, 1.8, 1.5])


def _seen_track(track_id: str, seed: int, frames: int = 8) -> Track:
    """A box car driving past the sensor; each frame keeps the sensor-facing surface points
    (no complete shape: export_tracks accumulates it)."""
    rng = np.random.default_rng(seed)
    surface = box_shell(4000, rng, SIZE, dtype=np.float32)
    t = np.arange(frames)
    poses = np.stack([8.0 + 0.8 * t, np.full(frames, 4.0 + seed), np.full(frames, -0.9),
                      np.full(frames, 0.1 * seed)], 1)
    points = []
    for pose in poses:
        s = canonical_to_sensor(surface, pose)
        near = s[np.linalg.norm(s[:, :2], axis=1) < np.linalg.norm(pose[:2])]
        points.append(near[rng.random(len(near)) < 0.3])
    return Track(track_id, points, poses, None, SIZE, t * 0.1, {"sequence": "0000"})


def _ids_hashing_to_val(n, val_fraction):
    ids = [f"0000_{i:04d}" for i in range(200)]
    return [i for i in ids if zlib.crc32(i.encode()) % 1000 / 1000 < val_fraction][:n]


def test_export_always_has_a_train_split(tmp_path):
    one = _ids_hashing_to_val(1, 0.3)[0]
    ds = export_tracks([_seen_track(one, 0)], tmp_path / "one", val_fraction=0.3)
    assert [e["split"] for e in ds.entries] == ["train"]
    two = _ids_hashing_to_val(2, 0.3)
    ds = export_tracks([_seen_track(i, k) for k, i in enumerate(two)], tmp_path / "two",
                       val_fraction=0.3)
    assert sorted(e["split"] for e in ds.entries) == ["train", "val"]


@pytest.mark.parametrize("n_tracks", [1, 3])
def test_export_tracks_then_cli_fine_tune(source, tmp_path, n_tracks, capsys):
    from seqshape.cli import main

    tracks = [_seen_track(f"0000_{k:04d}", k) for k in range(n_tracks)]
    export_tracks(tracks, tmp_path / "tracks")
    out = tmp_path / "ft"
    args = ["train", "--data", str(tmp_path / "tracks"), "--out", str(out), "--preset", "smoke",
            "--init", str(source / "model.pt"), "--stage-steps", "0,0,2", "--lr", "2e-4"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert f"initialised from {(source / 'model.pt').resolve()}" in printed
    assert ("initial weights: val CD" in printed) == (n_tracks > 1)
    conf = json.loads((out / "config.json").read_text())
    assert conf["init"]["source"] == str(source / "model.pt")
    assert conf["train_config"]["stages"][2]["lr"] == pytest.approx(1e-4)
    est = Estimator.from_checkpoint(out / "model.pt")
    res = est.step(["a"], [tracks[0].points[0]])[0]
    assert res.complete.shape == (128, 3) and np.all(np.isfinite(res.pose))


def _tiny_kitti(root, frames: int = 6):
    """A hand-built KITTI tracking sequence 0000: three box cars, the sensor-facing surface of
    each in the scan (plus ground), boxes in label_02."""
    return write_box_kitti(root, frames, cars=TWO_CARS + ((22, 3.5, 0.4, 0.05),), size=SIZE,
                           ground_points=2000)


def test_sc_gt_fine_tune_command_sequence(source, tmp_path):
    """docs/amodal.md: export tracks -> train --init -> label --mode sc-gt --checkpoint."""
    from seqshape.cli import main
    from seqshape.data.kins import read_kins

    kitti = _tiny_kitti(tmp_path / "kitti")
    tracks, run, labels = tmp_path / "tracks", tmp_path / "run", tmp_path / "labels.json"
    assert main(["label", "--kitti", str(kitti), "--sequence", "0000",
                 "--export-tracks", str(tracks)]) == 0
    splits = [e["split"] for e in json.loads((tracks / "manifest.json").read_text())["tracks"]]
    assert len(splits) == 3 and "train" in splits and "val" in splits
    assert main(["train", "--data", str(tracks), "--out", str(run), "--preset", "smoke",
                 "--init", str(source / "model.pt"), "--stage-steps", "0,0,2"]) == 0
    assert main(["label", "--kitti", str(kitti), "--sequence", "0000", "--mode", "sc-gt",
                 "--checkpoint", str(run / "model.pt"), "--out", str(labels)]) == 0
    assert labels.is_file()
    read_kins(labels)


def test_init_adds_a_zero_frame_skip(dataset, source, tmp_path):
    """--init weights without the frame skip into a run with it: same function at step 0."""
    cfg = dataclasses.replace(SMOKE.with_stage_steps((0, 0, 0)),
                              model_overrides={**SMOKE.model_overrides, "frame_skip": True})
    tr = Trainer(dataset.path, tmp_path / "run", "sequential", cfg, init=source / "model.pt")
    sd, src = tr.model.state_dict(), _weights(source / "model.pt")
    assert set(sd) - set(src) == {"skip.weight", "skip.bias"}
    assert not sd["skip.weight"].any() and all(torch.equal(sd[k], src[k]) for k in src)
    out = tr.run()
    pts = [np.random.default_rng(0).normal(size=(50, 3)) + [8, 2, 0]]
    a = Estimator.from_checkpoint(source / "model.pt").step(["t"], pts)[0]
    b = Estimator.from_checkpoint(out).step(["t"], pts)[0]
    np.testing.assert_allclose(b.complete, a.complete, atol=1e-5)


def test_init_switches_on_the_input_scale(dataset, source, tmp_path):
    """--init weights trained without the input scale into a run with it: accepted (no new
    parameters), and the exported model computes exactly the old function on cars."""
    cfg = dataclasses.replace(SMOKE.with_stage_steps((0, 0, 0)),
                              model_overrides={**SMOKE.model_overrides, "scale_norm": "length"})
    tr = Trainer(dataset.path, tmp_path / "run", "sequential", cfg, init=source / "model.pt")
    _assert_same(tr.model.state_dict(), _weights(source / "model.pt"))
    out = tr.run()
    payload = torch.load(out, weights_only=True)
    assert payload["model_config"]["scale_norm"] == "length"
    assert payload["init"]["path"] == str((source / "model.pt").resolve())
    rng = np.random.default_rng(0)
    old, new = Estimator.from_checkpoint(source / "model.pt"), Estimator.from_checkpoint(out)
    for _ in range(3):
        pts = [rng.uniform(-0.5, 0.5, (50, 3)) * [4.5, 1.8, 1.5] + [8, 2, 0]]
        a, b = old.step(["t"], pts)[0], new.step(["t"], pts)[0]
        assert b.scale == 1.0
        assert np.array_equal(a.complete, b.complete) and np.array_equal(a.pose, b.pose)
    # other differences are still refused
    bad = dataclasses.replace(cfg, model_overrides={**cfg.model_overrides, "hidden": 32})
    with pytest.raises(ConfigError, match="hidden"):
        Trainer(dataset.path, tmp_path / "bad", "sequential", bad, init=source / "model.pt")


def test_init_changes_the_points_per_frame(dataset, source, tmp_path):
    """--init weights into a run that cuts frames to fewer points (``num_points``, no
    parameters): accepted, the weights as they were, and a frame within both counts gives
    exactly the old estimate while a larger one is cut to the new count (``Estimate.num_points``
    is the number fed)."""
    old_n = torch.load(source / "model.pt", weights_only=True)["model_config"]["num_points"]
    cfg = dataclasses.replace(SMOKE.with_stage_steps((0, 0, 0)),
                              model_overrides={**SMOKE.model_overrides,
                                               "num_points": old_n // 2})
    tr = Trainer(dataset.path, tmp_path / "run", "sequential", cfg, init=source / "model.pt")
    _assert_same(tr.model.state_dict(), _weights(source / "model.pt"))
    out = tr.run()
    assert torch.load(out, weights_only=True)["model_config"]["num_points"] == old_n // 2
    old, new = (Estimator.from_checkpoint(p, backend="auto-float") for p in (source / "model.pt", out))
    rng = np.random.default_rng(1)
    small = [rng.uniform(-0.5, 0.5, (old_n // 4, 3)) * [4.5, 1.8, 1.5] + [8, 2, 0]]
    a, b = old.step(["t"], small)[0], new.step(["t"], small)[0]
    assert np.array_equal(a.complete, b.complete) and np.array_equal(a.pose, b.pose)
    big = [rng.uniform(-0.5, 0.5, (old_n, 3)) * [4.5, 1.8, 1.5] + [8, 2, 0]]
    a, b = old.step(["u"], big)[0], new.step(["u"], big)[0]
    assert (a.num_points, b.num_points) == (old_n, old_n // 2)  # the points fed
    assert not np.array_equal(a.complete, b.complete)


def test_cli_init_takes_the_architecture_of_its_weights():
    """``seqshape train --init pretrained`` (the fine-tuning recipe) builds the shipped
    weights' architecture whatever the preset's is; ``--model-set`` still wins; without
    ``--init`` the preset's stands."""
    import argparse

    from seqshape.model.estimator import read_model_file
    from seqshape.model.weights import pretrained_path
    from seqshape.scripts.train import add_arguments, build_config

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    shipped = read_model_file(pretrained_path("sequential"))["model_config"]
    args = parser.parse_args(["--data", "D", "--out", "O", "--init", "pretrained",
                              "--stage-steps", "0,0,10"])
    got = build_config(args).model_config().to_dict()
    assert {k: got[k] for k in shipped} == shipped
    assert got["motion_input"] and got["frame_skip"]  # what the preset lacks
    args = parser.parse_args(["--data", "D", "--out", "O", "--init", "pretrained",
                              "--model-set", "num_points=128"])
    assert build_config(args).model_config().num_points == 128
    plain = build_config(parser.parse_args(["--data", "D", "--out", "O"])).model_config()
    assert plain.to_dict() == get_train_config("small").model_config().to_dict()
