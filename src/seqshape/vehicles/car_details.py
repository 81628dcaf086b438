"""Details of fleet cars and vans, and `build_car`: body loft + wheels + mirrors, roof rails,
spoilers, the cabin interior and the pickup bed (build frame of `seqshape.vehicles.cars`).

Mirrors are flagged ``in_box=False`` (annotators leave them out of the box). Roof rails are
TRIM; the interior (dashboard and seat rows, INTERIOR) sits inside the closed body, reachable
only through the glass. The pickup bed is a U-section loft (walls and floor) whose rear cap
forms the tailgate.
"""

from __future__ import annotations

import numpy as np

from seqshape.vehicles.base import BODY, INTERIOR, TRIM
from seqshape.vehicles.cars import (
    _CAP_STEPS,
    _GAP,
    CarParams,
    _body_rings,
    _cap_labels,
    _floor_and_sill,
    _stations,
    _strip_labels,
    profile_knots,
)
from seqshape.vehicles.parts import (
    Part,
    beam,
    box_part,
    end_closed_loft,
    mirror_ring,
    segment_half_index,
    superellipsoid,
    wheel,
)


def _mirrors(p: CarParams, k: dict, info, x) -> list[Part]:
    s = k["cowl"] + 0.22 + 0.1 * (p.ws_deg > 40)
    xm = p.length - s
    i = int(np.searchsorted(x, xm).clip(0, len(x) - 1))
    zb, hw = info["zb"][i], info["hw"][i]
    hx, hy, hz = p.mirror
    out = []
    for sy in (1.0, -1.0):
        yc = sy * (hw + p.extra.get("mirror_out", 0.12) - hy)
        part = superellipsoid([xm - 0.02, yc, zb + 0.05 + hz], [hx, hy, hz], BODY, power=3.0,
                              n_lat=5, n_lon=10)
        part.in_box = False
        out.append(part)
    return out


def _rails(p: CarParams, k: dict, info, x) -> list[Part]:
    """Two roof rails following the roof line: chains of square beams (TRIM) whose highest top
    is at the sampled overall height (``p.height`` is the body height, 6 cm lower)."""
    s0, s1 = k["ws_top"] + p.roof_step + 0.25, k["roof_rear"] - 0.12
    sel = (p.length - x > s0) & (p.length - x < s1)
    if sel.sum() < 2 or s1 - s0 < 0.6:
        return []
    y = float(np.min(info["roof_hw"][sel])) - 0.1
    xs = p.length - np.linspace(s0, s1, 7)
    yr = np.interp(xs, x, info["roof_hw"]) - np.interp(xs, x, info["roof_rc"])
    f = np.clip(y / yr, 0.0, 1.0)
    z = np.interp(xs, x, info["zt"]) + np.interp(xs, x, info["crown"]) * (1 - f * f)
    z += p.height + 0.06 - 0.022 - z.max()  # rail tops reach the sampled height
    out = []
    for sy in (1.0, -1.0):
        pts = np.column_stack([xs, np.full(len(xs), sy * y), z])
        out += [beam(a, b, 0.022, TRIM) for a, b in zip(pts[:-1], pts[1:], strict=True)]
    return out


def _spoiler(p: CarParams, k: dict, info, x) -> list[Part]:
    if p.spoiler == "none":
        return []
    if p.spoiler == "roof":
        xr = p.length - k["roof_rear"] + 0.02
        i = int(np.searchsorted(x, xr).clip(0, len(x) - 1))
        z, hw = info["zt"][i], info["roof_hw"][i] - 0.02
        return [superellipsoid([xr - 0.06, 0.0, z + 0.005], [0.13, hw, 0.03], BODY, power=4.0,
                               n_lat=4, n_lon=12)]
    xr = x[0] + 0.08
    z, hw = info["zt"][0], info["roof_hw"][0] - 0.06
    if p.spoiler == "lip":
        return [superellipsoid([xr, 0.0, z + 0.01], [0.07, hw, 0.025], BODY, power=4.0,
                               n_lat=4, n_lon=12)]
    wing = superellipsoid([xr, 0.0, z + 0.2], [0.11, hw, 0.02], BODY, power=4.0, n_lat=4,
                          n_lon=12)
    struts = [box_part([xr - 0.04, sy * 0.45 - 0.015, z - 0.05], [xr + 0.04, sy * 0.45 + 0.015,
                                                                   z + 0.19], BODY)
              for sy in (1.0, -1.0)]
    return [wing, *struts]


