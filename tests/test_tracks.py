"""``seqshape tracks``: real logs -> track dataset, exact points, resume, shards, failures.

The command is tested on a tiny in-test :class:`DrivingLog` ("fake", registered in
``DATASETS`` for the test) so it does not depend on any one reader, and on a KITTI tracking
root written in the official format.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from seqshape.cli import main
from seqshape.data import TrackDataset
from seqshape.data.sequence import Box3D, DrivingLog
from seqshape.data.tracks_export import TracksConfig, extract_dataset, log_split
from seqshape.errors import ConfigError, DataError
from seqshape.geometry import canonical_to_sensor

SIZE = np.array([4.0, 1.8, 1.5])
SENSOR_HEIGHT = 1.7  # ground at z = -1.7 in the sensor frame
META_KEYS = {"source", "dataset", "log", "root", "object_id", "category", "class", "sensor",
             "frames", "dataset_num_points", "visibility", "crop", "split"}


class FakeLog(DrivingLog):
    """A log stored as ``ROOT/<name>.npz``: ``points_<frame>`` arrays and ``boxes`` (JSON)."""

    dataset = "fake"
    sensor = "fake-lidar"

    def __init__(self, root, name):
        self.root, self.name = Path(root), name
        path = self.root / f"{name}.npz"
        try:
            with np.load(path) as z:
                self._points = {int(k[7:]): z[k] for k in z.files if k.startswith("points_")}
                self._boxes = json.loads(str(z["boxes"]))
        except (OSError, ValueError, KeyError) as exc:
            raise DataError(path, f"unreadable fake log ({exc})") from None
        self.frames = sorted(self._points)

    def timestamp(self, frame):
        return 100.0 + 0.1 * frame

    def points(self, frame):
        return self._points[frame]

    def boxes(self, frame):
        return [Box3D(**b) for b in self._boxes.get(str(frame), [])]

    def ego_pose(self, frame):
        m = np.eye(4)
        m[0, 3] = 0.5 * frame
        return m

    @classmethod
    def log_names(cls, root):
        return sorted(p.stem for p in Path(root).glob("*.npz"))


@pytest.fixture
def fake(monkeypatch):
    from seqshape.data import sequence

    monkeypatch.setitem(sequence.DATASETS, "fake", f"{FakeLog.__module__}:FakeLog")


def _scene(rng, pose, size=SIZE):
    """A sweep around one box: (sweep (N, 4), the points that must come out of the crop).

    Interior points fill the box from 0.3 m above its bottom; flat ground (a 0.25 m grid,
    also under the box) at the box bottom; clutter 0.6 m beyond each side and above the top.
    """
    length, width, height = size
    inner = np.c_[rng.uniform(-0.48, 0.48, (60, 2)) * [length, width],
                  rng.uniform(-height / 2 + 0.3, height / 2 - 0.05, 60)]
    clutter = np.array([[length / 2 + 0.6, 0, 0], [-length / 2 - 0.6, 0.3, -0.2],
                        [0.5, width / 2 + 0.6, 0.1], [-1, -width / 2 - 0.6, 0.4],
                        [0.0, 0.0, height / 2 + 0.4]])
    g = np.arange(-7.0, 7.0, 0.25)
    gx, gy = np.meshgrid(g, g)
    ground = np.c_[gx.ravel() + pose[0], gy.ravel() + pose[1],
                   np.full(gx.size, pose[2] - height / 2)]
    interior = canonical_to_sensor(inner, pose).astype(np.float32)
    sweep = np.r_[interior, canonical_to_sensor(clutter, pose), ground,
                  [[pose[0] + 0.5, pose[1] - 4.0, pose[2]]]]  # the pedestrian's point
    sweep = np.c_[sweep, rng.uniform(0, 1, len(sweep))].astype(np.float32)
    return sweep, interior


def _box(oid, cls, pose, size=SIZE, category="CAR"):
    return {"track_id": oid, "category": category, "cls": cls, "centre": list(pose[:3]),
            "size": list(size), "yaw": float(pose[3]), "num_points": 60}


def write_fake_log(root: Path, name: str, n_frames: int = 3, seed: int = 0) -> dict:
    """Write log ``name``: one car driving past, a pedestrian; returns the expected values."""
    rng = np.random.default_rng(seed)
    arrays, boxes, expected = {}, {}, {"points": [], "poses": []}
    for f in range(n_frames):
        pose = np.array([8.0 + f, 3.0 - 0.2 * f, -SENSOR_HEIGHT + SIZE[2] / 2, 0.3 + 0.05 * f])
        sweep, interior = _scene(rng, pose)
        arrays[f"points_{f}"] = sweep
        ped = np.array([pose[0] + 0.5, pose[1] - 4.0, pose[2], 0.0])
        boxes[str(f)] = [_box("car1", "car", pose),
                         _box("ped", None, ped, [0.6, 0.6, 1.7], "PEDESTRIAN")]
        expected["points"].append(interior)
        expected["poses"].append(pose)
    root.mkdir(parents=True, exist_ok=True)
    np.savez(root / f"{name}.npz", boxes=np.array(json.dumps(boxes)), **arrays)
    return expected


def _sorted_rows(a):
    a = np.asarray(a)
    return a[np.lexsort(a.T[::-1])]


def _run(root, out, *extra):
    return main(["tracks", "--dataset", "fake", "--root", str(root), "--out", str(out),
                 "--no-reference", *extra])


def _manifest(out):
    m = json.loads((Path(out) / "manifest.json").read_text())
    return m["tracks"], m["config"], m["logs"]


@pytest.fixture
def logs(tmp_path, fake):
    root = tmp_path / "root"
    return root, {name: write_fake_log(root, name, seed=i) for i, name in enumerate("abc")}


def test_exact_points_poses_and_meta(logs, tmp_path, capsys):
    root, expected = logs
    out = tmp_path / "out"
    assert _run(root, out, "--sequence", "a,b", "--val-fraction", "0") == 0
    assert "2 logs extracted" in capsys.readouterr().out
    ds = TrackDataset(out)
    assert ds.track_ids == ["a_car1", "b_car1"]  # the pedestrian is not a vehicle
    for name, tr in zip("ab", ds, strict=True):
        exp = expected[name]
        assert len(tr) == 3 and tr.complete is None
        for got, want in zip(tr.points, exp["points"], strict=True):
            np.testing.assert_array_equal(_sorted_rows(got), _sorted_rows(want))
        np.testing.assert_allclose(tr.poses, np.stack(exp["poses"]), atol=1e-12)
        np.testing.assert_allclose(tr.size, SIZE)
        np.testing.assert_allclose(tr.timestamps, [100.0, 100.1, 100.2])
        assert META_KEYS <= set(tr.meta) and "reference" not in tr.meta
        m = tr.meta
        assert (m["source"], m["dataset"], m["log"], m["object_id"], m["class"]) == (
            "real", "fake", name, "car1", "car")
        assert m["frames"] == [0, 1, 2] and m["split"] == "train"
        assert m["crop"]["margin"] == 0.2 and m["crop"]["ground"] == "plane"
        np.testing.assert_allclose(np.array(m["ego_poses"])[:, 0, 3], [0.0, 0.5, 1.0])
    entries, config, done = _manifest(out)
    assert done == ["a", "b"] and config["dataset"] == "fake"
    assert [(e["class"], e["log"], e["split"]) for e in entries] == [("car", "a", "train"),
                                                                     ("car", "b", "train")]
    assert (out / "logs" / "fake_a.json").is_file()


def test_ground_none_keeps_the_ground_and_margin_widens(logs, tmp_path):
    root, expected = logs
    _run(root, tmp_path / "none", "--sequence", "a", "--ground", "none")
    _run(root, tmp_path / "wide", "--sequence", "a", "--margin", "0.7", "--ground", "box")
    n_inner = [len(p) for p in expected["a"]["points"]]
    none = TrackDataset(tmp_path / "none")[0]
    assert all(n > i for n, i in zip(none.num_points, n_inner, strict=True))
    wide = TrackDataset(tmp_path / "wide")[0]  # 4 side clutter points now inside, top not
    np.testing.assert_array_equal(wide.num_points, np.array(n_inner) + 4)


def test_splits_follow_the_log(logs, tmp_path):
    root, _ = logs
    _run(root, tmp_path / "v", "--val-fraction", "1")
    assert {e["split"] for e in _manifest(tmp_path / "v")[0]} == {"val"}
    _run(root, tmp_path / "f", "--split", "val", "--val-fraction", "0")
    assert len(TrackDataset(tmp_path / "f").split("val")) == 3
    _run(root, tmp_path / "h", "--val-fraction", "0.5")
    for e in _manifest(tmp_path / "h")[0]:
        assert e["split"] == log_split("fake", e["log"], 0.5)
    # --split-by track: the rule runs per vehicle, so one log's tracks can land in both splits
    _run(root, tmp_path / "t", "--val-fraction", "0.5", "--split-by", "track")
    entries = _manifest(tmp_path / "t")[0]
    for e in entries:
        tr = TrackDataset(tmp_path / "t").get(e["track_id"])
        assert e["split"] == log_split("fake", f"{e['log']}:{tr.meta['object_id']}", 0.5)
        assert e["split"] == tr.meta["split"]
    # the hash rule is stable and spreads logs over both splits
    splits = [log_split("av2", f"log{i}", 0.2) for i in range(1000)]
    assert 150 < splits.count("val") < 250
    assert splits == [log_split("av2", f"log{i}", 0.2) for i in range(1000)]


def test_resume_skips_done_logs_and_shards_add_up(logs, tmp_path, capsys):
    root, _ = logs
    full = tmp_path / "full"
    assert _run(root, full) == 0
    files = sorted(full.glob("tracks/*.npz")) + sorted(full.glob("logs/*.json"))
    mtimes = {f: f.stat().st_mtime_ns for f in files}
    capsys.readouterr()
    assert _run(root, full) == 0
    assert "0 logs extracted, 3 already done" in capsys.readouterr().out
    assert {f: f.stat().st_mtime_ns for f in files} == mtimes
    # a log whose record is gone is extracted again, and only that one
    (full / "logs" / "fake_b.json").unlink()
    assert _run(root, full) == 0
    assert "1 logs extracted, 2 already done" in capsys.readouterr().out
    assert (full / "tracks" / "a_car1.npz").stat().st_mtime_ns == mtimes[
        full / "tracks" / "a_car1.npz"]

    sharded = tmp_path / "sharded"
    assert _run(root, sharded, "--shard", "2/2") == 0  # logs a, b, c: shard 2 takes b
    assert "2 logs not done yet" in capsys.readouterr().out
    assert [e["log"] for e in _manifest(sharded)[0]] == ["b"]
    assert _run(root, sharded, "--shard", "1/2") == 0
    assert _manifest(sharded) == _manifest(full)
    for x, y in zip(TrackDataset(full), TrackDataset(sharded), strict=True):
        for p, q in zip(x.points, y.points, strict=True):
            np.testing.assert_array_equal(p, q)
        assert x.meta == y.meta


def test_workers_give_the_same_dataset(logs, tmp_path):
    root, _ = logs
    assert _run(root, tmp_path / "one") == 0
    assert _run(root, tmp_path / "two", "--workers", "2") == 0
    assert _manifest(tmp_path / "one") == _manifest(tmp_path / "two")
    for x, y in zip(TrackDataset(tmp_path / "one"), TrackDataset(tmp_path / "two"),
                    strict=True):
        np.testing.assert_array_equal(np.concatenate(x.points), np.concatenate(y.points))


def test_interrupt_leaves_complete_files_and_resumes(logs, tmp_path, monkeypatch):
    from seqshape.data import tracks_export

    root, _ = logs
    out = tmp_path / "out"
    real, calls = tracks_export.save_track, []

    def save_then_interrupt(path, tr, **kw):
        real(path, tr, **kw)
        calls.append(path)
        if len(calls) == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(tracks_export, "save_track", save_then_interrupt)
    assert _run(root, out) == 130
    assert sorted(p.name for p in out.glob("logs/*.json")) == ["fake_a.json"]
    assert not (out / "manifest.json").exists() and not list(out.rglob("*.tmp"))
    monkeypatch.setattr(tracks_export, "save_track", real)
    assert _run(root, out) == 0
    assert _manifest(out)[2] == ["a", "b", "c"]


def test_a_broken_log_is_skipped_and_counted(logs, tmp_path, capsys):
    root, _ = logs
    (root / "broken.npz").write_bytes(b"not a zip file")
    out = tmp_path / "out"
    assert _run(root, out) == 1
    text = capsys.readouterr().out
    assert "3 logs extracted, 0 already done, 1 failed" in text
    assert "failed: broken: " in text and "broken.npz: unreadable fake log" in text
    assert _manifest(out)[2] == ["a", "b", "c"]


def test_bad_input_gives_clean_errors(logs, tmp_path, capsys):
    root, _ = logs
    out = tmp_path / "out"
    for extra, message in [(["--sequence", "a,zz"], "unknown fake log(s) ['zz']"),
                           (["--shard", "3/2"], "needs 1 <= K <= N"),
                           (["--shard", "x"], "--shard must look like K/N"),
                           (["--classes", "car,boat"], "unknown vehicle class"),
                           (["--val-fraction", "2"], "--val-fraction must be in [0, 1]")]:
        assert _run(root, out, *extra) == 1
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err
    assert _run(tmp_path / "nowhere", out) == 1
    assert "no such fake dataset folder" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse refuses an unknown --dataset
        main(["tracks", "--dataset", "waymo", "--root", str(root), "--out", str(out)])
    with pytest.raises(ConfigError, match="unknown dataset 'waymo'"):
        extract_dataset(TracksConfig("waymo", str(root), ("car",)), out)


def test_other_settings_into_the_same_folder_are_refused(logs, tmp_path, capsys):
    root, _ = logs
    out = tmp_path / "out"
    assert _run(root, out, "--sequence", "a") == 0
    assert _run(root, out, "--sequence", "b", "--min-points", "3") == 1
    assert "min_points: 10 there vs 3 now" in capsys.readouterr().err
    assert _run(root, out, "--sequence", "b", "--sequence", "c") == 0  # same settings: fine
    assert _manifest(out)[2] == ["a", "b", "c"]


def _fake_reference(fail_on=()):
    def accumulated_reference(track, n_points=2048):
        if track.meta["log"] in fail_on:
            raise ValueError("too few points")
        pts = np.concatenate(track.points)[:n_points]
        return pts, {"kind": "accumulated", "n_frames": len(track), "n_points": n_points}

    return accumulated_reference


def test_reference_becomes_the_complete_shape(logs, tmp_path, monkeypatch):
    from seqshape.data import tracks_export

    root, _ = logs
    monkeypatch.setattr(tracks_export, "accumulated_reference", _fake_reference(fail_on={"b"}))
    out = tmp_path / "out"
    assert main(["tracks", "--dataset", "fake", "--root", str(root), "--out", str(out),
                 "--sequence", "a,b", "--reference-points", "50"]) == 0
    a, b = TrackDataset(out)
    np.testing.assert_array_equal(a.complete, np.concatenate(a.points)[:50])
    assert a.meta["reference"] == {"kind": "accumulated", "n_frames": 3, "n_points": 50}
    assert b.complete is None and b.meta["reference"]["error"] == "too few points"
    assert _manifest(out)[1]["reference_points"] == 50
    # the manifest says which tracks can be trained on
    assert [e["has_complete"] for e in _manifest(out)[0]] == [True, False]
    assert [t.track_id for t in TrackDataset(out).with_complete()] == [a.track_id]


def test_real_reference(logs, tmp_path):
    root, _ = logs
    out = tmp_path / "out"
    assert main(["tracks", "--dataset", "fake", "--root", str(root), "--out", str(out),
                 "--sequence", "a", "--reference-points", "256"]) == 0
    tr = TrackDataset(out)[0]
    assert tr.complete.shape == (256, 3) and tr.meta["reference"]["kind"] == "accumulated"
    # the reference lies in the canonical frame, inside the (mirrored) box
    assert np.all(np.abs(tr.complete) <= SIZE / 2 + 0.25)


# ----------------------------------------------------------------------------- KITTI


def test_kitti_root_round_trip(tmp_path):
    from seqshape.camera import kitti_default_calib, write_calib
    from seqshape.data.kitti import (
        KittiLabel,
        pose_to_label_fields,
        write_labels,
        write_velodyne,
    )

    calib = kitti_default_calib()
    root = tmp_path / "training"
    rng = np.random.default_rng(3)
    labels, expected = [], []
    for f in range(2):
        pose = np.array([9.0 + f, 2.0, -SENSOR_HEIGHT + SIZE[2] / 2, 0.2])
        sweep, interior = _scene(rng, pose)
        write_velodyne(root / "velodyne" / "0003" / f"{f:06d}.bin", sweep)
        labels.append(KittiLabel(frame=f, track_id=4, type="Car", truncated=0, occluded=0,
                                 bbox=[0, 0, 10, 10], **pose_to_label_fields(pose, SIZE, calib)))
        expected.append((pose, interior))
    write_labels(root / "label_02" / "0003.txt", labels)
    write_calib(root / "calib" / "0003.txt", calib)
    out = tmp_path / "out"
    assert main(["tracks", "--dataset", "kitti", "--root", str(root), "--out", str(out),
                 "--no-reference"]) == 0
    (tr,) = TrackDataset(out)
    assert tr.track_id == "0003_0004" and tr.meta["dataset"] == "kitti" and tr.meta["class"] == "car"
    for got, gpose, (pose, interior) in zip(tr.points, tr.poses, expected, strict=True):
        np.testing.assert_array_equal(_sorted_rows(got), _sorted_rows(interior))
        np.testing.assert_allclose(gpose, pose, atol=1e-5)
    np.testing.assert_allclose(tr.size, SIZE, atol=1e-5)


def _b(oid, x, y, cls="car"):
    return Box3D(track_id=oid, category="CAR", cls=cls, centre=[x, y, -0.9], size=SIZE, yaw=0.0)


def test_duplicate_annotations_are_found_by_hand():
    from seqshape.data.extract import duplicate_objects

    frames = [
        # a and b coincide (2 cm apart), c is a car beside them (2 m), d a van on a's spot
        [_b("a", 10, 0), _b("b", 10.02, 0), _b("c", 10, 2.0), _b("d", 10.1, 0, "van")],
        [_b("a", 11, 0), _b("b", 11.0, 0.03), _b("c", 11, 2.0)],
        [_b("a", 12, 0), _b("c", 12, 2.0)],  # b ends: a has more frames, a stays
        [_b("e", 5, 5), _b("f", 5.4, 5)],  # e and f coincide in their one shared frame
        [_b("e", 6, 5), _b("f", 9, 5)],  # ... but not in the next: 1 of 2 < 90 %
    ]
    assert duplicate_objects(frames) == {"b": "a"}
    # a chain: g~h in the first frame, h~i in the second; i has the most frames and stays
    chain = [[_b("g", 0, 10), _b("h", 0.3, 10)], [_b("h", 1, 10), _b("i", 1.3, 10)],
             [_b("g", 2, 10), _b("h", 2.1, 10), _b("i", 2.2, 10)], [_b("i", 3, 10)],
             [_b("i", 4, 10)]]
    assert duplicate_objects(chain) == {"g": "i", "h": "i"}
    # a tie in frames: the smaller id stays
    assert duplicate_objects([[_b("z", 0, 0), _b("y", 0.1, 0)]]) == {"z": "y"}
    assert duplicate_objects([]) == {} and duplicate_objects([[_b("a", 0, 0)]]) == {}


def test_tracks_leave_a_duplicate_annotation_out(tmp_path, fake, caplog):
    root = tmp_path / "root"
    write_fake_log(root, "d", seed=0)
    path = root / "d.npz"
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    boxes = json.loads(str(arrays.pop("boxes")))
    for rows in boxes.values():  # car0 annotates car1 again, 1 cm away
        twin = dict(rows[0], track_id="car0")
        twin["centre"] = [rows[0]["centre"][0] + 0.01, *rows[0]["centre"][1:]]
        rows.append(twin)
    np.savez(path, boxes=np.array(json.dumps(boxes)), **arrays)
    with caplog.at_level("WARNING"):
        assert _run(root, tmp_path / "out") == 0
    ds = TrackDataset(tmp_path / "out")
    assert ds.track_ids == ["d_car0"]  # a tie in frames: the smaller id stays
    assert ds[0].meta["duplicates"] == ["car1"]
    assert "car1 is a duplicate annotation of car0" in caplog.text
    assert _run(root, tmp_path / "all", "--keep-duplicates") == 0
    assert TrackDataset(tmp_path / "all").track_ids == ["d_car0", "d_car1"]
    assert "duplicates" not in TrackDataset(tmp_path / "all")[0].meta
