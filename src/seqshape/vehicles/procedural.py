"""Procedural vehicle bodies: sedan, hatchback, SUV, van and pickup.

A body is a loft of cross-sections along the length. Its side profile (top line: nose, hood,
windshield, roof, rear window, trunk deck / bed) comes from a handful of continuous parameters
(`VehicleParams`), smoothed so that the edges are rounded. Each cross-section (y-z plane) has a
flat underbody, wheel wells cut into both sides (deep over the wheels: the wheel arches), vertical
body sides up to the beltline, an inward-leaning greenhouse above it (tumblehome) and a rounded
roof edge. Near the ends the sections shrink towards their centre (rounded bumpers) and are
closed by caps. Four wheels (closed cylinders) sit in the arches. The result is a closed
(watertight) mesh of about 5 000 triangles.

Build frame: x from the rear (0) to the front (L), z up from the ground (0). The returned mesh is
moved to the canonical frame: centre of the bounding box (wheels included) at the origin, x
forward, y left, z up, metres. The pickup has an open bed (walls and tailgate 6 cm thick).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
import trimesh

from seqshape.errors import ConfigError
from seqshape.vehicles.base import BODY, KINDS, TYRE, Vehicle, centre_on_bbox

log = logging.getLogger(__name__)

# Sampling ranges per kind (uniform). Lengths in m, angles in degrees (from horizontal),
# heights as fractions of the total height.
_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "sedan": dict(length=(4.3, 5.1), width=(1.72, 1.90), height=(1.38, 1.52), hood=(0.25, 0.29),
                  trunk=(0.15, 0.19), ws=(26, 32), rw=(22, 30), belt=(0.62, 0.68),
                  deck=(0.68, 0.74), nose=(0.52, 0.57), clearance=(0.13, 0.17),
                  wheel_r=(0.30, 0.34), wheel_w=(0.20, 0.24), foh=(0.85, 1.00),
                  roh=(0.95, 1.15), tumble=(14, 20)),
    "hatchback": dict(length=(3.6, 4.4), width=(1.64, 1.80), height=(1.40, 1.56),
                      hood=(0.22, 0.27), trunk=(0.0, 0.03), ws=(27, 33), rw=(50, 65),
                      belt=(0.60, 0.66), deck=(0.68, 0.74), nose=(0.50, 0.56),
                      clearance=(0.13, 0.16), wheel_r=(0.28, 0.32), wheel_w=(0.18, 0.22),
                      foh=(0.75, 0.90), roh=(0.62, 0.80), tumble=(14, 20)),
    "suv": dict(length=(4.3, 5.0), width=(1.80, 2.00), height=(1.62, 1.85), hood=(0.23, 0.27),
                trunk=(0.0, 0.03), ws=(30, 38), rw=(62, 78), belt=(0.58, 0.64),
                deck=(0.62, 0.68), nose=(0.52, 0.58), clearance=(0.18, 0.23),
                wheel_r=(0.35, 0.39), wheel_w=(0.23, 0.27), foh=(0.85, 1.00),
                roh=(0.85, 1.05), tumble=(10, 16)),
    "van": dict(length=(4.8, 5.8), width=(1.90, 2.05), height=(1.78, 2.15), hood=(0.10, 0.16),
                trunk=(0.0, 0.02), ws=(40, 55), rw=(80, 87), belt=(0.48, 0.54),
                deck=(0.52, 0.58), nose=(0.42, 0.48), clearance=(0.16, 0.20),
                wheel_r=(0.33, 0.37), wheel_w=(0.21, 0.25), foh=(0.80, 0.95),
                roh=(0.90, 1.15), tumble=(4, 8)),
    "pickup": dict(length=(5.0, 5.8), width=(1.85, 2.05), height=(1.75, 1.95), hood=(0.25, 0.30),
                   trunk=(0.30, 0.36), ws=(33, 40), rw=(80, 87), belt=(0.58, 0.63),
                   deck=(0.64, 0.70), nose=(0.54, 0.60), clearance=(0.21, 0.27),
                   wheel_r=(0.37, 0.41), wheel_w=(0.25, 0.29), foh=(0.85, 1.00),
                   roh=(1.15, 1.35), tumble=(8, 14)),
}

# A realistic mix (30% sedan, 25% SUV, 20% hatchback, 15% pickup, 10% van) as a fixed cycle.
_MIX = ("sedan", "suv", "hatchback", "sedan", "pickup", "suv", "sedan", "van", "hatchback", "suv",
        "sedan", "pickup", "suv", "hatchback", "sedan", "van", "suv", "sedan", "hatchback",
        "pickup")

_ROOF_CROWN = 0.025   # m, roof centre above its edges
_MIN_ROOF = 0.35      # m, shortest flat roof
_WELL_GAP = 0.05      # m, clearance between tyre and arch / well wall
_END_R = 0.12         # m, radius of the rounded front and rear ends
_RAIL = 0.06          # m, thickness of the pickup bed's side walls and tailgate


@dataclass(frozen=True)
class VehicleParams:
    """Continuous parameters of one procedural body (metres, degrees from horizontal).

    ``hood_frac + cabin_frac + trunk_frac == 1``: fractions of the length taken by the hood
    (front to windshield base), the cabin (windshield base to the bottom of the rear window) and
    the trunk deck / pickup bed. ``front_overhang`` / ``rear_overhang`` are the distances from
    the front / rear end to the front / rear axle (the wheel positions).
    """

    kind: str
    length: float
    width: float
    height: float
    hood_frac: float
    cabin_frac: float
    trunk_frac: float
    windshield_deg: float
    rear_window_deg: float
    belt_height: float
    deck_height: float
    nose_height: float
    ground_clearance: float
    wheel_radius: float
    wheel_width: float
    front_overhang: float
    rear_overhang: float
    tumblehome_deg: float
    bed_depth: float = 0.0  # open pickup bed depth below the rail (0: closed deck)

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ConfigError(f"unknown vehicle kind {self.kind!r}; choose from {KINDS}")
        if abs(self.hood_frac + self.cabin_frac + self.trunk_frac - 1.0) > 1e-6:
            raise ConfigError("hood_frac + cabin_frac + trunk_frac must be 1")
        arch = self.wheel_radius + _WELL_GAP
        if min(self.front_overhang, self.rear_overhang) < arch + 0.15:
            raise ConfigError("overhangs too short for the wheel arches")
        if self.nose_height < 2 * self.wheel_radius:
            raise ConfigError("nose_height must be above the wheel tops")
        if self.bed_depth > 0 and self.bed_floor < 2 * self.wheel_radius + _WELL_GAP + 0.03:
            raise ConfigError("bed_depth too large: the bed floor would cut the wheel arches")

    @property
    def wheel_x(self) -> tuple[float, float]:
        """Axle positions (front, rear) in the build frame (x from the rear end)."""
        return self.length - self.front_overhang, self.rear_overhang

    @property
    def bed_floor(self) -> float:
        """Height of the open bed's floor (m); the deck height when there is no bed."""
        return self.deck_height - self.bed_depth

    @property
    def bed_x(self) -> tuple[float, float] | None:
        """Build-frame x range (rear, front) of the open bed, or None."""
        if self.bed_depth <= 0 or self.trunk_frac * self.length < 0.6:
            return None
        return _END_R + _RAIL, self.trunk_frac * self.length - 0.08


