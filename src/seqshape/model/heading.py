"""Heading post-processing: undo 180-degree flips of the network's yaw, per track.

A partial view of a vehicle is nearly symmetric front to back, so the network's yaw is
sometimes off by pi. Two pieces of evidence disambiguate it, both over the track rather than
one frame:

* **motion**: vehicles drive forwards. The track's estimated centres, in a FIXED frame, are
  fitted with a straight line over the last ``motion_frames`` frames with points; when the
  fitted travel is at least ``min_travel`` and the positions advance steadily along it
  (correlation of frame order and position along the line at least ``min_consistency``), its
  direction is the heading up to the vehicle reversing. Sensor-frame positions are confounded
  by the ego vehicle's own motion (a parked car passed by the ego "moves" backwards), so this is
  used only with per-frame ego poses (sensor frame -> fixed frame) or when the sensor is
  declared static (``static_sensor``, e.g. the synthetic generator's).
* **vote** (opt-in): a decaying vote of the raw yaws (unit vectors in the fixed frame, or the
  sensor frame without ego poses: the ego turns far less than 90 degrees between frames), with
  the motion-confirmed headings weighted ``motion_weight``. A raw yaw more than 90 degrees from
  the vote is flipped: an isolated flip of a parked or slow vehicle is outvoted by its
  neighbours.

A flip sets ``yaw += pi`` and keeps the placed complete shape as it is (the same point set in
the sensor frame, i.e. the canonical shape turned by pi): the shape was fitted to the observed
points by the Chamfer loss and is right where it stands; only the label of which end is the
front was wrong. Centre, extents and Chamfer distance are therefore unchanged; only the yaw is.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from seqshape.errors import ConfigError


@dataclass(frozen=True)
class HeadingConfig:
    """Options of the :class:`seqshape.Estimator` heading post-processing."""

    motion: bool = True
    """Flip the yaw against a confident motion direction (needs ego poses per step, or
    ``static_sensor``; without either it does nothing)."""
    static_sensor: bool = False
    """The sensor does not move: sensor-frame positions are fixed-frame positions."""
    min_travel: float = 1.5
    """Fitted travel (m) over the motion frames needed to trust the motion direction."""
    motion_frames: int = 10
    """Frames with points (the latest ones) the motion line is fitted to (at least 3)."""
    min_consistency: float = 0.8
    """Minimum correlation of frame order and position along the motion line."""
    vote: bool = False
    """Also flip raw yaws that disagree by more than 90 degrees with the track's vote."""
    vote_decay: float = 0.8
    """Per-frame decay of the vote (memory of about 1 / (1 - decay) frames)."""
    motion_weight: float = 3.0
    """Weight, in the vote, of a heading confirmed by motion (a raw yaw weighs 1)."""

    def __post_init__(self):
        if int(self.motion_frames) < 3:
            raise ConfigError(f"HeadingConfig.motion_frames must be >= 3, got "
                              f"{self.motion_frames}")
        if not 0.0 <= self.vote_decay < 1.0:
            raise ConfigError(f"HeadingConfig.vote_decay must be in [0, 1), got "
                              f"{self.vote_decay}")

    @property
    def active_without_poses(self) -> bool:
        """Whether anything is done on a step without ego poses."""
        return self.vote or (self.motion and self.static_sensor)


def wrap_angle(a: float) -> float:
    """``a`` wrapped to [-pi, pi)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def motion_direction(positions: np.ndarray, min_travel: float,
                     min_consistency: float) -> float | None:
    """Direction (rad) of a confident straight motion through ``positions`` (k, 2) in frame
    order, or None.

    Least-squares line ``p = a + v t`` over t = 0..k-1: travel ``|v| (k - 1)`` must reach
    ``min_travel`` and the correlation of t with the positions' projections on ``v`` must reach
    ``min_consistency`` (steady progress, not noise around a parked position).
    """
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    k = len(p)
    if k < 3:
        return None
    t = np.arange(k, dtype=np.float64) - (k - 1) / 2.0
    v = (t[:, None] * (p - p.mean(0))).sum(0) / (t * t).sum()
    speed = float(np.hypot(*v))
    if speed * (k - 1) < min_travel:
        return None
    along = (p - p.mean(0)) @ (v / speed)
    sd = float(along.std())
    if sd <= 0 or float((t * along).mean() / (t.std() * sd)) < min_consistency:
        return None
    return math.atan2(v[1], v[0])


def pose_yaw(ego_pose: np.ndarray) -> float:
    """Yaw of a (4, 4) pose's rotation about z."""
    return math.atan2(float(ego_pose[1, 0]), float(ego_pose[0, 0]))


class HeadingFilter:
    """One track's heading evidence; :meth:`update` says whether to flip this frame's yaw."""

    def __init__(self, cfg: HeadingConfig):
        self.cfg = cfg
        self.positions: deque[tuple[float, float]] = deque(maxlen=int(cfg.motion_frames))
        self.vote = np.zeros(2)

    def update(self, pose: np.ndarray, ego_pose: np.ndarray | None, has_points: bool) -> bool:
        """Feed this frame's raw estimate ``pose`` (x, y, z, yaw) in the sensor frame;
        ``ego_pose`` (4, 4) sensor -> fixed frame (None: none given). Returns True when the
        yaw is to be flipped by pi."""
        cfg = self.cfg
        fixed = ego_pose is not None or cfg.static_sensor
        yaw = float(pose[3])
        if ego_pose is not None:
            centre = ego_pose[:3, :3] @ np.asarray(pose[:3], np.float64) + ego_pose[:3, 3]
            yaw += pose_yaw(ego_pose)
        else:
            centre = np.asarray(pose[:3], np.float64)
        target = None
        if cfg.motion and fixed:
            if has_points:
                self.positions.append((float(centre[0]), float(centre[1])))
            target = motion_direction(np.array(self.positions), cfg.min_travel,
                                      cfg.min_consistency)
        moving = target is not None
        if not moving and cfg.vote and self.vote.any():
            target = math.atan2(self.vote[1], self.vote[0])
        flip = target is not None and abs(wrap_angle(yaw - target)) > math.pi / 2
        if cfg.vote and has_points:
            # a majority vote of the raw yaws, plus the motion-confirmed ones (weighted)
            vote_yaw, w = (yaw + math.pi if flip else yaw, cfg.motion_weight) if moving \
                else (yaw, 1.0)
            self.vote = cfg.vote_decay * self.vote + w * np.array([math.cos(vote_yaw),
                                                                   math.sin(vote_yaw)])
        return flip
