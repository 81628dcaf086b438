"""Input that cannot hurt, second round (issue 45): hangs, silent acceptances, tracebacks.

Seeded case classes per reader, each a file a user could really hand over: a FIFO, a folder
or a device where a file belongs; a KITTI sweep written as float64 or as (N, 3) float32, or
random bytes; projection entries of 1e308 and NUL separators in a calibration; track ids of
hundreds of digits; nuScenes sizes of booleans, records without a string token, attribute
tokens that are not a list, duplicated records; KINS images of one ``file_name`` and
duplicate category ids; a track file whose id disagrees with the manifest; trajectory CSVs with
positions 1,000 km away, headings of 1e300, a repeated column or a field over the csv module's
limit; an Argoverse 2 sweep moved kilometres away. Every case is impossible input, so the only
right outcome is a :class:`DataError` naming the file that holds the bad record (and, where
the refusal names a cause, that cause): a result is a silent acceptance, any other exception
a traceback, and a read still blocked after :data:`HANG_SECONDS` a hang.

The census of every reader is also a script (``python tests/test_fuzz_input.py``, or with
``PYTHONPATH=<older tree>/src`` to count what an older seqshape does): one row per reader and
case class with the outcomes.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shutil
import sys
import tempfile
import threading
import warnings
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))  # the fixtures, when run as a script

import _av2_fixture as av2fx  # noqa: E402
from _kitti_fixture import write_box_kitti  # noqa: E402
from _nuscenes_fixture import write_nuscenes  # noqa: E402

from seqshape.camera import read_calib  # noqa: E402
from seqshape.data import Track, TrackDataset, write_dataset  # noqa: E402
from seqshape.data import nuscenes as ns  # noqa: E402
from seqshape.data.av2 import Av2Log  # noqa: E402
from seqshape.data.kins import image_entry, kins_annotation, read_kins, write_kins  # noqa: E402
from seqshape.data.kitti import read_labels, read_velodyne  # noqa: E402
from seqshape.data.nuscenes import NuScenesLog, read_pcd_bin  # noqa: E402
from seqshape.errors import DataError  # noqa: E402
from seqshape.sim.trajectories import read_trajectory_csv  # noqa: E402

#: a read still blocked after this long is a hang (the test then opens the FIFO's other end)
HANG_SECONDS = 1.5

#: outcome names: the right one, and the three wrong ones
REFUSED, ACCEPTED, TRACEBACK, HANG, VAGUE, MISNAMED = (
    "refused", "silently accepted", "traceback", "hang", "refused, cause not named",
    "refused naming another file")
OUTCOMES = (REFUSED, ACCEPTED, TRACEBACK, HANG, VAGUE, MISNAMED)


# ----------------------------------------------------------------------------- the harness


class Case:
    """One impossible input: ``make(rng)`` writes it and returns ``(run, path, cause)``: the
    call that reads it, the file the refusal must name and a regex its message must match
    (None: any). ``undo()`` restores the fixture afterwards."""

    def __init__(self, cls: str, make: Callable, undo: Callable | None = None):
        self.cls, self.make, self.undo = cls, make, undo


def _unblock(path: Path) -> None:
    """Open the write end of a FIFO a reader is blocked on, and close it: the reader goes on
    (and reads an empty file)."""
    with contextlib.suppress(OSError):
        os.close(os.open(path, os.O_WRONLY | os.O_NONBLOCK))


def outcome(run: Callable, path: Path, cause: str | None, fifos: list[Path]) -> str:
    """Run one case: :data:`REFUSED` for a DataError naming ``path`` (and matching ``cause``),
    else what went wrong."""
    hung, done = threading.Event(), threading.Event()

    def watchdog():
        hung.set()
        while not done.wait(0.02):  # a reader may open the FIFO again: keep unblocking it
            for f in fifos:
                _unblock(f)

    timer = threading.Timer(HANG_SECONDS, watchdog) if fifos else None
    if timer:
        timer.start()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            run()
        result = ACCEPTED
    except DataError as exc:
        named = exc.path == str(path)
        result = REFUSED if named and (cause is None or re.search(cause, str(exc))) else \
            VAGUE if named else MISNAMED
    except Exception:  # noqa: BLE001 - any other exception is what the census counts
        result = TRACEBACK
    finally:
        done.set()
        if timer:
            timer.cancel()
            timer.join()
    return HANG if hung.is_set() else result


def census(cases: Iterator[Case], rng: np.random.Generator) -> dict[str, Counter]:
    """Outcomes per case class."""
    out: dict[str, Counter] = {}
    for case in cases:
        run, path, cause = case.make(rng)
        fifos = [path] if path.is_fifo() else []
        try:
            out.setdefault(case.cls, Counter())[outcome(run, path, cause, fifos)] += 1
        finally:
            if case.undo:
                case.undo()
    return out


def _replace(path: Path, kind: str) -> None:
    """Put a FIFO, a folder or a link to a character device where the file ``path`` is."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "folder":
        path.mkdir()
        (path / "x").write_bytes(b"")
    else:
        os.symlink("/dev/null", path)


