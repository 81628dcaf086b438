"""The Track, the unit of data, and its on-disk form (one ``.npz`` file per track).

File format ``seqshape-track`` version 1 (see docs/data-format.md):

=============  ===============  ===================================================
array          dtype, shape     meaning
=============  ===============  ===================================================
points         float32 (P, 3)   all frames' points, concatenated in frame order
offsets        int64 (T + 1,)   frame t holds ``points[offsets[t]:offsets[t + 1]]``
poses          float64 (T, 4)   ground-truth (x, y, z, yaw) per frame; NaN rows unknown
timestamps     float64 (T,)     seconds, strictly increasing
size           float64 (3,)     length, width, height of the bounding box (m)
complete       float32 (M, 3)   complete outside surface, canonical frame (optional)
meta           str (JSON)       dict: mesh id, sensor, split, generator version, seed ...
version        int64 ()         format version (1)
=============  ===============  ===================================================

:func:`load_track` checks every array (:func:`check_track_arrays`: dtype kind, shape,
finiteness, :data:`MAX_COORD`, order) and reads the archive member by member without pickles,
with each member's declared size matched against the bytes it holds (no allocation from an
absurd header) and its CRC verified; anything else is a :class:`DataError` naming the file.
:func:`save_track` applies the same checks, so every file it writes loads.
"""

from __future__ import annotations

import json
import math
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

import seqshape.limits as limits
from seqshape._io import atomic_save_npz, open_regular
from seqshape.errors import DataError
from seqshape.geometry import canonical_to_sensor

TRACK_FORMAT_VERSION = 1
_REQUIRED = ("points", "offsets", "poses", "timestamps", "size", "meta")
_OPTIONAL = ("complete", "version")
#: Largest coordinate (m) of a point, pose or complete shape, and largest box side, a track
#: file may hold: sensor-frame data of a vehicle lies within a few hundred metres, so a larger
#: value is a unit or frame mistake or a corrupt file.
MAX_COORD = limits.MAX_COORD
#: Largest array (bytes) a track file may declare (a track holds a few MB).
MAX_ARRAY_BYTES = limits.MAX_ARRAY_BYTES
_CHUNK = 1 << 18  # bytes per read of an array's data (as numpy.load reads)
_NUMERIC = "fiu"  # dtype kinds taken as numbers: float, signed and unsigned integer


@dataclass
class Track:
    """A sequence of partial point clouds of one vehicle, with its ground truth.

    ``points[t]`` is an ``(N_t, 3)`` float32 array in frame t's sensor frame (``N_t`` may be 0);
    ``poses[t]`` the vehicle's (x, y, z, yaw) in that frame; ``complete`` the complete outside
    surface in the canonical frame, or None when unknown (real data). Arrays of the wrong
    width (a (T, 3) ``poses``, an (M, 4) ``complete``) raise ``ValueError`` rather than being
    reshaped; flat arrays of a multiple of the width are reshaped.
    """

    track_id: str
    points: list[np.ndarray]
    poses: np.ndarray
    complete: np.ndarray | None
    size: np.ndarray
    timestamps: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        self.points = [_rows(p, np.float32, 3, self.track_id, "points") for p in self.points]
        self.poses = _rows(self.poses, np.float64, 4, self.track_id, "poses")
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        self.size = np.asarray(self.size, dtype=np.float64).reshape(3)
        if self.complete is not None:
            self.complete = _rows(self.complete, np.float32, 3, self.track_id, "complete")
        t = len(self.points)
        if self.poses.shape[0] != t or self.timestamps.shape[0] != t:
            raise ValueError(
                f"track {self.track_id}: {t} frames of points but poses {self.poses.shape} "
                f"and timestamps {self.timestamps.shape}")

    def __len__(self) -> int:
        return len(self.points)

    @property
    def num_points(self) -> np.ndarray:
        """Points per frame, ``(T,)`` int."""
        return np.array([len(p) for p in self.points], dtype=np.int64)

    @property
    def split(self) -> str | None:
        return self.meta.get("split")

    def complete_in_frame(self, t: int) -> np.ndarray:
        """The complete shape placed in frame ``t``'s sensor frame, ``(M, 3)`` float32."""
        if self.complete is None:
            raise ValueError(f"track {self.track_id} has no complete shape")
        return canonical_to_sensor(self.complete, self.poses[t])

    def ego_pose(self, t: int) -> np.ndarray | None:
        """Frame ``t``'s sensor frame -> the log's fixed frame, ``(4, 4)``, as a user's
        pipeline knows it: ``meta["ego_poses"]`` when recorded; the identity for a synthetic
        track without them (its sensor is static); None for a real track without them."""
        if self.meta.get("ego_poses"):
            return np.asarray(self.meta["ego_poses"][t], dtype=np.float64)
        return None if self.meta.get("source") == "real" else np.eye(4)

    def slice(self, start: int, stop: int) -> Track:
        """Frames ``start:stop`` as a new Track (arrays shared, not copied)."""
        return Track(self.track_id, self.points[start:stop], self.poses[start:stop],
                     self.complete, self.size, self.timestamps[start:stop], dict(self.meta))


