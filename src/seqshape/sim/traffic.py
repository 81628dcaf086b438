"""Traffic placement of sampled trajectories (``placement="traffic"``, the ``real`` preset).

A car-mounted LiDAR sees traffic mostly *along* its line of sight: the cars ahead and behind in
its own and the adjacent lanes, oncoming cars, cars parked at the kerb, and, less often, cars
crossing at an intersection. The crossing placement of
:func:`seqshape.sim.trajectories.sample_trajectory` makes every track cross the line of sight,
so broadside views dominate there; this module places a track on a road instead.

Road frame = the sensor frame of the track's first frame: x along the road in the ego's
direction, y to the left, z up, origin at the LiDAR. The road is straight with
``n_same`` = 1-3 lanes in the ego's direction (the ego on one of them, its centre on ``y = 0``),
0-3 oncoming lanes (0: a one-way street), lanes ``LANE_WIDTH`` wide, sometimes a median; in
left-hand traffic (share ``P_LEFT_HAND``) the layout is mirrored. The ego drives along +x at a
constant speed (0 with ``P_EGO_STOPPED``); the target's path (the bicycle model of
`trajectories`, with a nearly straight road: curvature amplitude at most ``ROAD_CURVATURE``)
is placed so that at an anchor frame ``k`` it sits at a sampled spot with the lane's heading:

* ``same_direction``: a lane of the ego's direction (the ego's own lane included), heading +x;
* ``oncoming``: an opposite lane, heading -x (on a one-way street: ``same_direction``);
* ``crossing``: a two-lane cross road at ``x = x_c``, heading +-y, on its right-hand lane;
* ``parked`` (the ``parked`` manoeuvre): at either kerb, parallel (heading of the traffic on
  that side) or, with ``P_PERPENDICULAR``, perpendicular to it (a parking bay).

The anchor's longitudinal offset (``x``, or ``x_c``) is ahead with ``P_AHEAD`` (a 360 deg
sensor: as likely behind; ``P_AHEAD_CROSSING`` for an intersection, mostly the one approached),
at a log-uniform distance in ``[near, 0.75 max_distance]`` as in the crossing placement. A
``turn`` is anchored at its first frame (it leaves the lane at an intersection) or its last
(it has turned into the lane), a ``u_turn`` at its first frame, the others at a random frame.
The track is reported in each frame's sensor frame: ``x_sensor = x_road - ego_x(t)``. Rules:
no frame brings the footprint within ``min_clearance`` of the sensor, the centre within
``min_distance``, or the footprint within ``EGO_MARGIN`` of the ego's (``EGO_SIZE``, centred
on the LiDAR); a footprint touching the ego's moves the anchor further along the road, away
from the ego, and a track passing beside the ego too close moves outward (a car parked close
to the kerb of a one-lane street keeps its centre ``min_distance`` from the LiDAR). Speeds
(the target's and the ego's together, so the relative motion shrinks) are scaled down until the
track stays within ``max_distance``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from seqshape.errors import ConfigError
from seqshape.sim.kinematics import (
    Trajectory,
    bicycle_path,
    footprint_distance,
    footprints_overlap,
    place_path,
)

LANE_WIDTH = 3.5
"""m, lane width (urban arterials and motorways: 3.0-3.75 m)."""
EGO_SIZE = (4.8, 2.0)
"""m, length and width of the ego car's footprint, centred on the LiDAR (a roof LiDAR sits
near the middle of the car)."""
EGO_MARGIN = 0.6
"""m, the smallest gap between the target's footprint and the ego's."""
ROAD_CURVATURE = 0.0004
"""1/m, amplitude bound of the road's curvature for traffic tracks (radius >= 2.5 km: the
target keeps its lane on the straight road, drifting < 0.5 m over 50 m)."""
TRAFFIC_MANOEUVRES = {"straight": 0.30, "turn": 0.10, "lane_change": 0.08,
                      "stop_and_go": 0.15, "u_turn": 0.02, "parked": 0.35}
"""Manoeuvre weights of traffic tracks (docs/generation.md, "Traffic placement")."""
SITUATIONS = {"same_direction": 0.45, "oncoming": 0.35, "crossing": 0.20}
"""Situation weights of moving traffic tracks (parked tracks are ``parked``)."""
P_EGO_STOPPED = 0.3
EGO_SPEED = (3.0, 14.0)
P_LEFT_HAND = 0.2
P_PERPENDICULAR = 0.2
P_AHEAD = 0.5
P_AHEAD_CROSSING = 0.75
P_NEAR_KERB = 0.5
_OPPOSITE_LANES = (0.15, 0.45, 0.30, 0.10)  # P(0, 1, 2, 3 oncoming lanes)


@dataclass(frozen=True)
class Road:
    """Lane centres (``y``, m) of a sampled road in the road frame.

    same: lanes in the ego's direction (the ego's own at 0); opposite: oncoming lanes (may be
    empty); near_kerb / far_kerb: ``y`` of the road edge beside the ego's direction (right in
    right-hand traffic) and beside the oncoming lanes; hand: +1 right-hand, -1 left-hand traffic.
    """

    same: tuple[float, ...]
    opposite: tuple[float, ...]
    near_kerb: float
    far_kerb: float
    hand: float


def sample_road(rng: np.random.Generator) -> Road:
    """A road layout (module doc); right-hand layouts mirrored for left-hand traffic."""
    n_same = int(rng.integers(1, 4))
    ego_lane = int(rng.integers(0, n_same))  # counted from the near kerb
    n_opp = int(rng.choice(len(_OPPOSITE_LANES), p=_OPPOSITE_LANES))
    median = 0.0 if n_opp == 0 or rng.random() < 0.7 else float(rng.uniform(1.0, 4.0))
    same = [LANE_WIDTH * (i - ego_lane) for i in range(n_same)]
    top = same[-1] + LANE_WIDTH / 2 + median
    opposite = [top + LANE_WIDTH * (i + 0.5) for i in range(n_opp)]
    far = (opposite[-1] if opposite else same[-1]) + LANE_WIDTH / 2
    hand = -1.0 if rng.random() < P_LEFT_HAND else 1.0
    return Road(tuple(hand * y for y in same), tuple(hand * y for y in opposite),
                hand * (same[0] - LANE_WIDTH / 2), hand * far, hand)


def _pick(rng, weights: dict) -> str:
    names = list(weights)
    return names[int(rng.choice(len(names), p=np.array(list(weights.values()))))]


def _anchor(rng, road: Road, situation: str, length: float, width: float, dist: float):
    """Anchor spot ``(x, y, heading)`` in the road frame for a situation (module doc)."""
    ahead = P_AHEAD_CROSSING if situation == "crossing" else P_AHEAD
    along = dist if rng.random() < ahead else -dist
    if situation == "same_direction":
        return along, float(rng.choice(road.same)) + rng.normal(0, 0.25), rng.normal(0, 0.02)
    if situation == "oncoming":
        y = float(rng.choice(road.opposite)) + rng.normal(0, 0.25)
        return along, y, math.pi + rng.normal(0, 0.02)
    if situation == "crossing":
        heading = float(rng.choice([-1.0, 1.0])) * math.pi / 2
        # keep right (right-hand traffic): moving +y is on the +x lane, moving -y on the -x lane
        x = along + road.hand * math.sin(heading) * LANE_WIDTH / 2
        return x, rng.uniform(-25.0, 25.0), heading + rng.normal(0, 0.02)
    near = rng.random() < P_NEAR_KERB
    kerb = road.near_kerb if near else road.far_kerb
    out = -road.hand if near else road.hand  # outward, away from the road
    if rng.random() < P_PERPENDICULAR:
        heading = float(rng.choice([-1.0, 1.0])) * math.pi / 2 + rng.normal(0, 0.1)
        return along, kerb + out * (length / 2 + 0.3), heading
    heading = 0.0 if near or not road.opposite else math.pi
    return along, kerb + out * (width / 2 + rng.uniform(0.1, 0.5)), heading + rng.normal(0, 0.04)


def _anchor_frame(rng, manoeuvre: str, n: int) -> int:
    if manoeuvre == "turn":
        return 0 if rng.random() < 0.5 else n - 1
    if manoeuvre == "u_turn":
        return 0
    return int(rng.integers(0, n))


def _ego_shift(rx, ry, yaw, length, width, push: float) -> float:
    """How far (m) to move the track along ``push`` (+-1 along x) so that no frame's footprint
    comes within ``EGO_MARGIN`` of the ego's; 0 when none does."""
    poses = np.stack([rx, ry, np.zeros_like(rx), yaw], 1)
    hit = footprints_overlap(poses, (length, width), np.zeros_like(poses), EGO_SIZE, EGO_MARGIN)
    if not hit.any():
        return 0.0
    reach = np.abs(np.cos(yaw)) * length / 2 + np.abs(np.sin(yaw)) * width / 2
    need = EGO_SIZE[0] / 2 + EGO_MARGIN + reach - push * rx
    return float(max(need[hit].max(), 0.0)) + 0.1