def sample_params(kind: str, rng: np.random.Generator) -> VehicleParams:
    """Draw `VehicleParams` of ``kind`` uniformly from that kind's realistic ranges."""
    if kind not in _RANGES:
        raise ConfigError(f"unknown vehicle kind {kind!r}; choose from {KINDS}")
    v = {k: float(rng.uniform(lo, hi)) for k, (lo, hi) in _RANGES[kind].items()}
    h = v["height"]
    bed_depth = 0.0
    if kind == "pickup":  # as deep as the rear wheel arches allow, up to 0.55 m
        floor = 2 * v["wheel_r"] + _WELL_GAP + 0.05
        bed_depth = min(float(rng.uniform(0.40, 0.55)), v["deck"] * h - floor)
    return VehicleParams(
        kind=kind, length=v["length"], width=v["width"], height=h, hood_frac=v["hood"],
        cabin_frac=1.0 - v["hood"] - v["trunk"], trunk_frac=v["trunk"],
        windshield_deg=v["ws"], rear_window_deg=v["rw"], belt_height=v["belt"] * h,
        deck_height=v["deck"] * h, nose_height=v["nose"] * h,
        ground_clearance=v["clearance"], wheel_radius=v["wheel_r"], wheel_width=v["wheel_w"],
        front_overhang=v["foh"], rear_overhang=v["roh"], tumblehome_deg=v["tumble"],
        bed_depth=max(bed_depth, 0.0))