def _rows(a, dtype, width: int, track_id: str, name: str) -> np.ndarray:
    """``a`` as a (n, width) array of ``dtype``; a 2-D array of another width is an error."""
    a = np.asarray(a, dtype=dtype)
    if a.ndim == 2 and a.shape[1] != width:
        raise ValueError(f"track {track_id}: {name} must have {width} columns, got shape "
                         f"{a.shape}")
    return a.reshape(-1, width)


def save_track(path: str | Path, track: Track, compressed: bool = True) -> None:
    """Write ``track`` to ``path`` (.npz) atomically.

    The arrays are checked as :func:`load_track` checks them (a :class:`DataError` naming
    ``path``, nothing written), so every file written here loads.
    """
    offsets = np.zeros(len(track) + 1, dtype=np.int64)
    offsets[1:] = np.cumsum(track.num_points)
    points = (np.concatenate(track.points) if len(track) else np.zeros((0, 3), np.float32))
    arrays = dict(points=points.astype(np.float32), offsets=offsets, poses=track.poses,
                  timestamps=track.timestamps, size=track.size,
                  meta=np.array(json.dumps({"track_id": track.track_id, **track.meta})),
                  version=np.array(TRACK_FORMAT_VERSION, dtype=np.int64))
    if track.complete is not None:
        arrays["complete"] = track.complete
    try:
        check_track_arrays(arrays)
    except ValueError as exc:
        raise DataError(path, f"refusing to write an invalid track {track.track_id!r}: "
                              f"{exc}") from None
    atomic_save_npz(path, compressed=compressed, **arrays)


def load_track(path: str | Path) -> Track:
    """Read a track written by :func:`save_track`; a bad file raises :class:`DataError`.

    Refused (with the file and the problem named): a missing, truncated or corrupt archive
    (bad zip structure, CRC or compressed stream), pickled object arrays, array headers whose
    declared size does not match the stored bytes or exceeds :data:`MAX_ARRAY_BYTES`, and any
    array that fails :func:`check_track_arrays`.
    """
    path = Path(path)
    arrays = _read_npz(path, _REQUIRED + _OPTIONAL)
    try:
        return _track(arrays, path.stem)
    except ValueError as exc:
        raise DataError(path, f"invalid track: {exc}") from None