def _radiator(p: CarParams, k: dict, info, x) -> Part:
    """The radiator behind the grille: one dark block between the front wheel wells from 5 cm
    behind the last full-width station back to 8 cm short of the front wheel arch (at least
    8 cm deep, at most 0.8 m, and 5 cm short of the cowl), up to 3 cm under the hood, inside
    the closed body (reached only through the grille's openings; label INTERIOR, so it is no
    part of the complete outside shape)."""
    L = p.length
    s0 = k["front"] + 0.05
    arch = L - max(p.wheel_x) - p.wheel_radius - 0.08
    s1 = max(min(k["cowl"] - 0.05, k["front"] + 0.8, arch), s0 + 0.08)
    span = (x >= L - s1 - 0.05) & (x <= L - s0 + 0.05)
    if not span.any():
        span = np.abs(x - (L - s0)) == np.abs(x - (L - s0)).min()
    zb, zt, hw, zf = (np.asarray(info[key])[span] for key in ("zb", "zt", "hw", "zf"))
    top = float(np.minimum(zb, zt).min()) - 0.03  # the grille's top: the beltline at the nose
    bottom = min(float(zf.max()) + 0.12, top - 0.1)
    half = max(float(hw.min()) - p.wheel_width - 0.12, 0.2)  # between the wheel wells
    return box_part([L - s1, -half, bottom], [L - s0, half, top], INTERIOR)


def _interior(p: CarParams, k: dict, info, x) -> list[Part]:
    """Dashboard, seats and the load floor inside the cabin (seen only through the glass).

    Sized like real car seats: front row two separate seats (~0.50 m wide, centred 0.37 m from
    the centre line, a console gap between them), rear row a bench as wide as the cabin;
    cushions ~0.36 m above the floor, seat backs ending a few cm above the beltline, one
    headrest (0.26 x 0.10 x 0.20 m) above each outer seat. Above the beltline a real cabin
    is mostly empty: rays through the windshield or a side window pass beside and between the
    headrests on to the rear window, the far panes and the load floor behind the last row
    (a parcel shelf under the rear window of a notchback / fastback, a cargo floor and a
    shelf at the belt of a hatchback, a cargo floor of an estate / SUV / MPV).
    """
    L = p.length

    def at(s):
        i = int(np.searchsorted(x, L - s).clip(0, len(x) - 1))
        return info["zb"][i], info["zt"][i], info["hw"][i], info["zf"][i]

    s_dash = k["cowl"] + 0.2
    zb, zt, hw, zf = at(s_dash)
    out = [superellipsoid([L - s_dash, 0.0, zb - 0.12], [0.16, hw - 0.25, 0.14], INTERIOR,
                          power=4.0, n_lat=4, n_lon=10)]
    rows = [k["ws_top"] + 0.55]
    if p.windows and len(p.windows) > 1 and p.rear_style != "cab":
        rows.append(rows[0] + 0.85)
    if p.rear_style == "cab" and p.extra.get("crew", True):
        rows.append(rows[0] + 0.8)
    last = None
    for r, s in enumerate(rows):
        if s > k["end"] - 0.3:
            break
        out += _seat_row(p, L - s, *at(s), bench=r > 0)
        last = s
    if last is not None and p.rear_style in ("notch", "fastback", "hatch", "box"):
        out += _load_floor(p, k, last, at)
    return out