def _top_profile(p: VehicleParams, x: np.ndarray) -> np.ndarray:
    """Height of the body's top line at build-frame positions ``x`` (m), smoothed."""
    L, top = p.length, p.height - _ROOF_CROWN
    hood, cabin = p.hood_frac * L, p.cabin_frac * L
    ws_run = (top - p.belt_height) / np.tan(np.radians(p.windshield_deg))
    rw_run = (top - p.deck_height) / np.tan(np.radians(p.rear_window_deg))
    if cabin - ws_run - rw_run < _MIN_ROOF:  # too steep for this cabin: shorten both slopes
        k = max(cabin - _MIN_ROOF, 0.2) / (ws_run + rw_run)
        ws_run, rw_run = ws_run * k, rw_run * k
    s = np.linspace(0.0, L, int(L / 0.01) + 1)  # distance from the front
    u = np.clip(s / hood, 0.0, 1.0)
    hood_z = p.nose_height + (p.belt_height - p.nose_height) * (1.0 - (1.0 - u) ** 2)
    knots_s = [hood, hood + ws_run, hood + cabin - rw_run, hood + cabin, L]
    knots_z = [p.belt_height, top, top, p.deck_height, p.deck_height - 0.02]
    z = np.where(s < hood, hood_z, np.interp(s, knots_s, knots_z))
    sigma = 0.06 / 0.01  # Gaussian smoothing, 6 cm
    k = np.arange(-int(3 * sigma), int(3 * sigma) + 1)
    w = np.exp(-0.5 * (k / sigma) ** 2)
    zs = np.convolve(np.pad(z, len(k) // 2, mode="edge"), w / w.sum(), mode="valid")
    return np.interp(L - x, s, zs)


def _stations(p: VehicleParams, end_r: float) -> np.ndarray:
    """Sorted x positions of the cross-sections: ~8 cm apart, ~3 cm over the wheel arches."""
    L = p.length
    xs = [np.linspace(end_r, L - end_r, int((L - 2 * end_r) / 0.1) + 1)]
    arch = p.wheel_radius + _WELL_GAP
    for wx in p.wheel_x:
        xs.append(wx + np.linspace(-arch, arch, 15))
        xs.append(wx + np.array([-arch - 0.01, arch + 0.01]))
    if p.bed_x is not None:
        b0, b1 = p.bed_x
        xs.append(np.array([b0, b0 + 0.015, b1 - 0.015, b1]))
    x = np.unique(np.round(np.concatenate(xs), 5))
    keep = np.concatenate([[True], np.diff(x) > 0.005])
    return x[keep]


def _half_section(p, hw, zf, zs, zt, bed=False, n_side=6, n_corner=5):
    """(m, 2) points (y, z) of the left half of a cross-section, bottom centre to top centre.

    The count is the same for every section; with ``bed`` the top is an open pickup bed (side
    wall of thickness _RAIL down to ``p.bed_floor``), otherwise a rounded roof or deck.
    """
    well_in = hw - p.wheel_width - 2 * _WELL_GAP
    rc = 0.03 if bed else min(0.16, 0.4 * (zt - zs))
    tumble = np.tan(np.radians(p.tumblehome_deg))

    def half_width(z):
        return hw - tumble * np.maximum(z - p.belt_height, 0.0)

    pts = [(0.0, zf), (well_in, zf), (well_in, zs), (hw - 0.025, zs)]
    z_side = np.linspace(zs + 0.025, zt - rc, n_side)
    pts += list(zip(half_width(z_side), z_side, strict=True))
    wt = half_width(zt - rc)
    th = np.linspace(0.0, np.pi / 2, n_corner + 1)[1:]
    pts += list(zip(wt - rc + rc * np.cos(th), zt - rc + rc * np.sin(th), strict=True))
    if bed:
        pts += [(wt - _RAIL, zt), (wt - _RAIL, p.bed_floor), (0.0, p.bed_floor)]
    else:
        crown = _ROOF_CROWN * min(1.0, (zt - zs) / 0.5)
        pts += [((wt - rc) * f, zt + crown * (1 - f * f)) for f in (0.66, 0.33)]
        pts.append((0.0, zt + crown))
    return np.asarray(pts)


def _body(p: VehicleParams) -> trimesh.Trimesh:
    """Closed lofted body (no wheels) in the build frame."""
    end_r = _END_R
    x = _stations(p, end_r)
    L = p.length
    s_front, s_rear = L - x, x
    hw = p.width / 2 * (1 - 0.07 * np.clip(1 - s_front / 0.7, 0, 1) ** 2
                        - 0.05 * np.clip(1 - s_rear / 0.6, 0, 1) ** 2)
    zf = (p.ground_clearance + 0.12 * np.clip(1 - s_front / 0.45, 0, 1) ** 2
          + 0.10 * np.clip(1 - s_rear / 0.5, 0, 1) ** 2)
    zs = zf + 0.03
    arch = p.wheel_radius + _WELL_GAP
    for wx in p.wheel_x:
        dx = np.abs(x - wx)
        inside = dx <= arch + 1e-9
        za = p.wheel_radius + np.sqrt(np.clip(arch**2 - dx**2, 0.0, None))
        zs = np.where(inside, np.maximum(zs, za), zs)
    zt = np.maximum(_top_profile(p, x), zs + 0.15)

    bed = np.zeros(len(x), dtype=bool)
    if p.bed_x is not None:
        bed = (x > p.bed_x[0] + 0.01) & (x < p.bed_x[1] - 0.01)
    rings = []
    for i in range(len(x)):
        half = _half_section(p, hw[i], zf[i], zs[i], zt[i], bed=bed[i])
        ring = np.concatenate([half, half[-2:0:-1] * [-1.0, 1.0]])  # (K, 2): y, z
        rings.append(np.column_stack([np.full(len(ring), x[i]), ring]))
    # rounded ends: shrink the end sections towards their centre over a quarter circle
    phi = np.radians(np.linspace(0, 80, 5)[1:])
    front, rear = [], []
    for ring, sign, out in ((rings[-1], 1.0, front), (rings[0], -1.0, rear)):
        c = np.array([ring[0, 0], 0.0, 0.5 * (ring[:, 2].min() + ring[:, 2].max())])
        d = np.linalg.norm(ring[:, 1:] - c[1:], axis=1, keepdims=True)
        for f in phi:
            k = np.maximum(0.15, 1.0 - end_r * (1 - np.cos(f)) / d)
            r = c + (ring - c) * np.column_stack([np.zeros(len(d)), k, k])
            r[:, 0] = c[0] + sign * end_r * np.sin(f)
            out.append(r)
        out.append(c + [sign * end_r, 0.0, 0.0])
    rings = rear[-2::-1] + rings + front[:-1]
    return _loft(np.stack(rings), rear[-1], front[-1])


def _loft(rings: np.ndarray, cap0: np.ndarray, cap1: np.ndarray) -> trimesh.Trimesh:
    """Close a stack of rings (N, K, 3) with two apex vertices into a watertight mesh."""
    n, k, _ = rings.shape
    idx = np.arange(n * k).reshape(n, k)
    a, b = idx[:-1], np.roll(idx[:-1], -1, axis=1)
    c, d = idx[1:], np.roll(idx[1:], -1, axis=1)
    quads = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3),
                            np.stack([a, d, c], -1).reshape(-1, 3)])
    i0, i1 = n * k, n * k + 1
    fan0 = np.column_stack([np.full(k, i0), idx[0, 1:].tolist() + [idx[0, 0]], idx[0]])
    fan1 = np.column_stack([np.full(k, i1), idx[-1], np.roll(idx[-1], -1)])
    verts = np.concatenate([rings.reshape(-1, 3), [cap0, cap1]])
    mesh = trimesh.Trimesh(verts, np.concatenate([quads, fan0, fan1]), process=False)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def _wheels(p: VehicleParams, sections: int = 28) -> list[trimesh.Trimesh]:
    """Four closed cylinders (axis y) in the build frame."""
    y = p.width / 2 - p.wheel_width / 2 - _WELL_GAP / 2
    out = []
    rot = trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])
    for wx in p.wheel_x:
        for sy in (1.0, -1.0):
            cyl = trimesh.creation.cylinder(radius=p.wheel_radius, height=p.wheel_width,
                                            sections=sections)
            cyl.apply_transform(rot)
            cyl.apply_translation([wx, sy * y, p.wheel_radius])
            out.append(cyl)
    return out