def _restore(path: Path, data: bytes) -> Callable:
    def undo():
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink(missing_ok=True)
        path.write_bytes(data)
    return undo


def special_files(path: Path, run: Callable, n: int, kinds=("fifo", "folder", "device")
                  ) -> Iterator[Case]:
    """``n`` cases: a FIFO, a folder or a device link in place of ``path``."""
    good = path.read_bytes()
    for i in range(n):
        kind = kinds[i % len(kinds)]

        def make(rng, kind=kind):
            _replace(path, kind)
            return run, path, "not a regular file"
        yield Case(f"{kind} in place of the file", make, _restore(path, good))


def rewrites(path: Path, cls: str, n: int, mutate: Callable, run: Callable,
             cause: str | None = None, named: Path | None = None) -> Iterator[Case]:
    """``n`` cases writing ``mutate(good bytes, rng)`` over ``path`` (the refusal must name
    ``named``, by default ``path``)."""
    good = path.read_bytes()

    def make(rng):
        path.unlink()
        path.write_bytes(mutate(good, rng))
        return run, named or path, cause
    for _ in range(n):
        yield Case(cls, make, _restore(path, good))


# ----------------------------------------------------------------------------- KITTI sweeps


def _sweep(rng, n: int) -> np.ndarray:
    """(n, 3) float64 coordinates of a plausible sweep: 2-80 m around, ground and walls."""
    r = rng.uniform(2, 80, n)
    a = rng.uniform(-np.pi, np.pi, n)
    return np.c_[r * np.cos(a), r * np.sin(a), rng.uniform(-2.5, 3, n)]


def _velodyne_layout(kind: str):
    def mutate(good, rng):
        n = int(rng.integers(50, 3000))
        xyz, refl = _sweep(rng, n), rng.random((n, 1))
        if kind == "float64 (N, 4)":
            return np.c_[xyz, refl].astype("<f8").tobytes()
        if kind == "float64 (N, 3)":
            return xyz.astype("<f8").tobytes()
        if kind == "float32 (N, 3)":
            return xyz.astype("<f4").tobytes()
        if kind == "float32 (N, 5)":
            return np.c_[xyz, refl, rng.integers(0, 64, (n, 1))].astype("<f4").tobytes()
        data = rng.integers(0, 256, 16 * n, dtype=np.uint8).tobytes()  # random bytes
        return data
    return mutate


def _far_points(good, rng):
    pts = np.frombuffer(good, "<f4").reshape(-1, 4).copy()
    k = max(int(len(pts) * rng.uniform(0.02, 1.0)), 1)
    rows = rng.choice(len(pts), k, replace=False)
    pts[rows, int(rng.integers(0, 3))] = rng.choice([1e4, -3e5, 6e4, 3.7e19, -1e30, 2e3])
    return pts.tobytes()


def velodyne_cases(root: Path) -> Iterator[Case]:
    path = root / "velodyne" / "0000" / "000000.bin"

    def run():
        return read_velodyne(path)
    yield from special_files(path, run, 15)
    for kind in ("float64 (N, 4)", "float64 (N, 3)", "float32 (N, 3)", "float32 (N, 5)"):
        yield from rewrites(path, f"written as {kind}", 60, _velodyne_layout(kind), run,
                            cause=re.escape(kind))
    yield from rewrites(path, "random bytes, a multiple of 16", 40, _velodyne_layout("random"),
                        run, cause="random or corrupt")
    yield from rewrites(path, "points beyond 1 km (over 1 %)", 40, _far_points, run,
                        cause="beyond 1000 m")


