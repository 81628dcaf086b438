"""Trucks, buses and trailers from the boxy-body builder (`boxy.BoxBody`) plus simple parts.

Every builder takes a random generator, draws its dimensions from the real-fleet statistics
(`fleet_stats.sample_dimensions`: length, width, height, wheelbase) and its style parameters
from the ranges written next to them, and returns ``(parts, params)`` in the build frame (x
from the rear end (0) to the front end (L), z up from the ground). Kinds:

* ``box_truck``: cab-over cab + box body on a frame, dual rear wheels;
* ``tractor``: semi-tractor without trailer, ``cabover`` (European, 4x2) or ``conventional``
  (North-American long nose, 6x4, day cab or sleeper with roof fairing);
* ``flatbed``: cab-over cab + flat load deck with headboard, half of them with dropsides;
* ``city_bus``: low floor (0.3 m), big side glass from ~1.1 m, large windshield, roof pods;
* ``coach``: high floor, side glass from ~1.9 m, raked windshield, 2 or 3 axles;
* ``semi_trailer``: box / curtain-sider on a tri-axle (EU) or tandem (US) bogie, landing legs,
  rear underride bar, side skirts on half of the US ones;
* ``car_trailer``: small trailer behind a car: open utility box or car-transporter deck,
  A-frame drawbar, one or two axles.
"""

from __future__ import annotations

import numpy as np

from seqshape.vehicles.base import BODY, CARGO, INTERIOR, TRIM
from seqshape.vehicles.boxy import (
    BoxBody,
    axle_wheels,
    build_box,
    const,
    depth_profile,
)
from seqshape.vehicles.fleet_stats import sample_dimensions, sample_style
from seqshape.vehicles.parts import Part, beam, box_part, superellipsoid


def _u(rng, lo, hi) -> float:
    return float(rng.uniform(lo, hi))


def _mirrors(x, hw, z, out: float, size=(0.06, 0.05, 0.28)) -> list[Part]:
    """Big truck / bus mirror heads on arms beside the cab front corners."""
    parts = []
    for sy in (1.0, -1.0):
        yc = sy * (hw + out)
        parts.append(superellipsoid([x, yc, z], size, BODY, power=4.0, n_lat=4, n_lon=8))
        parts.append(box_part([x - 0.02, min(sy * hw, yc) - 0.01, z + size[2] - 0.06],
                              [x + 0.02, max(sy * hw, yc) + 0.01, z + size[2] - 0.03], TRIM))
    for p in parts:
        p.in_box = False
    return parts


def _seats(x0, x1, y0, y1, z0, z1, both_sides=True) -> list[Part]:
    """Seat blocks (INTERIOR) inside a cab or a bus: y from ``y0`` to ``y1`` on each side."""
    sides = (1.0, -1.0) if both_sides else (1.0,)
    out = []
    for sy in sides:
        lo, hi = sorted([sy * y0, sy * y1])
        out.append(box_part([x0, lo, z0], [x1, hi, z1], INTERIOR))
    return out


def _cabover(rng, x_front, width, height, cab_len, floor, wheel_x, wr, ww, glass=True):
    """A cab-over-engine cab (front axle under the cab); returns (part, info)."""
    hw = width / 2
    ws_lo = floor + _u(rng, 0.4, 0.6)
    belt = ws_lo + _u(rng, 0.05, 0.2)
    g_top = min(height - _u(rng, 0.25, 0.45), ws_lo + _u(rng, 0.9, 1.15))  # high roofs
    lamp = floor + 0.2
    rake = _u(rng, 0.12, 0.3)
    d_bot = _u(rng, 0.15, 0.25)
    dmax = max(d_bot, rake + 0.06)
    door = _u(rng, 0.8, 1.05)
    x1 = x_front - dmax
    body = BoxBody(
        x0=x_front - cab_len, x1=x1, half_width=hw, bottom=const(floor), top=const(height - 0.03),
        levels=(lamp, ws_lo, belt, g_top),
        depth_front=depth_profile([floor, ws_lo, g_top, height + 0.1],
                                  [d_bot, rake + 0.06, 0.08, 0.03]),
        depth_rear=const(0.04), exp_front=_u(rng, 5.0, 8.0), exp_rear=10.0,
        r_top=_u(rng, 0.08, 0.16), r_bot=0.04, crown=0.03, lean=_u(rng, 0.0, 3.0),
        wheels=((wheel_x, wr, ww),), windows=((x1 - door, x1 - 0.08),),
        side_glass=(2, 3) if glass else None, front_glass=(1, 3) if glass else None,
        rear_lamps=False, step=0.12)
    parts = [build_box(body)]
    parts.append(box_part([x_front - dmax - 0.1, -hw + 0.02, max(floor - 0.45, 0.3)],
                          [x_front - dmax + d_bot + 0.02, hw - 0.02, floor + 0.1], TRIM))
    parts += _mirrors(x1 - 0.1, hw, ws_lo + 0.3, _u(rng, 0.2, 0.3))
    x0 = x_front - cab_len
    parts += _seats(x0 + 0.25, x0 + 0.8, -hw + 0.2, hw - 0.2, floor + 0.35, belt + 0.35, False)
    return parts, dict(ws_lo=ws_lo, belt=belt)


