"""One parametric "boxy body with rounded edges" loft, shared by trucks, buses and trailers.

A section (`box_half`, 16 points on the left half) has a flat bottom, wheel wells where an
axle is under the body, a rounded lower edge (radius ``r_bot``), a vertical side (leaning in by
``lean`` above level 2) through four named levels (e.g. windshield bottom, belt, glass top), a
rounded upper edge (``r_top``) and a crowned roof. Stations are lofted and closed by
`parts.sweep_end` caps whose depth per vertex (a function of its height) gives the front's
rake and bumper and the plan-view corner rounding (exponent). Glass, lamps and trim are labelled
by segment index and station (exact borders), see `BoxBody`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from seqshape.vehicles.base import BODY, GLASS, HEADLAMP, LAMP, RIM, TRIM, TYRE
from seqshape.vehicles.parts import Part, end_closed_loft, lathe, mirror_ring, segment_half_index

GAP = 0.06
M_BOX = 16
# indices of the four side levels in the half section
LEVEL_IDX = (6, 7, 8, 9)


@dataclass
class BoxBody:
    """A boxy loft between x0 and x1 (build frame, x forward).

    ``levels``: four side heights (m) named by position (0..3) with glass between level pairs:
    ``side_glass`` (pair of level numbers, e.g. (1, 2)) on stations inside ``windows`` (x
    intervals), ``front_glass`` / ``rear_glass`` pairs on the caps (None: no glass).
    ``top(x)``, ``bottom(x)``: roof and underside heights; ``depth_front(z)`` /
    ``depth_rear(z)``: cap depth by height.
    """

    x0: float
    x1: float
    half_width: float
    bottom: Callable[[np.ndarray], np.ndarray]
    top: Callable[[np.ndarray], np.ndarray]
    levels: tuple[float, float, float, float]
    depth_front: Callable[[np.ndarray], np.ndarray]
    depth_rear: Callable[[np.ndarray], np.ndarray]
    exp_front: float = 6.0
    exp_rear: float = 8.0
    r_top: float = 0.12
    r_bot: float = 0.05
    crown: float = 0.04
    lean: float = 0.0
    wheels: tuple = ()           # ((x, radius, width), ...) axles under this body
    windows: tuple = ()          # ((xa, xb), ...) side glass intervals
    side_glass: tuple | None = None
    front_glass: tuple | None = None
    rear_glass: tuple | None = None
    front_lamps: bool = True
    rear_lamps: bool = True
    label: int = BODY
    step: float = 0.15
    extra_x: tuple = field(default_factory=tuple)


def box_half(hw, zf, zs, zt, levels, r_top, r_bot, crown, lean, well_in):
    """(16, 2) points (y, z) of the left half of a boxy section."""
    lv = np.clip(np.asarray(levels, float), zs + r_bot + 0.01, zt - r_top - 0.01)
    lv = np.maximum.accumulate(lv + np.arange(4) * 1e-3)
    tan_l = np.tan(np.radians(lean))

    def y(z):
        return hw - tan_l * max(z - lv[2], 0.0)

    pts = [(0.0, zf), (well_in, zf), (well_in, zs), (hw - r_bot, zs),
           (hw - r_bot * (1 - np.sqrt(0.5)), zs + r_bot * (1 - np.sqrt(0.5))), (hw, zs + r_bot)]
    pts += [(y(z), z) for z in lv]
    yt = y(zt - r_top)
    pts.append((yt, zt - r_top))
    for a in (np.pi / 6, np.pi / 3):
        pts.append((yt - r_top + r_top * np.cos(a), zt - r_top + r_top * np.sin(a)))
    pts += [(yt - r_top, zt), (0.5 * (yt - r_top), zt + 0.75 * crown), (0.0, zt + crown)]
    return np.asarray(pts)


def _stations(b: BoxBody) -> np.ndarray:
    xs = [np.linspace(b.x0, b.x1, max(int((b.x1 - b.x0) / b.step), 2) + 1)]
    for wx, r, _ in b.wheels:
        arch = r + GAP
        xs.append(wx + arch * np.sin(np.linspace(-np.pi / 2, np.pi / 2, 11)))
        xs.append(wx + np.array([-arch - 0.015, arch + 0.015]))
    for a, c in b.windows:
        xs.append(np.array([a, c]))
    xs.append(np.asarray(b.extra_x, float))
    x = np.unique(np.round(np.concatenate(xs), 4))
    x = x[(x >= b.x0 - 1e-3) & (x <= b.x1 + 1e-3)]
    x = x[np.concatenate([[True], np.diff(x) > 0.012])]
    x[0], x[-1] = b.x0, b.x1
    return x


def build_box(b: BoxBody) -> Part:
    """Closed labelled part of a `BoxBody`."""
    x = _stations(b)
    zf = b.bottom(x)
    zt = b.top(x)
    zs = zf + 0.02
    well_in = np.full(len(x), b.half_width - 0.35)
    for wx, r, w in b.wheels:
        arch = r + GAP
        dx = np.abs(x - wx)
        za = r + np.sqrt(np.clip(arch**2 - dx**2, 0.0, None))
        inside = dx <= arch + 1e-9
        zs = np.where(inside, np.maximum(zs, za), zs)
        well_in = np.minimum(well_in, b.half_width - w - 2 * GAP)
    rings = []
    for i in range(len(x)):
        half = box_half(b.half_width, zf[i], zs[i], zt[i], b.levels, b.r_top, b.r_bot, b.crown,
                        b.lean, well_in[i])
        ring = mirror_ring(half)
        rings.append(np.column_stack([np.full(len(ring), x[i]), ring]))
    rings = np.stack(rings)
    h = segment_half_index(M_BOX)
    lab = np.full((len(x) - 1, len(h)), b.label, np.uint8)
    lab[:, h <= 1] = TRIM
    if b.side_glass is not None:
        xm = 0.5 * (x[:-1] + x[1:])
        inside = np.zeros(len(xm), bool)
        for a, c in b.windows:
            inside |= (xm > a) & (xm < c)
        lo, hi = (LEVEL_IDX[i] for i in b.side_glass)
        lab[inside[:, None] & (h >= lo)[None] & (h < hi)[None]] = GLASS

    def cap_labels(which, r):
        steps = r.shape[0] - 1
        j = np.arange(steps)[:, None]
        out = np.full((steps, len(h)), b.label, np.uint8)
        out[np.broadcast_to(h[None] <= 4, out.shape)] = TRIM
        glass = b.front_glass if which == "front" else b.rear_glass
        if glass is not None:
            lo, hi = (LEVEL_IDX[i] for i in glass)
            out[(h[None] >= lo) & (h[None] < hi) & (j >= 1)] = GLASS
        if b.front_lamps if which == "front" else b.rear_lamps:
            out[(h[None] == 5) & (j >= 1) & (j <= 2)] = HEADLAMP if which == "front" else LAMP
        return out

    zr, zfr = rings[0, :, 2], rings[-1, :, 2]
    return end_closed_loft(rings, lab, b.depth_front(zfr), b.depth_rear(zr), b.exp_front,
                           b.exp_rear, steps=5, cap_labels=cap_labels)


def depth_profile(z_knots, d_knots) -> Callable[[np.ndarray], np.ndarray]:
    """Cap depth as a piecewise-linear function of height."""
    zk, dk = np.asarray(z_knots, float), np.asarray(d_knots, float)
    return lambda z: np.interp(z, zk, dk)


def const(value: float) -> Callable[[np.ndarray], np.ndarray]:
    """A function of station x (or height) returning ``value`` everywhere."""
    return lambda x: np.full(np.shape(x), float(value))


def truck_wheel(centre, radius: float, width: float, side: float, dual: bool,
                segments: int = 18) -> Part:
    """A truck / bus / trailer wheel (single or dual tyres as one wide tyre), axis along y.

    The outer face is dished (rim, label RIM), the tread and sidewalls are TYRE.
    """
    r, w = radius, width / 2.0
    rr, sh, dish = 0.55 * radius, min(0.05, 0.3 * w), 0.05 if dual else 0.03
    prof = np.array([(0.0, w - dish), (rr, w - dish), (rr + 0.01, w), (r - sh, w),
                     (r, w - sh), (r, -w + sh), (r - sh, -w), (rr, -w), (0.0, -w)])
    labels = np.array([RIM, RIM, TYRE, TYRE, TYRE, TYRE, TYRE, RIM])
    part = lathe(prof, labels, segments)
    v = part.vertices.copy()
    v[:, 1] *= side
    part.vertices = v + np.asarray(centre, float)
    return part.oriented()


def axle_wheels(axles, track_half: float, side_sign=(1.0, -1.0)) -> list[Part]:
    """Wheels of ``axles`` ((x, radius, width, dual), ...): outer faces at +-``track_half``."""
    out = []
    for x, r, w, dual in axles:
        for sy in side_sign:
            out.append(truck_wheel([x, sy * (track_half - w / 2), r], r, w, sy, dual))
    return out
