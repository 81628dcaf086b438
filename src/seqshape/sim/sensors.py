"""Spinning LiDAR sensor presets and their ray directions.

A sensor fires one ray per (channel, azimuth step) per sweep. Channel ``i`` points at elevation
``elevations_deg[i]`` (positive up); azimuths lie on the fixed grid ``k * azimuth_step_deg``
(counter-clockwise from +x, the sensor's forward axis). Directions are unit vectors in the
sensor frame (x forward, y left, z up, origin at the LiDAR):

    d = (cos(e) cos(a), cos(e) sin(a), sin(e)).

A sensor owns everything the simulators ask of it: its sweep directions
(:meth:`LidarConfig.sweep_directions`, :meth:`LidarConfig.tables`, :func:`ray_window` for the
rays that can meet a box), its range limits (:meth:`LidarConfig.in_range`), range noise
(:meth:`LidarConfig.noisy_ranges`) and dropout (:meth:`LidarConfig.kept_returns`). The track
scan (:mod:`seqshape.sim.raycast`), the ``real`` path and the scene LiDAR
(:mod:`seqshape.sim.render`) use only these, so a new sensor is one :class:`LidarConfig`.

>>> cfg = get_sensor("vlp16")
>>> len(cfg.elevations_deg), cfg.rays_per_sweep
(16, 28800)
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from seqshape.errors import ConfigError


@dataclass(frozen=True)
class LidarConfig:
    """A spinning multi-channel LiDAR.

    Attributes:
        name: preset name ("vlp16", "hdl32", "hdl64") or a user label.
        elevations_deg: channel elevation angles in degrees, positive up.
        azimuth_step_deg: horizontal angle between two firings of a channel (degrees); it
            depends on the rotation rate (0.2 deg at 10 Hz for a VLP-16).
        max_range: returns beyond this range (m) are lost.
        min_range: returns closer than this (m) are lost.
        height: mounting height of the optical centre above the ground (m); the ground plane
            is at ``z = -height`` in the sensor frame.
        range_noise_std: standard deviation of the Gaussian range noise along the ray (m).
        dropout: probability that a return is lost (independently per return).
        rate_hz: sweeps per second; a track's frames are ``1 / rate_hz`` seconds apart.
        divergence_mrad: full beam divergence (mrad); only the ``real`` generation path uses it
            (mixed returns at silhouette edges, :mod:`seqshape.sim.real`). 0: not modelled.
        range_10pct: range (m) at which a 10 %-reflective Lambertian target is detected with
            probability 1/2; only the ``real`` path uses it (low-reflectivity dropout).
            0: not modelled.
    """

    name: str
    elevations_deg: tuple[float, ...]
    azimuth_step_deg: float
    max_range: float
    min_range: float
    height: float
    range_noise_std: float
    dropout: float
    rate_hz: float
    divergence_mrad: float = 0.0
    range_10pct: float = 0.0

    def __post_init__(self):
        if len(self.elevations_deg) == 0:
            raise ConfigError(f"sensor {self.name!r}: needs at least one channel")
        if not all(-90.0 < e < 90.0 for e in self.elevations_deg):
            raise ConfigError(f"sensor {self.name!r}: elevations must lie in (-90, 90) deg")
        if not 0.0 < self.azimuth_step_deg <= 45.0:
            raise ConfigError(f"sensor {self.name!r}: azimuth_step_deg must be in (0, 45]")
        if not 0.0 <= self.min_range < self.max_range:
            raise ConfigError(f"sensor {self.name!r}: need 0 <= min_range < max_range")
        if self.range_noise_std < 0 or not 0.0 <= self.dropout < 1.0:
            raise ConfigError(f"sensor {self.name!r}: need range_noise_std >= 0 and "
                              f"0 <= dropout < 1")
        if self.rate_hz <= 0 or self.height < 0:
            raise ConfigError(f"sensor {self.name!r}: need rate_hz > 0 and height >= 0")
        if self.divergence_mrad < 0 or self.range_10pct < 0:
            raise ConfigError(f"sensor {self.name!r}: need divergence_mrad >= 0 and "
                              f"range_10pct >= 0")

    @property
    def n_azimuths(self) -> int:
        """Azimuth steps per sweep."""
        return int(round(360.0 / self.azimuth_step_deg))

    @property
    def rays_per_sweep(self) -> int:
        return self.n_azimuths * len(self.elevations_deg)

    @property
    def elevations_rad(self) -> np.ndarray:
        """Channel elevations ``(C,)`` in radians, float64, in preset order."""
        return np.deg2rad(np.asarray(self.elevations_deg, dtype=np.float64))

    def without_noise(self) -> LidarConfig:
        """The same sensor with no range noise and no dropout."""
        return replace(self, range_noise_std=0.0, dropout=0.0)

    # -- what every simulator asks of a sensor: its rays, its range limits, noise, dropout

    def sweep_directions(self) -> np.ndarray:
        """All ray directions of a sweep, ``(R, 3)`` float64 (cached; see :func:`ray_directions`)."""
        return _sweep_directions(self)

    def tables(self) -> SensorTables:
        """Trig tables of the channels and azimuths (cached, :class:`SensorTables`)."""
        return sensor_tables(self)

    def in_range(self, r: np.ndarray) -> np.ndarray:
        """Mask of the ranges ``r`` the sensor reports: ``min_range <= r <= max_range``."""
        return (r >= self.min_range) & (r <= self.max_range)

    def noisy_ranges(self, r: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """``r`` plus Gaussian range noise (``range_noise_std``; no draw when it is 0)."""
        if self.range_noise_std > 0:
            return r + rng.normal(0.0, self.range_noise_std, len(r))
        return r

    def kept_returns(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``(n,)`` bool: which of ``n`` returns survive the dropout (no draw when it is 0)."""
        if self.dropout > 0:
            return rng.random(n) >= self.dropout
        return np.ones(n, dtype=bool)