def _seat_row(p: CarParams, xs: float, zb, zt, hw, zf, bench: bool) -> list[Part]:
    """One seat row whose seat backs stand at ``xs``: cushions, backs and headrests. Below the
    wheel-arch tops everything keeps clear of the wheel wells (``|y| <= inner``)."""
    inner = hw - p.wheel_width - 0.2
    arch_top = 2 * p.wheel_radius + 0.1
    cushion = min(zf + 0.36, zb - 0.3)
    back_top = min(zb + (0.04 if bench else 0.08), cushion + 0.65)
    head_top = min(back_top + 0.28, zt - 0.08)
    if bench:
        seats = [(0.0, hw - 0.14)]
        heads = [sy * min(0.40, hw - 0.3) for sy in (1.0, -1.0)]
    else:
        yc = min(0.37, hw - 0.39)
        seats = [(sy * yc, min(0.25, yc - 0.06)) for sy in (1.0, -1.0)]
        heads = [sy * yc for sy in (1.0, -1.0)]
    out = []
    for y, h in seats:
        lo, hi = max(y - h, -inner), min(y + h, inner)  # below the arches
        if hi - lo > 0.1:
            out.append(box_part([xs + 0.05, lo, cushion - 0.15], [xs + 0.45, hi, cushion],
                                INTERIOR))
        z_mid = min(max(arch_top, cushion), back_top - 0.1)
        if z_mid > cushion + 0.05 and hi - lo > 0.1:
            out.append(box_part([xs - 0.07, lo, cushion], [xs + 0.07, hi, z_mid], INTERIOR))
        else:
            z_mid = cushion
        out.append(superellipsoid([xs, y, 0.5 * (z_mid + back_top)],
                                  [0.07, h, 0.5 * (back_top - z_mid)], INTERIOR, power=4.0,
                                  n_lat=4, n_lon=10))
    hz = min(0.1, 0.5 * (head_top - back_top - 0.04))  # 4 cm of posts under the headrest
    if hz > 0.04:
        for y in heads:
            out.append(superellipsoid([xs - 0.02, y, head_top - hz], [0.05, 0.13, hz],
                                      INTERIOR, power=4.0, n_lat=4, n_lon=10))
    return out


def _load_floor(p: CarParams, k: dict, s_row: float, at) -> list[Part]:
    """What lies behind the last seat row, under the rear glass (docstring of `_interior`)."""
    L = p.length
    s0 = s_row + 0.1
    if p.rear_style in ("notch", "fastback"):
        s1 = k["rw_end"] - 0.05
        if s1 - s0 < 0.15:
            return []
        zb, zt, hw, zf = at(s1)
        z = p.deck_height - 0.04
        return [box_part([L - s1, -(hw - 0.2), z - 0.02], [L - s0, hw - 0.2, z], INTERIOR)]
    s1 = k["end"] - 0.12
    if s1 - s0 < 0.25:
        return []
    zb, zt, hw, zf = at(s1)
    inner = hw - p.wheel_width - 0.2
    floor = zf + 0.45
    out = [box_part([L - s1, -inner, floor - 0.05], [L - s0, inner, floor], INTERIOR)]
    if p.rear_style == "hatch":
        out.append(box_part([L - s1, -(hw - 0.2), zb], [L - s0, hw - 0.2, zb + 0.015],
                            INTERIOR))
    return out


