"""Fleet cars and car-derived vans: parameters, side profile and the labelled body loft.

The details (wheels, mirrors, rails, spoilers, interior, pickup bed) and `build_car` are in
`seqshape.vehicles.car_details`.

Build frame: x from the rear end (0) to the front end (L), y left, z up from the ground; ``s``
is the distance from the front end (s = L - x). The body is a loft of cross-sections (rings,
`parts.end_closed_loft`) between the last full-width stations at both ends, closed by caps that
sweep each ring vertex around a plan-view superellipse (`CarParams.exp_front`, ``exp_rear``) by
a depth that depends on its height (`CarParams.front_depth` / ``rear_depth``: bumper
protrusion, hood leading edge, tailgate slope). So the side view of the nose and tail comes
from the depths, the plan view from the exponents and the depths.

A cross-section (`_half_section`, 20 points on the left half, same count everywhere) has a flat
underbody, a wheel well at both sides, a sill tucked under, a side that curves in towards the
beltline (``belt_in``), a shoulder step (``shoulder``), a greenhouse leaning in by the
tumblehome angle, a glass top, a roof-side band, a rounded roof edge (``roof_radius``) and a
crowned roof (``crown``). Fixed point indices make the window borders exact: side glass is the
greenhouse band between `_I_G0` and `_I_GT` at stations inside the window intervals (pillars
between them), windshield / rear window / glass roof are the roof segments at stations on the
sloped (or flat) parts of the top line, and a vertical tailgate's glass is the greenhouse band
of the rear cap. Face labels: `seqshape.vehicles.base` codes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from seqshape.vehicles.base import BODY, GLASS, GRILLE, HEADLAMP, LAMP, TRIM
from seqshape.vehicles.parts import mirror_ring, segment_half_index

_GAP = 0.05          # m, tyre to arch clearance
_STEP = 0.09         # m, station spacing
_CAP_STEPS = 6
# indices into the 20-point half section
_I_BELT, _I_G0, _I_GT, _I_RT, _I_C2, _I_ROOF0, _I_R1 = 8, 9, 12, 13, 15, 16, 17
_M = 20


@dataclass(frozen=True)
class CarParams:
    """Parameters of one fleet car / van body (metres, degrees from horizontal).

    Side profile (top line, s from the front end): hood from the front (``nose_height``) to the
    cowl at ``hood_len`` (``belt + 0.02``), windshield at ``ws_deg`` up to ``ws_top``, roof
    (peak ``height - crown``, dropping by ``roof_drop_front/rear`` at its ends; a high-roof van
    rises from ``ws_top`` to the roof over ``roof_step``), then by ``rear_style``: ``"notch"``
    (rear window at ``rw_deg`` down to a trunk deck of length ``deck_len`` at ``deck_height``),
    ``"fastback"`` (same, long shallow window, short deck), ``"hatch"`` (rear window at
    ``rw_deg`` down to ``deck_height`` at the rear end), ``"box"`` (roof to the rear end; the
    tailgate is the rear cap) or ``"cab"`` (pickup cab, ends ``bed_len`` before the rear).
    """

    kind: str
    length: float
    width: float
    height: float
    wheelbase: float
    front_overhang: float
    wheel_radius: float
    wheel_width: float
    clearance: float
    hood_len: float
    ws_deg: float
    ws_top: float
    roof_step: float
    roof_drop_front: float
    roof_drop_rear: float
    rear_style: str
    rw_deg: float
    deck_len: float
    deck_height: float
    belt: float
    belt_rise: float
    nose_height: float
    tumble_deg: float
    shoulder: float
    belt_in: float
    roof_radius: float
    crown: float
    taper_front: float
    taper_rear: float
    gh_taper_rear: float
    front_depth: tuple[float, float, float]        # at floor, bumper, top
    front_bumper_z: float
    rear_depth: tuple[float, float, float, float]  # at floor, bumper, belt, top
    rear_bumper_z: float
    exp_front: float
    exp_rear: float
    windows: tuple[tuple[float, float], ...]       # side glass intervals (s from the front)
    rear_glass: bool
    glass_roof: bool
    cladding: bool
    mirror: tuple[float, float, float] = (0.09, 0.11, 0.07)  # housing half extents
    spoiler: str = "none"
    roof_rails: bool = False
    bed_len: float = 0.0
    bed_depth: float = 0.0
    extra: dict = field(default_factory=dict, compare=False)

    @property
    def rear_overhang(self) -> float:
        return self.length - self.wheelbase - self.front_overhang

    @property
    def wheel_x(self) -> tuple[float, float]:
        """Axle x (front, rear) in the build frame."""
        return self.length - self.front_overhang, self.rear_overhang


# ---------------------------------------------------------------- side profile


def _smooth(z: np.ndarray, sigma_cm: float) -> np.ndarray:
    k = np.arange(-int(3 * sigma_cm), int(3 * sigma_cm) + 1)
    w = np.exp(-0.5 * (k / sigma_cm) ** 2)
    return np.convolve(np.pad(z, len(k) // 2, mode="edge"), w / w.sum(), mode="valid")


def profile_knots(p: CarParams) -> dict[str, float]:
    """Key s positions (from the front end) of the top line: cowl, windshield top, roof end,
    rear window end, end of the greenhouse."""
    L, d_f = p.length, max(p.front_depth)
    s_end = L - max(p.rear_depth) if p.rear_style != "cab" else L - p.bed_len
    cowl = p.belt + 0.02
    ws_run = (p.ws_top - cowl) / np.tan(np.radians(p.ws_deg))
    s_wt = p.hood_len + ws_run
    roof_rear = p.height - p.crown - p.roof_drop_rear
    if p.rear_style in ("notch", "fastback", "hatch"):
        rw_run = (roof_rear - p.deck_height) / np.tan(np.radians(p.rw_deg))
        deck = p.deck_len if p.rear_style != "hatch" else 0.0
        s_rr = s_end - deck - rw_run
        s_min = s_wt + p.roof_step + 0.35
        if s_rr < s_min:  # squeeze the rear window to keep a roof
            rw_run = max(s_end - deck - s_min, 0.15)
            s_rr = s_end - deck - rw_run
        s_rw = s_rr + rw_run
    else:
        s_rr = s_rw = s_end
    return dict(front=d_f, cowl=p.hood_len, ws_top=s_wt, roof_rear=s_rr, rw_end=s_rw,
                end=s_end)


def top_line(p: CarParams, s: np.ndarray) -> np.ndarray:
    """Height of the body's top centre line (before the roof crown) at ``s`` (m)."""
    k = profile_knots(p)
    L = p.length
    grid = np.linspace(0.0, L, int(L / 0.01) + 1)
    cowl = p.belt + 0.02
    top = p.height - p.crown
    u = np.clip(grid / p.hood_len, 0.0, 1.0)
    hood = p.nose_height + (cowl - p.nose_height) * (1.0 - (1.0 - u) ** 2.2)
    roof_front = top - p.roof_drop_front
    s_roof0 = k["ws_top"] + p.roof_step
    xs = [p.hood_len, k["ws_top"], s_roof0]
    zs = [cowl, p.ws_top, roof_front]
    # roof: parabola through the front and rear drops with its peak in between
    roof_s = np.linspace(s_roof0, k["roof_rear"], 8)[1:]
    t = (roof_s - s_roof0) / max(k["roof_rear"] - s_roof0, 1e-6)
    peak = 0.35 + 0.3 * p.roof_drop_front / max(p.roof_drop_front + p.roof_drop_rear, 1e-6)
    a_f = p.roof_drop_front / peak**2
    a_r = p.roof_drop_rear / (1 - peak) ** 2
    roof_z = np.where(t < peak, top - a_f * (t - peak) ** 2, top - a_r * (t - peak) ** 2)
    xs += list(roof_s)
    zs += list(roof_z)
    if p.rear_style in ("notch", "fastback", "hatch"):
        xs += [k["rw_end"], L]
        zs += [p.deck_height, p.deck_height - 0.03]
    else:
        xs += [L]
        zs += [roof_z[-1] - 0.01]
    z = np.where(grid < p.hood_len, hood, np.interp(grid, xs, zs))
    if p.roof_step > 0:  # high roof: round the step more
        z = _smooth(z, 10.0)
    return np.interp(s, grid, _smooth(z, 4.0))