def _frame(x0, x1, z0, z1, half=0.45) -> list[Part]:
    """Two chassis rails (TRIM) centred at y = +-``half``."""
    return [box_part([x0, sy * half - 0.05, z0], [x1, sy * half + 0.05, z1], TRIM)
            for sy in (1.0, -1.0)]


def _underride(x, hw, z) -> Part:
    return box_part([x, -hw + 0.1, z], [x + 0.12, hw - 0.1, z + 0.12], TRIM)


def box_truck(rng):
    L, W, H, WB = sample_dimensions("box_truck", rng)
    light = W < 2.45
    wr = _u(rng, 0.37, 0.41) if light else _u(rng, 0.46, 0.52)
    foh = _u(rng, 1.0, 1.25)
    cab_w = float(np.clip(W - _u(rng, 0.05, 0.4), 1.85, 2.5))
    cab_h = _u(rng, 2.15, 2.4) if light else float(np.clip(H - _u(rng, 0.5, 0.9), 2.6, 3.1))
    cab_len = _u(rng, 1.55, 1.95)
    floor = 2 * wr + 0.08
    xf = L - foh
    xr = xf - WB
    parts, _ = _cabover(rng, L, cab_w, cab_h, cab_len, floor - 0.05, xf, wr, 0.26)
    box_floor = 2 * wr + _u(rng, 0.12, 0.25)
    gap = _u(rng, 0.05, 0.15)
    box = BoxBody(x0=0.04, x1=L - cab_len - gap, half_width=W / 2, bottom=const(box_floor),
                  top=const(H), levels=(box_floor + 0.2, box_floor + 0.3, H - 0.4, H - 0.3),
                  depth_front=const(0.03), depth_rear=const(0.04), exp_front=12.0,
                  exp_rear=12.0, r_top=0.05, r_bot=0.03, crown=0.0, front_lamps=False,
                  step=0.3)
    parts.append(build_box(box))
    parts += _frame(0.3, L - cab_len, wr - 0.05, wr + 0.22)
    parts.append(_underride(0.02, W / 2, 0.45))
    parts += axle_wheels([(xf, wr, 0.26, False), (xr, wr, 0.52, True)], cab_w / 2 - 0.02)
    parts.append(superellipsoid([0.5 * (xf + xr), W / 2 - 0.45, wr], [0.35, 0.22, 0.22], TRIM,
                                power=2.5, n_lat=4, n_lon=10))
    return parts, dict(length=L, width=W, height=H, wheelbase=WB, cab_height=cab_h)


