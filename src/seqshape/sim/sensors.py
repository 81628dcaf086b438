"""Spinning LiDAR sensor presets and their ray directions.

A sensor fires one ray per (channel, azimuth step) per sweep. Channel ``i`` points at elevation
``elevations_deg[i]`` (positive up); azimuths lie on the fixed grid ``k * azimuth_step_deg``
(counter-clockwise from +x, the sensor's forward axis). Directions are unit vectors in the
sensor frame (x forward, y left, z up, origin at the LiDAR):

    d = (cos(e) cos(a), cos(e) sin(a), sin(e)).

>>> cfg = get_sensor("vlp16")
>>> len(cfg.elevations_deg), cfg.rays_per_sweep
(16, 28800)
"""

from __future__ import annotations

from dataclasses import dataclass

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
        from dataclasses import replace

        return replace(self, range_noise_std=0.0, dropout=0.0)


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
