"""Track ``.npz`` files: the loader checks every array, and malformed files never get past it.

Hand-made malformed files (one per rule, each with the message it must give), round trips of
the writer, and a seeded fuzz test: a few hundred mutated files (byte flips, truncation,
inserted bytes, wrong shapes and dtypes, NaN/inf/huge values, unsorted timestamps, broken
offsets and metadata) each either raise :class:`DataError` naming the file or load as a track
that passes an independent check of the format's rules (:func:`assert_valid`).
"""

from __future__ import annotations

import io
import json
import zipfile

import numpy as np
import pytest

from seqshape.data.track import MAX_COORD, Track, load_track, save_track
from seqshape.errors import DataError

SEED = 20261202


def make_track(seed: int = 0, n_frames: int = 6, complete: bool = True) -> Track:
    rng = np.random.default_rng(seed)
    pts = [(rng.normal(size=(int(n), 3)) + [12, -3, -1]).astype(np.float32)
           for n in rng.integers(1, 30, n_frames)]
    pts[2] = np.zeros((0, 3), np.float32)  # an empty frame
    poses = np.c_[rng.normal(size=(n_frames, 3)) + [12, -3, -1], rng.uniform(-3, 3, n_frames)]
    poses[4] = np.nan  # an unknown pose
    shape = rng.normal(size=(40, 3)).astype(np.float32) if complete else None
    return Track(f"trk{seed}", pts, poses, shape, [4.5, 1.8, 1.5],
                 100.0 + 0.1 * np.arange(n_frames), {"split": "train", "sensor": "vlp16"})


def arrays_of(track: Track) -> dict[str, np.ndarray]:
    """The arrays :func:`save_track` writes for ``track`` (read back from its file)."""
    buf = io.BytesIO()
    np.savez(buf, **_raw(track))
    buf.seek(0)
    with np.load(buf) as z:
        return {k: z[k] for k in z.files}


def _raw(track: Track) -> dict[str, np.ndarray]:
    offsets = np.r_[0, np.cumsum(track.num_points)].astype(np.int64)
    out = {"points": np.concatenate(track.points), "offsets": offsets, "poses": track.poses,
           "timestamps": track.timestamps, "size": track.size,
           "meta": np.array(json.dumps({"track_id": track.track_id, **track.meta})),
           "version": np.array(1, np.int64)}
    if track.complete is not None:
        out["complete"] = track.complete
    return out


def assert_valid(tr: Track) -> None:
    """The format's rules (docs/data-format.md), checked independently of the loader."""
    assert isinstance(tr.track_id, str) and tr.track_id and isinstance(tr.meta, dict)
    t = len(tr.points)
    for p in tr.points:
        assert p.dtype == np.float32 and p.ndim == 2 and p.shape[1] == 3
        assert np.all(np.isfinite(p)) and np.all(np.abs(p) <= MAX_COORD)
    assert tr.poses.dtype == np.float64 and tr.poses.shape == (t, 4)
    known = np.isfinite(tr.poses).all(axis=1)
    assert np.all(known | np.isnan(tr.poses).all(axis=1))
    assert np.all(np.abs(tr.poses[known]) <= MAX_COORD)
    assert tr.timestamps.dtype == np.float64 and tr.timestamps.shape == (t,)
    assert np.all(np.isfinite(tr.timestamps)) and np.all(np.diff(tr.timestamps) > 0)
    assert tr.size.shape == (3,) and np.all(tr.size > 0) and np.all(tr.size <= MAX_COORD)
    if tr.complete is not None:
        c = tr.complete
        assert c.dtype == np.float32 and c.ndim == 2 and c.shape[1] == 3 and len(c) >= 1
        assert np.all(np.isfinite(c)) and np.all(np.abs(c) <= MAX_COORD)


def assert_same(a: Track, b: Track) -> None:
    assert a.track_id == b.track_id and a.meta == b.meta and len(a) == len(b)
    for p, q in zip(a.points, b.points, strict=True):
        assert p.dtype == q.dtype and np.array_equal(p, q)
    for k in ("poses", "timestamps", "size"):
        assert np.array_equal(getattr(a, k), getattr(b, k), equal_nan=True)
    assert (a.complete is None) == (b.complete is None)
    if a.complete is not None:
        assert a.complete.dtype == b.complete.dtype and np.array_equal(a.complete, b.complete)


