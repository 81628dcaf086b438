"""Malformed input against every driving-log reader (issue 18, item 10).

Each reader gets a few hundred seeded mutations of a valid file (truncation, flipped bytes,
NaN / inf / huge values, wrong column counts, wrong types, empty files, non-UTF-8 bytes) and
must either refuse it with the project's own :class:`DataError` naming the file (and, for the
KITTI text formats, the line) or return a result that is provably valid. For the text formats
"provably valid" is checked against an independent restatement of the format's rules
(``_label_row_ok`` ...): the reader must refuse exactly the files the restatement refuses, at
the line it names, and return every row otherwise. For the binary and tabular formats the
result is checked against the file read independently (numpy, pyarrow, json). Hand-made cases
cover each refusal once more, by name.
"""

from __future__ import annotations

import json
import math
import re
import warnings
from pathlib import Path

import _av2_fixture as av2fx
import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest
from _nuscenes_fixture import write_nuscenes

from seqshape.camera import kitti_default_calib, read_calib, write_calib
from seqshape.data import nuscenes as ns
from seqshape.data.av2 import Av2Log
from seqshape.data.kitti import (
    KittiLabel,
    KittiTrackingSequence,
    poses_to_oxts,
    read_labels,
    read_oxts,
    read_velodyne,
    write_labels,
    write_oxts,
    write_velodyne,
)
from seqshape.data.nuscenes import NuScenesLog, read_pcd_bin
from seqshape.errors import DataError

JUNK = ["nan", "NaN", "inf", "-inf", "1e308", "-1e39", "1e999", "abc", "0x1F", "1.5", "-7",
        "0", "-1", "1e6", "3", "-0.0", "4e-320", "1_0", "\u0661"]


# ----------------------------------------------------------------------------- mutations


def put(path: Path, data: bytes) -> None:
    """Write ``data`` as a new file (removing the old one first: truncating a file in place
    costs milliseconds on ext4, a new file microseconds)."""
    path.unlink(missing_ok=True)
    path.write_bytes(data)


def mutate_text(data: bytes, rng: np.random.Generator) -> bytes:
    """One random mutation of a whitespace-separated text file."""
    kind = int(rng.integers(0, 9))
    if kind == 0:
        return data[: int(rng.integers(0, len(data)))]
    if kind == 1:
        b = bytearray(data)
        for _ in range(int(rng.integers(1, 4))):
            b[int(rng.integers(0, len(b)))] ^= int(rng.integers(1, 256))
        return bytes(b)
    if kind == 5:
        j = int(rng.integers(0, len(data)))
        return data[:j] + b"\xff\xfe" + data[j:]
    if kind == 6:
        return b""
    lines = data.decode().splitlines()
    i = int(rng.integers(0, len(lines)))
    tokens = lines[i].split()
    j = int(rng.integers(0, len(tokens)))
    if kind in (2, 8):
        tokens[j] = str(rng.choice(JUNK))
    elif kind == 3:
        del tokens[j]
    elif kind == 4:
        tokens.insert(j, tokens[j])
    else:  # 7: a line twice
        lines.insert(i, lines[i])
    lines[i] = " ".join(tokens) if kind != 7 else lines[i]
    return ("\n".join(lines) + "\n").encode()


def expect_text(reader, path: Path, data: bytes, first_bad_line):
    """Run ``reader`` on ``data`` written to ``path``: a DataError naming the file at the line
    the reference names, or a result when the reference finds nothing wrong."""
    put(path, data)
    try:
        text = data.decode()
    except UnicodeDecodeError:
        with pytest.raises(DataError) as err:
            reader(path)
        assert err.value.path == str(path)
        return None
    bad = first_bad_line(text) if "\0" not in text else nul_line(text)
    if bad is None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return reader(path)
    with pytest.raises(DataError) as err:
        reader(path)
    assert err.value.path == str(path), err.value
    if bad is not True:  # True: a whole-file problem (no line)
        assert err.value.line == bad, (err.value, bad)
    return None


def nul_line(text: str) -> int:
    """The line of the first NUL character: every text reader refuses one (issue 45: a
    calibration key glued to its numbers by NULs was skipped as an unknown key)."""
    return len((text[:text.index("\0")] + "x").splitlines())


def _numbers(tokens):
    try:
        values = [float(t) for t in tokens]
    except ValueError:
        return None
    return values if all(math.isfinite(v) for v in values) else None


# ----------------------------------------------------------------------------- label_02


def _label_row_ok(tok: list[str]) -> bool:
    """The label_02 rules, restated (docs/kitti.md, "What the readers refuse")."""
    if len(tok) not in (17, 18):
        return False
    try:
        frame, track = int(tok[0]), int(tok[1])
    except ValueError:
        return False
    if max(len(tok[0]), len(tok[1])) > 20:
        return False
    v = _numbers(tok[3:])
    if v is None or not 0 <= frame <= 999_999 or not -1 <= track <= 999_999:
        return False
    left, top, right, bottom = v[3:7]
    if not (-1 <= v[0] <= 2 and v[1] in (-1, 0, 1, 2, 3) and left <= right and top <= bottom
            and max(map(abs, v[3:7])) <= 1e5):
        return False
    if tok[2] == "DontCare" or track < 0:
        return True
    return (all(0 < d <= 30 for d in v[7:10]) and np.linalg.norm(v[10:13]) <= 1000
            and abs(v[2]) <= 2 * np.pi and abs(v[13]) <= 2 * np.pi)