def sample_traffic(rng: np.random.Generator, t: np.ndarray, manoeuvre: str | None,
                   length: float, width: float, min_distance: float, max_distance: float,
                   min_clearance: float, ego_x: np.ndarray | None = None,
                   situation: str | None = None):
    """A traffic track (module doc) at times ``t``: a :class:`~seqshape.sim.trajectories.
    Trajectory` in each frame's sensor frame with ``ego_x`` and ``situation`` set.

    ``manoeuvre`` None: drawn with ``TRAFFIC_MANOEUVRES``. ``ego_x`` ``(T,)``: the ego's motion
    given (e.g. an occluder of another track's scene; then only the target is slowed down),
    else sampled. ``situation`` forces one of ``SITUATIONS`` for a moving manoeuvre (None:
    drawn).
    """
    if manoeuvre is None:
        manoeuvre = _pick(rng, TRAFFIC_MANOEUVRES)
    if manoeuvre not in TRAFFIC_MANOEUVRES:
        raise ConfigError(f"unknown manoeuvre {manoeuvre!r}; choose from "
                          f"{sorted(TRAFFIC_MANOEUVRES)}")
    n = len(t)
    if ego_x is not None and len(ego_x) != n:
        raise ConfigError(f"ego_x has {len(ego_x)} entries for {n} frames")
    if situation is not None and situation not in SITUATIONS:
        raise ConfigError(f"unknown situation {situation!r}; choose from {sorted(SITUATIONS)}")
    road = sample_road(rng)
    if manoeuvre == "parked":
        situation = "parked"
    elif situation is None:
        situation = _pick(rng, SITUATIONS)
    if situation == "oncoming" and not road.opposite:
        situation = "same_direction"  # a one-way street
    near = max(min_distance, min_clearance + math.hypot(length, width) / 2)
    far = max(near + 1.0, 0.75 * max_distance)
    dist = math.exp(rng.uniform(math.log(near), math.log(far)))
    ax0, ay0, heading = _anchor(rng, road, situation, length, width, dist)
    k = _anchor_frame(rng, manoeuvre, n)
    ego_speed = 0.0 if rng.random() < P_EGO_STOPPED else float(rng.uniform(*EGO_SPEED))
    path_seed = rng.integers(2 ** 63)
    push = 1.0 if ax0 >= 0 else -1.0
    scale = 1.0
    for _ in range(12):
        x, y, yaw = bicycle_path(np.random.default_rng(path_seed), manoeuvre, t, 0.6 * length,
                                 scale, ROAD_CURVATURE)
        ego = ego_speed * scale * (t - t[0]) if ego_x is None else np.asarray(ego_x, float)
        ax, ay = ax0, ay0
        for _ in range(40):
            wx = ax + ego[k]  # the anchor in the road frame
            px, py, pyaw = place_path(x, y, yaw, k, math.hypot(wx, ay), math.atan2(ay, wx),
                                      heading)
            rx = px - ego
            gap = np.minimum(footprint_distance(rx, py, pyaw, length, width) - min_clearance,
                             np.hypot(rx, py) - min_distance).min()
            shift = _ego_shift(rx, py, pyaw, length, width, push)
            if shift > 0:
                ax += push * shift
            elif gap < 0 and situation != "crossing":  # passing too close beside the ego
                ay += (1.0 if ay >= 0 else -1.0) * (0.5 - gap)
            elif gap < 0:
                ax += push * (0.5 - gap)
            else:
                break
        reach = np.hypot(rx, py).max()
        static = manoeuvre == "parked" and (ego_x is not None or np.ptp(ego) == 0)
        if reach <= max_distance or static:
            break
        d = math.hypot(ax, ay)
        scale *= 0.9 * max(max_distance - d, 1.0) / max(reach - d, 1.0)
    return Trajectory(t, rx, py, (pyaw + np.pi) % (2 * np.pi) - np.pi, manoeuvre,
                      ego_x=ego, situation=situation)