def load_or_error(path) -> Track | None:
    """The loaded track (checked by :func:`assert_valid`), or None after a DataError naming
    ``path``; any other exception fails the test."""
    try:
        tr = load_track(path)
    except DataError as exc:
        assert exc.path == str(path) and str(path) in str(exc)
        return None
    assert_valid(tr)
    return tr


# ------------------------------------------------------------------------------ round trips
@pytest.mark.parametrize("compressed", [True, False])
@pytest.mark.parametrize("complete", [True, False])
def test_written_tracks_load_unchanged(tmp_path, compressed, complete):
    tr = make_track(1, complete=complete)
    save_track(tmp_path / "t.npz", tr, compressed=compressed)
    back = load_track(tmp_path / "t.npz")
    assert_valid(back)
    assert_same(tr, back)
    assert back.points[2].shape == (0, 3) and np.isnan(back.poses[4]).all()
    back.points[0][0, 0] = 1.0  # writable arrays, as numpy.load gives
    empty = Track("none", [], np.zeros((0, 4)), None, [4, 2, 1.5], [])
    save_track(tmp_path / "e.npz", empty, compressed=compressed)
    assert_same(empty, load_track(tmp_path / "e.npz"))


def test_other_writers_numeric_dtypes_and_fortran_order_load(tmp_path):
    tr = make_track(2)
    arr = arrays_of(tr)
    arr["points"] = np.asfortranarray(arr["points"].astype(np.float64))
    arr["offsets"] = arr["offsets"].astype(np.uint32)
    arr["size"] = np.array([4, 2, 1], np.int16)
    arr["timestamps"] = np.arange(len(tr), dtype=np.int64) * 10 + 5
    del arr["version"]  # optional: version 1
    np.savez(tmp_path / "f.npz", **arr)
    back = load_track(tmp_path / "f.npz")
    assert_valid(back)
    np.testing.assert_array_equal(np.concatenate(back.points), np.concatenate(tr.points))
    assert back.size.tolist() == [4.0, 2.0, 1.0] and back.timestamps[1] == 15.0
    np.savez(tmp_path / "g.npz", extra=np.ones(3), **arrays_of(tr))  # unknown arrays: ignored
    assert_same(tr, load_track(tmp_path / "g.npz"))


# ------------------------------------------------------------------ one rule, one message
def _case(name: str, arr: dict) -> tuple[str, dict]:
    return name, arr


