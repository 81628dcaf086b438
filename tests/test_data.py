import json

import numpy as np
import pytest

from seqshape.data import Track, TrackDataset, load_track, save_track, write_dataset
from seqshape.errors import DataError


def make_track(track_id="t0", n_frames=5, split="train", seed=0, with_complete=True):
    rng = np.random.default_rng(seed)
    pts = [rng.normal(size=(int(n), 3)).astype(np.float32) for n in rng.integers(0, 40, n_frames)]
    pts[1] = np.zeros((0, 3), np.float32)  # an empty frame
    poses = np.c_[rng.normal(size=(n_frames, 3)), rng.uniform(-3, 3, n_frames)]
    complete = rng.normal(size=(64, 3)).astype(np.float32) if with_complete else None
    return Track(track_id, pts, poses, complete, [4.5, 1.8, 1.5], np.arange(n_frames) * 0.1,
                 {"split": split, "mesh_id": "box"})


def assert_tracks_equal(a, b):
    assert a.track_id == b.track_id and len(a) == len(b)
    for p, q in zip(a.points, b.points, strict=True):
        assert p.dtype == q.dtype == np.float32
        np.testing.assert_array_equal(p, q)
    np.testing.assert_array_equal(a.poses, b.poses)
    np.testing.assert_array_equal(a.timestamps, b.timestamps)
    np.testing.assert_array_equal(a.size, b.size)
    if a.complete is None:
        assert b.complete is None
    else:
        np.testing.assert_array_equal(a.complete, b.complete)
    assert a.meta == b.meta


@pytest.mark.parametrize("with_complete", [True, False])
def test_track_round_trip(tmp_path, with_complete):
    tr = make_track(with_complete=with_complete)
    save_track(tmp_path / "a.npz", tr)
    back = load_track(tmp_path / "a.npz")
    assert_tracks_equal(tr, back)
    assert back.points[1].shape == (0, 3)
    assert list(tmp_path.iterdir()) == [tmp_path / "a.npz"]  # no temp files left behind


def test_complete_in_frame_uses_pose():
    tr = make_track()
    np.testing.assert_allclose(
        tr.complete_in_frame(2)[0],
        tr.complete[0] @ np.array([[np.cos(tr.poses[2, 3]), -np.sin(tr.poses[2, 3]), 0],
                                   [np.sin(tr.poses[2, 3]), np.cos(tr.poses[2, 3]), 0],
                                   [0, 0, 1]]).T + tr.poses[2, :3], rtol=1e-5, atol=1e-5)


def test_track_rejects_mismatched_lengths():
    with pytest.raises(ValueError, match="frames"):
        Track("x", [np.zeros((1, 3))], np.zeros((2, 4)), None, [1, 1, 1], [0.0])


def test_dataset_len_index_split(tmp_path):
    tracks = [make_track(f"t{i}", split="val" if i % 3 == 0 else "train", seed=i) for i in range(7)]
    ds = write_dataset(tmp_path / "ds", tracks, config={"preset": "test"})
    assert len(ds) == 7
    assert_tracks_equal(ds.get("t4"), tracks[4])
    val = ds.split("val")
    assert sorted(val.track_ids) == ["t0", "t3", "t6"]
    assert all(t.split == "val" for t in val)
    assert len(ds.split("train")) == 4
    with pytest.raises(DataError, match="no tracks in split"):
        ds.split("test")
    with pytest.raises(IndexError):
        ds[7]
    m = json.loads((tmp_path / "ds" / "manifest.json").read_text())
    assert m["format"] == "seqshape-tracks" and m["version"] == 1


def test_bad_files_give_clear_errors(tmp_path):
    with pytest.raises(DataError, match="missing manifest"):
        TrackDataset(tmp_path)
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(DataError, match="manifest.json: invalid JSON"):
        TrackDataset(tmp_path)
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"garbage")
    with pytest.raises(DataError, match="bad.npz: unreadable"):
        load_track(bad)
    np.savez(tmp_path / "foreign.npz", x=np.zeros(3))
    with pytest.raises(DataError, match="not a seqshape track"):
        load_track(tmp_path / "foreign.npz")
    with pytest.raises(DataError, match="file not found"):
        load_track(tmp_path / "nope.npz")