def _label_first_bad(text: str):
    seen = set()
    for lineno, line in enumerate(text.splitlines(), start=1):
        tok = line.split()
        if not tok:
            continue
        if not _label_row_ok(tok):
            return lineno
        if tok[2] != "DontCare" and int(tok[1]) >= 0:
            if (int(tok[0]), int(tok[1])) in seen:
                return lineno
            seen.add((int(tok[0]), int(tok[1])))
    return None


GOOD_LABELS = (
    "0 -1 DontCare -1 -1 -10.000000 219.310000 188.490000 245.500000 218.560000 -1000.000000 "
    "-1000.000000 -1000.000000 -10.000000 -1.000000 -1.000000 -1.000000\n"
    "0 0 Van 0 0 -1.793451 296.744956 161.752147 455.226042 292.372804 2.000000 1.823255 "
    "4.433886 -4.552284 1.858523 13.410495 -2.115488\n"
    "0 1 Cyclist 0 0 -1.936993 737.619499 161.531951 931.112229 374.000000 1.739063 0.824591 "
    "1.785241 1.640400 1.675660 5.776261 -1.675458\n"
    "1 0 Van 0 1 -1.796862 294.898777 156.024256 452.199718 284.621269 2.000000 1.823255 "
    "4.433886 -4.650955 1.766774 13.581085 -2.121565\n"
    "2 0 Van 1 2 -1.800273 292.962000 150.308000 449.223000 276.869000 2.000000 1.823255 "
    "4.433886 -4.749626 1.675025 13.751675 -2.127643\n"
    "2 3 Car 0.25 3 1.550000 600.000000 170.000000 700.000000 230.000000 1.500000 1.600000 "
    "3.900000 0.500000 1.700000 20.000000 1.570000 0.875000\n"
)


def test_fuzz_label_02(tmp_path):
    rng = np.random.default_rng(18)
    good = GOOD_LABELS.encode()
    assert len(read_labels_from(tmp_path / "ok.txt", good)) == 6
    accepted = refused = 0
    for i in range(400):
        data = mutate_text(good, rng)
        out = expect_text(read_labels, tmp_path / f"l{i % 7}.txt", data, _label_first_bad)
        if out is None:
            refused += 1
            continue
        accepted += 1
        rows = [line.split() for line in data.decode().splitlines() if line.split()]
        assert len(out) == len(rows)  # nothing dropped silently
        for lab, tok in zip(out, rows, strict=True):
            assert (lab.frame, lab.track_id, lab.type) == (int(tok[0]), int(tok[1]), tok[2])
            np.testing.assert_array_equal(lab.location, [float(t) for t in tok[13:16]])
    assert accepted > 40 and refused > 200


def read_labels_from(path: Path, data: bytes):
    put(path, data)
    return read_labels(path)


@pytest.mark.parametrize("line, match", [
    ("0 0 Car 0 0 0.1 10 10 50 50 1.5 1.6 nan 1 1.7 20 0.1", "length is not finite"),
    ("0 0 Car 0 0 0.1 10 10 50 50 1.5 1.6 3.9 1 1.7 inf 0.1", "z is not finite"),
    ("0 0 Car 0 inf 0.1 10 10 50 50 1.5 1.6 3.9 1 1.7 20 0.1", "occluded is not finite"),
    ("0 0 Car 0 5 0.1 10 10 50 50 1.5 1.6 3.9 1 1.7 20 0.1", "occluded must be an integer"),
    ("0 0 Car 0 1.5 0.1 10 10 50 50 1.5 1.6 3.9 1 1.7 20 0.1", "occluded must be an integer"),
    ("0 0 Car 7 0 0.1 10 10 50 50 1.5 1.6 3.9 1 1.7 20 0.1", r"truncated must be in \[-1, 2\]"),
    ("0 0 Car 0 0 0.1 10 10 50 50 -1.5 1.6 3.9 1 1.7 20 0.1", r"each must be in \(0, 30\]"),
    ("0 0 Car 0 0 0.1 10 10 50 50 1.5 1.6 0 1 1.7 20 0.1", r"each must be in \(0, 30\]"),
    ("0 0 Car 0 0 0.1 10 10 50 50 1.5 1.6 31 1 1.7 20 0.1", r"each must be in \(0, 30\]"),
    ("0 0 Car 0 0 0.1 10 10 50 50 1.5 1.6 3.9 1 1.7 1200 0.1", "more than 1000 m"),
    ("0 0 Car 0 0 0.1 10 10 50 50 1.5 1.6 3.9 1 1.7 20 90", "rotation_y 90 rad"),
    ("0 0 Car 0 0 0.1 50 10 10 50 1.5 1.6 3.9 1 1.7 20 0.1", "left <= right"),
    ("0 0 Car 0 0 0.1 10 10 50 50 1.5 1.6 3.9 1 1.7 20", "expected 17 or 18 columns, got 16"),
    ("0.5 0 Car 0 0 0.1 10 10 50 50 1.5 1.6 3.9 1 1.7 20 0.1", "frame must be an integer"),
    ("0 x Car 0 0 0.1 10 10 50 50 1.5 1.6 3.9 1 1.7 20 0.1", "track_id must be an integer"),
    ("0 -2 Car 0 0 0.1 10 10 50 50 1.5 1.6 3.9 1 1.7 20 0.1", r"track_id must be in -1\.\.999999"),
    ("-1 0 Car 0 0 0.1 10 10 50 50 1.5 1.6 3.9 1 1.7 20 0.1", r"frame -1 is not in 0\.\.999999"),
    ("1000000 0 Car 0 0 0.1 10 10 50 50 1.5 1.6 3.9 1 1.7 20 0.1", "frame 1000000 is not in"),
    ("0 0 Car 0 0 0.1 10 10 50 50 1.5 1.6 3.9 1 1.7 20 0.1 nan", "score is not finite"),
    ("0 0 Car 0 0 abc 10 10 50 50 1.5 1.6 3.9 1 1.7 20 0.1", "bad number"),
    ("2 3 Car 0 0 0.1 10 10 50 50 1.5 1.6 3.9 1 1.7 20 0.1", "track 3 appears twice in frame 2 "
                                                            r"\(first on line 6\)"),
])
def test_label_refusals(tmp_path, line, match):
    path = tmp_path / "0003.txt"
    path.write_text(GOOD_LABELS + line + "\n")
    with pytest.raises(DataError, match=match) as err:
        read_labels(path)
    assert err.value.line == 7 and str(err.value).startswith(f"{path}:7: ")