def tractor(rng):
    style = sample_style("tractor", rng)
    L, W, H, WB = sample_dimensions("tractor", rng, style)
    wr = _u(rng, 0.49, 0.53)
    hw = W / 2
    if style == "cabover":
        foh = _u(rng, 1.35, 1.5)
        xf, cab_len = L - foh, _u(rng, 2.15, 2.4)
        parts, _ = _cabover(rng, L, W, H, cab_len, 2 * wr + 0.15, xf, wr, 0.32)
        axles = [(xf, wr, 0.32, False), (xf - WB, wr, 0.55, True)]
        cab_rear = L - cab_len
    else:
        foh = _u(rng, 1.0, 1.25)
        xf = L - foh
        hood_len = _u(rng, 1.7, 2.1)
        hood_top = _u(rng, 1.75, 2.0)
        hood = BoxBody(x0=L - hood_len - 0.1, x1=L - 0.12, half_width=hw - _u(rng, 0.05, 0.2),
                       bottom=const(0.55), top=lambda x: hood_top - 0.12 * np.clip(
                           (x - (L - hood_len)) / hood_len, 0, 1) ** 2,
                       levels=(0.75, 0.95, 1.2, hood_top - 0.2),
                       depth_front=depth_profile([0.5, 0.9, hood_top], [0.1, 0.12, 0.06]),
                       depth_rear=const(0.05), exp_front=_u(rng, 3.0, 5.0), exp_rear=6.0,
                       r_top=_u(rng, 0.15, 0.3), r_bot=0.05, crown=0.06,
                       wheels=((xf, wr, 0.32),), rear_lamps=False, step=0.12)
        parts = [build_box(hood)]
        sleeper = L > 7.6
        cab_len = _u(rng, 3.0, 3.5) if sleeper else _u(rng, 1.9, 2.2)
        cab_x1 = L - hood_len - 0.35
        cab_top = _u(rng, 3.0, 3.2) if sleeper else H - 0.04
        floor = _u(rng, 1.05, 1.2)
        ws_lo = hood_top - 0.05
        g_top = min(cab_top, H) - 0.45

        def cab_top_fn(x, x1=cab_x1, top=cab_top):
            return top + (H - 0.04 - top) * np.clip((x1 - 0.5 - x) / 1.0, 0, 1) ** 0.7

        cab = BoxBody(x0=cab_x1 - cab_len, x1=cab_x1, half_width=hw,
                      bottom=const(floor), top=cab_top_fn, levels=(floor + 0.2, ws_lo,
                                                                   ws_lo + 0.1, g_top),
                      depth_front=depth_profile([floor, ws_lo, g_top, H],
                                                [0.45, 0.45, 0.1, 0.03]),
                      depth_rear=const(0.05), exp_front=_u(rng, 4.0, 6.0), exp_rear=10.0,
                      r_top=_u(rng, 0.12, 0.25), r_bot=0.04, crown=0.04,
                      windows=((cab_x1 - 0.9, cab_x1 - 0.05),), side_glass=(2, 3),
                      front_glass=(1, 3), front_lamps=False, rear_lamps=False, step=0.12)
        parts.append(build_box(cab))
        parts += _seats(cab_x1 - 1.3, cab_x1 - 0.75, -hw + 0.2, hw - 0.2, floor + 0.35,
                        ws_lo + 0.45, False)
        parts += _mirrors(cab_x1 + 0.3, hw - 0.05, ws_lo + 0.3, _u(rng, 0.18, 0.28))
        if rng.random() < 0.6:  # exhaust stacks behind the cab
            x = cab_x1 - cab_len - 0.12
            for sy in (1.0, -1.0):
                parts.append(box_part([x - 0.07, sy * (hw - 0.25) - 0.07, 1.0],
                                      [x + 0.07, sy * (hw - 0.25) + 0.07, H - 0.1], TRIM))
        rear = _u(rng, 0.8, 1.1)
        axles = [(xf, wr, 0.32, False), (rear + 1.3, wr, 0.55, True), (rear, wr, 0.55, True)]
        cab_rear = cab_x1 - cab_len
    parts += _frame(0.0, cab_rear + 0.3, wr - 0.1, wr + 0.2)
    x5 = axles[-1][0] + (0.65 if len(axles) == 3 else 0.3)
    parts.append(box_part([x5 - 0.6, -0.5, wr + 0.2], [x5 + 0.6, 0.5, wr + 0.38], TRIM))
    parts.append(superellipsoid([cab_rear - 0.55, hw - 0.3, wr + 0.05], [0.55, 0.3, 0.3],
                                TRIM, power=2.2, n_lat=5, n_lon=10))
    for ax in axles[1:]:
        parts.append(box_part([ax[0] - wr - 0.05, -hw + 0.05, 2 * wr + 0.02],
                              [ax[0] + wr + 0.05, hw - 0.05, 2 * wr + 0.08], TRIM))
    parts += axle_wheels(axles, hw - 0.04)
    return parts, dict(length=L, width=W, height=H, wheelbase=WB, style=style)


