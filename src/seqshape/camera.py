"""Pinhole cameras (generic, and KITTI calibration): reading, writing and projecting LiDAR points.

Every dataset builds a :class:`PinholeCamera` of its LiDAR sensor frame; KITTI calibration
files are one way to make one (:meth:`KittiCalib.camera`).

Frames (KITTI conventions, fixed once here):

* **velodyne** (our sensor frame): x forward, y left, z up, origin at the LiDAR.
* **camera 0 (unrectified)**: x right, y down, z forward. ``Tr_velo_cam`` (3, 4) maps velodyne
  points into it: ``p_cam0 = Tr_velo_cam @ [p_velo; 1]``.
* **rectified camera 0** (``"cam"`` below, where KITTI labels live): ``p_rect = R_rect @ p_cam0``.
* **image of camera i**: ``[u*d, v*d, d] = P_i @ [p_rect; 1]``; ``P_i`` (3, 4) already contains
  the baseline of camera i with respect to camera 0, so every camera projects from the same
  rectified camera-0 coordinates. Camera 2 is the left colour camera (``image_02``).

Calibration file formats accepted by :func:`read_calib`::

    # tracking (calib/SSSS.txt)          # object (calib/NNNNNN.txt)
    P0: 12 numbers                       P0: 12 numbers ... P3:
    ...                                  R0_rect: 9 numbers
    R_rect 9 numbers                     Tr_velo_to_cam: 12 numbers
    Tr_velo_cam 12 numbers               Tr_imu_to_velo: 12 numbers
    Tr_imu_velo 12 numbers

A key may carry a trailing colon or not. :func:`write_calib` writes the tracking format with
shortest exact float representations, so write -> read is exact.

>>> calib = kitti_default_calib()
>>> uv, depth = project_points(np.array([[10.0, 0.0, 0.0]]), calib)
>>> uv.round(1).tolist(), depth.round(3).tolist()
([[614.0, 175.0]], [9.73])
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import seqshape.limits as limits
from seqshape._io import atomic_write_text, read_text
from seqshape.errors import DataError

#: KITTI colour image size (width, height) of the 2011_09_26 recordings.
KITTI_IMAGE_SIZE = (1242, 375)

# canonical key -> accepted spellings (colon stripped) and the expected number of values
_KEYS = {
    "P0": (("P0",), 12), "P1": (("P1",), 12), "P2": (("P2",), 12), "P3": (("P3",), 12),
    "R_rect": (("R_rect", "R0_rect", "R_rect_00"), 9),
    "Tr_velo_cam": (("Tr_velo_cam", "Tr_velo_to_cam"), 12),
    "Tr_imu_velo": (("Tr_imu_velo", "Tr_imu_to_velo"), 12),
}
_ALIASES = {alias: key for key, (aliases, _) in _KEYS.items() for alias in aliases}
_REQUIRED = ("P2", "R_rect", "Tr_velo_cam")


class _ImageSize:
    """``width`` and ``height`` of a class with ``image_size = (width, height)``."""

    image_size: tuple[int, int]

    @property
    def width(self) -> int:
        return self.image_size[0]

    @property
    def height(self) -> int:
        return self.image_size[1]


@dataclass
class KittiCalib(_ImageSize):
    """KITTI calibration of one sequence (or one object-dataset frame).

    ``P0..P3`` (3, 4) project rectified camera-0 points to camera i's pixels; ``R_rect`` (3, 3)
    rectifies camera 0; ``Tr_velo_cam`` (3, 4) maps velodyne points to (unrectified) camera 0;
    ``Tr_imu_velo`` (3, 4) maps IMU/GPS points to velodyne. ``image_size`` is (width, height).
    """

    P0: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    P3: np.ndarray
    R_rect: np.ndarray
    Tr_velo_cam: np.ndarray
    Tr_imu_velo: np.ndarray
    image_size: tuple[int, int] = field(default=KITTI_IMAGE_SIZE)

    def __post_init__(self):
        for name in ("P0", "P1", "P2", "P3", "Tr_velo_cam", "Tr_imu_velo"):
            setattr(self, name, np.asarray(getattr(self, name), dtype=np.float64).reshape(3, 4))
        self.R_rect = np.asarray(self.R_rect, dtype=np.float64).reshape(3, 3)
        self.image_size = (int(self.image_size[0]), int(self.image_size[1]))

    def P(self, cam: int) -> np.ndarray:
        """The (3, 4) projection matrix of camera ``cam`` (0..3)."""
        if cam not in (0, 1, 2, 3):
            raise ValueError(f"KITTI has cameras 0..3, not {cam}")
        return getattr(self, f"P{cam}")

    @property
    def velo_to_rect(self) -> np.ndarray:
        """(4, 4) homogeneous transform velodyne -> rectified camera 0."""
        return _h(self.R_rect) @ _h(self.Tr_velo_cam)

    @property
    def rect_to_velo(self) -> np.ndarray:
        """(4, 4) homogeneous transform rectified camera 0 -> velodyne."""
        return np.linalg.inv(self.velo_to_rect)

    @property
    def imu_to_velo(self) -> np.ndarray:
        """(4, 4) homogeneous transform IMU -> velodyne."""
        return _h(self.Tr_imu_velo)

    def intrinsics(self, cam: int = 2) -> np.ndarray:
        """The (3, 3) intrinsic matrix K of camera ``cam`` (left block of its P)."""
        return self.P(cam)[:, :3].copy()

    def camera(self, cam: int = 2) -> PinholeCamera:
        """Camera ``cam`` as a generic :class:`PinholeCamera` of the velodyne (sensor) frame."""
        return PinholeCamera(name=f"image_{cam:02d}", P=self.P(cam), T_cam_sensor=self.velo_to_rect,
                             image_size=self.image_size)


@dataclass
class PinholeCamera(_ImageSize):
    """A pinhole camera looking at a LiDAR's sensor frame (any dataset).

    ``T_cam_sensor`` (4, 4) maps sensor-frame points (x forward, y left, z up) into the
    camera's reference frame (x right, y down, z along the optical axis); ``P`` (3, 4) projects
    reference-frame points to pixels: ``[u*d, v*d, d] = P @ [T_cam_sensor @ p; 1]``. For a plain
    camera ``P = [K | 0]`` (:meth:`from_intrinsics`); KITTI's rectified cameras keep their
    ``P_i`` with its baseline term (:meth:`KittiCalib.camera`). ``image_size`` is
    (width, height); pixel centres sit at integer coordinates. ``depth`` is the third
    homogeneous coordinate, metres along the optical axis.

    ``radial`` = ``(k1, k2, k3)`` (only with ``P = [K | 0]``) adds radial lens distortion,
    ``x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6)`` on normalised coordinates (Argoverse 2's
    model); beyond the radius where that polynomial stops growing, a point would fold back
    into the image, so its pixel is NaN (never in the image).

    >>> cam = PinholeCamera.from_intrinsics(np.array([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]]),
    ...                                     np.eye(4), (100, 80))
    >>> uv, depth = cam.project(np.array([[1.0, 0.5, 10.0]]))
    >>> uv.tolist(), depth.tolist()
    ([[60.0, 45.0]], [10.0])
    """

    P: np.ndarray
    T_cam_sensor: np.ndarray
    image_size: tuple[int, int]
    name: str = "camera"
    radial: tuple[float, ...] = ()

    def __post_init__(self):
        self.P = np.asarray(self.P, dtype=np.float64).reshape(3, 4)
        self.radial = tuple(float(k) for k in self.radial)
        if self.radial and (len(self.radial) > 3 or np.any(self.P[:, 3] != 0)):
            raise ValueError(f"camera {self.name}: radial distortion takes up to 3 "
                             f"coefficients and a P = [K | 0]")
        self.T_cam_sensor = np.asarray(self.T_cam_sensor, dtype=np.float64).reshape(4, 4)
        self.image_size = (int(self.image_size[0]), int(self.image_size[1]))
        if min(self.image_size) <= 0:
            raise ValueError(f"camera {self.name}: image size must be positive, got "
                             f"{self.image_size}")

    @classmethod
    def from_intrinsics(cls, K, T_cam_sensor, image_size, name: str = "camera",
                        radial=()) -> PinholeCamera:
        """A camera from its (3, 3) intrinsic matrix and sensor -> camera transform."""
        return cls(P=np.c_[np.asarray(K, dtype=np.float64).reshape(3, 3), np.zeros(3)],
                   T_cam_sensor=T_cam_sensor, image_size=image_size, name=name,
                   radial=tuple(radial))

    def _r2_max(self) -> float:
        """Squared normalised radius up to which the distortion grows monotonically."""
        k = np.r_[self.radial, np.zeros(3 - len(self.radial))]
        r2 = np.linspace(0.0, 16.0, 16001)[1:]  # up to 4x the focal length off-axis
        grow = 1 + 3 * k[0] * r2 + 5 * k[1] * r2**2 + 7 * k[2] * r2**3  # d(r s(r)) / dr
        bad = np.flatnonzero(grow <= 0)
        return float(r2[bad[0] - 1]) if len(bad) else np.inf

    def _scale(self, r2: np.ndarray) -> np.ndarray:
        k = np.r_[self.radial, np.zeros(3 - len(self.radial))]
        return 1 + k[0] * r2 + k[1] * r2**2 + k[2] * r2**3

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix (left block of ``P``)."""
        return self.P[:, :3].copy()

    @property
    def matrix(self) -> np.ndarray:
        """(3, 4) sensor-frame projection ``P @ T_cam_sensor``."""
        return self.P @ self.T_cam_sensor

    @property
    def position(self) -> np.ndarray:
        """(3,) the optical centre in the sensor frame."""
        m = self.matrix
        return -np.linalg.solve(m[:, :3], m[:, 3])

    def project(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Sensor-frame points (N, 3) -> ``(uv (N, 2), depth (N,))`` float64."""
        uv, depth = _project(points, self.matrix)
        if not self.radial:
            return uv, depth
        f, c = np.diag(self.P)[:2], self.P[:2, 2]
        xy = (uv - c) / f
        r2 = np.sum(xy * xy, axis=1)
        with np.errstate(invalid="ignore"):
            out = xy * self._scale(r2)[:, None] * f + c
        out[~(r2 <= self._r2_max())] = np.nan
        return out, depth

    def undistort(self, uv) -> np.ndarray:
        """Pixels (N, 2) of this camera -> the pixels an undistorted camera would see."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if not self.radial:
            return uv
        f, c = np.diag(self.P)[:2], self.P[:2, 2]
        target = (uv - c) / f
        xy = target.copy()
        for _ in range(50):  # fixed point x = x_d / s(|x|^2); contracts for real lenses
            xy = target / self._scale(np.sum(xy * xy, axis=1))[:, None]
        return xy * f + c

    def unproject(self, uv, depth) -> np.ndarray:
        """Inverse of :meth:`project`: pixels (N, 2) and depths (N,) -> sensor frame (N, 3)."""
        uv = self.undistort(uv)
        depth = np.asarray(depth, dtype=np.float64).reshape(-1)
        m = self.matrix
        hom = np.c_[uv * depth[:, None], depth] - m[:, 3]
        return np.linalg.solve(m[:, :3], hom.T).T

    def in_image(self, uv, depth, min_depth: float = 0.0) -> np.ndarray:
        """Boolean (N,): in front (depth > min_depth) and inside the image bounds."""
        return _in_bounds(uv, depth, self.image_size, min_depth)


def as_camera(camera, cam: int = 2) -> PinholeCamera:
    """A :class:`PinholeCamera` from a camera or a :class:`KittiCalib` (its camera ``cam``)."""
    if isinstance(camera, PinholeCamera):
        return camera
    if isinstance(camera, KittiCalib):
        return camera.camera(cam)
    raise TypeError(f"expected a PinholeCamera or KittiCalib, got {type(camera).__name__}")


def _h(m: np.ndarray) -> np.ndarray:
    """Embed a (3, 3) or (3, 4) matrix in a (4, 4) homogeneous one."""
    out = np.eye(4)
    out[:3, : m.shape[1]] = m
    return out


def kitti_default_calib() -> KittiCalib:
    """The calibration of the KITTI 2011_09_26 recordings (tracking sequences 0000-0013).

    Image 1242 x 375; P2 with fx = fy = 721.5377, cx = 609.5593, cy = 172.854 and the 44.857
    baseline term; R_rect close to identity; Tr_velo_cam the standard velodyne -> camera
    rotation with translation (-0.004, -0.076, -0.272) m.
    """
    f, cx, cy = 7.215377e02, 6.095593e02, 1.728540e02
    k = [[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]]
    p = {name: np.c_[k, t] for name, t in (
        ("P0", [0.0, 0.0, 0.0]),
        ("P1", [-3.875744e02, 0.0, 0.0]),
        ("P2", [4.485728e01, 2.163791e-01, 2.745884e-03]),
        ("P3", [-3.395242e02, 2.199936e00, 2.729905e-03]))}
    r_rect = [[9.999239e-01, 9.837760e-03, -7.445048e-03],
              [-9.869795e-03, 9.999421e-01, -4.278459e-03],
              [7.402527e-03, 4.351614e-03, 9.999631e-01]]
    tr_velo_cam = [[7.533745e-03, -9.999714e-01, -6.166020e-04, -4.069766e-03],
                   [1.480249e-02, 7.280733e-04, -9.998902e-01, -7.631618e-02],
                   [9.998621e-01, 7.523790e-03, 1.480755e-02, -2.717806e-01]]
    tr_imu_velo = [[9.999976e-01, 7.553071e-04, -2.035826e-03, -8.086759e-01],
                   [-7.854027e-04, 9.998898e-01, -1.482298e-02, 3.195559e-01],
                   [2.024406e-03, 1.482454e-02, 9.998881e-01, -7.997231e-01]]
    return KittiCalib(R_rect=r_rect, Tr_velo_cam=tr_velo_cam, Tr_imu_velo=tr_imu_velo,
                      image_size=KITTI_IMAGE_SIZE, **p)


def read_calib(path: str | Path, image_size: tuple[int, int] = KITTI_IMAGE_SIZE) -> KittiCalib:
    """Read a KITTI calibration file (tracking or object format, see the module docstring).

    ``P2``, ``R_rect`` and ``Tr_velo_cam`` are required; a missing P0/P1/P3 is filled with P2
    and a missing ``Tr_imu_velo`` with the identity. Unknown keys (``Tr_cam_to_road`` ...) are
    ignored. Malformed lines raise :class:`DataError` naming the file and line: a wrong count,
    a non-numeric or non-finite value, a duplicate key, an ``R_rect`` or a rotation block of
    ``Tr_velo_cam`` / ``Tr_imu_velo`` that is not a rotation (:func:`rotation_problem`), a
    translation beyond 100 m, or a projection matrix whose intrinsic block is singular or that
    holds an entry beyond ``limits.MAX_PIXEL``; a NUL character (a key glued to its numbers)
    and a file that is not a regular file (a FIFO, a folder) are refused too.
    """
    path = Path(path)
    text = read_text(path, "calibration file")
    values: dict[str, np.ndarray] = {}
    for lineno, line in enumerate(text.splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        key = parts[0].rstrip(":")
        if key not in _ALIASES:
            continue
        canon = _ALIASES[key]
        n = _KEYS[canon][1]
        try:
            nums = np.array([float(v) for v in parts[1:]], dtype=np.float64)
        except ValueError:
            raise DataError(path, f"{key}: non-numeric value in {parts[1:]}", line=lineno) from None
        if nums.size != n:
            raise DataError(path, f"{key}: expected {n} numbers, got {nums.size}", line=lineno)
        if not np.all(np.isfinite(nums)):
            raise DataError(path, f"{key}: non-finite value", line=lineno)
        if canon in values:
            raise DataError(path, f"{key}: duplicate key", line=lineno)
        problem = _matrix_problem(canon, nums)
        if problem:
            raise DataError(path, f"{key}: {problem}", line=lineno)
        values[canon] = nums
    missing = [k for k in _REQUIRED if k not in values]
    if missing:
        raise DataError(path, f"missing calibration keys {missing} (found {sorted(values)})")
    for cam in ("P0", "P1", "P3"):
        values.setdefault(cam, values["P2"])
    values.setdefault("Tr_imu_velo", np.eye(4)[:3].ravel())
    return KittiCalib(image_size=image_size, **values)


#: A rotation read from a calibration file must satisfy ``|R^T R - I| <= 1e-3`` (each entry)
#: and ``|det R - 1| <= 1e-3``; the published KITTI matrices (7 significant digits) are within
#: 1e-6.
ROTATION_TOLERANCE = 1e-3

#: Largest translation (m) of ``Tr_velo_cam`` / ``Tr_imu_velo``: sensors of one vehicle
#: (:mod:`seqshape.limits`).
MAX_SENSOR_OFFSET = limits.MAX_SENSOR_OFFSET

#: Largest condition number of the intrinsic (left 3x3) block of a projection matrix.
MAX_CONDITION = 1e10


def rotation_problem(r) -> str | None:
    """Why ``r`` (3, 3) is not a rotation (orthonormal, det +1 within
    :data:`ROTATION_TOLERANCE`), or None.

    >>> rotation_problem(np.eye(3)) is None, rotation_problem(np.diag([1.0, 1.0, 0.0]))
    (True, 'not a rotation: max |R^T R - I| = 1, det = 0')
    """
    r = np.asarray(r, dtype=np.float64).reshape(3, 3)
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: inf/nan, refused below
        err = float(np.abs(r.T @ r - np.eye(3)).max())
        det = float(np.linalg.det(r))
    if err <= ROTATION_TOLERANCE and abs(det - 1) <= ROTATION_TOLERANCE:
        return None
    return f"not a rotation: max |R^T R - I| = {err:.3g}, det = {det:.3g}"


def _matrix_problem(key: str, nums: np.ndarray) -> str | None:
    """Why the (finite) values of calibration entry ``key`` are not usable, or None."""
    if key == "R_rect":
        return rotation_problem(nums)
    m = nums.reshape(3, 4)
    if key.startswith("P"):
        big = max(map(abs, nums.tolist()))  # 12 numbers: a third of np.abs(nums).max()
        if big > limits.MAX_PIXEL:
            return (f"entry {big:.6g} is beyond {limits.MAX_PIXEL:g} (pixels): no real "
                    "camera's projection (a unit mistake, or a corrupt file)")
        cond = np.linalg.cond(m[:, :3])
        if not cond <= MAX_CONDITION:
            return f"the intrinsic block P[:, :3] is singular (condition number {cond:.3g})"
        return None
    problem = rotation_problem(m[:, :3])
    if problem is None and np.abs(m[:, 3]).max() > MAX_SENSOR_OFFSET:
        problem = f"translation {m[:, 3].tolist()} is beyond {MAX_SENSOR_OFFSET:g} m"
    return problem


def _fmt(v: float) -> str:
    """Shortest string that reads back to exactly ``v``."""
    return repr(float(v))


def write_calib(path: str | Path, calib: KittiCalib) -> None:
    """Write ``calib`` in the KITTI tracking format (atomically); read back exactly."""
    lines = [f"P{i}: " + " ".join(_fmt(v) for v in calib.P(i).ravel()) for i in range(4)]
    lines.append("R_rect " + " ".join(_fmt(v) for v in calib.R_rect.ravel()))
    lines.append("Tr_velo_cam " + " ".join(_fmt(v) for v in calib.Tr_velo_cam.ravel()))
    lines.append("Tr_imu_velo " + " ".join(_fmt(v) for v in calib.Tr_imu_velo.ravel()))
    atomic_write_text(path, "\n".join(lines) + "\n")


def _apply(m: np.ndarray, points) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return pts @ m[:3, :3].T + m[:3, 3]


def velo_to_cam(points, calib: KittiCalib) -> np.ndarray:
    """Velodyne points (N, 3) -> rectified camera-0 coordinates (N, 3) float64."""
    return _apply(calib.velo_to_rect, points)


def cam_to_velo(points, calib: KittiCalib) -> np.ndarray:
    """Rectified camera-0 points (N, 3) -> velodyne coordinates (N, 3) float64."""
    return _apply(calib.rect_to_velo, points)


def project_rect(points_rect, calib: KittiCalib, cam: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Project rectified camera-0 points (N, 3) with ``P_cam``.

    Returns ``uv`` (N, 2) float64 pixel coordinates (x right, y down; pixel centres at integer
    coordinates as in KITTI) and ``depth`` (N,) float64, the third homogeneous coordinate, i.e.
    metres along the optical axis (plus P's small offset term). Points with depth <= 0 are
    behind the camera: their uv are still returned (meaningless), filter on ``depth > 0``.
    """
    return _project(points_rect, calib.P(cam))


def _project(points, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    hom = pts @ p[:, :3].T + p[:, 3]  # (N, 3)
    depth = hom[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = hom[:, :2] / depth[:, None]
    return uv, depth


def project_points(points_velo, calib, cam: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Project sensor-frame points (N, 3) into a camera: a :class:`PinholeCamera`, or camera
    ``cam`` of a :class:`KittiCalib` (``P_cam @ R_rect @ Tr_velo_cam``).

    Returns ``(uv (N, 2), depth (N,))`` float64 as :func:`project_rect`.
    """
    if isinstance(calib, PinholeCamera):
        return calib.project(points_velo)
    return _project(points_velo, calib.P(cam) @ calib.velo_to_rect)  # one (3, 4) matrix


def unproject_points(uv, depth, calib, cam: int = 2) -> np.ndarray:
    """Inverse of :func:`project_points`: pixels (N, 2) and depths (N,) -> sensor frame (N, 3)."""
    if isinstance(calib, PinholeCamera):
        return calib.unproject(uv, depth)
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    depth = np.asarray(depth, dtype=np.float64).reshape(-1)
    p = calib.P(cam)
    hom = np.c_[uv * depth[:, None], depth] - p[:, 3]  # (N, 3) = K @ p_rect
    rect = np.linalg.solve(p[:, :3], hom.T).T
    return cam_to_velo(rect, calib)


def in_image(uv, depth, calib, min_depth: float = 0.0) -> np.ndarray:
    """Boolean (N,): in front of the camera (depth > min_depth) and inside the image bounds
    of ``calib`` (a :class:`PinholeCamera` or :class:`KittiCalib`).

    The image covers ``-0.5 <= u < width - 0.5`` and ``-0.5 <= v < height - 0.5`` (pixel
    centres at integers).
    """
    return _in_bounds(uv, depth, calib.image_size, min_depth)


def _in_bounds(uv, depth, image_size, min_depth: float) -> np.ndarray:
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    w, h = image_size
    with np.errstate(invalid="ignore"):
        return ((np.asarray(depth) > min_depth) & (uv[:, 0] >= -0.5) & (uv[:, 0] < w - 0.5)
                & (uv[:, 1] >= -0.5) & (uv[:, 1] < h - 0.5))
