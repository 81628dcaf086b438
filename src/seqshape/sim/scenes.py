"""Traffic scenes for the camera + LiDAR generator: a road, an ego car and other vehicles.

World frame: x/y on flat ground (z = 0 is the ground, z up), the road's centre line starts at
the origin heading +x. The road has constant curvature ``kappa`` (1/m, positive turns left; 0
is straight). Road coordinates ``(s, d)``: ``s`` arc length along the centre line, ``d`` signed
lateral offset (left positive). Lanes are ``lane_width`` wide: the ego direction's lanes lie at
``d < 0`` (driving on the right), the oncoming ones at ``d > 0``; beyond each road edge is a
parking strip, then the pavement.

Moving vehicles follow their lane's centre (heading = lane tangent) with speeds from the
Intelligent Driver Model, so cars in one lane never run into each other; lanes are wider than
any vehicle, so vehicles in different lanes never touch; parked cars are placed bumper to bumper
with gaps. Every scene is checked frame by frame (footprint separating-axis test, 0.2 m margin)
before it is used; a violation raises :class:`SeqshapeError`.

Sensor-frame poses: the ego's LiDAR sits ``sensor.height`` above the ground at the ego's world
pose; :meth:`Scene.sensor_poses` gives every vehicle's ``(x, y, z, yaw)`` in that frame, with
``z = -sensor.height + size[2] / 2`` (vehicles stand on the ground).
"""

from __future__ import annotations

import logging
import numbers
import re
from dataclasses import dataclass, field

import numpy as np

from seqshape.errors import ConfigError, SeqshapeError
from seqshape.geometry import compose, invert, wrap_angle
from seqshape.sim.kinematics import footprints_overlap

log = logging.getLogger(__name__)

EGO_SIZE = np.array([4.6, 1.8, 1.6])  #: ego car footprint (for collision checks), LiDAR at centre
PARKING_WIDTH = 2.6  #: width of the parking strip beyond each road edge (m)
COLLISION_MARGIN = 0.2  #: minimum footprint clearance checked between any two vehicles (m)