def check_track_arrays(arr: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], dict]:
    """The arrays of a track file, checked and converted: ``(arrays, meta)``.

    ``arrays`` holds ``points`` float32 (P, 3), ``offsets`` int64 (T + 1,) from 0 to P and
    non-decreasing, ``poses`` float64 (T, 4) whose rows are finite or all NaN, ``timestamps``
    float64 (T,) finite and strictly increasing, ``size`` float64 (3,) positive, ``complete``
    float32 (M >= 1, 3) when present; coordinates and sizes within :data:`MAX_COORD`. Numbers
    may be stored as any float or integer dtype (not bool, complex or strings). ``meta`` is
    the JSON object of the ``meta`` string; ``version`` an integer from 1 to
    :data:`TRACK_FORMAT_VERSION`. Raises ``ValueError`` naming the array and the problem.
    """
    missing = [k for k in _REQUIRED if k not in arr]
    if missing:
        raise ValueError(f"not a seqshape track: missing arrays {missing}")
    _check_version(arr.get("version"))
    meta = _meta(arr["meta"])
    points = _coords(arr["points"], "points", np.float32, (None, 3))
    offsets = _offsets(arr["offsets"], len(points))
    t = len(offsets) - 1
    poses = _coords(arr["poses"], "poses", np.float64, (t, 4), nan_rows=True)
    times = _numbers(arr["timestamps"], "timestamps", np.float64, (t,))
    if not np.all(np.isfinite(times)):
        raise ValueError("timestamps are not all finite")
    if np.any(np.diff(times) <= 0):
        k = int(np.argmax(np.diff(times) <= 0))
        raise ValueError(f"timestamps are not strictly increasing (frame {k + 1}: "
                         f"{times[k + 1]!r} after {times[k]!r})")
    size = _coords(arr["size"], "size", np.float64, (3,))
    if not np.all(size > 0):
        raise ValueError(f"size (length, width, height) must be positive, got {size.tolist()}")
    out = {"points": points, "offsets": offsets, "poses": poses, "timestamps": times,
           "size": size}
    if "complete" in arr:
        out["complete"] = _coords(arr["complete"], "complete", np.float32, (None, 3))
        if not len(out["complete"]):
            raise ValueError("complete holds no points (leave the array out when unknown)")
    return out, meta


def _track(arr: dict[str, np.ndarray], default_id: str) -> Track:
    checked, meta = check_track_arrays(arr)
    track_id = meta.pop("track_id", default_id)
    if not isinstance(track_id, str) or not track_id:
        raise ValueError(f"meta track_id must be a non-empty string, got {track_id!r}")
    points, offsets = checked["points"], checked["offsets"]
    frames = [points[offsets[i]:offsets[i + 1]] for i in range(len(offsets) - 1)]
    return Track(track_id, frames, checked["poses"], checked.get("complete"), checked["size"],
                 checked["timestamps"], meta)


def _check_version(version: np.ndarray | None) -> None:
    if version is None:
        return
    if version.shape != () or version.dtype.kind not in "iu":
        raise ValueError(f"version must be an integer scalar, got {version.dtype} "
                         f"{version.shape}")
    v = int(version)
    if v > TRACK_FORMAT_VERSION:
        raise ValueError(f"track format version {v} is newer than this seqshape understands "
                         f"({TRACK_FORMAT_VERSION}); upgrade")
    if v < 1:
        raise ValueError(f"track format version {v} does not exist (versions start at 1)")


def _meta(meta: np.ndarray) -> dict:
    if meta.shape != () or meta.dtype.kind != "U":
        raise ValueError(f"meta must be a JSON string, got {meta.dtype} {meta.shape}")
    try:
        out = json.loads(str(meta))
    except (json.JSONDecodeError, RecursionError) as exc:
        raise ValueError(f"corrupt track metadata ({type(exc).__name__}: "
                         f"{str(exc)[:200]})") from None
    if not isinstance(out, dict):
        raise ValueError(f"meta must be a JSON object, got {type(out).__name__}")
    return out


def _numbers(a: np.ndarray, name: str, dtype, shape: tuple) -> np.ndarray:
    """``a`` converted to ``dtype`` after checking its kind and shape (None: any length)."""
    if a.dtype.kind not in _NUMERIC:
        raise ValueError(f"{name} must hold numbers, got dtype {a.dtype}")
    if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape,
                                                                           strict=True)):
        want = "(" + ", ".join("n" if s is None else str(s) for s in shape) + \
            ("," if len(shape) == 1 else "") + ")"
        raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    with np.errstate(over="ignore", invalid="ignore"):  # out-of-range values: refused later
        return np.asarray(a, dtype=dtype)


