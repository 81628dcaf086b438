"""Planar motion primitives shared by the trajectory samplers (:mod:`seqshape.sim.trajectories`,
:mod:`seqshape.sim.traffic`) and the scene layouts: the :class:`Trajectory` record, the
kinematic bicycle model (:func:`bicycle_path`, see :mod:`seqshape.sim.trajectories` for the
model), rigid placement of a path (:func:`place_path`) and footprint tests
(:func:`footprint_distance`, :func:`footprints_overlap`).

They sit below both samplers so that neither imports the other's module back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MAX_STEER = math.radians(35.0)
_DS = 0.1  # arc-length step (m) of the path integration


@dataclass
class Trajectory:
    """A planar trajectory in the sensor frame: ``(T,)`` float64 arrays.

    ``x, y`` position of the vehicle's bounding-box centre (m), ``yaw`` its heading (rad,
    wrapped to [-pi, pi)), ``t`` time (s, strictly increasing). ``manoeuvre`` names how it was
    made ("straight", ..., or "csv"), ``source`` the CSV file when read from one.
    ``ego_x`` ``(T,)`` (traffic placement only, else None): how far the ego has driven along
    its own +x axis since the first frame (m); ``x, y, yaw`` are then in each frame's sensor
    frame. ``situation`` names the traffic situation ("" for the crossing placement).
    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    manoeuvre: str = ""
    source: str = ""
    ego_x: np.ndarray | None = None
    situation: str = ""

    def __post_init__(self):
        for k in ("t", "x", "y", "yaw"):
            setattr(self, k, np.asarray(getattr(self, k), dtype=np.float64).reshape(-1))
        if not len(self.t) == len(self.x) == len(self.y) == len(self.yaw):
            raise ValueError("trajectory arrays t, x, y, yaw differ in length")
        if self.ego_x is not None:
            self.ego_x = np.asarray(self.ego_x, dtype=np.float64).reshape(-1)
            if len(self.ego_x) != len(self.t):
                raise ValueError("trajectory ego_x differs in length from t")

    def __len__(self) -> int:
        return len(self.t)

    def poses(self, z: float) -> np.ndarray:
        """``(T, 4)`` poses (x, y, z, yaw) with a constant height ``z``."""
        return np.stack([self.x, self.y, np.full(len(self), float(z)), self.yaw], 1)

    def ego_poses(self, slope_x: float = 0.0) -> np.ndarray:
        """``(T, 4, 4)`` ego poses: sensor frame of frame t -> sensor frame of the first frame.

        The ego drives straight along +x by ``ego_x`` (identities when ``ego_x`` is None); on a
        ground of longitudinal slope ``slope_x`` (rise / run in the sensor frame) its sensor
        rises by ``slope_x * ego_x``, so the ground plane is the same in every frame.
        """
        out = np.tile(np.eye(4), (len(self), 1, 1))
        if self.ego_x is not None:
            out[:, 0, 3] = self.ego_x
            out[:, 2, 3] = slope_x * self.ego_x
        return out


# ------------------------------------------------------------------------ speed and steering

def _smooth_noise(rng, t: np.ndarray, amplitude: float) -> np.ndarray:
    """A smooth zero-mean signal: three sinusoids with periods of 3-15 s."""
    out = np.zeros_like(t)
    for _ in range(3):
        out += np.sin(2 * np.pi * t / rng.uniform(3.0, 15.0) + rng.uniform(0, 2 * np.pi))
    return amplitude * out / 3.0


def _speed_profile(rng, manoeuvre: str, t: np.ndarray) -> np.ndarray:
    """Speed (m/s) at times ``t`` for a manoeuvre (non-negative)."""
    if manoeuvre == "parked":
        return np.zeros_like(t)
    lo, hi = {"straight": (4.0, 14.0), "turn": (3.0, 8.0), "lane_change": (6.0, 14.0),
              "stop_and_go": (4.0, 10.0), "u_turn": (2.0, 5.0)}[manoeuvre]
    v0 = rng.uniform(lo, hi)
    v = v0 * (1.0 + _smooth_noise(rng, t, 0.12))
    if manoeuvre == "stop_and_go":
        dur = t[-1] - t[0] if len(t) > 1 else 0.0
        # comes to rest at t_zero inside the track (braking from earlier, or already slow)
        t_zero = t[0] + rng.uniform(0.2, 0.7) * dur
        dec, acc = rng.uniform(1.5, 3.0), rng.uniform(1.0, 2.5)
        wait = rng.uniform(1.0, 4.0)
        env = np.clip((t_zero - t) * dec, 0.0, None)              # braking ramp to 0
        env = np.where(t > t_zero, np.clip((t - t_zero - wait) * acc, 0.0, None), env)
        v = np.minimum(v, env)
    return np.maximum(v, 0.0)


def _trapezoid(s, s0, length, ramp, value):
    """A curvature pulse: linear ramp up, plateau, ramp down; its integral is ``value*(length)``."""
    ramp = min(ramp, length / 2)
    plateau = length - ramp
    up = np.clip((s - s0) / ramp, 0, 1)
    down = np.clip((s0 + plateau + ramp - s) / ramp, 0, 1)
    return value * np.minimum(up, down)


