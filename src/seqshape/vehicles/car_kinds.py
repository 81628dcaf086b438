"""Shape-parameter ranges of each car / van kind and the sampler of `cars.CarParams`.

Dimensions (length, width, height, wheelbase) come from the real-fleet statistics in
`fleet_stats`; the style parameters below, which no spec sheet lists, are drawn uniformly from
ranges read off side, top and rear views of the same models (angles in degrees from
horizontal, lengths in m, ``hood`` as a fraction of the length, ``foh`` as the front share of
the two overhangs). ``rear`` gives the probability of each rear style.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from seqshape.vehicles.cars import CarParams, profile_knots
from seqshape.vehicles.fleet_stats import sample_dimensions

_CAR_BASE = dict(
    tumble=(14, 20), shoulder=(0.015, 0.04), belt_in=(0.02, 0.045), rc=(0.07, 0.11),
    crown=(0.02, 0.035), taper_f=(0.04, 0.07), taper_r=(0.03, 0.06), gh_taper=(0.02, 0.07),
    drop_f=(0.03, 0.06), drop_r=(0.04, 0.08), belt_rise=(0.03, 0.07), exp_f=(2.3, 3.0),
    exp_r=(2.8, 4.0), deck_ab=(0.04, 0.10), deck_len=(0.0, 0.0), rw=(50, 62),
    p_glass_roof=0.1, p_rails=0.0, p_clad=0.1, spoiler={"none": 1.0}, roof_step=(0.0, 0.0),
    mirror=((0.05, 0.06), (0.10, 0.12), (0.065, 0.08)), rear_glass=1.0, mirror_out=(0.10, 0.13),
)

KIND_STYLE: dict[str, dict] = {
    "city_car": dict(hood=(0.17, 0.21), ws=(28, 34), gh=(0.50, 0.56), nose=(0.72, 0.80),
                     clear=(0.13, 0.16), wr=(0.28, 0.30), ww=(0.16, 0.19), foh=(0.55, 0.62),
                     rear={"hatch": 1.0}, rw=(62, 76), drop_r=(0.03, 0.06),
                     depth_f=((0.10, 0.15), (0.20, 0.30), (0.12, 0.18)), bump_f=(0.40, 0.48),
                     depth_r=((0.05, 0.08), (0.10, 0.16), (0.07, 0.12), (0.03, 0.06)),
                     bump_r=(0.42, 0.52), exp_r=(3.0, 4.5), spoiler={"none": .5, "roof": .5},
                     doors=(2, 4), p_doors4=0.7),
    "hatchback": dict(hood=(0.21, 0.25), ws=(26, 31), gh=(0.46, 0.52), nose=(0.70, 0.78),
                      clear=(0.13, 0.15), wr=(0.30, 0.33), ww=(0.19, 0.23), foh=(0.54, 0.60),
                      rear={"hatch": 1.0}, rw=(48, 62), drop_r=(0.05, 0.10),
                      depth_f=((0.12, 0.18), (0.28, 0.40), (0.16, 0.24)), bump_f=(0.40, 0.48),
                      depth_r=((0.06, 0.10), (0.13, 0.20), (0.09, 0.15), (0.05, 0.09)),
                      bump_r=(0.45, 0.55), spoiler={"none": .3, "roof": .7}, p_doors4=0.85),
    "sedan": dict(hood=(0.26, 0.30), ws=(24, 29), gh=(0.42, 0.48), nose=(0.70, 0.78),
                  clear=(0.12, 0.15), wr=(0.32, 0.35), ww=(0.21, 0.25), foh=(0.43, 0.50),
                  rear={"notch": 0.8, "fastback": 0.2}, rw=(22, 30), rw_fast=(16, 21),
                  deck_len=(0.35, 0.55), deck_len_fast=(0.15, 0.30), tumble=(16, 22),
                  gh_taper=(0.04, 0.10), taper_r=(0.04, 0.07), drop_f=(0.03, 0.05),
                  drop_r=(0.03, 0.06), exp_f=(2.2, 2.8), exp_r=(2.5, 3.5),
                  depth_f=((0.12, 0.18), (0.32, 0.45), (0.18, 0.28)), bump_f=(0.42, 0.50),
                  depth_r=((0.10, 0.16), (0.20, 0.30), (0.14, 0.22), (0.10, 0.16)),
                  bump_r=(0.45, 0.55), p_glass_roof=0.15, spoiler={"none": .75, "lip": .25},
                  p_doors4=1.0),
    "estate": dict(hood=(0.25, 0.29), ws=(25, 30), gh=(0.44, 0.50), nose=(0.70, 0.78),
                   clear=(0.13, 0.15), wr=(0.32, 0.35), ww=(0.21, 0.25), foh=(0.43, 0.50),
                   rear={"box": 1.0}, drop_r=(0.06, 0.12), gh_taper=(0.04, 0.10),
                   depth_f=((0.12, 0.18), (0.32, 0.45), (0.18, 0.28)), bump_f=(0.42, 0.50),
                   depth_r=((0.08, 0.14), (0.18, 0.26), (0.14, 0.22), (0.06, 0.10)),
                   bump_r=(0.45, 0.55), p_rails=0.5, spoiler={"none": .4, "roof": .6},
                   p_doors4=1.0, quarter=True),
    "coupe": dict(hood=(0.30, 0.36), ws=(22, 27), gh=(0.34, 0.40), nose=(0.66, 0.74),
                  clear=(0.11, 0.13), wr=(0.33, 0.35), ww=(0.23, 0.27), foh=(0.42, 0.52),
                  rear={"fastback": 0.7, "notch": 0.3}, rw=(20, 26), rw_fast=(14, 20),
                  deck_len=(0.20, 0.35), deck_len_fast=(0.12, 0.25), tumble=(18, 26),
                  shoulder=(0.03, 0.06), drop_f=(0.02, 0.04), drop_r=(0.03, 0.06),
                  taper_f=(0.05, 0.09), taper_r=(0.05, 0.09), gh_taper=(0.06, 0.12),
                  exp_f=(2.1, 2.6), exp_r=(2.3, 3.2), belt_rise=(0.04, 0.10),
                  depth_f=((0.10, 0.15), (0.30, 0.42), (0.16, 0.26)), bump_f=(0.38, 0.46),
                  depth_r=((0.10, 0.15), (0.18, 0.28), (0.12, 0.20), (0.08, 0.14)),
                  bump_r=(0.42, 0.52), spoiler={"none": .45, "lip": .4, "wing": .15},
                  p_doors4=0.0),
    "mpv": dict(hood=(0.15, 0.20), ws=(27, 34), gh=(0.58, 0.66), nose=(0.78, 0.88),
                clear=(0.14, 0.17), wr=(0.32, 0.36), ww=(0.21, 0.25), foh=(0.48, 0.56),
                rear={"box": 1.0}, tumble=(8, 14), shoulder=(0.01, 0.03), rc=(0.08, 0.13),
                crown=(0.025, 0.04), taper_r=(0.02, 0.05), gh_taper=(0.02, 0.06),
                drop_f=(0.03, 0.06), drop_r=(0.04, 0.08), exp_f=(2.4, 3.2), exp_r=(3.5, 5.0),
                depth_f=((0.12, 0.18), (0.26, 0.36), (0.16, 0.24)), bump_f=(0.45, 0.55),
                depth_r=((0.06, 0.10), (0.14, 0.20), (0.10, 0.16), (0.05, 0.08)),
                bump_r=(0.50, 0.60), p_glass_roof=0.15, p_rails=0.4,
                spoiler={"none": .5, "roof": .5}, p_doors4=1.0, quarter=True),
    "crossover": dict(hood=(0.23, 0.27), ws=(27, 33), gh=(0.48, 0.55), nose=(0.82, 0.92),
                      clear=(0.17, 0.20), wr=(0.34, 0.37), ww=(0.22, 0.25), foh=(0.46, 0.54),
                      rear={"hatch": 0.6, "box": 0.4}, rw=(45, 60), drop_f=(0.04, 0.06),
                      drop_r=(0.06, 0.12), tumble=(12, 18), rc=(0.08, 0.12),
                      taper_f=(0.05, 0.08), taper_r=(0.04, 0.07), gh_taper=(0.04, 0.10),
                      belt_rise=(0.04, 0.09), deck_ab=(0.05, 0.12),
                      depth_f=((0.14, 0.20), (0.30, 0.40), (0.18, 0.26)), bump_f=(0.50, 0.60),
                      depth_r=((0.08, 0.12), (0.16, 0.24), (0.12, 0.20), (0.05, 0.09)),
                      bump_r=(0.52, 0.62), p_glass_roof=0.2, p_rails=0.5, p_clad=0.7,
                      spoiler={"none": .2, "roof": .8}, p_doors4=1.0, quarter=True),
    "suv": dict(hood=(0.24, 0.28), ws=(30, 38), gh=(0.52, 0.60), nose=(0.95, 1.08),
                clear=(0.19, 0.24), wr=(0.36, 0.40), ww=(0.24, 0.28), foh=(0.45, 0.52),
                rear={"box": 1.0}, drop_f=(0.02, 0.05), drop_r=(0.02, 0.06), tumble=(8, 14),
                shoulder=(0.02, 0.04), belt_in=(0.02, 0.04), rc=(0.08, 0.13),
                taper_r=(0.03, 0.05), gh_taper=(0.02, 0.06), belt_rise=(0.02, 0.06),
                exp_f=(2.8, 3.8), exp_r=(3.5, 5.0),
                depth_f=((0.14, 0.20), (0.28, 0.40), (0.18, 0.28)), bump_f=(0.55, 0.68),
                depth_r=((0.08, 0.12), (0.16, 0.24), (0.12, 0.18), (0.05, 0.08)),
                bump_r=(0.58, 0.70), p_glass_roof=0.15, p_rails=0.6, p_clad=0.5,
                spoiler={"none": .4, "roof": .6}, p_doors4=1.0, quarter=True,
                mirror=((0.055, 0.065), (0.11, 0.13), (0.08, 0.09))),
    "pickup": dict(hood=(0.27, 0.31), ws=(33, 40), gh=(0.50, 0.58), nose=(1.05, 1.20),
                   clear=(0.21, 0.26), wr=(0.38, 0.42), ww=(0.26, 0.29), foh=(0.38, 0.45),
                   rear={"cab": 1.0}, bed_len=(1.62, 1.95), bed_depth=(0.48, 0.56),
                   rail_below_belt=(-0.02, 0.05), drop_f=(0.02, 0.04), drop_r=(0.01, 0.03),
                   tumble=(6, 12), belt_in=(0.01, 0.03), taper_r=(0.0, 0.02),
                   belt_rise=(0.0, 0.03), exp_f=(3.0, 4.5), exp_r=(5.0, 8.0),
                   depth_f=((0.14, 0.20), (0.28, 0.38), (0.18, 0.26)), bump_f=(0.60, 0.72),
                   depth_r=((0.06, 0.10), (0.14, 0.20), (0.05, 0.08), (0.05, 0.08)),
                   bump_r=(0.55, 0.65), p_rails=0.15, p_clad=0.3, p_doors4=1.0,
                   mirror=((0.06, 0.07), (0.12, 0.14), (0.10, 0.12)), mirror_out=(0.14, 0.20)),
    "panel_van": dict(hood=(0.12, 0.17), ws=(45, 58), belt=(1.08, 1.18), nose=(0.95, 1.05),
                      clear=(0.16, 0.20), wr=(0.33, 0.36), ww=(0.21, 0.24), foh=(0.42, 0.52),
                      rear={"box": 1.0}, drop_f=(0.04, 0.08), drop_r=(0.0, 0.02),
                      tumble=(3, 7), shoulder=(0.0, 0.02), belt_in=(0.01, 0.03),
                      rc=(0.08, 0.14), crown=(0.02, 0.03), taper_f=(0.05, 0.09),
                      taper_r=(0.0, 0.03), gh_taper=(0.0, 0.02), belt_rise=(0.0, 0.02),
                      exp_f=(2.6, 3.4), exp_r=(6.0, 10.0),
                      depth_f=((0.15, 0.22), (0.28, 0.38), (0.18, 0.26)), bump_f=(0.48, 0.58),
                      depth_r=((0.04, 0.08), (0.10, 0.16), (0.05, 0.09), (0.03, 0.06)),
                      bump_r=(0.45, 0.55), rear_glass=0.4, p_rails=0.1, van=True,
                      p_kombi=0.3, mirror=((0.06, 0.07), (0.12, 0.14), (0.13, 0.16)),
                      mirror_out=(0.18, 0.24)),
    "high_roof_van": dict(hood=(0.12, 0.16), ws=(50, 60), belt=(1.15, 1.30),
                          ws_top=(1.95, 2.10), roof_step=(0.35, 0.55), nose=(1.00, 1.10),
                          clear=(0.18, 0.22), wr=(0.35, 0.38), ww=(0.21, 0.24),
                          foh=(0.40, 0.50), rear={"box": 1.0}, drop_f=(0.0, 0.03),
                          drop_r=(0.0, 0.02), tumble=(2, 5), shoulder=(0.0, 0.02),
                          belt_in=(0.01, 0.03), rc=(0.10, 0.16), crown=(0.02, 0.04),
                          taper_f=(0.05, 0.09), taper_r=(0.0, 0.02), gh_taper=(0.0, 0.0),
                          belt_rise=(0.0, 0.02), exp_f=(2.6, 3.4), exp_r=(8.0, 12.0),
                          depth_f=((0.15, 0.22), (0.25, 0.35), (0.18, 0.25)),
                          bump_f=(0.50, 0.60),
                          depth_r=((0.04, 0.08), (0.08, 0.14), (0.05, 0.08), (0.03, 0.05)),
                          bump_r=(0.50, 0.60), rear_glass=0.5, van=True, p_kombi=0.2,
                          mirror=((0.06, 0.07), (0.13, 0.15), (0.15, 0.18)),
                          mirror_out=(0.20, 0.26)),
}

CAR_KINDS = tuple(KIND_STYLE)


def _u(rng, lo_hi) -> float:
    lo, hi = lo_hi
    return float(rng.uniform(lo, hi))


def _pick(rng, probs: dict) -> str:
    keys = list(probs)
    w = np.array([probs[k] for k in keys], float)
    return keys[int(rng.choice(len(keys), p=w / w.sum()))]


def _windows(p: CarParams, st: dict, rng) -> tuple[tuple[float, float], ...]:
    """Side glass intervals (s from the front) for the body's doors and pillars."""
    k = profile_knots(p)
    a = k["cowl"] + 0.04
    if st.get("van"):
        door = _u(rng, (0.80, 0.95))
        wins = [(a, k["ws_top"] + door)]
        if rng.random() < st.get("p_kombi", 0.0):
            s = wins[-1][1] + 0.12
            while s + 0.6 < k["end"] - 0.35:
                wins.append((s, min(s + _u(rng, (0.75, 0.95)), k["end"] - 0.3)))
                s = wins[-1][1] + 0.1
        return tuple(wins)
    if p.rear_style in ("notch", "fastback"):
        g_end = k["roof_rear"] + _u(rng, (0.0, 0.22))
    elif p.rear_style == "hatch":
        g_end = k["roof_rear"] - _u(rng, (0.06, 0.25))
    elif p.rear_style == "cab":
        g_end = k["end"] - _u(rng, (0.10, 0.16))
    else:  # box: rear door window, C pillar, quarter window, D pillar
        g_end = k["end"] - _u(rng, (0.55, 0.85))
    four = rng.random() < st.get("p_doors4", 1.0)
    if four:
        b = a + _u(rng, (0.45, 0.52)) * (g_end - a)
        pw = _u(rng, (0.07, 0.12))
        wins = [(a, b - pw / 2), (b + pw / 2, g_end)]
    else:
        q = a + _u(rng, (0.64, 0.74)) * (g_end - a)
        wins = [(a, q), (q + 0.05, g_end)]
    if p.rear_style == "box" and st.get("quarter"):
        wins.append((g_end + _u(rng, (0.08, 0.14)), k["end"] - _u(rng, (0.10, 0.18))))
    return tuple(w for w in wins if w[1] - w[0] > 0.1)