def _bed(p: CarParams, k: dict, wheels) -> Part:
    """Open pickup bed: a U-section loft (walls, floor) closed at the tailgate."""
    x1 = p.bed_len + 0.06
    x0 = max(p.rear_depth)
    x = _stations(p, dict(cowl=-1, ws_top=-1, roof_rear=-1, rw_end=-1), x0, x1, wheels)
    x = x[x <= x1]
    zf, zs = _floor_and_sill(p, x, x0, x1 + 1.0, wheels)
    rail = p.deck_height
    floor = rail - p.bed_depth
    wall = 0.06
    rings = []
    for i in range(len(x)):
        hw = p.width / 2 - p.taper_rear * np.clip((p.wheel_x[1] - x[i]) / p.wheel_x[1], 0, 1) ** 2
        well_in = hw - p.wheel_width - 2 * _GAP
        half = [(0.0, zf[i]), (well_in, zf[i]), (well_in, zs[i]), (hw - 0.04, zs[i])]
        half += [(hw - p.belt_in * t * t, zs[i] + t * (rail - zs[i])) for t in (0.3, 0.7, 0.95)]
        half += [(hw - p.belt_in - 0.01, rail), (hw - p.belt_in - wall, rail),
                 (hw - p.belt_in - wall, floor), (0.0, floor)]
        ring = mirror_ring(np.asarray(half))
        rings.append(np.column_stack([np.full(len(ring), x[i]), ring]))
    rings = np.stack(rings)
    kk = rings.shape[1]
    lab = np.full((len(x) - 1, kk), BODY, np.uint8)
    h = segment_half_index(len(half))
    lab[:, h <= 1] = TRIM
    lab[:, h >= len(half) - 2] = TRIM  # bed floor liner
    d_r = np.interp(rings[0, :, 2], [0.0, p.rear_bumper_z, rail],
                    [p.rear_depth[0], p.rear_depth[1], p.rear_depth[2]])
    d_r *= max(p.rear_depth) / d_r.max()
    d_f = np.full(kk, 0.02)
    return end_closed_loft(rings, lab, d_f, d_r, 6.0, p.exp_rear, steps=4)


def build_car(p: CarParams) -> tuple[list[Part], dict]:
    """Labelled parts of one car / van in the build frame, and the profile positions."""
    k = profile_knots(p)
    L = p.length
    x1 = L - k["front"]
    x0 = L - k["end"]
    wheels = [w for w in p.wheel_x if x0 < w < x1]
    x = _stations(p, k, x0, x1, wheels)
    rings, info = _body_rings(p, k, x, wheels)
    labels = _strip_labels(p, k, x)
    zf_r, top_r = rings[0, :, 2].min(), rings[0, :, 2].max()
    zf_f, top_f = rings[-1, :, 2].min(), rings[-1, :, 2].max()
    df = np.interp(rings[-1, :, 2], [zf_f, p.front_bumper_z, top_f], list(p.front_depth))
    df *= max(p.front_depth) / df.max()  # the deepest ring vertex reaches the front end
    belt_r = info["zb"][0]
    zr = rings[0, :, 2]
    if p.rear_style == "cab":
        dr = np.full(len(zr), 0.04)
        exp_r = 8.0
    else:
        knots = sorted({zf_r: p.rear_depth[0], p.rear_bumper_z: p.rear_depth[1],
                        belt_r: p.rear_depth[2], top_r: p.rear_depth[3]}.items())
        dr = np.interp(zr, [a for a, _ in knots], [b for _, b in knots])
        dr *= max(p.rear_depth) / dr.max()  # the deepest ring vertex reaches the rear end
        exp_r = p.exp_rear
    body = end_closed_loft(rings, labels, df, dr, p.exp_front, exp_r, steps=_CAP_STEPS,
                           cap_labels=lambda which, r: _cap_labels(p, which, r))
    parts = [body]
    # tyre faces ~3.5 cm inside the body side (the plan-view taper starts beyond the axles)
    ywheel = p.width / 2 - p.wheel_width / 2 - _GAP / 2 - 0.01
    for wx in p.wheel_x:
        for sy in (1.0, -1.0):
            parts.append(wheel([wx, sy * ywheel, p.wheel_radius], p.wheel_radius,
                               p.wheel_width, sy))
    parts += _mirrors(p, k, info, x)
    if p.roof_rails:
        parts += _rails(p, k, info, x)
    parts += _spoiler(p, k, info, x)
    parts += _interior(p, k, info, x)
    parts.append(_radiator(p, k, info, x))
    if p.rear_style == "cab":
        parts.append(_bed(p, k, [w for w in p.wheel_x if w < x0]))
    return parts, k