def pcd_cases(root: Path) -> Iterator[Case]:
    path = root / "velodyne" / "0000" / "000001.bin"

    def run():
        return read_pcd_bin(path)
    yield from special_files(path, run, 6)
    for kind in ("float64 (N, 4)", "float64 (N, 3)", "float32 (N, 3)"):
        yield from rewrites(path, f"nuScenes .pcd.bin written as {kind}", 20,
                            _velodyne_layout(kind), run)


# ----------------------------------------------------------------------------- KITTI text


_P_KEYS = ("P0", "P1", "P2", "P3")
_OPTIONAL_CALIB = ("P0:", "P1:", "P3:", "Tr_imu_velo")


def _huge_projection(good, rng):
    lines = good.decode().splitlines()
    key = _P_KEYS[int(rng.integers(4))]
    i = next(k for k, ln in enumerate(lines) if ln.startswith(key))
    parts = lines[i].split()
    if rng.random() < 0.3:  # the whole matrix scaled: a projection of 1e307
        scale = float(rng.choice([1e304, 1e300, 1e36, 1e8]))
        parts[1:] = [repr(float(v) * scale) for v in parts[1:]]
    else:
        parts[int(rng.integers(1, 13))] = str(rng.choice(
            ["1e308", "3.4e38", "-1e307", "1e12", "-2.5e5", "7.2e9"]))
    lines[i] = " ".join(parts)
    return ("\n".join(lines) + "\n").encode()


def _nul_separators(good, rng):
    lines = good.decode().splitlines()
    key = _OPTIONAL_CALIB[int(rng.integers(len(_OPTIONAL_CALIB)))]
    i = next(k for k, ln in enumerate(lines) if ln.startswith(key))
    sep = ["\0", "\0\0", " \0"][int(rng.integers(3))]
    lines[i] = sep.join(lines[i].split(" ")) if sep != " \0" else lines[i].replace(" ", sep, 3)
    return ("\n".join(lines) + "\n").encode()


def calib_cases(root: Path) -> Iterator[Case]:
    path = root / "calib" / "0000.txt"

    def run():
        return read_calib(path)
    yield from special_files(path, run, 15)
    yield from rewrites(path, "projection entries of 1e308, 3.4e38 ...", 165, _huge_projection,
                        run, cause="beyond 100000")
    yield from rewrites(path, "NUL separators in an optional line", 120, _nul_separators, run,
                        cause="NUL character")


def _long_track_id(good, rng):
    lines = good.decode().splitlines()
    i = int(rng.integers(len(lines)))
    parts = lines[i].split()
    digits = int(rng.choice([7, 12, 19, 25, 60, 400]))
    parts[1] = str(int(rng.integers(1, 10))) + "".join(
        str(d) for d in rng.integers(0, 10, digits - 1))
    lines[i] = " ".join(parts)
    return ("\n".join(lines) + "\n").encode()


def _nul_in_row(good, rng):
    b = bytearray(good)
    spaces = [k for k, c in enumerate(b) if c == 32]
    for k in rng.choice(spaces, int(rng.integers(1, 4)), replace=False):
        b[int(k)] = 0
    return bytes(b)


def label_cases(root: Path) -> Iterator[Case]:
    path = root / "label_02" / "0000.txt"

    def run():
        return read_labels(path)
    yield from special_files(path, run, 15)
    yield from rewrites(path, "track id of 7 to 400 digits", 185, _long_track_id, run,
                        cause="track_id must be")
    yield from rewrites(path, "NUL separators", 100, _nul_in_row, run, cause="NUL character")


# ----------------------------------------------------------------------------- nuScenes


def _nuscenes_run(root: Path) -> Callable:
    def run():
        ns.clear_cache()
        for name in NuScenesLog.log_names(root):
            log = NuScenesLog(root, name)
            for f in log.frames:
                log.boxes(f)
                log.points(f)
    return run


def _json_edit(edit: Callable) -> Callable:
    def mutate(good, rng):
        records = json.loads(good)
        edit(records, rng)
        return json.dumps(records).encode()
    return mutate


def _bool_size(records, rng):
    rec = records[int(rng.integers(len(records)))]
    rec["size"] = [[True, True, True], [True, 1.5, 1.0], [1.8, False, 1.5],
                   [True, True, False]][int(rng.integers(4))]


