"""The Track, the unit of data, and its on-disk form (one ``.npz`` file per track).

File format ``seqshape-track`` version 1 (see docs/data-format.md):

=============  ===============  ===================================================
array          dtype, shape     meaning
=============  ===============  ===================================================
points         float32 (P, 3)   all frames' points, concatenated in frame order
offsets        int64 (T + 1,)   frame t holds ``points[offsets[t]:offsets[t + 1]]``
poses          float64 (T, 4)   ground-truth (x, y, z, yaw) per frame; NaN rows unknown
timestamps     float64 (T,)     seconds
size           float64 (3,)     length, width, height of the bounding box (m)
complete       float32 (M, 3)   complete outside surface, canonical frame (optional)
meta           str (JSON)       dict: mesh id, sensor, split, generator version, seed ...
version        int64 ()         format version (1)
=============  ===============  ===================================================
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from seqshape._io import atomic_save_npz
from seqshape.errors import DataError
from seqshape.geometry import canonical_to_sensor

TRACK_FORMAT_VERSION = 1
_REQUIRED = ("points", "offsets", "poses", "timestamps", "size", "meta")


@dataclass
class Track:
    """A sequence of partial point clouds of one vehicle, with its ground truth.

    ``points[t]`` is an ``(N_t, 3)`` float32 array in frame t's sensor frame (``N_t`` may be 0);
    ``poses[t]`` the vehicle's (x, y, z, yaw) in that frame; ``complete`` the complete outside
    surface in the canonical frame, or None when unknown (real data).
    """

    track_id: str
    points: list[np.ndarray]
    poses: np.ndarray
    complete: np.ndarray | None
    size: np.ndarray
    timestamps: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        self.points = [np.asarray(p, dtype=np.float32).reshape(-1, 3) for p in self.points]
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4)
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        self.size = np.asarray(self.size, dtype=np.float64).reshape(3)
        if self.complete is not None:
            self.complete = np.asarray(self.complete, dtype=np.float32).reshape(-1, 3)
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

    def slice(self, start: int, stop: int) -> Track:
        """Frames ``start:stop`` as a new Track (arrays shared, not copied)."""
        return Track(self.track_id, self.points[start:stop], self.poses[start:stop],
                     self.complete, self.size, self.timestamps[start:stop], dict(self.meta))


def save_track(path: str | Path, track: Track, compressed: bool = True) -> None:
    """Write ``track`` to ``path`` (.npz) atomically."""
    offsets = np.zeros(len(track) + 1, dtype=np.int64)
    offsets[1:] = np.cumsum(track.num_points)
    points = (np.concatenate(track.points) if len(track) else np.zeros((0, 3), np.float32))
    arrays = dict(points=points.astype(np.float32), offsets=offsets, poses=track.poses,
                  timestamps=track.timestamps, size=track.size,
                  meta=np.array(json.dumps({"track_id": track.track_id, **track.meta})),
                  version=np.array(TRACK_FORMAT_VERSION, dtype=np.int64))
    if track.complete is not None:
        arrays["complete"] = track.complete
    atomic_save_npz(path, compressed=compressed, **arrays)


def load_track(path: str | Path) -> Track:
    """Read a track written by :func:`save_track`; a bad file raises :class:`DataError`."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in _REQUIRED if k not in z.files]
            if missing:
                raise DataError(path, f"not a seqshape track: missing arrays {missing}")
            version = int(z["version"]) if "version" in z.files else 1
            if version > TRACK_FORMAT_VERSION:
                raise DataError(path, f"track format version {version} is newer than this "
                                      f"seqshape understands ({TRACK_FORMAT_VERSION}); upgrade")
            arr = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise DataError(path, "file not found") from None
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise DataError(path, f"unreadable track file ({exc})") from None
    offsets = arr["offsets"]
    points = arr["points"]
    if offsets.ndim != 1 or offsets[0] != 0 or offsets[-1] != len(points) or np.any(
            np.diff(offsets) < 0):
        raise DataError(path, "corrupt track: offsets do not index the points array")
    try:
        meta = json.loads(str(arr["meta"]))
    except json.JSONDecodeError as exc:
        raise DataError(path, f"corrupt track metadata ({exc})") from None
    track_id = meta.pop("track_id", path.stem)
    frames = [points[offsets[i]:offsets[i + 1]] for i in range(len(offsets) - 1)]
    try:
        return Track(track_id, frames, arr["poses"], arr.get("complete"), arr["size"],
                     arr["timestamps"], meta)
    except ValueError as exc:
        raise DataError(path, str(exc)) from None