def _malformed() -> list[tuple[str, dict, str]]:
    """(name, arrays, expected message) of files that break one rule each."""
    base = arrays_of(make_track(3))
    t = len(base["timestamps"])

    def w(**changes):
        out = {**base, **changes}
        return {k: v for k, v in out.items() if v is not None}

    unsorted = base["timestamps"].copy()
    unsorted[[1, 3]] = unsorted[[3, 1]]
    partial = base["poses"].copy()
    partial[0, 3] = np.nan
    nan_points = base["points"].copy()
    nan_points[5, 1] = np.nan
    return [
        ("complete (999, 4)", w(complete=np.zeros((999, 4), np.float32)),
         r"complete must have shape \(n, 3\), got \(999, 4\)"),
        ("flat complete", w(complete=np.zeros(999, np.float32)), r"complete must have shape"),
        ("empty complete", w(complete=np.zeros((0, 3), np.float32)), "complete holds no points"),
        ("poses (T, 3)", w(poses=np.zeros((t, 3))), rf"poses must have shape \({t}, 4\)"),
        ("poses too few", w(poses=np.zeros((t - 1, 4))), "poses must have shape"),
        ("points (P, 4)", w(points=np.zeros((len(base["points"]), 4), np.float32)),
         "points must have shape"),
        ("timestamps 2-D", w(timestamps=base["timestamps"][:, None]), "timestamps must have"),
        ("size (4,)", w(size=np.ones(4)), r"size must have shape \(3,\)"),
        ("unsorted timestamps", w(timestamps=unsorted), "not strictly increasing.*frame 2"),
        ("repeated timestamp", w(timestamps=np.r_[base["timestamps"][:2],
                                                  base["timestamps"][1:-1]]),
         "not strictly increasing"),
        ("NaN timestamp", w(timestamps=np.r_[np.nan, base["timestamps"][1:]]), "not all finite"),
        ("NaN point", w(points=nan_points), r"points row 5 holds nan: not finite"),
        ("inf pose", w(poses=np.where(np.isnan(base["poses"]), np.nan, np.inf)),
         "poses row 0 holds inf: not finite"),
        ("partly unknown pose", w(poses=partial), r"row is either finite or all NaN"),
        ("huge point", w(points=base["points"] * 1e5), "beyond 10000 m"),
        ("float64 overflow", w(points=base["points"].astype(np.float64) * 1e300),
         "points row 0 holds .*inf"),
        ("zero size", w(size=np.array([4.0, 0.0, 1.5])), "size .* must be positive"),
        ("negative size", w(size=np.array([-4.0, 1.8, 1.5])), "must be positive"),
        ("bool points", w(points=base["points"] > 0), "points must hold numbers, got dtype bool"),
        ("complex poses", w(poses=base["poses"].astype(complex)), "poses must hold numbers"),
        ("string timestamps", w(timestamps=base["timestamps"].astype(str)),
         "timestamps must hold numbers"),
        ("float offsets", w(offsets=base["offsets"].astype(float)), "offsets must be"),
        ("offsets past the end", w(offsets=base["offsets"] + 1), "offsets do not index"),
        ("offsets falling", w(offsets=base["offsets"][::-1]), "offsets do not index"),
        ("meta not JSON", w(meta=np.array("{oops")), "corrupt track metadata"),
        ("meta a list", w(meta=np.array("[1, 2]")), "meta must be a JSON object, got list"),
        ("meta nested deep", w(meta=np.array("[" * 100_000 + "]" * 100_000)),
         "corrupt track metadata"),
        ("meta bytes", w(meta=np.array(b"{}")), "meta must be a JSON string"),
        ("track_id a number", w(meta=np.array('{"track_id": 7}')),
         "track_id must be a non-empty string"),
        ("newer version", w(version=np.array(2)), "version 2 is newer"),
        ("version 0", w(version=np.array(0)), "version 0 does not exist"),
        ("version float", w(version=np.array(1.0)), "version must be an integer scalar"),
        ("missing poses", w(poses=None), r"missing arrays \['poses'\]"),
        ("pickled objects", w(points=np.array([None, "x"], dtype=object)),
         "holds Python objects"),
    ]


@pytest.mark.parametrize(("name", "arrays", "message"), _malformed(),
                         ids=[c[0] for c in _malformed()])
def test_each_rule_gives_a_clear_error(tmp_path, name, arrays, message):
    path = tmp_path / "bad.npz"
    np.savez(path, **arrays)
    with pytest.raises(DataError, match=message) as info:
        load_track(path)
    assert info.value.path == str(path)


def _npy(header: dict | str, data: bytes = b"", version: int = 1) -> bytes:
    text = header if isinstance(header, str) else repr(header)
    text += " " * (63 - len(text) % 64) + "\n"
    size = len(text).to_bytes(2 if version == 1 else 4, "little")
    return b"\x93NUMPY" + bytes([version, 0]) + size + text.encode("latin1") + data


def _zip(path, members: list[tuple[str, bytes]]) -> None:
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in members:
            zf.writestr(name, data)


def _members(track: Track, **replace: bytes) -> list[tuple[str, bytes]]:
    out = []
    for k, v in arrays_of(track).items():
        buf = io.BytesIO()
        np.save(buf, v)
        out.append((f"{k}.npy", replace.get(k, buf.getvalue())))
    return out