# ---------------------------------------------------------------- sections


def _half_section(p: CarParams, hw, zf, zs, zb, zt, crown, rc, inset):
    """(20, 2) points (y, z) of the left half of a section, bottom centre to top centre."""
    well_in = hw - p.wheel_width - 2 * _GAP
    tuck = 0.04
    pts = [(0.0, zf), (well_in, zf), (well_in, zs), (hw - tuck, zs)]
    for t in (0.2, 0.45, 0.7, 0.9):
        y = hw - tuck * max(0.0, 1 - t / 0.35) ** 2 - p.belt_in * max(0.0, (t - 0.5) / 0.5) ** 2
        pts.append((y, zs + t * (zb - zs)))
    yb = hw - p.belt_in
    pts.append((yb, zb))                                     # 8 belt
    tan_t = np.tan(np.radians(p.tumble_deg))
    e = min(0.025, 0.1 * (zt - zb))
    z0, zg = zb + 0.012, zt - rc - e

    def y_gh(z):
        f = (z - z0) / max(zt - z0, 1e-6)
        return yb - p.shoulder - tan_t * (z - z0) - inset * f

    for f in (0.0, 1 / 3, 2 / 3, 1.0):                       # 9..12 glass band
        z = z0 + f * (zg - z0)
        pts.append((y_gh(z), z))
    yc = y_gh(zt - rc)
    pts.append((yc, zt - rc))                                # 13 roof-side band top
    for a in (np.pi / 6, np.pi / 3):                         # 14, 15 roof edge
        pts.append((yc - rc + rc * np.cos(a), zt - rc + rc * np.sin(a)))
    yr = yc - rc
    pts.append((yr, zt))                                     # 16 roof starts
    for f in (0.7, 0.4):                                     # 17, 18 crowned roof
        pts.append((yr * f, zt + crown * (1 - f * f)))
    pts.append((0.0, zt + crown))                            # 19 top centre
    return np.asarray(pts)


