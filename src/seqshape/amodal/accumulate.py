"""GT-Accumulation: the paper's shape from boxes alone, and track export for fine-tuning.

A track's partial segments (each in its frame's sensor frame) are mapped into the canonical
vehicle frame with the ground-truth poses (``sensor_to_canonical``), concatenated, and mirrored
about the heading axis (the canonical x axis: ``y -> -y``, vehicles being left-right
symmetric). The result, thinned on a voxel grid so its density is even, is then placed back in
every frame with that frame's pose (``canonical_to_sensor``). Frames whose pose is unknown
(NaN) get an empty cloud.

The accumulation in the canonical frame, the mirroring and the voxel thinning live in the data
layer (:mod:`seqshape.data.reference`, which also makes the cleaned, resampled reference shapes
of real tracks); they are re-exported here under their old names.

:func:`export_tracks` writes KITTI tracks as a :class:`~seqshape.data.TrackDataset` whose
``complete`` shape is this mirrored accumulation, so ``seqshape train --data DIR`` can fine-tune
the sequential model on the very data to be labelled, as the paper does for SC-GT.
"""

from __future__ import annotations

import logging
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from seqshape.data.dataset import write_dataset
from seqshape.data.reference import (
    BOX_MARGIN,
    VOXEL,
    accumulate_canonical,
    mirror_y,
    voxel_downsample,
)
from seqshape.data.track import Track
from seqshape.geometry import canonical_to_sensor

__all__ = ["BOX_MARGIN", "VOXEL", "accumulate_canonical", "export_tracks",
           "gt_accumulation_clouds", "mirror_y", "place_in_frames", "voxel_downsample"]

log = logging.getLogger(__name__)


def place_in_frames(canonical, poses) -> list[np.ndarray]:
    """A canonical cloud placed with each pose ``(T, 4)``: T arrays ``(M, 3)`` (empty if NaN)."""
    canonical = np.asarray(canonical, dtype=np.float32).reshape(-1, 3)
    return [canonical_to_sensor(canonical, pose) if np.all(np.isfinite(pose))
            else np.zeros((0, 3), np.float32) for pose in np.asarray(poses).reshape(-1, 4)]


def gt_accumulation_clouds(track: Track, **kwargs) -> list[np.ndarray]:
    """GT-Accumulation of one track: the mirrored accumulation in every frame's sensor frame."""
    return place_in_frames(accumulate_canonical(track, **kwargs), track.poses)


def export_tracks(tracks: Sequence[Track], out: str | Path, val_fraction: float = 0.2,
                  min_points: int = 50, **kwargs):
    """Write ``tracks`` as a TrackDataset whose ``complete`` is the mirrored accumulation.

    Tracks with fewer than ``min_points`` accumulated points are left out (their reference
    shape would be meaningless). About ``val_fraction`` of the tracks (chosen by a stable hash of
    the track id) go to the "val" split, the rest to "train", so that ``seqshape train --data
    out`` works directly: there is always at least one "train" track, and at least one "val"
    track when two or more tracks are kept and ``val_fraction > 0`` (a single track is "train"
    only; the trainer then skips validation with a warning). Returns the opened dataset.
    """
    if not 0 <= val_fraction < 1:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    kept = []
    for tr in tracks:
        complete = accumulate_canonical(tr, **kwargs)
        if len(complete) < min_points:
            log.info("export: track %s skipped (%d accumulated points)", tr.track_id,
                     len(complete))
            continue
        h = zlib.crc32(tr.track_id.encode()) % 1000 / 1000
        meta = {**tr.meta, "split": "val" if h < val_fraction else "train",
                "complete_source": "mirrored-accumulation"}
        kept.append(Track(tr.track_id, tr.points, tr.poses, complete, tr.size, tr.timestamps,
                          meta))
    if not kept:
        raise ValueError("no track has enough points to export")
    splits = [t.meta["split"] for t in kept]
    if "train" not in splits:  # every track hashed into val: keep one for training
        kept[0].meta["split"] = "train"
    elif "val" not in splits and len(kept) > 1 and val_fraction > 0:
        kept[-1].meta["split"] = "val"
    log.info("export: %d train / %d val tracks", sum(t.meta["split"] == "train" for t in kept),
             sum(t.meta["split"] == "val" for t in kept))
    return write_dataset(out, kept, config={"source": "seqshape label --export-tracks",
                                            "val_fraction": val_fraction})