def test_dontcare_sentinels_and_unknown_types(tmp_path, caplog):
    # DontCare rows keep KITTI's -1 / -1000 / -10 sentinels (as in the official files)
    labels = read_labels_from(tmp_path / "a.txt", GOOD_LABELS.encode())
    assert labels[0].is_dontcare and labels[0].dimensions.tolist() == [-1000.0] * 3
    assert labels[0].location.tolist() == [-10.0, -1.0, -1.0] and labels[0].occluded == -1
    # ... but even a DontCare row must hold finite numbers
    path = tmp_path / "b.txt"
    path.write_text(GOOD_LABELS.replace("-1000.000000 -1000.000000 -1000.000000",
                                        "nan -1000 -1000", 1))
    with pytest.raises(DataError, match=r"b\.txt:1: height is not finite"):
        read_labels(path)
    # a type KITTI does not define is read, with one warning for the file
    path.write_text(GOOD_LABELS.replace("Cyclist", "Hovercraft"))
    with caplog.at_level("WARNING"):
        assert [lab.type for lab in read_labels(path)][2] == "Hovercraft"
    assert "Hovercraft" in caplog.text and str(path) in caplog.text
    # what seqshape writes reads back (write -> read is the identity on valid labels)
    write_labels(tmp_path / "c.txt", labels)
    assert len(read_labels(tmp_path / "c.txt")) == 6


# ----------------------------------------------------------------------------- calibration


_CALIB_KEYS = {"P0": 12, "P1": 12, "P2": 12, "P3": 12, "R_rect": 9, "R0_rect": 9,
               "R_rect_00": 9, "Tr_velo_cam": 12, "Tr_velo_to_cam": 12, "Tr_imu_velo": 12,
               "Tr_imu_to_velo": 12}
_CANON = {"R0_rect": "R_rect", "R_rect_00": "R_rect", "Tr_velo_to_cam": "Tr_velo_cam",
          "Tr_imu_to_velo": "Tr_imu_velo"}


def _is_rotation(r) -> bool:
    r = np.asarray(r).reshape(3, 3)
    with np.errstate(over="ignore", invalid="ignore"):
        return bool(np.abs(r.T @ r - np.eye(3)).max() <= 1e-3
                    and abs(np.linalg.det(r) - 1) <= 1e-3)


def _calib_first_bad(text: str):
    found = set()
    for lineno, line in enumerate(text.splitlines(), start=1):
        tok = line.split()
        if not tok or tok[0].rstrip(":") not in _CALIB_KEYS:
            continue
        key = tok[0].rstrip(":")
        canon = _CANON.get(key, key)
        v = _numbers(tok[1:])
        if v is None or len(v) != _CALIB_KEYS[key] or canon in found:
            return lineno
        found.add(canon)
        m = np.array(v)
        if canon == "R_rect":
            ok = _is_rotation(m)
        elif canon.startswith("P"):
            ok = np.abs(m).max() <= 1e5 and np.linalg.cond(m.reshape(3, 4)[:, :3]) <= 1e10
        else:
            ok = _is_rotation(m.reshape(3, 4)[:, :3]) and np.abs(m.reshape(3, 4)[:, 3]).max() <= 100
        if not ok:
            return lineno
    return None if {"P2", "R_rect", "Tr_velo_cam"} <= found else True


def test_fuzz_calib(tmp_path):
    rng = np.random.default_rng(180)
    write_calib(tmp_path / "good.txt", kitti_default_calib())
    good = (tmp_path / "good.txt").read_bytes()
    accepted = 0
    for i in range(300):
        data = mutate_text(good, rng)
        out = expect_text(read_calib, tmp_path / f"c{i % 5}.txt", data, _calib_first_bad)
        if out is not None:
            accepted += 1
            for name in ("P2", "R_rect", "Tr_velo_cam"):
                assert np.all(np.isfinite(getattr(out, name)))
            assert _is_rotation(out.R_rect) and _is_rotation(out.Tr_velo_cam[:, :3])
    assert accepted > 10