def _bad_token(records, rng):
    rec = records[int(rng.integers(len(records)))]
    value = [None, 17, 3.5, True, ["a"], {"t": 1}, "", "missing"][int(rng.integers(8))]
    if value == "missing":
        del rec["token"]
    else:
        rec["token"] = value


def _bad_attributes(records, rng):
    rec = records[int(rng.integers(len(records)))]
    rec["attribute_tokens"] = ["abc", 5, {"a": 1}, [1, 2], "", 2.5][int(rng.integers(6))]


def _duplicate_record(records, rng):
    i = int(rng.integers(len(records)))
    records.insert(int(rng.integers(len(records) + 1)), dict(records[i]))


def nuscenes_cases(root: Path, version: str) -> Iterator[Case]:
    tables = root / version
    run = _nuscenes_run(root)
    ann = tables / "sample_annotation.json"
    pcd = next((root / "samples" / "LIDAR_TOP").glob("*.pcd.bin"))
    for path in (ann, tables / "instance.json", pcd):
        yield from special_files(path, run, 6)
    yield from rewrites(ann, "size of booleans", 70, _json_edit(_bool_size), run, "size")
    yield from rewrites(ann, "sample_annotation token missing, numeric, empty ...", 70,
                        _json_edit(_bad_token), run, "token")
    yield from rewrites(ann, "attribute_tokens not a list of tokens", 60,
                        _json_edit(_bad_attributes), run, "attribute_tokens")
    yield from rewrites(ann, "a sample_annotation record twice", 60,
                        _json_edit(_duplicate_record), run, "twice")
    for name in ("instance", "sample", "ego_pose", "calibrated_sensor"):
        yield from rewrites(tables / f"{name}.json", f"a {name} record twice", 6,
                            _json_edit(_duplicate_record), run, "twice")
    yield from rewrites(pcd, ".pcd.bin written as float64 (N, 5)", 16,
                        lambda good, rng: np.frombuffer(good, "<f4").astype("<f8").tobytes(),
                        run, "float64")


# ----------------------------------------------------------------------------- KINS


def _kins_edit(kind: str):
    def mutate(good, rng):
        doc = json.loads(good)
        if kind == "file_name":
            i, j = rng.choice(len(doc["images"]), 2, replace=False)
            doc["images"][int(j)]["file_name"] = doc["images"][int(i)]["file_name"]
        else:
            cats = doc["categories"]
            i = int(rng.integers(len(cats)))
            cats.insert(int(rng.integers(len(cats) + 1)),
                        {"id": cats[i]["id"], "name": ["other", cats[i]["name"], "car"][
                            int(rng.integers(3))]})
        return json.dumps(doc).encode()
    return mutate


def kins_cases(tmp: Path, rng) -> Iterator[Case]:
    h, w = 12, 16
    images = [image_entry(i, "0000", i, h, w) for i in range(6)]
    anns = []
    for k in range(8):
        a = np.zeros((h, w), bool)
        a[2:8, k:k + 6] = True
        anns.append(kins_annotation(k + 1, k % 6, 4, a, a, 0, 0, track_id=k))
    path = tmp / "amodal.json"
    write_kins(path, images, anns)

    def run():
        return read_kins(path)
    yield from special_files(path, run, 15)
    yield from rewrites(path, "two images of one file_name", 150, _kins_edit("file_name"), run,
                        "file_name")
    yield from rewrites(path, "a category id twice", 150, _kins_edit("category"), run,
                        "duplicate category id")


# ----------------------------------------------------------------------------- track datasets


def _track(tid: str, rng) -> Track:
    t = int(rng.integers(1, 4))
    return Track(tid, [rng.normal(0, 1, (3, 3)).astype(np.float32) for _ in range(t)],
                 np.zeros((t, 4)), None, np.ones(3), np.arange(t) * 0.1, {"split": "train"})