@dataclass(frozen=True)
class Road:
    """A constant-curvature road; see the module docstring for ``(s, d)``."""

    kappa: float = 0.0
    lane_width: float = 3.5
    lanes_forward: int = 2
    lanes_backward: int = 1

    def heading(self, s) -> np.ndarray:
        """Centre-line heading (rad) at arc length ``s``."""
        return self.kappa * np.asarray(s, dtype=np.float64)

    def to_world(self, s, d) -> tuple[np.ndarray, np.ndarray]:
        """World ``(x, y)`` of road coordinates ``(s, d)`` (arrays broadcast)."""
        s = np.asarray(s, dtype=np.float64)
        d = np.asarray(d, dtype=np.float64)
        a = self.kappa * s
        small = np.abs(a) < 1e-9
        a_safe = np.where(small, 1.0, a)
        f1 = np.where(small, 1.0 - a * a / 6.0, np.sin(a_safe) / a_safe)
        f2 = np.where(small, a / 2.0, (1.0 - np.cos(a_safe)) / a_safe)
        th = a
        return s * f1 - d * np.sin(th), s * f2 + d * np.cos(th)

    def to_road(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Road ``(s, d)`` of world points (inverse of :meth:`to_world` for |d| < 1/|kappa|)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        if abs(self.kappa) < 1e-12:
            return x, y
        r = 1.0 / self.kappa
        sg = np.sign(r)
        th = np.arctan2(x * sg, -(y - r) * sg)
        return th / self.kappa, r - sg * np.hypot(x, y - r)

    def lane_offsets(self) -> tuple[np.ndarray, np.ndarray]:
        """Centre offsets ``d`` of the forward lanes (d < 0) and of the oncoming lanes (d > 0)."""
        w = self.lane_width
        return (-(np.arange(self.lanes_forward) + 0.5) * w,
                (np.arange(self.lanes_backward) + 0.5) * w)

    @property
    def edges(self) -> tuple[float, float]:
        """Right and left road edge offsets (kerb of the driving lanes)."""
        return -self.lanes_forward * self.lane_width, self.lanes_backward * self.lane_width


@dataclass
class Agent:
    """One non-ego vehicle of a scene.

    ``track_id`` is its KITTI track id; ``vehicle_index`` indexes :attr:`Scene.vehicles`;
    ``world`` ``(T, 3)`` holds its world ``(x, y, yaw)`` per frame.
    """

    track_id: int
    vehicle_index: int
    parked: bool
    world: np.ndarray


@dataclass
class Scene:
    """A generated traffic sequence (world frame, see the module docstring).

    ``ego`` ``(T, 3)`` world (x, y, yaw) of the ego LiDAR; ``vehicles`` the meshes used
    (``seqshape.vehicles.Vehicle``); ``colours`` ``(K, 3)`` float RGB in [0, 1] per agent.
    """

    road: Road
    ego: np.ndarray
    agents: list[Agent]
    vehicles: list
    sensor_height: float
    rate_hz: float
    colours: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def n_frames(self) -> int:
        return len(self.ego)

    @property
    def timestamps(self) -> np.ndarray:
        return np.arange(self.n_frames) / self.rate_hz

    def size(self, k: int) -> np.ndarray:
        """(3,) length, width, height of agent ``k``'s vehicle."""
        return self.vehicles[self.agents[k].vehicle_index].size

    def mesh(self, k: int):
        return self.vehicles[self.agents[k].vehicle_index].mesh

    def ego_pose(self, t: int) -> np.ndarray:
        """World pose ``(x, y, z, yaw)`` of the LiDAR at frame ``t`` (z = sensor height)."""
        x, y, yaw = self.ego[t]
        return np.array([x, y, self.sensor_height, yaw])

    def world_poses(self, t: int) -> np.ndarray:
        """``(K, 4)`` world poses (box centre, vehicles on the ground) at frame ``t``."""
        out = np.zeros((len(self.agents), 4))
        for k, a in enumerate(self.agents):
            out[k] = [a.world[t, 0], a.world[t, 1], self.size(k)[2] / 2, a.world[t, 2]]
        return out

    def sensor_poses(self, t: int) -> np.ndarray:
        """``(K, 4)`` poses of every agent in frame ``t``'s sensor frame."""
        inv = invert(self.ego_pose(t))
        return np.array([compose(inv, p) for p in self.world_poses(t)]).reshape(-1, 4)


def check_vehicle_range(n_vehicles, what: str = "n_vehicles") -> tuple[int, int]:
    """``n_vehicles`` as an inclusive ``(min, max)`` pair of ints, ``0 <= min <= max``;
    :class:`ConfigError` naming ``what`` otherwise (strings of digits are accepted, as a
    command line gives them)."""
    try:
        lo, hi = n_vehicles
    except (TypeError, ValueError):
        raise ConfigError(f"{what} must be two integers MIN MAX, got {n_vehicles!r}") from None
    out = []
    for v in (lo, hi):
        if isinstance(v, str) and re.fullmatch(r"\s*[+-]?[0-9]+\s*", v):
            v = int(v)
        if isinstance(v, bool) or not isinstance(v, numbers.Integral):
            raise ConfigError(f"{what} must be two integers MIN MAX, got {lo!r} {hi!r}")
        out.append(int(v))
    if not 0 <= out[0] <= out[1]:
        raise ConfigError(f"{what} must satisfy 0 <= MIN <= MAX, got {out[0]} {out[1]}")
    return out[0], out[1]


@dataclass(frozen=True)
class LayoutConfig:
    """Random layout parameters of one sequence."""

    n_frames: int = 20
    n_vehicles: tuple[int, int] = (5, 8)  # inclusive range of non-ego vehicles
    parked_fraction: float = 0.4
    max_abs_kappa: float = 1.0 / 300.0  # gentle curves; 0 forces a straight road
    straight_prob: float = 0.4
    ego_speed: tuple[float, float] = (6.0, 10.0)  # m/s
    other_speed: tuple[float, float] = (5.0, 12.0)
    lookahead: float = 45.0  # vehicles are spread up to this far beyond the ego's end point (m)

    def __post_init__(self):
        check_vehicle_range(self.n_vehicles, "LayoutConfig.n_vehicles")


def _idm_lanes(lanes, n_frames: int, dt: float, substeps: int = 5):
    """Integrate the Intelligent Driver Model per lane.

    ``lanes``: list of lists of ``[u0, v0_desired, length, direction]`` (lane arc length u,
    m/s, m, +-1). Returns per lane an array ``(n, T)`` of arc lengths.
    """
    a_max, b, s0, headway = 1.2, 2.0, 2.5, 1.2
    out = []
    for cars in lanes:
        if not cars:
            out.append(np.zeros((0, n_frames)))
            continue
        c = np.asarray(cars, dtype=np.float64)
        u, v_des, length, sgn = c[:, 0].copy(), c[:, 1], c[:, 2], c[:, 3]
        v = v_des.copy()
        order = np.argsort(-u * sgn)  # leader first along the driving direction
        traj = np.zeros((len(c), n_frames))
        h = dt / substeps
        for t in range(n_frames):
            traj[:, t] = u
            for _ in range(substeps):
                acc = a_max * (1 - (v / v_des) ** 4)
                for lead, fol in zip(order[:-1], order[1:], strict=True):
                    gap = (u[lead] - u[fol]) * sgn[fol] - (length[lead] + length[fol]) / 2
                    dv = v[fol] - v[lead]
                    want = s0 + v[fol] * headway + v[fol] * dv / (2 * np.sqrt(a_max * b))
                    acc[fol] -= a_max * (max(want, s0) / max(gap, 0.1)) ** 2
                v = np.maximum(v + h * acc, 0.0)
                u = u + h * v * sgn
        out.append(traj)
    return out


def _place_row(rng, n: int, lo: float, hi: float, lengths: list[float], gap: tuple[float, float]):
    """Up to ``n`` bumper-to-bumper positions (centres) in ``[lo, hi]`` with random gaps."""
    pos, cursor = [], lo + rng.uniform(0, 6.0)
    for length in lengths[:n]:
        centre = cursor + length / 2
        if centre + length / 2 > hi:
            break
        pos.append(centre)
        cursor = centre + length / 2 + rng.uniform(*gap)
    return pos


def build_scene(cfg: LayoutConfig, vehicles: list, rng: np.random.Generator,
                sensor_height: float, rate_hz: float = 10.0) -> Scene:
    """Lay out one sequence: road, ego trajectory and ``len(vehicles)``-bounded agents.

    ``vehicles`` (``seqshape.vehicles.Vehicle``) are used in order, one per agent; their count
    caps the number of agents. Raises :class:`SeqshapeError` if the result has overlapping
    vehicles (a bug, never expected).
    """
    straight = rng.random() < cfg.straight_prob or cfg.max_abs_kappa == 0
    road = Road(kappa=0.0 if straight else float(rng.uniform(-1, 1) * cfg.max_abs_kappa),
                lanes_forward=int(rng.integers(1, 3)), lanes_backward=1)
    dt = 1.0 / rate_hz
    fwd, back = road.lane_offsets()
    ego_lane = int(rng.integers(0, len(fwd)))
    ego_v = float(rng.uniform(*cfg.ego_speed))
    travel = ego_v * dt * cfg.n_frames
    n_total = min(int(rng.integers(cfg.n_vehicles[0], cfg.n_vehicles[1] + 1)), len(vehicles))
    n_parked = int(round(n_total * cfg.parked_fraction))
    sizes = [v.size for v in vehicles[:n_total]]
    end = travel + cfg.lookahead
    # parked cars: fill the two strips from a random start, alternating sides
    right_d = road.edges[0] - PARKING_WIDTH / 2
    left_d = road.edges[1] + PARKING_WIDTH / 2
    idx = list(range(n_parked))
    sides = [idx[0::2], idx[1::2]] if rng.random() < 0.5 else [idx[1::2], idx[0::2]]
    parked_world: dict[int, np.ndarray] = {}
    for side_d, members in ((right_d, sides[0]), (left_d, sides[1])):
        pos = _place_row(rng, len(members), 4.0, end, [sizes[i][0] for i in members], (0.8, 5.0))
        flip = side_d > 0 and rng.random() < 0.5  # parked against the direction on the left
        for i, s in zip(members, pos, strict=False):
            d = side_d + rng.uniform(-0.15, 0.15) * (PARKING_WIDTH - sizes[i][1])
            x, y = road.to_world(s, d)
            yaw = road.heading(s) + rng.normal(0, 0.03) + (np.pi if flip else 0.0)
            parked_world[i] = np.tile([float(x), float(y), float(wrap_angle(yaw))],
                                      (cfg.n_frames, 1))
    # moving vehicles: ego lane, other forward lanes, oncoming lanes
    lane_ds = list(fwd) + list(back)
    lanes: list[list] = [[] for _ in lane_ds]
    members: list[list[int]] = [[] for _ in lane_ds]
    lanes[ego_lane].append([0.0, ego_v, EGO_SIZE[0], 1.0])
    members[ego_lane].append(-1)
    for i in range(n_parked, n_total):
        lane = int(rng.integers(0, len(lane_ds)))
        sgn = 1.0 if lane < len(fwd) else -1.0
        v = float(rng.uniform(*cfg.other_speed))
        lo, hi = (-25.0, end) if sgn > 0 else (10.0, end + v * dt * cfg.n_frames)
        scale = 1.0 - road.kappa * lane_ds[lane]
        taken = [c[0] for c in lanes[lane]]
        for _ in range(50):
            u = rng.uniform(lo, hi) * scale
            if all(abs(u - w) > 8.0 + 1.2 * v + sizes[i][0] for w in taken):
                lanes[lane].append([u, v, sizes[i][0], sgn])
                members[lane].append(i)
                break
    trajs = _idm_lanes(lanes, cfg.n_frames, dt)
    moving_world: dict[int, np.ndarray] = {}
    ego = None
    for lane, d in enumerate(lane_ds):
        scale = 1.0 - road.kappa * d
        for row, i in enumerate(members[lane]):
            s = trajs[lane][row] / scale
            x, y = road.to_world(s, d)
            yaw = road.heading(s) + (0.0 if lane < len(fwd) else np.pi)
            w = np.stack([x, y, wrap_angle(yaw)], 1)
            if i < 0:
                ego = w
            else:
                moving_world[i] = w
    placed = sorted(list(parked_world) + list(moving_world))
    if len(placed) < n_total:
        log.info("placed %d of %d vehicles: the road is full (section Denser scenes of "
                 "docs/scenes.md)", len(placed), n_total)
    agents = [Agent(track_id=k, vehicle_index=i, parked=i in parked_world,
                    world=parked_world.get(i, moving_world.get(i))) for k, i in enumerate(placed)]
    colours = _colours(rng, len(agents))
    scene = Scene(road, ego, agents, list(vehicles), float(sensor_height), float(rate_hz),
                  colours)
    check_no_overlap(scene)
    return scene


def _colours(rng: np.random.Generator, n: int) -> np.ndarray:
    """Car paint colours ``(n, 3)`` in [0, 1]: mostly greys, some saturated."""
    base = np.array([[0.85, 0.85, 0.87], [0.15, 0.15, 0.17], [0.55, 0.56, 0.58],
                     [0.70, 0.12, 0.10], [0.12, 0.25, 0.60], [0.90, 0.90, 0.88],
                     [0.20, 0.45, 0.25], [0.80, 0.60, 0.15], [0.35, 0.20, 0.45]])
    pick = base[rng.integers(0, len(base), n)]
    return np.clip(pick + rng.normal(0, 0.04, (n, 3)), 0.02, 0.98)


def check_no_overlap(scene: Scene, margin: float = COLLISION_MARGIN) -> None:
    """Raise :class:`SeqshapeError` if two vehicles (ego included) overlap in any frame."""
    ego = np.c_[scene.ego[:, :2], np.zeros(scene.n_frames), scene.ego[:, 2]]
    boxes = [(ego, EGO_SIZE, "ego")]
    for k, a in enumerate(scene.agents):
        boxes.append((np.c_[a.world[:, :2], np.zeros(scene.n_frames), a.world[:, 2]],
                      scene.size(k), f"track {a.track_id}"))
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            hit = footprints_overlap(boxes[i][0], boxes[i][1], boxes[j][0], boxes[j][1], margin)
            if hit.any():
                raise SeqshapeError(f"scene layout bug: {boxes[i][2]} and {boxes[j][2]} overlap "
                                    f"at frame {int(np.argmax(hit))}")


def road_material(road: Road, s: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ground colour ``(N, 3)`` RGB in [0, 1] and LiDAR albedo ``(N,)`` at road coordinates.

    Asphalt lanes with a solid centre line, dashed lane dividers (3 m every 9 m) and solid
    edge lines; lighter parking strips; grey pavement beyond, then grass.
    """
    right, left = road.edges
    rgb = np.tile([0.30, 0.30, 0.31], (len(s), 1))
    albedo = np.full(len(s), 0.12)
    strip = ((d < right) & (d >= right - PARKING_WIDTH)) | ((d > left) & (d <= left + PARKING_WIDTH))
    rgb[strip] = [0.36, 0.36, 0.36]
    pave = ((d < right - PARKING_WIDTH) & (d >= right - PARKING_WIDTH - 3.0)) | (
        (d > left + PARKING_WIDTH) & (d <= left + PARKING_WIDTH + 3.0))
    rgb[pave] = [0.55, 0.54, 0.52]
    albedo[pave] = 0.25
    grass = (d < right - PARKING_WIDTH - 3.0) | (d > left + PARKING_WIDTH + 3.0)
    rgb[grass] = [0.25, 0.42, 0.18]
    albedo[grass] = 0.35
    half = 0.07
    line = (np.abs(d) < half) | (np.abs(d - right) < half) | (np.abs(d - left) < half)
    dash = (np.mod(s, 9.0) < 3.0)
    for k in range(1, road.lanes_forward):
        line |= (np.abs(d + k * road.lane_width) < half) & dash
    for k in range(1, road.lanes_backward):
        line |= (np.abs(d - k * road.lane_width) < half) & dash
    rgb[line] = [0.88, 0.88, 0.85]
    albedo[line] = 0.6
    return rgb, albedo


def ground_material(scene: Scene, t: int):
    """A callable mapping frame ``t`` sensor-frame ground points ``(N, 3)`` to
    :func:`road_material` (for :mod:`seqshape.sim.render`)."""
    x0, y0, yaw = scene.ego[t]
    c, s_ = np.cos(yaw), np.sin(yaw)

    def material(points: np.ndarray):
        wx = x0 + c * points[:, 0] - s_ * points[:, 1]
        wy = y0 + s_ * points[:, 0] + c * points[:, 1]
        return road_material(scene.road, *scene.road.to_road(wx, wy))

    return material