def flatbed(rng):
    L, W, H, WB = sample_dimensions("flatbed", rng)
    wr = _u(rng, 0.37, 0.42) if L < 8 else _u(rng, 0.46, 0.5)
    foh = _u(rng, 1.0, 1.25)
    xf = L - foh
    cab_len = _u(rng, 1.5, 1.9)
    parts, _ = _cabover(rng, L, min(W, _u(rng, 1.95, 2.45)), H, cab_len, 2 * wr + 0.05, xf,
                        wr, 0.26)
    deck = 2 * wr + _u(rng, 0.15, 0.3)
    x1 = L - cab_len - _u(rng, 0.05, 0.15)
    parts.append(box_part([0.0, -W / 2, deck - 0.15], [x1, W / 2, deck], CARGO))
    head = min(deck + _u(rng, 0.7, 1.1), H - 0.1)
    parts.append(box_part([x1 - 0.08, -W / 2 + 0.03, deck - 0.01], [x1, W / 2 - 0.03, head],
                          BODY))
    if rng.random() < 0.5:  # dropsides
        side = _u(rng, 0.35, 0.6)
        for sy in (1.0, -1.0):
            y0, y1 = sorted([sy * W / 2, sy * (W / 2 - 0.04)])
            parts.append(box_part([0.0, y0, deck - 0.01], [x1 - 0.08, y1, deck + side], CARGO))
        parts.append(box_part([0.0, -W / 2, deck - 0.01], [0.04, W / 2, deck + side], CARGO))
    parts += _frame(0.3, L - cab_len, wr - 0.05, deck - 0.15)
    parts.append(_underride(0.1, W / 2, 0.45))
    parts += axle_wheels([(xf, wr, 0.26, False), (xf - WB, wr, 0.5, True)], W / 2 - 0.1)
    return parts, dict(length=L, width=W, height=H, wheelbase=WB)


def _bus_windows(x0, x1, rng, bay=(1.2, 1.5), pillar=0.1):
    wins, x = [], x1
    while x - x0 > 0.6:
        b = min(_u(rng, *bay), x - x0)
        wins.append((float(x - b + pillar / 2), float(x - pillar / 2)))
        x -= b
    return tuple(wins)


def city_bus(rng):
    L, W, H, WB = sample_dimensions("city_bus", rng)
    hw = W / 2
    pod = _u(rng, 0.2, 0.35) if rng.random() < 0.7 else 0.0
    zt = H - pod - 0.03
    zf = _u(rng, 0.28, 0.34)
    wr = _u(rng, 0.48, 0.51)
    foh = _u(rng, 2.55, 2.8)
    xf = L - foh
    xr = xf - WB
    ws_lo, belt = _u(rng, 0.8, 1.0), _u(rng, 1.05, 1.2)
    g_top = zt - _u(rng, 0.3, 0.45)
    d = _u(rng, 0.1, 0.18)
    body = BoxBody(
        x0=0.0 + 0.08, x1=L - d - 0.03, half_width=hw, bottom=const(zf), top=const(zt),
        levels=(0.6, ws_lo, belt, g_top),
        depth_front=depth_profile([zf, 0.6, ws_lo, g_top, zt + 0.1],
                                  [d * 0.8, d + 0.03, d, 0.07, 0.03]),
        depth_rear=const(0.08), exp_front=_u(rng, 4.0, 7.0), exp_rear=_u(rng, 6.0, 10.0),
        r_top=_u(rng, 0.12, 0.25), r_bot=0.06, crown=0.05, lean=_u(rng, 0.5, 2.5),
        wheels=((xf, wr, 0.3), (xr, wr, 0.55)),
        windows=_bus_windows(0.5, L - 0.45, rng), side_glass=(2, 3), front_glass=(1, 3),
        rear_glass=(2, 3) if rng.random() < 0.4 else None, step=0.25)
    parts = [build_box(body)]
    if pod > 0:
        plen = _u(rng, 1.5, 3.5)
        xc = L - _u(rng, 2.5, 4.0) - plen / 2
        parts.append(superellipsoid([xc, 0.0, zt + pod / 2], [plen / 2, hw - 0.35, pod / 2 + 0.04],
                                    BODY, power=6.0, n_lat=4, n_lon=12))
    parts += _mirrors(L - 0.25, hw, 2.3, _u(rng, 0.15, 0.3), size=(0.06, 0.06, 0.25))
    parts += _seats(1.0, L - 2.6, 0.35, hw - 0.12, max(zf + 0.35, 2 * wr + 0.12), belt + 0.3)
    parts += axle_wheels([(xf, wr, 0.3, False), (xr, wr, 0.55, True)], hw - 0.06)
    return parts, dict(length=L, width=W, height=H, wheelbase=WB, roof_pod=pod, belt=belt,
                       windshield_bottom=ws_lo, windows=body.windows)