def track_cases(tmp: Path, rng) -> Iterator[Case]:
    ds = write_dataset(tmp / "ds", [_track(t, rng) for t in ("a", "b", "c")])
    mpath = ds.path / "manifest.json"

    def run():
        d = TrackDataset(ds.path)
        return [d[i] for i in range(len(d))]
    for name in ("a", "b", "c"):
        # (a link to /dev/null leaves the dataset folder: refused naming the manifest, as
        # before)
        yield from special_files(ds.path / "tracks" / f"{name}.npz", run, 30, ("fifo", "folder"))
    yield from special_files(mpath, run, 10, ("fifo", "folder"))
    good_manifest = mpath.read_bytes()

    def renamed(rng):
        doc = json.loads(good_manifest)
        i = int(rng.integers(3))
        doc["tracks"][i]["track_id"] = "".join(rng.choice(list("xyz0123_-"), 6))
        mpath.write_text(json.dumps(doc))
        return run, ds.path / doc["tracks"][i]["file"], "holds track"

    def swapped(rng):
        doc = json.loads(good_manifest)
        i, j = (int(v) for v in rng.choice(3, 2, replace=False))
        doc["tracks"][i]["file"] = f"tracks/{doc['tracks'][j]['track_id']}.npz"
        mpath.write_text(json.dumps(doc))
        return run, ds.path / doc["tracks"][i]["file"], "holds track"
    for _ in range(100):
        yield Case("manifest id renamed", renamed, _restore(mpath, good_manifest))
        yield Case("manifest entry pointing at another track's file", swapped,
                   _restore(mpath, good_manifest))


# ----------------------------------------------------------------------------- trajectories


def _trajectory_text(rng, edit: str) -> str:
    n = int(rng.integers(3, 30))
    t = np.arange(n) * 0.1
    x, y, yaw = rng.uniform(-40, 40, n), rng.uniform(-40, 40, n), rng.uniform(-3, 3, n)
    header = ["t", "x", "y", "yaw"]
    rows = [[f"{a:.3f}", f"{b:.3f}", f"{c:.3f}", f"{d:.4f}"] for a, b, c, d in zip(
        t, x, y, yaw, strict=True)]
    k = int(rng.integers(n))
    if edit == "far":
        col = int(rng.integers(1, 3))
        value = float(rng.choice([1e6, -2e5, 5e4, 1e9, 1.5e3]))
        for r in rows if rng.random() < 0.5 else rows[k:k + 1]:
            r[col] = repr(value)
    elif edit == "yaw":
        rows[k][3] = str(rng.choice(["1e300", "-1e300", "1e4", "-2500", "1e20"]))
    elif edit == "column":
        header.insert(int(rng.integers(5)), str(rng.choice(header)))
        for r in rows:
            r.insert(header.index(header[0]), r[0])
    else:  # a field over the csv module's limit, quoted (a newline in it) or not
        big = "9" * int(rng.integers(131_073, 200_000))
        rows[k][int(rng.integers(4))] = f'"{big}\n"' if rng.random() < 0.5 else big
    buf = io.StringIO()
    buf.write(",".join(header) + "\n")
    for r in rows:
        buf.write(",".join(r) + "\n")
    return buf.getvalue()


def trajectory_cases(tmp: Path, rng) -> Iterator[Case]:
    path = tmp / "traj.csv"
    path.write_text(_trajectory_text(rng, "far").replace("1e+06", "1.0"))

    def run():
        return read_trajectory_csv(path)
    yield from special_files(path, run, 15)
    for edit, cls, cause, n in (
            ("far", "position beyond 1 km (x = 1e6 ...)", "more than 1000 m", 80),
            ("yaw", "heading of 1e300 ...", "beyond 1000 rad", 70),
            ("column", "a column twice in the header", "twice", 70),
            ("long", "a field over 131,072 characters", "field", 70)):
        yield from rewrites(path, cls, n, lambda good, rng, e=edit: _trajectory_text(
            rng, e).encode(), run, cause)


# ----------------------------------------------------------------------------- Argoverse 2


def av2_cases(tmp: Path) -> Iterator[Case]:
    fx = av2fx.write_log(tmp, n_sweeps=1, cameras=av2fx.RING[:1], n_clutter=100)
    sweep = next((fx.path / "sensors" / "lidar").glob("*.feather"))
    import pyarrow.feather as feather

    table = feather.read_table(str(sweep))

    def run():
        return Av2Log(tmp, fx.path.name).points(0)

    def shifted(good, rng):
        d = float(rng.choice([2e3, 6e4, 6e4, 1e5, 3e6]))
        a = rng.uniform(-np.pi, np.pi)
        t = table
        import pyarrow as pa

        for col, off in (("x", d * np.cos(a)), ("y", d * np.sin(a))):
            v = t[col].to_numpy().astype(np.float64) + off
            t = t.set_column(t.column_names.index(col), col, pa.array(v.astype(np.float32)))
        buf = pa.BufferOutputStream()
        feather.write_feather(t, buf)
        return buf.getvalue().to_pybytes()
    yield from special_files(sweep, run, 30)
    yield from rewrites(sweep, "sweep moved kilometres away (60 km ...)", 270, shifted, run,
                        "km from its sensor")