def build_vehicle_mesh(params: VehicleParams) -> trimesh.Trimesh:
    """Closed mesh of a body with four wheels, in the canonical frame (bbox centre at origin)."""
    parts = [_body(params), *_wheels(params)]
    mesh = trimesh.util.concatenate(parts)
    return centre_on_bbox(mesh)


def procedural_vehicle(kind: str, seed: int) -> Vehicle:
    """One procedural vehicle of ``kind`` whose parameters are drawn with ``seed``."""
    if kind not in KINDS:
        raise ConfigError(f"unknown vehicle kind {kind!r}; choose from {KINDS}")
    if int(seed) < 0:
        raise ConfigError(f"seed must be >= 0, got {seed}")
    rng = np.random.default_rng([int(seed), KINDS.index(kind)])
    params = sample_params(kind, rng)
    mesh = build_vehicle_mesh(params)
    mesh.metadata["params"] = asdict(params)
    # faces: the body first, then the four tyres (no glass on these bodies)
    n_tyre = sum(len(w.faces) for w in _wheels(params))
    labels = np.full(len(mesh.faces), BODY, dtype=np.uint8)
    labels[len(labels) - n_tyre:] = TYRE
    mesh.metadata["face_labels"] = labels
    return Vehicle(vehicle_id=f"proc-s{int(seed)}-{kind}", mesh=mesh, kind=kind,
                   source=f"procedural:{kind}:{int(seed)}",
                   cls="van" if kind == "van" else "car", face_labels=labels)