def _hdl64_elevations() -> tuple[float, ...]:
    # HDL-64E (KITTI): upper block 32 lasers +2.0 .. -8.33 deg every 1/3 deg,
    # lower block 32 lasers -8.83 .. -24.33 deg every 1/2 deg.
    upper = [2.0 - i / 3.0 for i in range(32)]
    lower = [-8.83 - 0.5 * i for i in range(32)]
    return tuple(round(e, 4) for e in upper + lower)


# Velodyne VLP-32C vertical angles (deg) by laser id, from the VLP-32C user manual (table
# "laser firing sequence / vertical angle"): non-uniform, dense around the horizon, -25..+15 deg.
VLP32C_ELEVATIONS = (-25.0, -1.0, -1.667, -15.639, -11.31, 0.0, -0.667, -8.843, -7.254, 0.333,
                     -0.333, -6.148, -5.333, 1.333, 0.667, -4.0, -4.667, 1.667, 1.0, -3.667,
                     -3.333, 3.333, 2.333, -2.667, -3.0, 7.0, 4.667, -2.333, -2.0, 15.0, 10.333,
                     -1.333)


#: Argoverse 2's two VLP-32C, one upright, one upside down (``vlp32c_pair``).
VLP32C_PAIR_ELEVATIONS = VLP32C_ELEVATIONS + tuple(round(0.1 - e, 4) for e in VLP32C_ELEVATIONS)


def _uniform(lo: float, hi: float, n: int) -> tuple[float, ...]:
    return tuple(round(float(e), 4) for e in np.linspace(lo, hi, n))


