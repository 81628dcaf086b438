"""seqshape.sim.generate and the ``seqshape generate`` command: content, determinism, resume."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from seqshape._runner import parse_shard
from seqshape.cli import main
from seqshape.data import TrackDataset
from seqshape.errors import ConfigError, DataError
from seqshape.geometry import sensor_to_canonical
from seqshape.scripts.stats import collect, format_table
from seqshape.sim.generate import (
    PRESETS,
    GenerateConfig,
    generate_dataset,
    preset_config,
    scaled_preset_config,
    scaled_val_vehicles,
    track_lengths,
)
from seqshape.sim.sensors import get_sensor
from seqshape.sim.trajectories import sample_track_length, track_length_location
from seqshape.vehicles import vehicle_library

SMALL = GenerateConfig("small", n_vehicles=3, n_val_vehicles=1, tracks_per_vehicle=2,
                       min_frames=6, max_frames=14, mean_frames=9.0, max_distance=30.0,
                       num_points=512)


def _arrays_equal(a: TrackDataset, b: TrackDataset) -> None:
    assert a.track_ids == b.track_ids
    for x, y in zip(a, b, strict=False):
        assert len(x) == len(y)
        for p, q in zip(x.points, y.points, strict=False):
            np.testing.assert_array_equal(p, q)
        np.testing.assert_array_equal(x.poses, y.poses)
        np.testing.assert_array_equal(x.complete, y.complete)
        np.testing.assert_array_equal(x.timestamps, y.timestamps)
        assert x.meta == y.meta


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    out = tmp_path_factory.mktemp("small")
    s = generate_dataset(SMALL, out)
    assert s.manifest_written and s.n_generated == s.n_tracks == 6
    return out


def test_presets_match_the_paper():
    p = PRESETS["paper"]
    assert (p.n_vehicles, p.n_val_vehicles, p.tracks_per_vehicle) == (183, 15, 11)
    assert p.sensor == "vlp16" and not p.ground and p.max_occluders == 0 and not p.noise
    r = PRESETS["realistic"]
    assert r.ground and r.max_occluders > 0 and r.noise
    assert get_sensor(p.sensor).height == 2.0


def test_dataset_content_and_splits(small):
    ds = TrackDataset(small)
    assert len(ds) == 6
    train, val = ds.split("train"), ds.split("val")
    assert len(train) == 4 and len(val) == 2
    mesh_train = {t.meta["mesh_id"] for t in train}
    mesh_val = {t.meta["mesh_id"] for t in val}
    assert len(mesh_val) == 1 and not mesh_train & mesh_val  # split by vehicle
    for tr in ds:
        assert 6 <= len(tr) <= 14 and tr.complete.shape == (512, 3)
        np.testing.assert_allclose(np.diff(tr.timestamps), 0.1, atol=1e-12)
        for key in ("mesh_id", "kind", "sensor", "split", "generator_version", "seed",
                    "manoeuvre"):
            assert key in tr.meta
        assert all(p.dtype == np.float32 and p.shape[1] == 3 for p in tr.points)
        # vehicles stand on the ground (z = -2 m for the VLP-16)
        np.testing.assert_allclose(tr.poses[:, 2] - tr.size[2] / 2, -2.0, atol=1e-6)


def test_points_lie_on_the_vehicle_surface(small):
    lib = {v.vehicle_id: v.mesh for v in vehicle_library(SMALL.n_vehicles, SMALL.seed)}
    elev = np.array(get_sensor("vlp16").elevations_deg)
    n_points = 0
    for tr in TrackDataset(small):
        tree = cKDTree(tr.complete)
        for p, pose in zip(tr.points, tr.poses, strict=False):
            if not len(p):
                continue
            n_points += len(p)
            local = sensor_to_canonical(p, pose).astype(np.float64)
            _, d_mesh, _ = trimesh.proximity.closest_point(lib[tr.meta["mesh_id"]], local)
            assert d_mesh.max() < 1e-4
            # 512 complete points are ~0.3 m apart: nearest distances stay well below that
            assert np.percentile(tree.query(local)[0], 95) < 0.3
            e = np.degrees(np.arcsin(p[:, 2] / np.linalg.norm(p, axis=1)))
            assert np.abs(e[:, None] - elev[None]).min(1).max() < 1e-3
    assert n_points > 1000


def test_identical_across_workers_and_shards(small, tmp_path):
    two = tmp_path / "two"
    generate_dataset(SMALL, two, workers=2)
    _arrays_equal(TrackDataset(small), TrackDataset(two))
    sharded = tmp_path / "sharded"
    first = generate_dataset(SMALL, sharded, shard=(2, 2))
    assert not first.manifest_written and first.n_generated == 2 and len(first.missing) == 4
    assert not (sharded / "manifest.json").exists()
    second = generate_dataset(SMALL, sharded, shard=(1, 2))
    assert second.manifest_written and second.n_generated == 4 and second.n_skipped == 2
    _arrays_equal(TrackDataset(small), TrackDataset(sharded))


def test_resume_regenerates_only_missing_tracks(small, tmp_path):
    out = tmp_path / "resume"
    generate_dataset(SMALL, out)
    files = sorted((out / "tracks").glob("*.npz"))
    (out / "manifest.json").unlink()
    files[0].unlink()
    files[1].write_bytes(files[1].read_bytes()[:100])  # a corrupt file (not from our writer)
    kept = {f: f.stat().st_mtime_ns for f in files[2:]}
    s = generate_dataset(SMALL, out)
    assert s.n_generated == 2 and s.n_skipped == 4 and s.manifest_written
    assert all(f.stat().st_mtime_ns == m for f, m in kept.items())
    _arrays_equal(TrackDataset(small), TrackDataset(out))


def test_resume_after_killed_process(small, tmp_path):
    """SIGKILL the generating process right after its third track file is written."""
    out = tmp_path / "killed"
    env = {**os.environ, "SEQSHAPE_PROGRESS": "0", "SEQSHAPE_TEST_KILL_AFTER": "3"}
    proc = subprocess.run([sys.executable, "-c", _KILL_SCRIPT, str(out)], env=env,
                          cwd=Path(__file__).resolve().parents[1], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == -9, proc.stderr
    done = list((out / "tracks").glob("*.npz"))
    assert len(done) == 3 and not (out / "manifest.json").exists()
    assert not list((out / "tracks").glob(".*.tmp"))  # atomic writes: no half files
    s = generate_dataset(SMALL, out)
    assert s.n_generated == 3 and s.manifest_written
    _arrays_equal(TrackDataset(small), TrackDataset(out))


_KILL_SCRIPT = """
import os, signal, sys
from seqshape.data import track
from tests.test_generate import SMALL
from seqshape.sim.generate import generate_dataset
real, count = track.save_track, [0]
def save_then_maybe_die(path, tr, **kw):
    real(path, tr, **kw)
    count[0] += 1
    if count[0] == int(os.environ["SEQSHAPE_TEST_KILL_AFTER"]):
        os.kill(os.getpid(), signal.SIGKILL)