def coach(rng):
    L, W, H, WB = sample_dimensions("coach", rng)
    hw = W / 2
    zt = H - 0.06
    zf = _u(rng, 0.32, 0.4)
    wr = _u(rng, 0.5, 0.53)
    foh = _u(rng, 2.5, 2.8)
    xf = L - foh
    tri = L > 12.8
    xr = xf - WB
    ws_lo, belt = _u(rng, 1.0, 1.3), _u(rng, 1.8, 2.05)
    g_top = zt - _u(rng, 0.3, 0.4)
    rake = _u(rng, 0.15, 0.35)
    body = BoxBody(
        x0=0.06, x1=L - rake - 0.1, half_width=hw, bottom=const(zf), top=const(zt),
        levels=(0.7, ws_lo, belt, g_top),
        depth_front=depth_profile([zf, 0.7, ws_lo, g_top, zt + 0.1],
                                  [rake * 0.8, rake + 0.1, rake + 0.08, 0.1, 0.03]),
        depth_rear=const(0.06), exp_front=_u(rng, 3.5, 6.0), exp_rear=_u(rng, 5.0, 8.0),
        r_top=_u(rng, 0.2, 0.35), r_bot=0.06, crown=0.07, lean=_u(rng, 1.0, 3.0),
        wheels=((xf, wr, 0.3), (xr, wr, 0.55)) + (((xr - 1.35, wr, 0.3),) if tri else ()),
        windows=_bus_windows(1.0, L - 1.1, rng, (1.4, 1.9), 0.08), side_glass=(2, 3),
        front_glass=(1, 3), rear_glass=None, step=0.25)
    parts = [build_box(body)]
    parts += _mirrors(L - 0.2, hw, 2.2, _u(rng, 0.15, 0.28), size=(0.07, 0.06, 0.25))
    parts += _seats(1.2, L - 2.4, 0.35, hw - 0.12, max(belt - 0.6, 2 * wr + 0.15), belt + 0.35)
    axles = [(xf, wr, 0.3, False), (xr, wr, 0.55, True)]
    if tri:
        axles.append((xr - 1.35, wr, 0.3, False))
    parts += axle_wheels(axles, hw - 0.06)
    return parts, dict(length=L, width=W, height=H, wheelbase=WB, axles=len(axles), belt=belt,
                       windshield_bottom=ws_lo, windows=body.windows)


def semi_trailer(rng):
    style = sample_style("semi_trailer", rng)
    L, W, H, WB = sample_dimensions("semi_trailer", rng, style)
    hw = W / 2
    floor = _u(rng, 1.15, 1.3)
    wr = _u(rng, 0.47, 0.52)
    king = _u(rng, 0.9, 1.6)
    centre = max(L - king - WB, wr + 1.0)
    if style == "eu":
        axles = [(centre + d, wr, 0.38, False) for d in (1.31, 0.0, -1.31)]
    else:
        axles = [(centre + d, wr, 0.55, True) for d in (0.62, -0.62)]
    body = BoxBody(x0=0.04, x1=L - 0.05, half_width=hw, bottom=const(floor), top=const(H),
                   levels=(floor + 0.2, floor + 0.3, H - 0.4, H - 0.3),
                   depth_front=const(0.05), depth_rear=const(0.04), exp_front=8.0,
                   exp_rear=12.0, r_top=0.05, r_bot=0.03, crown=0.0, front_lamps=False,
                   step=0.5)
    parts = [build_box(body)]
    bogie0, bogie1 = axles[-1][0] - wr - 0.2, axles[0][0] + wr + 0.2
    parts += _frame(bogie0, bogie1, floor - 0.35, floor + 0.01, half=0.5)
    legs = L - king - _u(rng, 1.2, 1.8)
    foot = _u(rng, 0.25, 0.4)  # landing legs raised for driving
    for sy in (1.0, -1.0):
        parts.append(box_part([legs - 0.08, sy * 0.9 - 0.08, foot], [legs + 0.08, sy * 0.9 + 0.08,
                                                                      floor + 0.01], TRIM))
    parts.append(box_part([legs - 0.15, -0.95, foot - 0.06], [legs + 0.15, 0.95, foot], TRIM))
    parts.append(_underride(0.1, hw, 0.45))
    if style.startswith("us") and rng.random() < 0.5:  # aerodynamic side skirts
        for sy in (1.0, -1.0):
            y0, y1 = sorted([sy * (hw - 0.05), sy * (hw - 0.08)])
            parts.append(box_part([bogie1 + 0.3, y0, 0.35], [legs - 0.3, y1, floor + 0.01],
                                  TRIM))
    parts += axle_wheels([a for a in axles], hw - 0.05)
    return parts, dict(length=L, width=W, height=H, wheelbase=WB, style=style,
                       axles=len(axles))