def _curvature(rng, manoeuvre: str, s: np.ndarray, total: float,
               road_curvature: float = 0.004) -> np.ndarray:
    """Path curvature (1/m) of the rear axle along arc length ``s`` for a manoeuvre; the road
    itself curves with an amplitude uniform in ``[0, road_curvature]``."""
    kappa = rng.uniform(0, road_curvature) * np.sin(2 * np.pi * s / rng.uniform(80, 300)
                                           + rng.uniform(0, 2 * np.pi))
    sign = rng.choice([-1.0, 1.0])
    if manoeuvre in ("turn", "u_turn"):
        if manoeuvre == "turn":
            angle, radius, ramp = math.radians(rng.uniform(60, 100)), rng.uniform(6, 20), 3.0
        else:
            angle, radius, ramp = math.pi, rng.uniform(4.5, 7.0), 1.5
        length = angle * radius  # arc length of the turn; the trapezoid keeps the total angle
        s0 = rng.uniform(0.1, 0.5) * max(total - length, 0.0)
        kappa = kappa + _trapezoid(s, s0, length, ramp, sign / radius)
    elif manoeuvre == "lane_change":
        shift, length = rng.uniform(3.0, 3.8), rng.uniform(25.0, 60.0)
        s0 = rng.uniform(0.1, 0.6) * max(total - length, 0.0)
        k0 = 2 * np.pi * shift / length ** 2
        inside = (s >= s0) & (s <= s0 + length)
        kappa = kappa + np.where(inside, sign * k0 * np.sin(2 * np.pi * (s - s0) / length), 0.0)
    return kappa


def bicycle_path(rng, manoeuvre: str, t: np.ndarray, wheelbase: float, speed_scale=1.0,
                 road_curvature: float = 0.004):
    """Integrate the bicycle model from the origin heading +x: centre ``x, y, yaw`` at ``t``
    (``road_curvature``: see :func:`_curvature`)."""
    v = _speed_profile(rng, manoeuvre, t) * speed_scale
    dt = np.diff(t, prepend=t[0])
    s_t = np.cumsum(0.5 * (v + np.concatenate([v[:1], v[:-1]])) * dt)  # trapezoidal arc length
    total = float(s_t[-1])
    s = np.arange(0.0, total + 2 * _DS, _DS)
    limit = math.tan(MAX_STEER) / wheelbase
    kappa = np.clip(_curvature(rng, manoeuvre, s, total, road_curvature), -limit, limit)
    psi = np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * _DS)])
    xr = np.concatenate([[0.0], np.cumsum(0.5 * (np.cos(psi[1:]) + np.cos(psi[:-1])) * _DS)])
    yr = np.concatenate([[0.0], np.cumsum(0.5 * (np.sin(psi[1:]) + np.sin(psi[:-1])) * _DS)])
    yaw = np.interp(s_t, s, psi)
    x = np.interp(s_t, s, xr) + wheelbase / 2 * np.cos(yaw)
    y = np.interp(s_t, s, yr) + wheelbase / 2 * np.sin(yaw)
    return x, y, yaw


# --------------------------------------------------------------------------------- placement

def footprint_distance(x, y, yaw, length: float, width: float) -> np.ndarray:
    """Planar distance ``(T,)`` from the sensor (origin) to the vehicle's footprint rectangle."""
    c, s = np.cos(yaw), np.sin(yaw)
    qx, qy = -(c * x + s * y), -(-s * x + c * y)  # sensor in the canonical frame
    dx = np.maximum(np.abs(qx) - length / 2, 0.0)
    dy = np.maximum(np.abs(qy) - width / 2, 0.0)
    return np.hypot(dx, dy)


def place_path(x, y, yaw, k: int, dist: float, bearing: float, heading: float):
    """Rigidly move a path so that frame ``k`` sits at ``dist, bearing`` with ``heading``."""
    rot = heading - yaw[k]
    c, s = math.cos(rot), math.sin(rot)
    xr, yr = c * x - s * y, s * x + c * y
    px, py = dist * math.cos(bearing), dist * math.sin(bearing)
    return xr - xr[k] + px, yr - yr[k] + py, yaw + rot


def footprints_overlap(poses_a, size_a, poses_b, size_b, margin: float = 0.3) -> np.ndarray:
    """Per frame, do two vehicles' footprints (grown by ``margin`` m) overlap? ``(T,)`` bool.

    ``poses_*`` are ``(T, 4)``; ``size_*`` (length, width, height). Separating-axis test.
    """
    pa, pb = np.asarray(poses_a, float), np.asarray(poses_b, float)
    ha = np.asarray(size_a[:2], float) / 2 + margin / 2
    hb = np.asarray(size_b[:2], float) / 2 + margin / 2
    axes_a = np.stack([np.stack([np.cos(pa[:, 3]), np.sin(pa[:, 3])], -1),
                       np.stack([-np.sin(pa[:, 3]), np.cos(pa[:, 3])], -1)], 1)  # (T, 2, 2)
    axes_b = np.stack([np.stack([np.cos(pb[:, 3]), np.sin(pb[:, 3])], -1),
                       np.stack([-np.sin(pb[:, 3]), np.cos(pb[:, 3])], -1)], 1)
    d = pb[:, :2] - pa[:, :2]
    separated = np.zeros(len(pa), dtype=bool)
    for axis in np.concatenate([axes_a, axes_b], 1).transpose(1, 0, 2):  # 4 axes of (T, 2)
        ra = np.abs(np.einsum("tij,tj->ti", axes_a, axis)) @ ha
        rb = np.abs(np.einsum("tij,tj->ti", axes_b, axis)) @ hb
        separated |= np.abs(np.einsum("ti,ti->t", d, axis)) > ra + rb
    return ~separated