@pytest.mark.parametrize("key, values, match", [
    ("R_rect", "1 0 0 0 1 0 0 0 0", r"R_rect: not a rotation: .*det = 0"),  # rank 2
    ("R_rect", "1 0 0 0 1 0 0 0 -1", "det = -1"),  # a reflection
    ("R_rect", "2 0 0 0 2 0 0 0 2", r"not a rotation: max \|R\^T R - I\| = 3"),
    ("R_rect", "1 0 0 0 1 0 0 0 nan", "R_rect: non-finite value"),
    ("R_rect", "1 0 0 0 1 0 0 0", "R_rect: expected 9 numbers, got 8"),
    ("Tr_velo_cam", "0 -1 0 0 0 0 -1 0 1 0 0.01 0", "Tr_velo_cam: not a rotation"),
    ("Tr_velo_cam", "0 -1 0 0 0 0 -1 0 1 0 0 500", "translation .* beyond 100 m"),
    ("Tr_imu_velo", "1 0 0 0 0 1 0 0 0 0 2 0", "Tr_imu_velo: not a rotation"),
    ("P2:", "700 0 600 0 0 0 0 0 0 0 1 0", "P2: the intrinsic block P.* is singular"),
    ("P2:", "700 0 600 0 0 700 180 0 0 0 1 inf", "P2: non-finite value"),
])
def test_calib_refusals(tmp_path, key, values, match):
    lines = {"P2:": "700 0 600 0 0 700 180 0 0 0 1 0", "R_rect": "1 0 0 0 1 0 0 0 1",
             "Tr_velo_cam": "0 -1 0 0 0 0 -1 0 1 0 0 0", "Tr_imu_velo": "1 0 0 0 0 1 0 0 0 0 1 0"}
    lines[key] = values
    path = tmp_path / "0007.txt"
    path.write_text("".join(f"{k} {v}\n" for k, v in lines.items()))
    with pytest.raises(DataError, match=match) as err:
        read_calib(path)
    assert err.value.path == str(path) and err.value.line == list(lines).index(key) + 1


# ----------------------------------------------------------------------------- oxts


def _oxts_first_bad(text: str):
    for lineno, line in enumerate(text.splitlines(), start=1):
        tok = line.split()
        if not tok:
            continue
        v = _numbers(tok)
        if (v is None or len(v) != 30 or not -90 < v[0] < 90 or not -180 <= v[1] <= 180
                or abs(v[2]) > 1e5 or max(abs(a) for a in v[3:6]) > 2 * np.pi
                or any(s < 0 or not s.is_integer() for s in v[25:30])):
            return lineno
    return None


def _good_oxts(tmp_path) -> bytes:
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, 0, 3] = [0.0, 1.0, 2.1, 3.3]
    rows = poses_to_oxts(poses)
    rows[:, 6:25] = np.random.default_rng(3).normal(size=(4, 19))
    write_oxts(tmp_path / "good.txt", rows)
    return (tmp_path / "good.txt").read_bytes()


def test_fuzz_oxts(tmp_path):
    rng = np.random.default_rng(1800)
    good = _good_oxts(tmp_path)
    accepted = 0
    for i in range(300):
        data = mutate_text(good, rng)
        out = expect_text(read_oxts, tmp_path / f"o{i % 5}.txt", data, _oxts_first_bad)
        if out is not None:
            accepted += 1
            rows = [line.split() for line in data.decode().splitlines() if line.split()]
            np.testing.assert_array_equal(out, np.array(rows, dtype=float).reshape(-1, 30))
    assert accepted > 20


@pytest.mark.parametrize("col, value, match", [
    (0, "nan", "lat is not finite"), (0, "91", r"latitude 91 is not in \(-90, 90\)"),
    (0, "-90", r"latitude -90 is not in \(-90, 90\)"), (1, "181", "longitude 181"),
    (2, "1e9", "altitude"), (5, "1e3", "yaw 1000 rad"), (10, "inf", "vu is not finite"),
    (26, "2.5", "numsats must be a non-negative integer"), (25, "-1", "navstat"),
])
def test_oxts_refusals(tmp_path, col, value, match):
    lines = _good_oxts(tmp_path).decode().splitlines()
    tok = lines[2].split()
    tok[col] = value
    lines[2] = " ".join(tok)
    path = tmp_path / "0001.txt"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=match) as err:
        read_oxts(path)
    assert err.value.path == str(path) and err.value.line == 3
    path.write_text(" ".join(lines[0].split()[:29]) + "\n")
    with pytest.raises(DataError, match="expected 30 oxts columns, got 29"):
        read_oxts(path)


# ----------------------------------------------------------------------------- point files