SENSORS: dict[str, LidarConfig] = {
    # Velodyne VLP-16 at 10 Hz, mounted 2 m above the ground as in the paper; divergence
    # 3.0 mrad; "up to 100 m" (taken at ~80 % reflectivity; sqrt scaling -> ~35 m at 10 %).
    "vlp16": LidarConfig("vlp16", tuple(float(e) for e in range(-15, 16, 2)), 0.2,
                         max_range=100.0, min_range=0.5, height=2.0, range_noise_std=0.015,
                         dropout=0.02, rate_hz=10.0, divergence_mrad=3.0, range_10pct=35.0),
    # Velodyne VLP-32C at 10 Hz: the manual's non-uniform table, 0.2 deg azimuth step, 200 m
    # range (~70 m at 10 %), accuracy +-3 cm, divergence 3.4 mrad (horizontal), 1.84 m
    "vlp32c": LidarConfig("vlp32c", VLP32C_ELEVATIONS, 0.2, max_range=200.0, min_range=1.0,
                          height=1.84, range_noise_std=0.015, dropout=0.01, rate_hz=10.0,
                          divergence_mrad=3.4, range_10pct=70.0),
    # Two VLP-32C stacked on the roof, the lower one upside down (Argoverse 2's pair, at
    # 1.64 and 1.53 m): the upright unit's table and the inverted one's (-e) in one 64-channel
    # head, the second set 0.1 deg higher as measured on the AV2 log (so no two channels
    # coincide); both dense bands (0.33 deg) lie near the horizon, -4.7..+1.7 and -1.6..+4.8.
    "vlp32c_pair": LidarConfig("vlp32c_pair", VLP32C_PAIR_ELEVATIONS, 0.2, max_range=200.0,
                               min_range=1.0, height=1.6, range_noise_std=0.015, dropout=0.01,
                               rate_hz=10.0, divergence_mrad=3.4, range_10pct=70.0),
    # Ouster OS1-128 (rev 6) at 10 Hz, 1024 columns: 128 beams uniform over 45 deg (+-22.5),
    # 0.352 deg azimuth step, precision +-3 cm, divergence 0.18 deg (3.1 mrad), 45 m at 10 %
    # (datasheet: 90 % detection) -> ~50 m at 50 %
    "os128": LidarConfig("os128", _uniform(-22.5, 22.5, 128), 360.0 / 1024, max_range=120.0,
                         min_range=0.5, height=1.9, range_noise_std=0.02, dropout=0.01,
                         rate_hz=10.0, divergence_mrad=3.1, range_10pct=50.0),
    # Velodyne HDL-32E at 10 Hz: 32 channels evenly from -30.67 to +10.67 deg (~1.33 deg).
    "hdl32": LidarConfig("hdl32", tuple(round(float(e), 4) for e in np.linspace(-30.67, 10.67, 32)),
                         0.16, max_range=100.0, min_range=1.0, height=1.84,
                         range_noise_std=0.01, dropout=0.02, rate_hz=10.0),
    # Velodyne HDL-64E at 10 Hz as mounted on the KITTI car (1.73 m); divergence 2.0 mrad,
    # datasheet "50 m for pavement (~10 %), 120 m for cars and foliage".
    "hdl64": LidarConfig("hdl64", _hdl64_elevations(), 0.08, max_range=120.0, min_range=1.0,
                         height=1.73, range_noise_std=0.01, dropout=0.02, rate_hz=10.0,
                         divergence_mrad=2.0, range_10pct=50.0),
}
DEFAULT_SENSOR = "vlp16"


def get_sensor(name: str = DEFAULT_SENSOR) -> LidarConfig:
    """The preset called ``name`` (a key of `SENSORS`); :class:`ConfigError` otherwise."""
    try:
        return SENSORS[name]
    except KeyError:
        raise ConfigError(f"unknown sensor {name!r}; choose one of {sorted(SENSORS)}") from None


def azimuth_grid(cfg: LidarConfig, azimuth_range=None) -> np.ndarray:
    """Azimuths (rad, float64) of the firings, on the fixed grid ``k * azimuth_step``.

    ``azimuth_range=(lo, hi)`` in radians keeps the grid azimuths within ``[lo, hi]`` going
    counter-clockwise from ``lo`` (``hi`` may be < ``lo`` across the +-pi seam; the result is
    wrapped to [-pi, pi)). ``None`` gives the full sweep.
    """
    step = np.deg2rad(cfg.azimuth_step_deg)
    n = cfg.n_azimuths
    if azimuth_range is None:
        k = np.arange(n)
    else:
        lo, hi = (float(a) for a in azimuth_range)
        span = (hi - lo) % (2 * np.pi)
        k0 = int(np.ceil(lo / step - 1e-9))
        k1 = int(np.floor((lo + span) / step + 1e-9))
        k = np.arange(k0, k1 + 1)
        if len(k) > n:
            k = k[:n]
    az = k * step
    return (az + np.pi) % (2 * np.pi) - np.pi


def directions(elevations: np.ndarray, azimuths: np.ndarray) -> np.ndarray:
    """Unit directions ``(E * A, 3)`` for every (elevation, azimuth) pair, elevation-major."""
    e = np.asarray(elevations, dtype=np.float64)[:, None]
    a = np.asarray(azimuths, dtype=np.float64)[None, :]
    ce = np.cos(e)
    d = np.empty((e.shape[0], a.shape[1], 3))
    d[..., 0] = ce * np.cos(a)
    d[..., 1] = ce * np.sin(a)
    d[..., 2] = np.sin(e)
    return d.reshape(-1, 3)