def _coords(a: np.ndarray, name: str, dtype, shape: tuple, nan_rows: bool = False
            ) -> np.ndarray:
    """:func:`_numbers` plus every value finite and within :data:`MAX_COORD` (with
    ``nan_rows``, rows that are all NaN are allowed: unknown)."""
    a = _numbers(a, name, dtype, shape)
    if not a.size or -MAX_COORD <= a.min() and a.max() <= MAX_COORD:  # False for NaN, inf
        return a
    with np.errstate(invalid="ignore"):
        ok = np.abs(a) <= MAX_COORD
    if nan_rows:
        ok |= np.isnan(a).all(axis=-1, keepdims=True)
        if ok.all():
            return a
    bad = np.argwhere(~ok)[0]
    value = float(a[tuple(bad)])
    what = "not finite" if not np.isfinite(value) else f"beyond {MAX_COORD:g} m"
    where = "" if a.ndim == 1 else f" row {int(bad[0])}"
    rule = " (a row is either finite or all NaN)" if nan_rows and np.isnan(value) else ""
    raise ValueError(f"{name}{where} holds {value!r}: {what}{rule}")


def _offsets(a: np.ndarray, n_points: int) -> np.ndarray:
    if a.dtype.kind not in "iu" or a.ndim != 1 or len(a) == 0:
        raise ValueError(f"offsets must be a non-empty 1-D integer array, got {a.dtype} "
                         f"{a.shape}")
    if a[0] != 0 or a[-1] != n_points or np.any(a[1:] < a[:-1]):
        raise ValueError("corrupt track: offsets do not index the points array (they must "
                         f"rise from 0 to {n_points})")
    return a.astype(np.int64, copy=False)


def _read_npz(path: Path, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The arrays ``keys`` of the ``.npz`` archive ``path`` that are present (other members
    are not read); a :class:`DataError` for anything but a sound archive of plain arrays."""
    out: dict[str, np.ndarray] = {}
    try:
        with open_regular(path, "track file", "track") as fh, zipfile.ZipFile(fh) as zf:
            for info in zf.infolist():
                key = info.filename[:-4] if info.filename.endswith(".npy") else None
                if key not in keys:
                    continue
                if key in out:
                    raise DataError(path, f"the archive holds array {key!r} twice")
                with zf.open(info) as fp:
                    out[key] = _read_member(path, key, fp, info.file_size)
    except FileNotFoundError:
        raise DataError(path, "file not found") from None
    except (zipfile.BadZipFile, zipfile.LargeZipFile, zlib.error, EOFError, OSError,
            ValueError, TypeError, NotImplementedError, RuntimeError) as exc:
        # RuntimeError: an encrypted member; NotImplementedError: an unknown compression
        raise DataError(path, f"unreadable track file ({type(exc).__name__}: "
                              f"{str(exc)[:200]})") from None
    return out


def _read_member(path: Path, key: str, fp: IO[bytes], size: int) -> np.ndarray:
    """One ``.npy`` member: header checked against the member's ``size`` before reading."""
    version = np.lib.format.read_magic(fp)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(fp)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(fp)
    else:
        raise DataError(path, f"array {key!r}: unsupported .npy format version {version}")
    if dtype.hasobject:
        raise DataError(path, f"array {key!r} holds Python objects (a pickle); refused")
    if any(n < 0 for n in shape):
        raise DataError(path, f"array {key!r}: negative shape {shape} in its header")
    nbytes = math.prod(shape) * dtype.itemsize
    stored = size - fp.tell()
    if nbytes != stored or nbytes > MAX_ARRAY_BYTES:
        raise DataError(path, f"array {key!r}: its header declares {dtype} {shape} "
                              f"({nbytes} bytes) but the archive holds {stored} bytes")
    buf = bytearray(nbytes)
    view = memoryview(buf)
    for start in range(0, nbytes, _CHUNK):  # chunks: decompressed data stays in the cache
        want = min(_CHUNK, nbytes - start)
        chunk = fp.read(want)
        if len(chunk) != want:
            raise DataError(path, f"array {key!r}: truncated data")
        view[start:start + len(chunk)] = chunk
    if fp.read(1):  # reading to the end checks the CRC
        raise DataError(path, f"array {key!r}: more data than its header declares")
    a = np.frombuffer(buf, dtype=dtype)
    return a.reshape(shape[::-1]).T if fortran else a.reshape(shape)