def vehicle_library(n: int, seed: int = 0, kinds: Sequence[str] | None = None) -> list[Vehicle]:
    """``n`` distinct procedural vehicles, deterministic for ``seed``.

    Kinds follow a fixed realistic mix (30% sedan, 25% SUV, 20% hatchback, 15% pickup,
    10% van), restricted to ``kinds`` when given. Ids are ``proc-<index:04d>-<kind>``; each
    vehicle's ``source`` (``procedural:<kind>:<seed>``) rebuilds it with `procedural_vehicle`.
    """
    if n < 0:
        raise ConfigError(f"n must be >= 0, got {n}")
    kinds = tuple(KINDS if kinds is None else kinds)
    bad = [k for k in kinds if k not in KINDS]
    if bad or not kinds:
        raise ConfigError(f"unknown vehicle kinds {bad}; choose from {KINDS}")
    cycle = [k for k in _MIX if k in kinds]
    seeds = np.random.SeedSequence([int(seed), 0x5EC5]).generate_state(max(n, 1), np.uint32)
    out = []
    for i in range(n):
        kind = cycle[i % len(cycle)]
        v = procedural_vehicle(kind, int(seeds[i]))
        v.vehicle_id = f"proc-{i:04d}-{kind}"
        out.append(v)
    return out