def ray_directions(cfg: LidarConfig, azimuth_range=None) -> np.ndarray:
    """Unit ray directions ``(R, 3)`` float64 in the sensor frame, channel-major.

    ``azimuth_range`` as in :func:`azimuth_grid`; ``None`` gives the full sweep
    (``R = cfg.rays_per_sweep``).
    """
    return directions(cfg.elevations_rad, azimuth_grid(cfg, azimuth_range))


def mount_rotation(pitch: float, roll: float) -> np.ndarray:
    """``(3, 3)`` rotation of a LiDAR mounted with ``pitch`` and ``roll`` (rad) on a level car.

    The sensor frame stays level (the ego axes, origin at the LiDAR); the LiDAR head is tilted,
    so a beam at (elevation, azimuth) of the head points along ``R @ d(e, a)`` in the sensor
    frame, ``R = Ry(pitch) @ Rx(roll)`` (right-handed): positive pitch turns the forward beams
    down (``x -> (cos p, 0, -sin p)``), positive roll turns the left (+y) beams up.
    """
    cp, sp, cr, sr = np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return ry @ rx


@lru_cache(maxsize=8)
def _sweep_directions(cfg: LidarConfig) -> np.ndarray:
    return ray_directions(cfg)


@dataclass(frozen=True)
class SensorTables:
    """Per-sensor trig tables; channels in ascending elevation (not the preset's order).

    ``elev`` (C,) rad ascending with ``cos_e`` / ``sin_e`` (float64) and ``cos_e32`` /
    ``sin_e32`` (float32); ``az`` (A,) rad on the grid ``k * azimuth_step`` (not wrapped) with
    ``cos_a`` / ``sin_a`` (float64).
    """

    elev: np.ndarray
    cos_e: np.ndarray
    sin_e: np.ndarray
    cos_e32: np.ndarray
    sin_e32: np.ndarray
    az: np.ndarray
    cos_a: np.ndarray
    sin_a: np.ndarray


@lru_cache(maxsize=8)
def sensor_tables(cfg: LidarConfig) -> SensorTables:
    """The :class:`SensorTables` of ``cfg`` (cached)."""
    elev = np.sort(cfg.elevations_rad)
    az = np.arange(cfg.n_azimuths) * np.deg2rad(cfg.azimuth_step_deg)
    ce, se = np.cos(elev), np.sin(elev)
    return SensorTables(elev, ce, se, ce.astype(np.float32), se.astype(np.float32), az,
                        np.cos(az), np.sin(az))


@lru_cache(maxsize=8)
def direction_table(cfg: LidarConfig) -> np.ndarray:
    """All ray directions of a sweep, ``(C, A, 3)`` float64 (channel in preset order, azimuth
    ``k * step`` not wrapped)."""
    az = np.arange(cfg.n_azimuths) * np.deg2rad(cfg.azimuth_step_deg)
    return directions(cfg.elevations_rad, az).reshape(len(cfg.elevations_deg), -1, 3)


BOX_MARGIN = 0.05  #: spatial margin (m) around a box in :func:`ray_window`
AZ_MARGIN_STEPS = 1.5  #: angular margin (azimuth steps) of :func:`ray_window`