def _stations(p: CarParams, k: dict, x0: float, x1: float, wheels) -> np.ndarray:
    L = p.length
    xs = [np.linspace(x0, x1, max(int((x1 - x0) / _STEP), 2) + 1)]
    arch = p.wheel_radius + _GAP
    for wx in wheels:
        xs.append(wx + arch * np.sin(np.linspace(-np.pi / 2, np.pi / 2, 13)))
        xs.append(wx + np.array([-arch - 0.012, arch + 0.012]))
    feats = [k["cowl"], k["ws_top"], *np.linspace(k["roof_rear"], k["rw_end"], 5)]
    for a, b in p.windows:
        feats += [a, b]
    xs.append(L - np.asarray(feats))
    x = np.unique(np.round(np.concatenate(xs), 4))
    x = x[(x >= x0 - 1e-3) & (x <= x1 + 1e-3)]
    keep = np.concatenate([[True], np.diff(x) > 0.012])
    x = x[keep]
    x[0], x[-1] = x0, x1
    return x


def _floor_and_sill(p: CarParams, x, x0, x1, wheels):
    """Underbody height zf and side bottom zs per station (wheel wells cut in)."""
    zf = (p.clearance + 0.10 * np.clip(1 - (x1 - x) / 0.5, 0, 1) ** 2
          + 0.08 * np.clip(1 - (x - x0) / 0.5, 0, 1) ** 2)
    zs = zf + 0.04
    arch = p.wheel_radius + _GAP
    for wx in wheels:
        dx = np.abs(x - wx)
        za = p.wheel_radius + np.sqrt(np.clip(arch**2 - dx**2, 0.0, None))
        zs = np.where(dx <= arch + 1e-9, np.maximum(zs, za), zs)
    return zf, zs