def test_union_of_dataset_folders(tmp_path):
    def tr(tid, split):
        return Track(tid, [np.full((2, 3), len(tid), np.float32)], np.zeros((1, 4)), None,
                     np.ones(3), np.zeros(1), {"split": split})

    write_dataset(tmp_path / "a", [tr("a1", "train"), tr("a2", "val")])
    write_dataset(tmp_path / "b", [tr("bb1", "train")])
    u = TrackDataset.union([tmp_path / "a", tmp_path / "b"])
    assert u.track_ids == ["a1", "a2", "bb1"]
    assert u.split("train").track_ids == ["a1", "bb1"]
    np.testing.assert_array_equal(u.get("bb1").points[0], np.full((2, 3), 3))
    assert TrackDataset.union([tmp_path / "a"]).track_ids == ["a1", "a2"]
    write_dataset(tmp_path / "c", [tr("a1", "train")])
    with pytest.raises(DataError, match="a1"):
        TrackDataset.union([tmp_path / "a", tmp_path / "c"])


def test_union_fractions_keep_a_stable_share(tmp_path):
    tracks = [Track(f"t{i:03d}", [np.zeros((1, 3), np.float32)], np.zeros((1, 4)), None,
                    np.ones(3), np.zeros(1), {"split": "train"}) for i in range(400)]
    write_dataset(tmp_path / "a", tracks)
    t0 = tracks[0]
    write_dataset(tmp_path / "b", [Track("b0", t0.points, t0.poses, None, t0.size,
                                         t0.timestamps, {"split": "train"})])
    u = TrackDataset.union([tmp_path / "a", tmp_path / "b"], [0.25, 1.0])
    kept = [t for t in u.track_ids if t.startswith("t")]
    assert 70 < len(kept) < 130 and "b0" in u.track_ids
    assert TrackDataset.union([tmp_path / "a", tmp_path / "b"], [0.25, 1.0]).track_ids == u.track_ids
    smaller = set(TrackDataset.union([tmp_path / "a", tmp_path / "b"], [0.1, 1.0]).track_ids)
    assert smaller < set(u.track_ids)  # a smaller share is a subset of a larger one
    with pytest.raises(ValueError, match="fraction"):
        TrackDataset.union([tmp_path / "a"], [0.0])


# ----------------------------------------------------------------- manifest checks (issue 18)


@pytest.mark.parametrize("change,message", [
    (lambda m: [1, 2], "expected a JSON object, got list"),
    (lambda m: {**m, "version": "1"}, "version must be a positive integer, got '1'"),
    (lambda m: {**m, "version": 1.0}, "version must be a positive integer"),
    (lambda m: {**m, "version": True}, "version must be a positive integer"),
    (lambda m: {k: v for k, v in m.items() if k != "version"}, "version must be"),
    (lambda m: {**m, "version": 2}, "version 2 is newer"),
    (lambda m: {**m, "format": "other"}, "not a seqshape-tracks manifest"),
    (lambda m: {**m, "tracks": {"a": 1}}, "'tracks' must be a list"),
    (lambda m: {**m, "tracks": ["tracks/a.npz"]}, "track entry 0: expected an object"),
    (lambda m: {**m, "tracks": [{"file": "tracks/a.npz"}]}, "lacks 'track_id' or 'file'"),
    (lambda m: {**m, "tracks": [{**m["tracks"][0], "track_id": 7}]}, "track_id must be"),
    (lambda m: {**m, "tracks": [{**m["tracks"][0], "file": ["x"]}]}, "file must be"),
    (lambda m: {**m, "tracks": [{**m["tracks"][0], "n_frames": "5"}]}, "n_frames must be"),
    (lambda m: {**m, "tracks": [{**m["tracks"][0], "has_complete": 1}]}, "has_complete"),
    (lambda m: {**m, "tracks": [{**m["tracks"][0], "split": 3}]}, "split must be"),
    (lambda m: {**m, "tracks": m["tracks"] * 2}, "duplicate track_id 'a'"),
    (lambda m: {**m, "tracks": [{**m["tracks"][0], "file": "../a.npz"}]}, "leaves the dataset"),
])
def test_manifest_content_is_checked(tmp_path, change, message):
    ds = write_dataset(tmp_path / "ds", [make_track("a")])
    mpath = ds.path / "manifest.json"
    mpath.write_text(json.dumps(change(json.loads(mpath.read_text()))))
    with pytest.raises(DataError, match=message) as info:
        TrackDataset(ds.path)
    assert info.value.path == str(mpath)


def test_manifest_encoding_and_old_fields(tmp_path):
    ds = write_dataset(tmp_path / "ds", [make_track("a")])
    mpath = ds.path / "manifest.json"
    good = json.loads(mpath.read_text())
    mpath.write_bytes(b'{"format": "seqshape-tracks\xff"}')
    with pytest.raises(DataError, match="not UTF-8"):
        TrackDataset(ds.path)
    # entries as older releases wrote them: split null, no counts
    good["tracks"] = [{"track_id": "a", "file": "tracks/a.npz", "split": None}]
    mpath.write_text(json.dumps(good))
    assert TrackDataset(ds.path).track_ids == ["a"]