def mutate_bytes(data: bytes, rng: np.random.Generator) -> bytes:
    kind = int(rng.integers(0, 4))
    if kind == 0:
        return data[: int(rng.integers(0, len(data)))]
    if kind == 1:
        return data + bytes(rng.integers(0, 256, int(rng.integers(1, 20)), dtype=np.uint8))
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 6))):
        if kind == 2:  # flip a byte
            b[int(rng.integers(0, len(b)))] ^= int(rng.integers(1, 256))
        else:  # write a NaN, an infinity or a huge value over one float
            j = 4 * int(rng.integers(0, len(b) // 4))
            b[j:j + 4] = np.array(rng.choice([np.nan, np.inf, -np.inf, 3e38]), "<f4").tobytes()
    return bytes(b)


def _sweep(rng, n: int, columns: int) -> np.ndarray:
    """A plausible sweep: coordinates within 100 m, a reflectance in [0, 1], ring 0-31."""
    pts = np.c_[rng.normal(0, 20, (n, 3)), rng.random(n)]
    if columns == 5:
        pts = np.c_[pts, rng.integers(0, 32, n)]
    return pts.astype("<f4")


def _impossible_points(ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(finite, impossible)`` rows of ``ref`` by the sweep rules restated (docs/datasets.md):
    a coordinate beyond 1000 m or a negative reflectance / intensity (column 3)."""
    finite = np.isfinite(ref).all(1)
    with np.errstate(invalid="ignore"):
        impossible = finite & ((np.abs(ref[:, :3]) > 1000).any(1) | (ref[:, 3] < 0))
    return finite, impossible


@pytest.mark.parametrize("reader, columns", [(read_velodyne, 4), (read_pcd_bin, 5)])
def test_fuzz_point_files(tmp_path, reader, columns):
    rng = np.random.default_rng(columns)
    good = _sweep(rng, 200, columns).tobytes()
    warned = refused = 0
    for i in range(300):
        data = mutate_bytes(good, rng)
        path = tmp_path / f"p{i % 3}.bin"
        put(path, data)
        if len(data) % (4 * columns):
            with pytest.raises(DataError, match=re.escape(f"{path}: size {len(data)} bytes is "
                                                          f"not a multiple of {4 * columns}")):
                reader(path)
            continue
        ref = np.frombuffer(data, "<f4").reshape(-1, columns)
        finite, impossible = _impossible_points(ref)
        if impossible.sum() > 0.01 * finite.sum():
            with pytest.raises(DataError, match="impossible") as err:
                reader(path)
            assert err.value.path == str(path)
            refused += 1
            continue
        keep = finite & ~impossible
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            out = reader(path)
        np.testing.assert_array_equal(out, ref[keep])
        assert out.dtype == np.float32 and out.flags.writeable
        if keep.all():
            assert not caught
        else:
            warned += 1
            assert len(caught) == 1
            why = "with a non-finite value" + ("" if not impossible.any() else ", a coordinate")
            assert str(caught[0].message).startswith(
                f"{path}: dropped {int((~keep).sum())} of {len(ref)} points {why}")
    assert warned > 40 and refused >= 3
    with pytest.raises(DataError, match="not found"):
        reader(tmp_path / "missing.bin")


def test_velodyne_tail_bytes_are_refused(tmp_path):
    for extra in (1, 2, 3):  # 16k + 1..3 bytes passed before, the tail dropped
        path = tmp_path / f"v{extra}.bin"
        path.write_bytes(b"\0" * (32 + extra))
        with pytest.raises(DataError, match=f"size {32 + extra} bytes is not a multiple of 16"):
            read_velodyne(path)


# ----------------------------------------------------------------------------- Argoverse 2


def _av2_run(fx, tmp_path):
    """Everything the reader offers on the log (errors propagate)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        log = Av2Log(tmp_path, fx.path.name)
        return log, [log.points(f) for f in log.frames], [log.boxes(f) for f in log.frames], \
            [log.ego_pose(f) for f in log.frames], [log.camera(c, 0) for c in log.camera_names]


def _check_av2_result(fx, result):
    """A result the reader returned is valid: finite, sane, and nothing dropped silently."""
    log, points, boxes, poses, cameras = result
    ann = feather.read_table(str(fx.path / "annotations.feather"))
    stamps = ann["timestamp_ns"].to_numpy()
    for f, bs in enumerate(boxes):
        assert len(bs) == int(np.sum(stamps == log.sweep_ns[f]))
        for b in bs:
            assert np.all(np.isfinite(b.centre)) and np.isfinite(b.yaw)
            assert np.all((b.size > 0) & (b.size <= 30)) and np.linalg.norm(b.centre) <= 1000
    for f, pts in enumerate(points):
        sweep = feather.read_table(str(log.sweep_path(f)))
        xyz = np.stack([sweep[c].to_numpy().astype(float) for c in "xyz"], 1) - log.lidar_offset
        xyz = xyz.astype(np.float32)
        with np.errstate(invalid="ignore"):
            keep = np.isfinite(xyz).all(1) & (np.abs(xyz) <= 1000).all(1)
        assert len(pts) == int(keep.sum())
        assert np.all(np.isfinite(pts)) and np.all(np.abs(pts[:, :3]) <= 1000)
    for m in [p for p in poses if p is not None] + [c.T_cam_sensor for c in cameras]:
        assert np.all(np.isfinite(m))
        np.testing.assert_allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-9)


_AV2_VALUES = [np.nan, np.inf, -np.inf, 1e300, -5.0, 0.0, 1e5, 31.0, 2.0, -1.0]


def _mutate_table(table: pa.Table, rng: np.random.Generator) -> pa.Table:
    """One value-level mutation of a Feather table."""
    kind = int(rng.integers(0, 5))
    j = int(rng.integers(0, table.num_columns))
    name = table.column_names[j]
    col = table[name]
    if kind == 0:
        return table.drop_columns([name])
    if kind == 1:  # a wrong type
        return table.set_column(j, name, pa.array([str(v) for v in col.to_pylist()]))
    if kind == 2:  # a null
        values = col.to_pylist()
        values[int(rng.integers(0, len(values)))] = None
        return table.set_column(j, name, pa.array(values, col.type))
    if kind == 3 and pa.types.is_floating(col.type):  # NaN, inf, huge, negative ...
        values = col.to_numpy().astype(np.float64)
        values[int(rng.integers(0, len(values)))] = rng.choice(_AV2_VALUES)
        return table.set_column(j, name, pa.array(values.astype(col.type.to_pandas_dtype()),
                                                  col.type))
    if {"qw", "qx"} <= set(table.column_names):  # a quaternion off unit by 1e-4 .. 1e-2
        values = table["qw"].to_numpy().astype(np.float64)
        values[int(rng.integers(0, len(values)))] *= 1 + rng.choice([1e-4, 5e-4, 2e-3, 1e-2])
        return table.set_column(table.column_names.index("qw"), "qw", pa.array(values))
    return table


def test_fuzz_av2(tmp_path):
    rng = np.random.default_rng(2)
    fx = av2fx.write_log(tmp_path, n_sweeps=1, cameras=av2fx.RING[:1], n_clutter=50)
    files = [fx.path / "annotations.feather", fx.path / "city_SE3_egovehicle.feather",
             fx.path / "calibration" / "egovehicle_SE3_sensor.feather",
             fx.path / "calibration" / "intrinsics.feather",
             next((fx.path / "sensors" / "lidar").glob("*.feather"))]
    good = {p: p.read_bytes() for p in files}
    tables = {p: feather.read_table(str(p)) for p in files}
    _check_av2_result(fx, _av2_run(fx, tmp_path))
    outcome = {"ok": 0, "refused": 0}
    for i in range(300):
        path = files[i % len(files)]
        if rng.random() < 0.5:
            put(path, mutate_bytes(good[path], rng))
        else:
            path.unlink()
            feather.write_feather(_mutate_table(tables[path], rng), str(path))
        try:
            result = _av2_run(fx, tmp_path)
        except DataError as exc:
            assert exc.path == str(path), (exc, path)
            outcome["refused"] += 1
        else:
            _check_av2_result(fx, result)
            outcome["ok"] += 1
        put(path, good[path])
    assert outcome["ok"] > 30 and outcome["refused"] > 100


def _rewrite(path, fn):
    feather.write_feather(fn(feather.read_table(str(path))), str(path))


def _set(table, name, row, value):
    values = table[name].to_pylist()
    values[row] = value
    return table.set_column(table.column_names.index(name), name,
                            pa.array(values, table[name].type))


@pytest.mark.parametrize("file, edit, match", [
    ("annotations.feather", lambda t: _set(t, "length_m", 0, -4.0),
     r"row 0 \(track car-0\): size \(-4, 1.875, 1.5\) m: each dimension must be in \(0, 30\]"),
    ("annotations.feather", lambda t: _set(t, "height_m", 2, 45.0), r"each dimension .* \(0, 30\]"),
    ("annotations.feather", lambda t: _set(t, "tx_m", 1, 5000.0), "more than 1000 m"),
    ("annotations.feather", lambda t: _set(t, "qw", 0, 0.9), r"norm 0.9\d+, not 1"),
    ("annotations.feather", lambda t: _set(t, "num_interior_pts", 0, -3),
     "negative num_interior_pts"),
    ("annotations.feather", lambda t: _set(t, "track_uuid", 1, "car-0"),
     "rows 0 and 1: track car-0 twice"),
    ("city_SE3_egovehicle.feather", lambda t: _set(t, "tx_m", 0, 1e9), "beyond 1e[+]07 m"),
    ("city_SE3_egovehicle.feather", lambda t: _set(t, "qz", 0, 0.5), "not 1"),
    ("calibration/egovehicle_SE3_sensor.feather", lambda t: _set(t, "tz_m", 0, 2000.0),
     "beyond 1000 m"),
    ("calibration/egovehicle_SE3_sensor.feather",
     lambda t: _set(t, "sensor_name", 0, "up_lidar"), "sensor_name 'up_lidar' appears twice"),
    ("calibration/intrinsics.feather", lambda t: _set(t, "fx_px", 0, 0.0),
     "focal lengths must be positive"),
])
def test_av2_refusals(tmp_path, file, edit, match):
    fx = av2fx.write_log(tmp_path, n_sweeps=1, n_clutter=20)
    _rewrite(fx.path / file, edit)
    with pytest.raises(DataError, match=match) as err:
        _av2_run(fx, tmp_path)
    assert err.value.path == str(fx.path / file)


def test_av2_quaternion_close_to_unit_is_normalised_and_nonfinite_points_dropped(tmp_path):
    fx = av2fx.write_log(tmp_path, n_sweeps=1, n_clutter=20)
    ref = _av2_run(fx, tmp_path)
    ann = fx.path / "annotations.feather"
    _rewrite(ann, lambda t: t.set_column(6, "qw", pa.array(t["qw"].to_numpy() * 1.0005)))
    _rewrite(ann, lambda t: t.set_column(9, "qz", pa.array(t["qz"].to_numpy() * 1.0005)))
    boxes = _av2_run(fx, tmp_path)[2][0]
    for a, b in zip(ref[2][0], boxes, strict=True):
        assert abs(a.yaw - b.yaw) < 1e-12 and np.array_equal(a.centre, b.centre)
    sweep = next((fx.path / "sensors" / "lidar").glob("*.feather"))
    _rewrite(sweep, lambda t: _set(_set(t, "x", 3, float("nan")), "z", 7, float("inf")))
    with pytest.warns(UserWarning, match=re.escape(f"{sweep}: dropped 2 of {len(ref[1][0])} "
                                                   "points")):
        pts = Av2Log(tmp_path, fx.path.name).points(0)
    np.testing.assert_array_equal(pts, np.delete(ref[1][0], [3, 7], axis=0))


def test_av2_sweep_name_beyond_int64(tmp_path):
    fx = av2fx.write_log(tmp_path, n_sweeps=1, n_clutter=20)
    for digits in (20, 200):  # beyond int64
        path = fx.path / "sensors" / "lidar" / ("9" * digits + ".feather")
        path.write_bytes(b"")
        with pytest.raises(DataError, match="file name is not a timestamp"):
            Av2Log(tmp_path, fx.path.name)
        path.unlink()


# ----------------------------------------------------------------------------- nuScenes


_JSON_JUNK = [float("nan"), float("inf"), -1e308, 1e20, -1, 0, "x", None, [], {}, True,
              [1, 2], [float("nan")] * 4, "../../etc/passwd", 1.5]


def _ns_run(root):
    ns.clear_cache()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = []
        for name in NuScenesLog.log_names(root):
            log = NuScenesLog(root, name)
            for f in log.frames:
                out.append((log, f, log.points(f), log.boxes(f), log.ego_pose(f),
                            [log.camera(c, f) for c in log.camera_names]))
                log.image_path(f)
        return out


def _check_ns_result(tables, result):
    for log, f, points, boxes, pose, cameras in result:
        sample = log.sample_token(f)
        assert len(boxes) == sum(1 for a in tables["sample_annotation"]
                                 if a.get("sample_token") == sample)
        assert np.all(np.isfinite(points))
        for b in boxes:
            assert np.all(np.isfinite(b.centre)) and np.isfinite(b.yaw)
            assert np.all((b.size > 0) & (b.size <= 30)) and np.linalg.norm(b.centre) <= 1000
            assert b.num_points is None or b.num_points >= 0
        for m in [pose] + [c.T_cam_sensor for c in cameras]:
            assert np.all(np.isfinite(m))
            np.testing.assert_allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-6)
        assert all(np.all(np.isfinite(c.K)) and c.K[0, 0] > 0 for c in cameras)


def _mutate_records(records: list, rng: np.random.Generator):
    rec = records[int(rng.integers(0, len(records)))]
    key = list(rec)[int(rng.integers(0, len(rec)))]
    if rng.random() < 0.15:
        del rec[key]
    elif isinstance(rec[key], list) and rec[key] and rng.random() < 0.5:
        rec[key][int(rng.integers(0, len(rec[key])))] = _JSON_JUNK[
            int(rng.integers(0, len(_JSON_JUNK)))]
    else:
        rec[key] = _JSON_JUNK[int(rng.integers(0, len(_JSON_JUNK)))]


def test_fuzz_nuscenes(tmp_path):
    rng = np.random.default_rng(3)
    fx = write_nuscenes(tmp_path, images=False, n_background=40)
    table_dir = tmp_path / fx.version
    names = [p.stem for p in sorted(table_dir.glob("*.json"))] + ["pcd"]
    good = {p: p.read_bytes() for p in table_dir.glob("*.json")}
    lidar = fx.lidar_files["scene-0061", 0]
    good[lidar] = lidar.read_bytes()
    outcome = {"ok": 0, "refused": 0}
    for i in range(300):
        name = names[i % len(names)]
        path = lidar if name == "pcd" else table_dir / f"{name}.json"
        if name == "pcd":
            put(path, mutate_bytes(good[path], rng))
        elif rng.random() < 0.3:
            put(path, mutate_text(good[path], rng) if rng.random() < 0.5
                else good[path][: int(rng.integers(0, len(good[path])))])
        else:
            records = json.loads(good[path])
            for _ in range(int(rng.integers(1, 3))):
                _mutate_records(records, rng)
            put(path, json.dumps(records).encode())
        try:
            result = _ns_run(tmp_path)
        except DataError as exc:
            assert exc.path == str(path) or Path(exc.path).parent == table_dir, (exc, path)
            outcome["refused"] += 1
        else:
            tables = {"sample_annotation": json.loads(
                (table_dir / "sample_annotation.json").read_text())}
            _check_ns_result(tables, result)
            outcome["ok"] += 1
        put(path, good[path])
    assert outcome["ok"] > 30 and outcome["refused"] > 100


def _edit_first(fx, table, key, value, where=None):
    path = fx.root / fx.version / f"{table}.json"
    records = json.loads(path.read_text())
    rec = next(r for r in records if where is None or where(r))
    rec[key] = value
    path.write_text(json.dumps(records))
    return path


@pytest.mark.parametrize("table, key, value, match", [
    ("sample_annotation", "size", [1.9, 0.0, 1.6], r"each dimension must be in \(0, 30\]"),
    ("sample_annotation", "size", [1.9, 40.0, 1.6], r"each dimension must be in \(0, 30\]"),
    ("sample_annotation", "size", [1.9, float("nan"), 1.6], "non-finite"),
    ("sample_annotation", "translation", [1e5, 0.0, 0.0], "more than 1000 m from the sensor"),
    ("sample_annotation", "rotation", [0.5, 0.0, 0.0, 0.0], r"norm 0.5, not 1"),
    ("sample_annotation", "num_lidar_pts", float("nan"), "num_lidar_pts nan is not"),
    ("sample_annotation", "num_lidar_pts", -4, "num_lidar_pts -4 is not"),
    ("ego_pose", "rotation", [2.0, 0.0, 0.0, 0.0], "norm 2, not 1"),
    ("ego_pose", "translation", [1e9, 0.0, 0.0], "beyond 1e[+]07 m"),
    ("calibrated_sensor", "translation", [0.0, 0.0, 5000.0], "beyond 1000 m"),
    ("sample_data", "timestamp", float("inf"), "timestamp inf is not a time"),
    ("sample_data", "timestamp", True, "field 'timestamp' not a"),
    ("sample_data", "calibrated_sensor_token", ["a"], "field 'calibrated_sensor_token' not a"),
    ("sample_data", "filename", "../../../../etc/passwd", "is not a path inside the data root"),
    ("sample_data", "filename", "/etc/passwd", "is not a path inside the data root"),
    ("sample_data", "is_key_frame", "yes", "field 'is_key_frame' not a bool"),
])
def test_nuscenes_refusals(tmp_path, table, key, value, match):
    fx = write_nuscenes(tmp_path, images=False, n_background=20)
    path = _edit_first(fx, table, key, value,
                       where=(lambda r: r.get("is_key_frame")) if table == "sample_data" else None)
    with pytest.raises(DataError, match=match) as err:
        _ns_run(tmp_path)
    assert err.value.path == str(path)


def test_nuscenes_two_keyframes_of_one_channel(tmp_path):
    fx = write_nuscenes(tmp_path, images=False, n_background=20)
    path = fx.root / fx.version / "sample_data.json"
    records = json.loads(path.read_text())
    sweep = next(r for r in records if not r["is_key_frame"] and "LIDAR_TOP" in r["filename"])
    sweep["is_key_frame"] = True  # a sweep between keyframes claiming to be one
    path.write_text(json.dumps(records))
    with pytest.raises(DataError, match=r"sample .* has two LIDAR_TOP keyframes") as err:
        _ns_run(tmp_path)
    assert err.value.path == str(path)


def test_nuscenes_near_unit_quaternion_and_nonfinite_points(tmp_path):
    fx = write_nuscenes(tmp_path, images=False, n_background=20)
    ref = _ns_run(tmp_path)
    path = fx.root / fx.version / "sample_annotation.json"
    records = json.loads(path.read_text())
    for r in records:
        r["rotation"] = [v * 1.0008 for v in r["rotation"]]
    path.write_text(json.dumps(records))
    for (_, _, _, a, _, _), (_, _, _, b, _, _) in zip(ref, _ns_run(tmp_path), strict=True):
        for x, y in zip(a, b, strict=True):
            assert abs(x.yaw - y.yaw) < 1e-12
            np.testing.assert_allclose(x.extra["rotation"], y.extra["rotation"], atol=1e-12)
    lidar = fx.lidar_files["scene-0061", 0]
    pts = np.fromfile(lidar, "<f4").reshape(-1, 5)
    pts[[1, 4], 2] = [np.nan, -np.inf]
    pts.tofile(lidar)
    with pytest.warns(UserWarning, match=re.escape(f"{lidar}: dropped 2 of {len(pts)} points")):
        out = read_pcd_bin(lidar)
    np.testing.assert_array_equal(out, np.delete(pts, [1, 4], axis=0))


def test_nuscenes_corrupt_json(tmp_path):
    fx = write_nuscenes(tmp_path, images=False, n_background=20)
    path = fx.root / fx.version / "scene.json"
    for data in (b"\xff\xfe[]", b"[" * 100000 + b"]" * 100000, b"[" + b"1" * 5000 + b"]", b""):
        path.write_bytes(data)
        with pytest.raises(DataError) as err:
            _ns_run(tmp_path)
        assert err.value.path == str(path)


def test_kitti_label_fixture_written_by_seqshape_reads(tmp_path):
    """Labels seqshape writes (sim scenes) are valid input: the writer's conventions pass."""
    lab = KittiLabel(frame=0, track_id=4, type="Car", truncated=0.123457, occluded=1,
                     alpha=0.3, bbox=[0.0, 10.0, 1241.0, 374.0], dimensions=[1.5, 1.6, 3.9],
                     location=[1.0, 1.7, 25.0], rotation_y=-3.1)
    write_labels(tmp_path / "0000.txt", [lab])
    back = read_labels(tmp_path / "0000.txt")[0]
    assert back.occluded == 1 and back.truncated == 0.123457


def test_kitti_names_with_non_ascii_digits_are_not_frames(tmp_path):
    """``"²".isdigit()`` is True but ``int("²")`` fails: such names are not frames or logs."""
    write_velodyne(tmp_path / "velodyne" / "0000" / "000000.bin", np.zeros((3, 3)))
    write_velodyne(tmp_path / "velodyne" / "0000" / "00000\u00b2.bin", np.zeros((3, 3)))
    (tmp_path / "velodyne" / "00\u00b2").mkdir()
    assert KittiTrackingSequence(tmp_path, "0000").frames == [0]
    assert KittiTrackingSequence.sequences(tmp_path) == ["0000"]