def ray_window(cfg: LidarConfig, bounds: np.ndarray, poses: np.ndarray):
    """The rays of ``cfg`` that can meet a box ``bounds`` (2, 3) (canonical) at ``poses`` (T, 4).

    Per frame: channel range ``c0:c1`` in ascending-elevation order (:class:`SensorTables`)
    and azimuth indices ``k0..k1`` (all ``(T,)`` int64; ``k`` may leave ``0..A-1``: take it
    modulo ``n_azimuths``).

    The window covers the posed box grown by :data:`BOX_MARGIN` exactly in elevation (a
    conservative bound from the nearest and farthest footprint distances) and in azimuth (the
    footprint corners, plus :data:`AZ_MARGIN_STEPS`). A frame whose footprint contains the
    sensor gets the full sweep.
    """
    lo, hi = bounds[0] - BOX_MARGIN, bounds[1] + BOX_MARGIN
    c, s = np.cos(poses[:, 3]), np.sin(poses[:, 3])
    # sensor origin in the canonical frame of each pose (planar part)
    qx = -(c * poses[:, 0] + s * poses[:, 1])
    qy = -(-s * poses[:, 0] + c * poses[:, 1])
    dx = np.maximum(np.maximum(lo[0] - qx, qx - hi[0]), 0.0)
    dy = np.maximum(np.maximum(lo[1] - qy, qy - hi[1]), 0.0)
    rmin = np.hypot(dx, dy)
    cx = np.array([lo[0], hi[0], hi[0], lo[0]])
    cy = np.array([lo[1], lo[1], hi[1], hi[1]])
    px = poses[:, :1] + c[:, None] * cx - s[:, None] * cy  # (T, 4) footprint corners
    py = poses[:, 1:2] + s[:, None] * cx + c[:, None] * cy
    rmax = np.hypot(px, py).max(1)
    zlo, zhi = poses[:, 2] + lo[2], poses[:, 2] + hi[2]
    inside = rmin <= 1e-9
    rmin_s = np.maximum(rmin, 1e-9)
    e_hi = np.where(zhi > 0, np.arctan2(zhi, rmin_s), np.arctan2(zhi, rmax))
    e_lo = np.where(zlo < 0, np.arctan2(zlo, rmin_s), np.arctan2(zlo, rmax))
    e_hi[inside & (zhi > 0)] = np.pi / 2
    e_lo[inside & (zlo < 0)] = -np.pi / 2
    elev = np.sort(cfg.elevations_rad)
    c0 = np.searchsorted(elev, e_lo - 1e-6, side="left")
    c1 = np.searchsorted(elev, e_hi + 1e-6, side="right")
    centre = np.arctan2(poses[:, 1], poses[:, 0])
    rel = (np.arctan2(py, px) - centre[:, None] + np.pi) % (2 * np.pi) - np.pi
    step = np.deg2rad(cfg.azimuth_step_deg)
    a_lo = centre + rel.min(1) - AZ_MARGIN_STEPS * step
    a_hi = centre + rel.max(1) + AZ_MARGIN_STEPS * step
    k0 = np.ceil(a_lo / step).astype(np.int64)
    k1 = np.floor(a_hi / step).astype(np.int64)
    k1 = np.minimum(k1, k0 + cfg.n_azimuths - 1)
    k0[inside] = 0
    k1[inside] = cfg.n_azimuths - 1
    return c0, c1, k0, k1


@dataclass(frozen=True)
class RayGrid:
    """The rays of per-frame windows (:func:`window_grid`): frame-major, then channel in
    ascending elevation, then azimuth (counter-clockwise). A *row* is one (frame, channel)
    pair, a *column* one (frame, azimuth); all ``int64``.

    Attributes:
        row_frame / row_ch: ``(n_rows,)`` frame and channel (ascending-elevation index).
        col_frame / col_k: ``(n_cols,)`` frame and azimuth index (``0 .. n_azimuths - 1``).
        ray_row / ray_col: ``(R,)`` row and column of each ray.
        frame_rays: ``(T,)`` rays per frame.
    """

    row_frame: np.ndarray
    row_ch: np.ndarray
    col_frame: np.ndarray
    col_k: np.ndarray
    ray_row: np.ndarray
    ray_col: np.ndarray
    frame_rays: np.ndarray


def window_grid(cfg: LidarConfig, c0, c1, k0, k1) -> RayGrid:
    """Enumerate the rays of per-frame windows (channels ``c0:c1``, azimuth indices
    ``k0..k1``, all ``(T,)``, as :func:`ray_window` returns them) as a :class:`RayGrid`."""
    n_ch = np.maximum(c1 - c0, 0)
    n_az = np.where(n_ch > 0, np.maximum(k1 - k0 + 1, 0), 0)
    n_ch = np.where(n_az > 0, n_ch, 0)
    frames = np.arange(len(n_ch))
    col_start = np.cumsum(n_az) - n_az
    col_frame = np.repeat(frames, n_az)
    col_k = (np.arange(len(col_frame)) + np.repeat(k0 - col_start, n_az)) % cfg.n_azimuths
    # rows: one per (frame, channel), each a run of n_az[frame] consecutive columns
    row_frame = np.repeat(frames, n_ch)
    row_ch = np.arange(len(row_frame)) + np.repeat(c0 - (np.cumsum(n_ch) - n_ch), n_ch)
    width = n_az[row_frame]
    ray_row = np.repeat(np.arange(len(row_frame)), width)
    row_first = np.cumsum(width) - width
    ray_col = np.arange(len(ray_row)) + (col_start[row_frame] - row_first)[ray_row]
    return RayGrid(row_frame, row_ch, col_frame, col_k, ray_row, ray_col, n_ch * n_az)