def car_trailer(rng):
    L, W, H, WB = sample_dimensions("car_trailer", rng)
    transporter = L > 4.8
    draw = _u(rng, 1.0, 1.35)
    wr = _u(rng, 0.25, 0.3) if not transporter else _u(rng, 0.28, 0.33)
    ww = _u(rng, 0.15, 0.2)
    x1 = L - draw
    centre = x1 * _u(rng, 0.5, 0.58)
    axles = [(centre, wr, ww, False)] if L < 4.3 else [(centre + 0.38, wr, ww, False),
                                                      (centre - 0.38, wr, ww, False)]
    if transporter:
        deck = 2 * wr + _u(rng, 0.05, 0.12)
        box_hw, side = W / 2, _u(rng, 0.08, 0.14)
    else:
        deck = min(_u(rng, 0.55, 0.7), H - 0.25)
        box_hw, side = W / 2 - ww - 0.08, H - deck
    parts = [box_part([0.0, -box_hw, deck - 0.08], [x1, box_hw, deck], CARGO)]
    top = deck + side
    t = 0.04
    for sy in (1.0, -1.0):
        y0, y1 = sorted([sy * box_hw, sy * (box_hw - t)])
        parts.append(box_part([0.0, y0, deck - 0.08], [x1, y1, top], BODY))
    parts.append(box_part([0.0, -box_hw, deck - 0.08], [t, box_hw, top], BODY))
    parts.append(box_part([x1 - t, -box_hw, deck - 0.08], [x1, box_hw, top], BODY))
    if transporter:  # loading ramps stowed upright at the rear, and a rail to H
        for sy in (1.0, -1.0):
            parts.append(box_part([0.02, sy * 0.6 - 0.15, deck], [0.1, sy * 0.6 + 0.15, H], CARGO))
    # A-frame drawbar to the hitch at the front end
    zb = deck - 0.15
    for sy in (1.0, -1.0):
        parts.append(beam([x1 - 0.3, sy * (box_hw - 0.1), zb], [L - 0.15, 0.0, zb], 0.04, TRIM))
    parts.append(superellipsoid([L - 0.12, 0.0, zb + 0.02], [0.12, 0.06, 0.06], TRIM,
                                power=3.0, n_lat=4, n_lon=8))
    track = W / 2
    for ax in axles:
        if not transporter:
            for sy in (1.0, -1.0):
                parts.append(superellipsoid([ax[0], sy * (track - ww / 2), 2 * wr + 0.03],
                                            [wr + 0.08, ww / 2 + 0.03, 0.03], BODY, power=3.0,
                                            n_lat=3, n_lon=10))
    parts += axle_wheels(axles, track - (0.0 if not transporter else 0.02))
    parts.append(box_part([centre - 0.5, -box_hw + 0.05, wr - 0.05],
                          [centre + 0.5, box_hw - 0.05, deck - 0.08], TRIM))
    return parts, dict(length=L, width=W, height=H, wheelbase=WB, transporter=transporter)


HEAVY_BUILDERS = {"box_truck": box_truck, "tractor": tractor, "flatbed": flatbed,
                  "city_bus": city_bus, "coach": coach, "semi_trailer": semi_trailer,
                  "car_trailer": car_trailer}
