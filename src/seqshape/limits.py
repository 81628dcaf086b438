"""What a value read from a user's file may be: the physical limits every reader shares.

One place for the numbers behind docs/datasets.md ("What the readers refuse"): a value beyond
them cannot come from a real sensor, vehicle or log (a unit or frame mistake, a file written in
another layout, or a corrupt file) and is refused with a :class:`~seqshape.errors.DataError`
naming the file, never read as data. The readers import the limits from here (the older names
in :mod:`seqshape.data.sequence`, :mod:`seqshape.camera` and :mod:`seqshape.data.track` are the
same objects).

Sweeps: :func:`check_sweep` is the one plausibility check of a LiDAR point array. A real sweep
has every coordinate within :data:`MAX_POINT_RANGE` of its sensor and a non-negative return
strength; a file of another layout read as this one (float64 values read as float32, three
floats per point read as four, random bytes) has a large share of points that break these
rules, and the refusal names the layout its byte length fits.

>>> import numpy as np
>>> pts = np.array([[1.0, 2.0, -1.5, 0.3]] * 200, dtype=np.float32)
>>> check_sweep(pts, "a.bin", "velodyne file").shape
(200, 4)
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from seqshape.errors import DataError

# ------------------------------------------------------------------------ boxes and positions

#: Largest box dimension (m): longer than any road vehicle (an articulated bus is 18-25 m);
#: a dimension <= 0 or above this is garbage.
MAX_BOX_SIZE = 30.0

#: Farthest (m) a box centre, a sensor or a trajectory point may be from the sensor frame's
#: origin.
MAX_RANGE = 1000.0

#: Largest coordinate (m) of a pose in a dataset's world frame (city, global, GPS Mercator):
#: 10,000 km, beyond any real frame, so only overflowed or corrupt values are refused.
MAX_WORLD = 1.0e7

#: Largest coordinate (m) of a point, pose or complete shape in a track file.
MAX_COORD = 1.0e4

#: A quaternion whose norm is within this of 1 is normalised; any other is refused.
QUATERNION_TOLERANCE = 1e-3

#: Largest magnitude of a 2D box coordinate (pixels) and of an entry of a projection matrix
#: (pixels; a focal length of 100,000 px is a 1,000x telephoto).
MAX_PIXEL = 1.0e5

#: Largest magnitude (rad) of an angle in a label row (a heading, an observation angle).
MAX_ANGLE = 2 * math.pi

#: Largest magnitude (rad) of a heading in a trajectory log: headings may be unwrapped (many
#: turns add up), but not beyond 160 turns, where float64 keeps far under a micro-radian.
MAX_UNWRAPPED_ANGLE = 1000.0

#: Largest translation (m) between two sensors of one vehicle (a calibration's ``Tr_*``).
MAX_SENSOR_OFFSET = 100.0

#: Largest object / track id (a KITTI track id; ids are written with four to six digits).
MAX_ID = 999_999

# ------------------------------------------------------------------------------------- sweeps

#: Largest coordinate magnitude (m) of a LiDAR point in its sensor frame: no automotive LiDAR
#: returns beyond a few hundred metres.
MAX_POINT_RANGE = 1000.0

#: Largest share of a sweep's finite points that may break the sweep rules (a coordinate
#: beyond :data:`MAX_POINT_RANGE`, a negative return strength): below it those points are
#: dropped with one warning, above it the file is refused (another layout, or corrupt).
MAX_BAD_POINT_SHARE = 0.01

# ------------------------------------------------------------------------------ file sizes

#: Largest file (bytes) read whole, by kind. Real files are far smaller (a KITTI sweep 2 MB,
#: a label file 1 MB, nuScenes' largest table 500 MB); a larger one is refused before reading.
MAX_FILE_BYTES = {"text": 1 << 28, "points": 1 << 29, "json": 1 << 32, "table": 1 << 31,
                  "track": 1 << 33, "mesh": 1 << 30, "image": 1 << 28}

#: Largest array (bytes) a track file may declare (a track holds a few MB).
MAX_ARRAY_BYTES = 1 << 31

#: Longest field (characters) of a CSV row (the ``csv`` module's own limit, named here).
MAX_CSV_FIELD = 131_072


# ------------------------------------------------------------------------------ sweep check


def check_sweep(points: np.ndarray, path, what: str, names: str = "x y z reflectance",
                strength: int | None = 3, file_bytes: int | None = None) -> np.ndarray:
    """``points`` ``(N, C)`` float32 (x, y, z first) of the sweep file ``path``, checked.

    Points with a NaN or an infinity are dropped (one warning naming the file and the count).
    A finite point with a coordinate beyond :data:`MAX_POINT_RANGE` or a negative return
    strength (column ``strength``; None: no such column) is impossible: up to
    :data:`MAX_BAD_POINT_SHARE` of them are dropped with the same warning, more is a
    :class:`DataError` naming the file, the share and the likely cause (for a headerless
    float32 file of ``file_bytes`` bytes: the other layout its length fits). The common case
    (every point valid) costs three reductions and no copy.
    """
    flat = points.reshape(-1)
    if not flat.size:
        return points
    with np.errstate(invalid="ignore"):
        ok = -MAX_POINT_RANGE <= flat.min() and flat.max() <= MAX_POINT_RANGE  # False for NaN
        if ok and strength is not None:
            ok = points[:, strength].min() >= 0
    if ok:
        return points
    return _drop_bad_points(points, Path(path), what, names, strength, file_bytes)


def _bad_rows(points: np.ndarray, strength: int | None) -> tuple[np.ndarray, np.ndarray]:
    """``(non-finite (N,), impossible (N,))`` rows of ``points``."""
    finite = np.isfinite(points).all(axis=1)
    with np.errstate(invalid="ignore"):
        far = (np.abs(points[:, :3]) > MAX_POINT_RANGE).any(axis=1)
        if strength is not None:
            far |= points[:, strength] < 0
    return ~finite, far & finite


def _drop_bad_points(points, path: Path, what, names, strength, file_bytes) -> np.ndarray:
    nonfinite, far, negative = _bad_rows(points, strength)
    impossible = far | negative
    n_bad, n_finite = int(impossible.sum()), int(len(points) - nonfinite.sum())
    if n_bad > MAX_BAD_POINT_SHARE * max(n_finite, 1):
        raise DataError(path, _sweep_refusal(points, far, negative, n_finite, what, names,
                                             strength, file_bytes))
    keep = ~(nonfinite | impossible)
    dropped = int(len(points) - keep.sum())
    if not dropped:  # a strength beyond the coordinates' range: allowed
        return points
    why = "a non-finite value" if not n_bad else (
        f"a non-finite value, a coordinate beyond {MAX_POINT_RANGE:g} m"
        + (" or a negative strength" if strength is not None else ""))
    warnings.warn(f"{path}: dropped {dropped} of {len(points)} points with {why}",
                  stacklevel=4)
    return points[keep]


def _bad_rows(points: np.ndarray, strength: int | None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(non-finite, far, negative strength)`` (N,) masks of ``points`` (the last two among
    the finite rows only)."""
    finite = np.isfinite(points).all(axis=1)
    with np.errstate(invalid="ignore"):
        far = (np.abs(points[:, :3]) > MAX_POINT_RANGE).any(axis=1) & finite
        negative = np.zeros(len(points), bool)
        if strength is not None:
            negative = (points[:, strength] < 0) & finite & ~far
    return ~finite, far, negative