import seqshape.sim._worker as w
w.save_track = save_then_maybe_die
generate_dataset(SMALL, sys.argv[1])
"""


def test_config_mismatch_is_refused(small):
    from dataclasses import replace

    with pytest.raises(ConfigError, match="seed: 0 there vs 5 now"):
        generate_dataset(replace(SMALL, seed=5), small)


def test_csv_trajectories_drive_the_vehicles(tmp_path):
    from dataclasses import replace

    t = np.arange(12) / 10
    csv = tmp_path / "logs"
    csv.mkdir()
    rows = "\n".join(f"{a:.1f},{8 + 1.0 * a:.3f},-6.0,0.0" for a in t)
    (csv / "a.csv").write_text("t,x,y,yaw\n" + rows + "\n")
    cfg = replace(SMALL, n_vehicles=2, tracks_per_vehicle=1, trajectories=str(csv))
    generate_dataset(cfg, tmp_path / "out")
    for tr in TrackDataset(tmp_path / "out"):
        np.testing.assert_allclose(tr.poses[:, 0], 8 + t, atol=1e-9)
        np.testing.assert_allclose(tr.poses[:, 1], -6.0)
        np.testing.assert_allclose(tr.timestamps, t)
        assert tr.meta["manoeuvre"] == "csv" and tr.num_points.min() > 0
    # a log running through the sensor is refused, naming the file
    (csv / "a.csv").write_text("t,x,y,yaw\n0,5,0,0\n0.1,1,0,0\n")
    with pytest.raises(DataError, match="overlap the sensor") as info:
        generate_dataset(cfg, tmp_path / "out2")
    assert info.value.path.endswith("a.csv")


def test_realistic_options_block_but_never_add_points(tmp_path):
    from dataclasses import replace

    cfg = replace(SMALL, name="real", ground=True, max_occluders=3, noise=True,
                  n_vehicles=4, tracks_per_vehicle=3)
    generate_dataset(cfg, tmp_path / "r")
    n_occ = 0
    for tr in TrackDataset(tmp_path / "r"):
        n_occ += len(tr.meta["occluders"])
        for p, pose in zip(tr.points, tr.poses, strict=False):
            # target returns only: inside the target's box (+ noise margin), above the ground
            local = sensor_to_canonical(p, pose)
            assert np.all(np.abs(local) <= tr.size / 2 + 0.1)
            assert np.all(p[:, 2] >= -2.0 - 0.1)
    assert n_occ > 0


def test_bad_arguments(tmp_path, capsys):
    with pytest.raises(ConfigError, match="K/N"):
        parse_shard("2")
    with pytest.raises(ConfigError, match="1 <= K <= N"):
        parse_shard("3/2")
    with pytest.raises(ConfigError, match="unknown preset"):
        preset_config("huge")
    with pytest.raises(ConfigError, match="unknown sensor"):
        preset_config("tiny", sensor="vlp17")
    with pytest.raises(ConfigError, match="workers"):
        generate_dataset(SMALL, tmp_path / "w", workers=0)
    assert main(["generate", "--preset", "tiny", "--out", str(tmp_path / "x"),
                 "--shard", "0/3"]) == 1
    assert "--shard K/N needs 1 <= K <= N" in capsys.readouterr().err
    assert main(["generate", "--preset", "tiny", "--out", str(tmp_path / "y"),
                 "--meshes", str(tmp_path / "no-such-folder")]) == 1
    assert "no-such-folder" in capsys.readouterr().err
    bad = tmp_path / "bad.csv"
    bad.write_text("t,x,y\n0,1,2\n")
    assert main(["generate", "--preset", "tiny", "--out", str(tmp_path / "z"),
                 "--trajectories", str(bad)]) == 1
    assert "bad.csv:1: missing column" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["generate", "--preset", "huge", "--out", str(tmp_path / "q")])


def test_cli_tiny_runs_and_resumes(tmp_path, capsys):
    out = tmp_path / "tiny"
    assert main(["generate", "--preset", "tiny", "--out", str(out), "--num-points", "256"]) == 0
    assert "12 tracks generated" in capsys.readouterr().out
    assert main(["generate", "--preset", "tiny", "--out", str(out), "--num-points", "256"]) == 0
    assert "0 tracks generated, 12 already there" in capsys.readouterr().out
    assert TrackDataset(out)[0].complete.shape == (256, 3)


def test_stats_table_matches_hand_count(small, capsys):
    ds = TrackDataset(small)
    stats = collect(ds)
    frames = sum(len(t) for t in ds)
    pts = np.concatenate([t.num_points for t in ds])
    dist = np.concatenate([np.hypot(t.poses[:, 0], t.poses[:, 1]) for t in ds])
    assert len(stats["all"]["lengths"]) == 6 and int(np.sum(stats["all"]["lengths"])) == frames
    table = format_table(stats)
    assert f"| all   | 6      | {frames}" in table
    near = pts[dist < 10]
    if len(near):
        assert f"{near.mean():.1f}" in table.split("0-10 m")[1].splitlines()[0]
    assert main(["stats", str(small)]) == 0
    assert "10-20 m" in capsys.readouterr().out


def test_show_writes_png_and_offline_html(small, tmp_path, capsys):
    tid = TrackDataset(small).track_ids[1]
    assert main(["show", str(small), "--track", tid, "--out", str(tmp_path)]) == 0
    png, html = tmp_path / f"{tid}.png", tmp_path / f"{tid}.html"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    text = html.read_text()
    assert "Plotly.newPlot" in text and len(text) > 3_000_000  # plotly.js is embedded
    assert '<script src="http' not in text and "<script src='http" not in text
    assert main(["show", str(small), "--track", "nope", "--out", str(tmp_path)]) == 1
    assert "no track 'nope'" in capsys.readouterr().err


def test_scaled_val_vehicles_hand_computed():
    paper, tiny = PRESETS["paper"], PRESETS["tiny"]  # 15 of 183; 2 of 6
    assert scaled_val_vehicles(paper, 50) == 4      # 50 * 15 / 183 = 4.10
    assert scaled_val_vehicles(paper, 100) == 8     # 8.20
    assert scaled_val_vehicles(paper, 10) == 1      # 0.82 -> at least 1
    assert scaled_val_vehicles(tiny, 9) == 3        # 9 * 2 / 6
    assert scaled_val_vehicles(tiny, 2) == 1        # at most n - 1
    assert scaled_val_vehicles(tiny, 1) == 0        # a single vehicle trains
    assert scaled_val_vehicles(paper, 183) == 15


def test_track_lengths_hand_computed():
    paper, tiny = PRESETS["paper"], PRESETS["tiny"]  # frames 10-200; 10-30
    assert track_lengths(paper, 50) == {"mean_frames": 50.0, "min_frames": 10, "max_frames": 150}
    assert track_lengths(paper, 100) == {"mean_frames": 100.0, "min_frames": 10,
                                         "max_frames": 200}  # the preset's cap
    assert track_lengths(tiny, 12.5) == {"mean_frames": 12.5, "min_frames": 10,
                                         "max_frames": 30}
    assert track_lengths(tiny, 40) == {"mean_frames": 40.0, "min_frames": 10,
                                       "max_frames": 40}  # never below the mean
    assert track_lengths(tiny, 4) == {"mean_frames": 4.0, "min_frames": 4, "max_frames": 12}


def test_scaled_preset_config_as_the_command_sets_it():
    assert scaled_preset_config("paper") == PRESETS["paper"]
    cfg = scaled_preset_config("paper", n_vehicles=50, mean_frames=20, seed=3, sensor=None)
    assert (cfg.n_vehicles, cfg.n_val_vehicles, cfg.seed, cfg.sensor) == (50, 4, 3, "vlp16")
    assert (cfg.min_frames, cfg.mean_frames, cfg.max_frames) == (10, 20.0, 60)
    # an explicit value wins over the derived one
    assert scaled_preset_config("paper", n_vehicles=50, n_val_vehicles=7).n_val_vehicles == 7
    assert preset_config("paper", n_vehicles=50).n_val_vehicles == 15  # preset_config: as given
    with pytest.raises(ConfigError, match="unknown preset"):
        scaled_preset_config("huge", n_vehicles=3)


def test_cli_tracks_per_vehicle_and_mean_frames(tmp_path):
    out = tmp_path / "g"
    assert main(["generate", "--preset", "tiny", "--out", str(out), "--tracks-per-vehicle", "1",
                 "--mean-frames", "12"]) == 0
    m = json.loads((out / "manifest.json").read_text())
    assert len(m["tracks"]) == 6  # 6 vehicles x 1 track
    assert (m["config"]["mean_frames"], m["config"]["max_frames"]) == (12.0, 30)
    assert all(10 <= e["n_frames"] <= 30 for e in m["tracks"])


def test_unreachable_mean_length_is_refused_before_writing(tmp_path, capsys):
    # the truncated log-normal over [6, 18] frames cannot have a mean of exactly 6: its lowest
    # reachable mean is above the lower bound (a clear error, not scipy's root-finder message)
    out = tmp_path / "never"
    assert main(["generate", "--preset", "tiny", "--mean-frames", "6", "--out", str(out)]) != 0
    err = capsys.readouterr().err
    assert "mean track length of 6.0 frames" in err and "choose a mean in [" in err
    assert not out.exists()
    with pytest.raises(ConfigError, match="cannot be drawn"):
        track_length_location(6, 18, 6.0)
    rng = np.random.default_rng(0)
    lengths = [sample_track_length(rng, 6, 18, 7.0) for _ in range(4000)]
    assert min(lengths) >= 6 and max(lengths) <= 18 and abs(np.mean(lengths) - 7.0) < 0.1