def sample_car_params(kind: str, rng: np.random.Generator) -> CarParams:
    """Draw `CarParams` of a car / van ``kind``: fleet dimensions, then style parameters."""
    st = {**_CAR_BASE, **KIND_STYLE[kind]}
    length, width, height, wb = sample_dimensions(kind, rng)
    rear = _pick(rng, st["rear"])
    wr, ww = _u(rng, st["wr"]), _u(rng, st["ww"])
    foh = _u(rng, st["foh"]) * (length - wb)
    arch = wr + 0.05
    rails = rng.random() < st["p_rails"]
    h_body = height - (0.06 if rails else 0.0)
    crown = _u(rng, st["crown"])
    drop_f, drop_r = _u(rng, st["drop_f"]), _u(rng, st["drop_r"])
    belt = _u(rng, st["belt"]) if "belt" in st else h_body - _u(rng, st["gh"])
    roof_front = h_body - crown - drop_f
    roof_step = _u(rng, st["roof_step"])
    ws_top = min(_u(rng, st["ws_top"]), roof_front - 0.2) if "ws_top" in st else roof_front
    if roof_step <= 0:
        ws_top = roof_front
    df = [_u(rng, r) for r in st["depth_f"]]
    df = list(np.minimum(df, foh - arch - 0.04))
    dr = [_u(rng, r) for r in st["depth_r"]]
    dr = list(np.minimum(dr, length - wb - foh - arch - 0.04))
    fast = rear == "fastback"
    deck_h = belt + _u(rng, st["deck_ab"])
    bed_len = bed_depth = 0.0
    if rear == "cab":
        bed_len = _u(rng, st["bed_len"])
        deck_h = belt - _u(rng, st["rail_below_belt"])
        bed_depth = min(_u(rng, st["bed_depth"]), deck_h - 2 * wr - 0.12)
    nose = min(_u(rng, st["nose"]), belt - 0.06)
    spoiler = _pick(rng, st["spoiler"])
    if rear in ("notch", "fastback") and spoiler == "roof":
        spoiler = "lip"
    p = CarParams(
        kind=kind, length=float(length), width=float(width), height=float(h_body),
        wheelbase=float(wb), front_overhang=float(foh), wheel_radius=wr, wheel_width=ww,
        clearance=_u(rng, st["clear"]), hood_len=_u(rng, st["hood"]) * length,
        ws_deg=_u(rng, st["ws"]), ws_top=float(ws_top), roof_step=float(roof_step),
        roof_drop_front=drop_f, roof_drop_rear=drop_r, rear_style=rear,
        rw_deg=_u(rng, st["rw_fast"] if fast else st["rw"]),
        deck_len=_u(rng, st["deck_len_fast"] if fast else st["deck_len"]),
        deck_height=float(deck_h), belt=float(belt), belt_rise=_u(rng, st["belt_rise"]),
        nose_height=float(nose), tumble_deg=_u(rng, st["tumble"]),
        shoulder=_u(rng, st["shoulder"]), belt_in=_u(rng, st["belt_in"]),
        roof_radius=_u(rng, st["rc"]), crown=crown, taper_front=_u(rng, st["taper_f"]),
        taper_rear=_u(rng, st["taper_r"]), gh_taper_rear=_u(rng, st["gh_taper"]),
        front_depth=tuple(float(v) for v in df), front_bumper_z=_u(rng, st["bump_f"]),
        rear_depth=tuple(float(v) for v in dr), rear_bumper_z=_u(rng, st["bump_r"]),
        exp_front=_u(rng, st["exp_f"]), exp_rear=_u(rng, st["exp_r"]), windows=(),
        rear_glass=bool(rear in ("box", "cab") and rng.random() < st["rear_glass"]),
        glass_roof=bool(rng.random() < st["p_glass_roof"]),
        cladding=bool(rng.random() < st["p_clad"]),
        mirror=tuple(_u(rng, r) for r in st["mirror"]), spoiler=spoiler, roof_rails=rails,
        bed_len=bed_len, bed_depth=max(bed_depth, 0.0),
        extra=dict(crew=True, mirror_out=_u(rng, st["mirror_out"])))
    return replace(p, windows=_windows(p, st, rng))