def _sweep_refusal(points, far, negative, n_finite, what, names, strength,
                   file_bytes) -> str:
    share = (far.sum() + negative.sum()) / max(n_finite, 1)
    rules = []
    if far.any():
        rules.append(f"{far.mean():.0%} a coordinate beyond {MAX_POINT_RANGE:g} m")
    if negative.any():
        rules.append(f"{negative.mean():.0%} a negative {names.split()[strength]}")
    head = (f"{share:.0%} of the {n_finite} finite points are impossible "
            f"({', '.join(rules)}): not a plausible {what} of float32 ({names}) points")
    if file_bytes is not None:
        # the points are the whole file, in order (a headerless float32 file)
        data = np.ascontiguousarray(points).view(np.uint8).reshape(-1)[:file_bytes]
        layout = likely_layout(data, points.shape[1])
        return head + (f"; its {file_bytes} bytes read as {layout} give plausible points: "
                       "likely written in that layout" if layout else "; no other layout "
                       "fits: random or corrupt data")
    with np.errstate(invalid="ignore", over="ignore"):
        dist = np.sqrt((points[:, :3].astype(np.float64) ** 2).sum(1))
    dist = dist[np.isfinite(dist)]
    if len(dist) and np.median(dist) > MAX_POINT_RANGE:
        return head + (f"; the sweep lies {np.median(dist) / 1000:.3g} km from its sensor: "
                       "points of another log, or in world (city) coordinates")
    return head


#: layouts a headerless point file may have been written in: (dtype, columns)
#: (wider first: a narrower layout read as a wider one puts coordinates, half of them
#: negative, in the strength column, but a wider one read as narrower looks plausible)
_LAYOUTS = (("<f4", 5), ("<f4", 4), ("<f4", 3), ("<f8", 5), ("<f8", 4), ("<f8", 3))

#: bytes of a file :func:`likely_layout` looks at (a multiple of every layout's point size)
_SAMPLE_BYTES = 480 * 2048


def likely_layout(data, columns: int) -> str | None:
    """The layout a headerless float32 point file of ``columns`` columns was likely written
    in instead, from its bytes ``data`` (the first ~1 MB are enough), or None.

    A layout is named when the file's length fits it and its points are plausible: at least
    99 % finite with coordinates within :data:`MAX_POINT_RANGE`, a non-negative fourth
    column (reflectance, intensity) where it has one, and a median distance of at least
    0.5 m (float32 pairs read as float64 give tiny values).

    >>> import numpy as np
    >>> xyz = np.random.default_rng(0).normal(0, 20, (300, 3))
    >>> likely_layout(xyz.astype("<f8").tobytes(), 4), likely_layout(xyz.tobytes()[:-1], 4)
    ('float64 (N, 3)', None)
    """
    data = np.frombuffer(memoryview(data).cast("B"), np.uint8)
    size = len(data)
    sample = data[:_SAMPLE_BYTES]
    for dtype, cols in _LAYOUTS:
        width = np.dtype(dtype).itemsize * cols
        if (dtype, cols) == ("<f4", columns) or not size or size % width:
            continue
        other = np.frombuffer(sample[:len(sample) - len(sample) % width], dtype=dtype)
        other = other.reshape(-1, cols)
        with np.errstate(invalid="ignore", over="ignore"):
            good = np.isfinite(other).all(1) & (np.abs(other[:, :3]) <= MAX_POINT_RANGE).all(1)
            if cols > 3:
                good &= other[:, 3] >= 0
            if not len(other) or good.mean() < 1 - MAX_BAD_POINT_SHARE:
                continue
            dist = np.sqrt((other[good, :3].astype(np.float64) ** 2).sum(1))
        if np.median(dist) >= 0.5:
            kind = "float64" if dtype == "<f8" else "float32"
            return f"{kind} (N, {cols})"
    return None