def test_corrupt_archives_and_absurd_headers(tmp_path):
    tr = make_track(4)
    good = tmp_path / "good.npz"
    save_track(good, tr)
    data = good.read_bytes()
    huge = {"descr": "<f4", "fortran_order": False, "shape": (10 ** 12, 3)}
    cases = {
        "truncated": (data[: len(data) // 2], "unreadable track file"),
        "not a zip": (b"hello world" * 10, "unreadable track file.*BadZipFile"),
        "empty": (b"", "unreadable track file"),
    }
    for name, (content, message) in cases.items():
        path = tmp_path / f"{name}.npz"
        path.write_bytes(content)
        with pytest.raises(DataError, match=message):
            load_track(path)
    built = {
        "absurd shape": (_members(tr, points=_npy(huge, b"\0" * 12)),
                         r"header declares float32 \(1000000000000, 3\)"),
        "short data": (_members(tr, points=_npy({**huge, "shape": (50, 3)}, b"\0" * 12)),
                       r"declares float32 \(50, 3\) \(600 bytes\) but the archive holds 12"),
        "negative shape": (_members(tr, points=_npy({**huge, "shape": (-1, -3)}, b"\0" * 12)),
                           "negative shape"),
        "header too long": (_members(tr, points=_npy(repr(huge) + " " * 70_000, version=2)),
                            "unreadable track file.*ValueError"),
        "bad header": (_members(tr, points=_npy("{'descr': <f4}")), "unreadable track file"),
        "bad dtype": (_members(tr, points=_npy({**huge, "descr": "<q9", "shape": (1,)}, b"1")),
                      "unreadable track file"),
        "npy version 9": (_members(tr, points=b"\x93NUMPY\x09\x00" + b"\0" * 20),
                          "unreadable track file|unsupported"),
        "twice": (_members(tr) + [("points.npy", _members(tr)[0][1])], "holds array 'points' twice"),
    }
    for name, (members, message) in built.items():
        path = tmp_path / f"{name}.npz"
        with pytest.warns(UserWarning) if name == "twice" else _nothing():
            _zip(path, members)
        with pytest.raises(DataError, match=message) as info:
            load_track(path)
        assert info.value.path == str(path), name
    with pytest.raises(DataError, match="file not found"):
        load_track(tmp_path / "missing.npz")


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_crc_is_checked(tmp_path):
    """A flipped byte inside an array's data (a stored member: no compression to notice it)
    is caught by the archive's CRC."""
    path = tmp_path / "t.npz"
    save_track(path, make_track(5), compressed=False)
    data = bytearray(path.read_bytes())
    pos = data.index(b"\x93NUMPY") + 200  # inside the first array's data
    data[pos] ^= 0x10
    path.write_bytes(bytes(data))
    with pytest.raises(DataError, match="Bad CRC-32"):
        load_track(path)


def test_writer_refuses_what_the_loader_refuses(tmp_path):
    tr = make_track(6)
    tr.timestamps[3] = tr.timestamps[1]
    with pytest.raises(DataError, match="refusing to write an invalid track 'trk6': timestamps"):
        save_track(tmp_path / "t.npz", tr)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="complete must have 3 columns"):
        Track("x", [np.zeros((1, 3))], np.zeros((1, 4)), np.zeros((999, 4)), [1, 1, 1], [0.0])
    with pytest.raises(ValueError, match="poses must have 4 columns"):
        Track("x", [np.zeros((1, 3))], np.zeros((1, 3)), None, [1, 1, 1], [0.0])


def test_generated_dataset_loads(tmp_path):
    """Every track ``seqshape generate --preset tiny`` writes passes the checks."""
    from seqshape.cli import main
    from seqshape.data import TrackDataset

    assert main(["generate", "--preset", "tiny", "--out", str(tmp_path / "d")]) == 0
    ds = TrackDataset(tmp_path / "d")
    assert len(ds) > 0
    for tr in ds:
        assert_valid(tr)


# ------------------------------------------------------------------------------------ fuzz
def _byte_mutation(rng, data: bytes) -> bytes:
    b = bytearray(data)
    op = rng.integers(4)
    if op == 0:  # flip 1-8 bytes
        for pos in rng.integers(0, len(b), rng.integers(1, 9)):
            b[pos] ^= int(rng.integers(1, 256))
    elif op == 1:  # truncate
        del b[int(rng.integers(0, len(b))):]
    elif op == 2:  # insert bytes
        pos = int(rng.integers(0, len(b)))
        b[pos:pos] = rng.bytes(int(rng.integers(1, 16)))
    else:  # overwrite a range with 0x00 or 0xff
        pos = int(rng.integers(0, len(b)))
        b[pos:pos + int(rng.integers(1, 64))] = bytes([0xFF * int(rng.integers(2))]) * 64
    return bytes(b)


_KEYS = ("points", "offsets", "poses", "timestamps", "size", "complete", "meta", "version")
_VALUES = (np.nan, np.inf, -np.inf, 1e30, -1e300, 2.0 ** 70)


def _array_mutation(rng, arr: dict) -> tuple[dict, bool]:
    """One array of ``arr`` broken; returns (arrays, whether the file must be refused)."""
    arr = dict(arr)
    key = _KEYS[rng.integers(len(_KEYS))]
    a = arr[key]
    op = int(rng.integers(6))
    if key == "meta":
        arr[key] = np.array(["{", "[]", "null", '{"track_id": []}', '{"track_id": ""}',
                             "[" * 5000, '"text"'][rng.integers(7)])
        return arr, True
    if key == "version":
        arr[key] = np.array([2, -1, 0, 99][rng.integers(4)]) if op < 4 else np.array("1")
        return arr, True
    if op == 0:  # wrong shape
        shapes = [a.reshape(-1), a.reshape(1, -1), a[..., None], a.reshape(-1)[:-1]]
        if a.ndim == 2:
            shapes += [a[:, :-1], np.c_[a, a[:, :1]], a.T]
        new = shapes[rng.integers(len(shapes))]
        arr[key] = new
        return arr, new.shape != a.shape
    if op == 1:  # wrong dtype
        dtype = [bool, complex, "U8", "S4", object, "M8[s]", [("a", "<f4")]][rng.integers(7)]
        arr[key] = np.array(a.tolist(), dtype=object) if dtype is object else \
            np.zeros(a.shape, dtype)
        return arr, True
    if op == 2 and a.size:  # a non-finite or huge value
        new = a.astype(np.float64)
        i, value = int(rng.integers(a.size)), _VALUES[rng.integers(len(_VALUES))]
        new.reshape(-1)[i] = value
        arr[key] = new
        # harmless only as NaN in a pose row that was all NaN already (an unknown pose)
        unknown = key == "poses" and np.isnan(a[i // 4]).all() and np.isnan(value)
        return arr, not unknown
    if op == 3 and key in ("timestamps", "offsets") and a.size > 2:  # order broken
        new = a.copy()
        i = int(rng.integers(1, a.size - 1))
        new[i], new[i + 1] = new[i + 1], new[i]
        arr[key] = new
        return arr, not np.array_equal(new, a)
    if op == 4:  # missing (optional ones may go)
        del arr[key]
        return arr, key != "complete"
    arr[key] = a.astype(np.float32 if a.dtype.kind == "f" else np.int32)  # other numeric dtype
    return arr, False


def test_fuzz_mutated_files_are_refused_or_valid(tmp_path):
    rng = np.random.default_rng(SEED)
    bases = []
    for i, compressed in enumerate((True, False)):
        path = tmp_path / f"base{i}.npz"
        save_track(path, make_track(10 + i), compressed=compressed)
        bases.append(path.read_bytes())
    arrays = [arrays_of(make_track(20 + i)) for i in range(3)]
    refused = loaded = 0
    for case in range(400):
        path = tmp_path / f"case{case:03d}.npz"
        if case % 2:
            path.write_bytes(_byte_mutation(rng, bases[case % 4 // 2]))
            must_fail = False
        else:
            arr, must_fail = _array_mutation(rng, arrays[case % 3])
            (np.savez_compressed if case % 4 else np.savez)(path, **arr)
        tr = load_or_error(path)
        assert not (must_fail and tr is not None), f"case {case}: garbage accepted"
        refused += tr is None
        loaded += tr is not None
    assert refused > 200 and loaded > 10  # both outcomes were exercised
