"""Planar vehicle trajectories in the sensor frame: a kinematic bicycle model, or CSV logs.

The model is the kinematic bicycle with the reference point on the rear axle:

    x' = v cos(psi),   y' = v sin(psi),   psi' = v tan(delta) / L,

with wheelbase ``L`` (60 % of the vehicle's length, axles symmetric about the box centre).
The steering ``delta`` is given as a function of the travelled arc length (so the path of a
manoeuvre keeps its geometry whatever the speed) and the speed ``v`` as a function of time; the
steering is limited to 35 degrees. The pose reported is that of the bounding-box centre, half a
wheelbase ahead of the rear axle, which has the small side-slip of a real car in a turn.

Manoeuvres: ``straight`` (gently curved road), ``turn`` (60-100 deg at an intersection),
``lane_change``, ``stop_and_go``, ``u_turn`` and ``parked``. Two placements:

* ``"crossing"`` (the paper, realistic presets): the vehicle passes a static sensor: at a random
  frame it is at the sampled closest distance (3 to 0.75 * max_distance m, log-uniform) moving
  across the line of sight with a varied heading;
* ``"traffic"`` (the real preset, :func:`sample_traffic`): a straight road through the sensor,
  the ego on one of its lanes (3.5 m wide) driving along +x at a sampled speed (0: stopped);
  the target drives in the ego's direction on any of its lanes, oncoming on the opposite
  lanes, on a cross road at an intersection, or is parked at the kerb. The track is expressed
  in each frame's sensor frame (the ego's motion is taken out) and ``Trajectory.ego_x`` holds
  how far the ego has driven; no footprint overlaps the ego's (``EGO_SIZE``).

In both, no frame brings the target's footprint closer than ``min_clearance`` to the sensor or
its centre closer than ``min_distance``, and speeds are scaled down so that the track stays
within ``max_distance``. Angles: yaw counter-clockwise from +x; the *view angle*
(:func:`view_angle`) is the angle between the vehicle's heading and the direction from its
centre to the sensor: 0 deg the sensor sees the nose, 180 deg the tail, 90 deg a side.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
from scipy.optimize import brentq
from scipy.special import ndtr

import seqshape.limits as limits
from seqshape._io import read_text
from seqshape.errors import ConfigError, DataError
from seqshape.sim.kinematics import (  # noqa: F401  (re-exported: their former home)
    MAX_STEER,
    Trajectory,
    bicycle_path,
    footprint_distance,
    footprints_overlap,
)
from seqshape.sim.kinematics import place_path as _place
from seqshape.sim.traffic import sample_traffic

MANOEUVRES = {"straight": 0.32, "turn": 0.18, "lane_change": 0.15, "stop_and_go": 0.12,
              "u_turn": 0.05, "parked": 0.18}
PLACEMENTS = ("crossing", "traffic")


# --------------------------------------------------------------------------- track lengths

def _truncated_lognormal_mean(mu: float, sigma: float, lo: float, hi: float) -> float:
    a, b = (math.log(lo) - mu) / sigma, (math.log(hi) - mu) / sigma
    return math.exp(mu + sigma ** 2 / 2) * (ndtr(b - sigma) - ndtr(a - sigma)) / (ndtr(b) - ndtr(a))


def track_length_location(min_frames: int, max_frames: int, mean_frames: float,
                          sigma: float = 0.7) -> float:
    """The log-normal location ``mu`` whose truncation to ``[min_frames, max_frames]`` has the
    mean ``mean_frames`` (:class:`ConfigError` naming the reachable means when there is none)."""
    if not 1 <= min_frames <= mean_frames <= max_frames:
        raise ConfigError(f"need 1 <= min_frames ({min_frames}) <= mean_frames ({mean_frames}) "
                          f"<= max_frames ({max_frames})")
    lo, hi = min_frames - 0.5, max_frames + 0.5
    bracket = (math.log(lo) - 5 * sigma, math.log(hi) + 5 * sigma)
    reach = [_truncated_lognormal_mean(m, sigma, lo, hi) for m in bracket]
    if not reach[0] <= mean_frames <= reach[1]:
        raise ConfigError(f"a mean track length of {mean_frames} frames cannot be drawn between "
                          f"{min_frames} and {max_frames} frames with sigma {sigma}: choose a "
                          f"mean in [{math.ceil(reach[0] * 10) / 10}, "
                          f"{math.floor(reach[1] * 10) / 10}]")
    return brentq(lambda m: _truncated_lognormal_mean(m, sigma, lo, hi) - mean_frames, *bracket)


def sample_track_length(rng: np.random.Generator, min_frames: int = 10, max_frames: int = 200,
                        mean_frames: float = 70.0, sigma: float = 0.7) -> int:
    """A track length in ``[min_frames, max_frames]``: log-normal truncated to that range, with
    its location chosen so that the truncated mean is ``mean_frames``."""
    if min_frames == max_frames and 1 <= min_frames == mean_frames:
        return int(min_frames)
    mu = track_length_location(min_frames, max_frames, mean_frames, sigma)
    while True:
        n = int(round(rng.lognormal(mu, sigma)))
        if min_frames <= n <= max_frames:
            return n


def sample_trajectory(rng: np.random.Generator, n_frames: int | None = None,
                      manoeuvre: str | None = None, length: float = 4.5, width: float = 1.8,
                      rate_hz: float = 10.0, min_distance: float = 3.0,
                      max_distance: float = 60.0, min_clearance: float = 1.5,
                      min_frames: int = 10, max_frames: int = 200,
                      mean_frames: float = 70.0, placement: str = "crossing",
                      ego_x: np.ndarray | None = None) -> Trajectory:
    """A random track of a ``length x width`` vehicle near the sensor (see module doc).

    ``n_frames`` / ``manoeuvre`` are drawn when None (lengths from
    :func:`sample_track_length`, manoeuvres with the weights of ``MANOEUVRES``, or of
    ``seqshape.sim.traffic.TRAFFIC_MANOEUVRES`` for the traffic placement). ``placement``:
    ``"crossing"`` or ``"traffic"`` (:func:`seqshape.sim.traffic.sample_traffic`, which also
    takes a given ego motion ``ego_x`` ``(n_frames,)``; ignored by the crossing placement).
    """
    if placement not in PLACEMENTS:
        raise ConfigError(f"unknown placement {placement!r}; choose from {list(PLACEMENTS)}")
    if placement == "traffic":
        return _traffic(rng, n_frames, manoeuvre, length, width, rate_hz, min_distance,
                        max_distance, min_clearance, min_frames, max_frames, mean_frames, ego_x)
    if manoeuvre is None:
        names = list(MANOEUVRES)
        manoeuvre = names[rng.choice(len(names), p=np.array(list(MANOEUVRES.values())))]
    if manoeuvre not in MANOEUVRES:
        raise ConfigError(f"unknown manoeuvre {manoeuvre!r}; choose from {sorted(MANOEUVRES)}")
    if not 0 < min_distance < max_distance:
        raise ConfigError(f"need 0 < min_distance ({min_distance}) < max_distance "
                          f"({max_distance})")
    if n_frames is None:
        n_frames = sample_track_length(rng, min_frames, max_frames, mean_frames)
    t = np.arange(int(n_frames)) / rate_hz
    wheelbase = 0.6 * length
    near = max(min_distance, min_clearance + math.hypot(length, width) / 2)
    far = max(near + 1.0, 0.75 * max_distance)
    dist = math.exp(rng.uniform(math.log(near), math.log(far)))
    bearing = rng.uniform(-math.pi, math.pi)
    k = int(rng.integers(0, n_frames))
    if manoeuvre == "parked":
        heading = rng.uniform(-math.pi, math.pi)
    else:
        heading = bearing + rng.choice([-1.0, 1.0]) * math.pi / 2 + rng.normal(0, 0.35)
    path_seed = rng.integers(2 ** 63)
    scale = 1.0
    for _ in range(12):
        # the same path draws at every attempt: only the speed scale and the offset change
        x, y, yaw = bicycle_path(np.random.default_rng(path_seed), manoeuvre, t, wheelbase,
                                 scale)
        d = dist
        for _ in range(20):
            px, py, pyaw = _place(x, y, yaw, k, d, bearing, heading)
            gap = np.minimum(footprint_distance(px, py, pyaw, length, width) - min_clearance,
                             np.hypot(px, py) - min_distance).min()
            if gap >= 0:
                break
            d += 0.5 - gap
        reach = np.hypot(px, py).max()
        if reach <= max_distance or manoeuvre == "parked":
            break
        scale *= 0.9 * max(max_distance - d, 1.0) / max(reach - d, 1.0)
    return Trajectory(t, px, py, (pyaw + np.pi) % (2 * np.pi) - np.pi, manoeuvre)


def _traffic(rng, n_frames, manoeuvre, length, width, rate_hz, min_distance, max_distance,
             min_clearance, min_frames, max_frames, mean_frames, ego_x) -> Trajectory:
    if not 0 < min_distance < max_distance:
        raise ConfigError(f"need 0 < min_distance ({min_distance}) < max_distance "
                          f"({max_distance})")
    if n_frames is None:
        n_frames = len(ego_x) if ego_x is not None else sample_track_length(
            rng, min_frames, max_frames, mean_frames)
    t = np.arange(int(n_frames)) / rate_hz
    return sample_traffic(rng, t, manoeuvre, length, width, min_distance, max_distance,
                          min_clearance, ego_x)


def view_angle(x, y, yaw) -> np.ndarray:
    """Degrees ``[0, 180]`` between a vehicle's heading ``yaw`` and the direction from its
    centre ``(x, y)`` (sensor frame) to the sensor: 0 the sensor sees the nose, 90 a side,
    180 the tail. Arrays broadcast."""
    to_sensor = np.arctan2(-np.asarray(y, float), -np.asarray(x, float))
    return np.degrees(np.abs((to_sensor - np.asarray(yaw, float) + np.pi) % (2 * np.pi) - np.pi))


# ---------------------------------------------------------------------------------- CSV logs

_COLUMNS = ("t", "x", "y", "yaw")


def read_trajectory_csv(path: str | Path) -> Trajectory:
    """Read a trajectory from a CSV file with a header naming the columns ``t, x, y, yaw``.

    Columns may come in any order (extra columns are ignored); units are seconds, metres and
    radians; positions are the bounding-box centre in the sensor frame. Each row becomes one
    LiDAR frame. Raises :class:`DataError` naming the file (and line) for a missing,
    non-regular (a FIFO, a folder) or over-long file, a missing or repeated column, a field
    over ``limits.MAX_CSV_FIELD`` characters or another CSV error, a malformed or non-finite
    number, a position beyond ``limits.MAX_RANGE`` from the sensor, a heading beyond
    ``limits.MAX_UNWRAPPED_ANGLE`` rad, or times that do not strictly increase.
    """
    path = Path(path)
    text = read_text(path, "trajectory file", encoding="utf-8-sig")
    rows = _csv_rows(text, path)
    if not rows or not any(c.strip() for c in rows[0]):
        raise DataError(path, "empty file: expected a header with columns t,x,y,yaw", line=1)
    header = [c.strip().lower() for c in rows[0]]
    missing = [c for c in _COLUMNS if c not in header]
    if missing:
        raise DataError(path, f"missing column(s) {missing} in header {rows[0]} "
                              f"(need {list(_COLUMNS)})", line=1)
    twice = sorted({c for c in header if c and header.count(c) > 1})
    if twice:
        raise DataError(path, f"column(s) {twice} appear twice in the header: which one is "
                              "meant?", line=1)
    cols = [header.index(c) for c in _COLUMNS]
    values = []
    for lineno, row in enumerate(rows[1:], start=2):
        if not row or not any(c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise DataError(path, f"expected {len(header)} fields, got {len(row)}", line=lineno)
        try:
            vals = [float(row[c]) for c in cols]
        except ValueError:
            raise DataError(path, f"not a number in {[row[c][:40] for c in cols]}",
                            line=lineno) from None
        problem = _row_problem(vals)
        if problem:
            raise DataError(path, problem, line=lineno)
        if values and vals[0] <= values[-1][1][0]:
            raise DataError(path, f"time {vals[0]} does not increase (previous row: "
                                  f"{values[-1][1][0]})", line=lineno)
        values.append((lineno, vals))
    if not values:
        raise DataError(path, "no data rows after the header")
    a = np.array([v for _, v in values])
    return Trajectory(a[:, 0], a[:, 1], a[:, 2], (a[:, 3] + np.pi) % (2 * np.pi) - np.pi,
                      "csv", str(path))


def _csv_rows(text: str, path: Path) -> list[list[str]]:
    """The CSV rows of ``text``; a CSV error (a field over ``limits.MAX_CSV_FIELD``
    characters, a NUL) is a :class:`DataError` naming the file and line."""
    lines = text.splitlines()
    reader = csv.reader(lines)
    rows = []
    try:
        for row in reader:
            rows.append(row)
    except csv.Error as exc:
        raise DataError(path, f"not a readable CSV row ({exc}; fields are limited to "
                              f"{limits.MAX_CSV_FIELD} characters)",
                        line=reader.line_num) from None
    return rows


def _row_problem(vals: list[float]) -> str | None:
    """Why a row ``(t, x, y, yaw)`` cannot be a vehicle's pose, or None."""
    bad = [n for n, v in zip(_COLUMNS, vals, strict=False) if not math.isfinite(v)]
    if bad:
        return f"non-finite value in column(s) {bad}"
    t, x, y, yaw = vals
    if math.hypot(x, y) > limits.MAX_RANGE:
        return (f"position ({x:g}, {y:g}) m is more than {limits.MAX_RANGE:g} m from the "
                "sensor: positions are in the sensor frame (not map coordinates), in metres")
    if abs(yaw) > limits.MAX_UNWRAPPED_ANGLE:
        return (f"yaw {yaw:g} is beyond {limits.MAX_UNWRAPPED_ANGLE:g} rad: headings are in "
                "radians")
    return None
