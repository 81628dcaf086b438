"""LiDAR odometry: a log's ego poses from its own sweeps.

The causal and offline smoothers, the shape average and the whole-track heading vote work in
the fixed frame of a log's ego poses (docs/model.md): a parked car is a constant there only if
the poses are right. Some logs' poses are not: the shared KITTI tracking log 0000's oxts poses
give 3.5 % less travel than its sweeps and jitter by about 5 cm from frame to frame
(``benchmarks/bm_ego_poses.py``), so a car parked while the ego drives by creeps 0.3-0.5 m in
their frame. Other logs have no ego poses at all.

:func:`lidar_odometry` registers each sweep to the one before it (point-to-point ICP over the
closest share of the point pairs, :func:`register`), started from the log's own relative
motion (or, without ego poses, from the last registered motion), and chains the results:

* only the static scene is used: the ground (points below ``min_z`` in the sensor frame), the
  ego's own returns (within ``min_range``) and far points (beyond ``max_range``, sparse) are
  left out, and the closest ``keep`` share of the pairs within ``max_pair`` drive each
  iteration, so moving vehicles (a small part of a sweep) are outvoted;
* a pair is trusted when the median distance of its matched points is at most
  ``max_residual`` and, with ego poses, the registered motion is within ``max_disagreement``
  of theirs; otherwise, and across a time gap over ``max_gap``, the log's own relative motion
  bridges the two sweeps (the identity without ego poses);
* the first frame keeps its ego pose (the identity without one), so the result stays in the
  log's reference frame up to the drift that the poses carried.

:func:`with_lidar_odometry` gives a :class:`~seqshape.data.sequence.DrivingLog` these poses
(``seqshape tracks --ego-poses lidar``, ``seqshape label --ego-poses lidar``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from seqshape._progress import progress
from seqshape.errors import ConfigError

#: Sources of the ego poses a log's tracks get: the log's own (``given``) or LiDAR odometry.
EGO_POSES = ("given", "lidar")


@dataclass(frozen=True)
class OdometryConfig:
    """How sweeps are registered (module doc).

    min_z: points at or below this height (m, sensor frame) are left out (the ground of a
        LiDAR mounted 1.5-2 m up).
    min_range, max_range: planar range (m) of the points used.
    voxel: the moving sweep's points are thinned to one per cube of this edge (m); the fixed
        sweep keeps all of its points.
    iterations: most ICP iterations of a pair.
    max_pair: a point pair further apart than this (m) is not matched.
    keep: share of the matched pairs (the closest) that drive an iteration.
    max_residual: a registration whose matched pairs' median distance (m) is above this has
        not converged.
    max_gap: sweeps further apart in time (s) are not registered (0.6: nuScenes' keyframes,
        2 Hz, are registered; a 10 Hz log's one dropped sweep too).
    max_disagreement: with ego poses, a registered motion whose translation differs from
        theirs by more than this (m) plus ``max_disagreement_share`` of their travel, or whose
        rotation differs by more than ``max_turn_deg``, is not trusted.
    min_points: a sweep with fewer usable points is not registered.
    """

    min_z: float = -1.3
    min_range: float = 3.0
    max_range: float = 40.0
    voxel: float = 0.15
    iterations: int = 40
    max_pair: float = 1.0
    keep: float = 0.8
    max_residual: float = 0.15
    max_gap: float = 0.6
    max_disagreement: float = 0.3
    max_disagreement_share: float = 0.25
    max_turn_deg: float = 3.0
    min_points: int = 200

    def __post_init__(self):
        for name in ("min_range", "max_range", "voxel", "max_pair", "max_residual", "max_gap",
                     "max_disagreement", "max_turn_deg"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ConfigError(f"OdometryConfig.{name} must be a positive number, got {v!r}")
        if not self.max_range > self.min_range:
            raise ConfigError(f"OdometryConfig.max_range ({self.max_range}) must exceed "
                              f"min_range ({self.min_range})")
        if not 0.0 < self.keep <= 1.0:
            raise ConfigError(f"OdometryConfig.keep must be in (0, 1], got {self.keep}")
        if self.iterations < 1 or self.min_points < 3:
            raise ConfigError("OdometryConfig.iterations must be >= 1 and min_points >= 3, "
                              f"got {self.iterations} and {self.min_points}")
        if not self.max_disagreement_share >= 0:
            raise ConfigError("OdometryConfig.max_disagreement_share must be >= 0, got "
                              f"{self.max_disagreement_share}")


@dataclass
class PairResult:
    """One registration: sweep ``b`` onto sweep ``a`` (log frame numbers).

    ``used``: whether the registered motion entered the chain (else ``reason`` says why and
    the log's own relative motion, or the identity, bridged the pair); ``residual_m``: median
    distance of the matched points after the last iteration (NaN: not registered);
    ``given_m``, ``lidar_m``: travel between the sweeps by the ego poses (NaN without) and by
    the registration."""

    a: int
    b: int
    used: bool
    reason: str = ""
    residual_m: float = math.nan
    given_m: float = math.nan
    lidar_m: float = math.nan


@dataclass
class Odometry:
    """:func:`lidar_odometry`'s result: ``poses`` (frame -> (4, 4) sensor frame -> the log's
    reference frame) and one :class:`PairResult` per pair of consecutive frames."""

    poses: dict[int, np.ndarray]
    pairs: list[PairResult] = field(default_factory=list)

    def summary(self) -> dict:
        """Pairs used / bridged, the median residual and the ratio of the ego poses' travel to
        the registered one over the pairs used (NaN when there is none)."""
        used = [p for p in self.pairs if p.used]
        moved = [p for p in used if np.isfinite(p.given_m) and p.lidar_m > 0.05]
        return {"pairs": len(self.pairs), "used": len(used),
                "bridged": len(self.pairs) - len(used),
                "residual_m": float(np.median([p.residual_m for p in used])) if used
                else math.nan,
                "travel_ratio": float(sum(p.given_m for p in moved)
                                      / sum(p.lidar_m for p in moved)) if moved else math.nan}


def registration_cloud(points: np.ndarray, config: OdometryConfig | None = None
                       ) -> np.ndarray:
    """The points of a sweep that a registration uses: above ``min_z`` and within the planar
    range band, float64 (M, 3)."""
    cfg = config or OdometryConfig()
    p = np.asarray(points, dtype=np.float64)
    p = p[:, :3] if p.ndim == 2 else p.reshape(-1, 3)  # (N, C >= 3), or an empty sweep
    p = p[np.all(np.isfinite(p), axis=1)]
    r = np.hypot(p[:, 0], p[:, 1])
    return p[(p[:, 2] > cfg.min_z) & (r > cfg.min_range) & (r < cfg.max_range)]


def thin(points: np.ndarray, voxel: float) -> np.ndarray:
    """One point per cube of edge ``voxel`` (the first in order). Only the moving side of a
    registration is thinned: thinning both sides ties each to its own grid and biases the
    registered travel (docs/history/model.md, "Ego poses from the sweeps")."""
    if not len(points):
        return points
    keys = np.floor(points / voxel).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return points[np.sort(first)]


def rigid_fit(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(4, 4) least-squares rigid motion taking points ``p (N, 3)`` onto ``q (N, 3)``
    (Kabsch / Umeyama without scale)."""
    mp, mq = p.mean(axis=0), q.mean(axis=0)
    u, _, vt = np.linalg.svd((p - mp).T @ (q - mq))
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = r, mq - r @ mp
    return out


def register(moving: np.ndarray, fixed: np.ndarray, init: np.ndarray | None = None,
             config: OdometryConfig | None = None, tree=None) -> tuple[np.ndarray, float]:
    """(4, 4) rigid motion taking ``moving (N, 3)`` onto ``fixed (M, 3)``, started from
    ``init`` (default the identity), and the median distance (m) of the matched pairs after
    the last iteration (NaN when too few pairs matched). ``tree``: a ``cKDTree`` of ``fixed``
    to reuse."""
    from scipy.spatial import cKDTree

    cfg = config or OdometryConfig()
    tree = cKDTree(fixed) if tree is None else tree
    T = np.eye(4) if init is None else np.array(init, dtype=np.float64).reshape(4, 4)
    residual = math.nan
    for _ in range(cfg.iterations):
        moved = moving @ T[:3, :3].T + T[:3, 3]
        d, i = tree.query(moved, distance_upper_bound=cfg.max_pair)
        ok = np.isfinite(d)
        if ok.sum() < cfg.min_points // 2:
            return T, math.nan
        ok &= d <= np.quantile(d[ok], cfg.keep)
        step = rigid_fit(moved[ok], fixed[i[ok]])
        T = step @ T
        residual = float(np.median(d[ok]))
        if np.linalg.norm(step[:3, 3]) < 1e-4 and _turn(step) < 1e-5:
            break
    return T, residual


def _turn(m: np.ndarray) -> float:
    """The rotation angle (rad) of the rigid motion ``m (4, 4)``."""
    return math.acos(float(np.clip((np.trace(m[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))


def lidar_odometry(log, frames: Sequence[int] | None = None,
                   config: OdometryConfig | None = None, show_progress: bool | None = None
                   ) -> Odometry:
    """Ego poses of ``frames`` (default: all of the log's, in order) from the log's sweeps
    (module doc). ``log``: a :class:`~seqshape.data.sequence.DrivingLog`."""
    from scipy.spatial import cKDTree

    cfg = config or OdometryConfig()
    frames = sorted(int(f) for f in (log.frames if frames is None else frames))
    poses: dict[int, np.ndarray] = {}
    pairs: list[PairResult] = []
    prev = None  # (frame, time, given pose, cloud, tree)
    last_motion = None  # (relative (4, 4), seconds) of the last pair used
    bar = progress(frames, desc=f"odometry {log.name}", unit="sweep",
                   disable=True if not frames else None if show_progress is None
                   else not show_progress)
    for f in bar:
        given = log.ego_pose(f)
        given = None if given is None else np.asarray(given, dtype=np.float64)
        time = float(log.timestamp(f))
        cloud = registration_cloud(log.points(f), cfg)
        tree = cKDTree(cloud) if len(cloud) >= cfg.min_points else None
        moving = thin(cloud, cfg.voxel)
        if prev is None:
            poses[f] = np.eye(4) if given is None else given.copy()
        else:
            a, t_a, given_a, cloud_a, tree_a = prev
            rel_given = (np.linalg.inv(given_a) @ given
                         if given is not None and given_a is not None else None)
            res = PairResult(a, f, False, given_m=math.nan if rel_given is None else
                             float(np.linalg.norm(rel_given[:3, 3])))
            dt = time - t_a
            if not 0.0 < dt <= cfg.max_gap:
                res.reason = f"{dt:.2f} s apart"
            elif tree is None or tree_a is None:
                res.reason = "too few points"
            else:
                init = rel_given
                if init is None and last_motion is not None:
                    init = _scaled_motion(*last_motion, dt)
                rel, res.residual_m = register(moving, cloud_a, init, cfg, tree_a)
                res.lidar_m = float(np.linalg.norm(rel[:3, 3]))
                if not res.residual_m <= cfg.max_residual:
                    res.reason = "not converged"
                elif rel_given is not None and (
                        np.linalg.norm(rel[:3, 3] - rel_given[:3, 3]) > cfg.max_disagreement
                        + cfg.max_disagreement_share * res.given_m
                        or math.degrees(_turn(np.linalg.inv(rel_given) @ rel))
                        > cfg.max_turn_deg):
                    res.reason = "disagrees with the ego poses"
                else:
                    res.used = True
                    last_motion = (rel, dt)
            if not res.used:
                rel = rel_given if rel_given is not None else np.eye(4)
            poses[f] = poses[a] @ rel
            pairs.append(res)
        prev = (f, time, given, cloud, tree)
    return Odometry(poses, pairs)


def _scaled_motion(rel: np.ndarray, dt: float, new_dt: float) -> np.ndarray:
    """A relative motion ``rel`` over ``dt`` seconds extrapolated to ``new_dt`` (constant
    velocity: the rotation angle and the translation scaled; exact for small angles)."""
    from scipy.spatial.transform import Rotation

    s = new_dt / dt
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(Rotation.from_matrix(rel[:3, :3]).as_rotvec() * s
                                       ).as_matrix()
    out[:3, 3] = rel[:3, 3] * s
    return out


def with_lidar_odometry(log, config: OdometryConfig | None = None,
                        show_progress: bool | None = None):
    """``log`` (in place; returned) with its ``ego_pose(frame)`` replaced by
    :func:`lidar_odometry` over its frames, ``ego_pose_source`` ``"lidar"``; the
    :class:`Odometry` is kept as ``log.odometry``. Frames outside ``log.frames`` get None."""
    odo = lidar_odometry(log, config=config, show_progress=show_progress)
    log.ego_pose = OdometryPoses(odo.poses)
    log.ego_pose_source = "lidar"
    log.odometry = odo
    return log


class OdometryPoses:
    """``ego_pose(frame)`` of a log given :func:`with_lidar_odometry`: a copy of the frame's
    registered pose, None for another frame (a class, not a closure: the log still pickles
    for worker processes)."""

    def __init__(self, poses: dict[int, np.ndarray]):
        self.poses = poses

    def __call__(self, frame: int) -> np.ndarray | None:
        pose = self.poses.get(int(frame))
        return None if pose is None else pose.copy()