# ----------------------------------------------------------------------------- the readers


def reader_cases(tmp: Path, rng) -> dict[str, Callable[[], Iterator[Case]]]:
    """Reader name -> its cases (fixtures written under ``tmp`` when first asked for)."""
    def kitti(fn):
        def cases():
            root = write_box_kitti(tmp / f"kitti_{fn.__name__}", frames=2, ground_points=200)
            return fn(root)
        return cases

    def nuscenes():
        fx = write_nuscenes(tmp / "nuscenes", images=False, n_background=20)
        return nuscenes_cases(fx.root, fx.version)

    return {"KITTI velodyne": kitti(velodyne_cases), "KITTI calibration": kitti(calib_cases),
            "KITTI label_02": kitti(label_cases), "nuScenes tables": nuscenes,
            "nuScenes .pcd.bin": kitti(pcd_cases),
            "KINS": lambda: kins_cases(_mk(tmp / "kins"), rng),
            "track dataset": lambda: track_cases(_mk(tmp / "tracks"), rng),
            "trajectory CSV": lambda: trajectory_cases(_mk(tmp / "traj"), rng),
            "Argoverse 2 sweep": lambda: av2_cases(_mk(tmp / "av2"))}


def _mk(path: Path) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    return path


READERS = ("KITTI velodyne", "KITTI calibration", "KITTI label_02", "nuScenes tables",
           "nuScenes .pcd.bin", "KINS", "track dataset", "trajectory CSV", "Argoverse 2 sweep")


@pytest.mark.parametrize("reader", READERS)
def test_impossible_input_is_refused_naming_its_file(tmp_path, reader):
    rng = np.random.default_rng(45 + READERS.index(reader))
    counts = census(reader_cases(tmp_path, rng)[reader](), rng)
    total = sum(sum(c.values()) for c in counts.values())
    if reader != "nuScenes .pcd.bin":  # a small companion of the KITTI sweep classes
        assert total >= 300, (reader, total)
    wrong = {cls: dict(c) for cls, c in counts.items() if set(c) != {REFUSED}}
    assert not wrong, f"{reader}: {wrong}"


def test_plausible_sweeps_still_read(tmp_path):
    """The controls: real-looking sweeps (and a few dropped points) read as before."""
    rng = np.random.default_rng(7)
    path = tmp_path / "a.bin"
    for _ in range(50):
        n = int(rng.integers(1, 2000))
        pts = np.c_[_sweep(rng, n), rng.random(n)].astype("<f4")
        path.write_bytes(pts.tobytes())
        np.testing.assert_array_equal(read_velodyne(path), pts)
    pts[0, 0] = 5e4  # one point beyond 1 km in 2,000: dropped, with a warning
    path.write_bytes(pts.tobytes())
    with pytest.warns(UserWarning, match=r"dropped 1 of \d+ points with a non-finite value, a "
                                         "coordinate beyond 1000 m"):
        assert len(read_velodyne(path)) == len(pts) - 1


# ----------------------------------------------------------------------------- the census


def main() -> None:
    import seqshape

    print(f"seqshape from {Path(seqshape.__file__).parent}")
    print("| reader | case class | cases | " + " | ".join(OUTCOMES) + " |")
    print("|---|---|---:" + "|---:" * len(OUTCOMES) + "|")
    totals: dict[str, Counter] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for k, reader in enumerate(READERS):
            rng = np.random.default_rng(45 + k)
            counts = census(reader_cases(Path(tmp), rng)[reader](), rng)
            for cls, c in counts.items():
                totals.setdefault(reader, Counter()).update(c)
                print(f"| {reader} | {cls} | {sum(c.values())} | " + " | ".join(
                    str(c[o]) for o in OUTCOMES) + " |")
    print("\n| reader | cases | " + " | ".join(OUTCOMES) + " |\n|---|---:"
          + "|---:" * len(OUTCOMES) + "|")
    for reader, c in totals.items():
        print(f"| {reader} | {sum(c.values())} | " + " | ".join(str(c[o]) for o in OUTCOMES)
              + " |")


if __name__ == "__main__":
    main()