def _body_rings(p: CarParams, k: dict, x: np.ndarray, wheels):
    L = p.length
    s = L - x
    x0, x1 = x[0], x[-1]
    wf, wr = p.wheel_x
    uf = np.clip((x - wf) / max(x1 - wf, 1e-6), 0, 1)
    ur = np.clip((wr - x) / max(wr - x0, 1e-6), 0, 1)
    hw = p.width / 2 - p.taper_front * uf**2 - p.taper_rear * ur**2
    zf, zs = _floor_and_sill(p, x, x0, x1, wheels)
    zt = top_line(p, s)
    zb = p.belt + p.belt_rise * np.clip((s - k["cowl"]) / max(k["end"] - k["cowl"], 1e-6), 0, 1)
    zb = np.minimum(zb, zt - 0.09)
    zb = np.maximum(zb, zs + 0.10)
    zt = np.maximum(zt, zb + 0.09)
    gh = zt - zb
    crown = p.crown * np.clip((gh - 0.1) / 0.25, 0.3, 1.0)
    rc = np.minimum(p.roof_radius, 0.3 * gh)
    span = max(k["end"] - k["ws_top"], 1e-6)
    inset = p.gh_taper_rear * np.clip((s - k["ws_top"]) / span, 0, 1) ** 2
    inset *= np.clip((gh - 0.1) / 0.2, 0, 1)
    rings = []
    for i in range(len(x)):
        half = _half_section(p, hw[i], zf[i], zs[i], zb[i], zt[i], crown[i], rc[i], inset[i])
        ring = mirror_ring(half)
        rings.append(np.column_stack([np.full(len(ring), x[i]), ring]))
    rings = np.stack(rings)
    return rings, dict(hw=hw, zb=zb, zt=zt, zf=zf, roof_hw=rings[:, _I_RT, 1], roof_rc=rc,
                       crown=crown)


def _strip_labels(p: CarParams, k: dict, x: np.ndarray) -> np.ndarray:
    """(N - 1, K) labels of the body strips."""
    s_mid = p.length - 0.5 * (x[:-1] + x[1:])
    h = segment_half_index(_M)[None, :]  # (1, K)
    lab = np.full((len(s_mid), len(h[0])), BODY, np.uint8)
    side = (h >= _I_G0) & (h < _I_GT)
    in_win = np.zeros(len(s_mid), bool)
    for a, b in p.windows:
        in_win |= (s_mid > a) & (s_mid < b)
    lab[in_win[:, None] & side] = GLASS
    roof = (h >= _I_C2) & (h <= _M - 2)
    ws = (s_mid > k["cowl"] + 0.03) & (s_mid < k["ws_top"] - 0.03)
    lab[ws[:, None] & roof] = GLASS
    if p.rear_style in ("notch", "fastback", "hatch"):
        m = min(0.05, 0.2 * (k["rw_end"] - k["roof_rear"]))
        rw = (s_mid > k["roof_rear"] + m) & (s_mid < k["rw_end"] - 0.5 * m)
        lab[rw[:, None] & roof] = GLASS
    if p.glass_roof:
        gr = (s_mid > k["ws_top"] + p.roof_step + 0.12) & (s_mid < k["roof_rear"] - 0.15)
        lab[gr[:, None] & (h >= _I_ROOF0) & (h <= _M - 2)] = GLASS
    lab[:, (h[0] <= 1)] = TRIM  # underbody
    if p.cladding:
        lab[:, (h[0] >= 2) & (h[0] <= 3)] = TRIM
    return lab


def _cap_labels(p: CarParams, which: str, rings: np.ndarray) -> np.ndarray:
    steps, kk = rings.shape[0] - 1, rings.shape[1]
    h = segment_half_index(_M)[None, :]
    j = np.arange(steps)[:, None]
    lab = np.full((steps, kk), BODY, np.uint8)
    lab[np.broadcast_to(h <= 3, lab.shape)] = TRIM          # lower bumper / valance
    lamp_band = (h >= 6) & (h <= 7)
    lamp = lamp_band & (j >= 1) & (j <= 2)
    if which == "front":
        # the open grille between the headlamps and the lower intake under the bumper bar
        # (h 5, painted) across the middle of the nose; the radiator sits behind them
        lab[((h == 4) | lamp_band) & (j >= 3)] = GRILLE
        lab[lamp] = HEADLAMP
    else:
        lab[lamp] = LAMP
    if which == "rear" and p.rear_glass:
        lab[(h >= _I_G0) & (h < _I_GT) & (j >= 2)] = GLASS
    return lab
