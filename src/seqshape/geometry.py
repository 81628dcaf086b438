"""Planar poses and rigid transforms.

Convention (fixed once, used everywhere): a pose is ``(x, y, z, yaw)``, the position of a
vehicle's canonical origin (centre of its 3D bounding box) in the sensor frame and its heading
about +z, counter-clockwise seen from above (x forward, y left, z up). Points map as

    p_sensor = R_z(yaw) @ p_canonical + (x, y, z).

>>> import numpy as np
>>> p = np.array([[1.0, 0.0, 0.0]])
>>> canonical_to_sensor(p, np.array([10.0, 0.0, 0.0, np.pi / 2])).round(6)
array([[10.,  1.,  0.]])
"""

from __future__ import annotations

import numpy as np


def wrap_angle(a):
    """Wrap angles to [-pi, pi).

    >>> float(wrap_angle(3 * np.pi / 2))
    -1.5707963267948966
    """
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def yaw_to_rotmat(yaw) -> np.ndarray:
    """Rotation matrices about +z, shape ``(..., 3, 3)`` for ``yaw`` of shape ``(...)``."""
    yaw = np.asarray(yaw, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    z, o = np.zeros_like(yaw), np.ones_like(yaw)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1),
                     np.stack([z, z, o], -1)], -2)


def pose_to_matrix(pose) -> np.ndarray:
    """Homogeneous canonical-to-sensor transforms ``(..., 4, 4)`` from poses ``(..., 4)``."""
    pose = np.asarray(pose, dtype=np.float64)
    m = np.zeros(pose.shape[:-1] + (4, 4))
    m[..., :3, :3] = yaw_to_rotmat(pose[..., 3])
    m[..., :3, 3] = pose[..., :3]
    m[..., 3, 3] = 1.0
    return m


def matrix_to_pose(m) -> np.ndarray:
    """Poses ``(..., 4)`` from homogeneous transforms (the rotation must be about z)."""
    m = np.asarray(m, dtype=np.float64)
    yaw = np.arctan2(m[..., 1, 0], m[..., 0, 0])
    return np.concatenate([m[..., :3, 3], yaw[..., None]], -1)


def canonical_to_sensor(points, pose) -> np.ndarray:
    """Map ``(N, 3)`` canonical points to the sensor frame with one pose ``(4,)``.

    The dtype of ``points`` is kept (float32 in, float32 out).
    """
    points = np.asarray(points)
    pose = np.asarray(pose, dtype=np.float64)
    r = yaw_to_rotmat(pose[3])
    out = points.astype(np.float64) @ r.T + pose[:3]
    return out.astype(points.dtype if points.dtype.kind == "f" else np.float64)


def sensor_to_canonical(points, pose) -> np.ndarray:
    """Inverse of :func:`canonical_to_sensor`.

    >>> p = np.random.default_rng(0).normal(size=(5, 3))
    >>> q = np.array([1.0, -2.0, 0.5, 0.3])
    >>> bool(np.allclose(sensor_to_canonical(canonical_to_sensor(p, q), q), p))
    True
    """
    points = np.asarray(points)
    pose = np.asarray(pose, dtype=np.float64)
    r = yaw_to_rotmat(pose[3])
    out = (points.astype(np.float64) - pose[:3]) @ r
    return out.astype(points.dtype if points.dtype.kind == "f" else np.float64)


def compose(a, b) -> np.ndarray:
    """Pose of ``b`` expressed through ``a``: ``T(compose(a, b)) = T(a) @ T(b)``.

    >>> compose([1.0, 0.0, 0.0, np.pi / 2], [2.0, 0.0, 0.0, 0.0]).round(6)
    array([1.      , 2.      , 0.      , 1.570796])
    """
    return matrix_to_pose(pose_to_matrix(a) @ pose_to_matrix(b))


def invert(pose) -> np.ndarray:
    """The inverse transform as a pose: ``compose(pose, invert(pose)) == 0``.

    >>> q = np.array([3.0, -1.0, 0.5, 0.4])
    >>> bool(np.allclose(compose(q, invert(q)), 0.0))
    True
    """
    return matrix_to_pose(np.linalg.inv(pose_to_matrix(pose)))


def box_corners(size, pose=None) -> np.ndarray:
    """The 8 corners ``(8, 3)`` of a box of ``size`` (l, w, h), in the canonical frame or posed.

    Order: the four bottom corners counter-clockwise from front-left, then the four top ones.

    >>> box_corners((4.0, 2.0, 1.0))[:4]
    array([[ 2. ,  1. , -0.5],
           [-2. ,  1. , -0.5],
           [-2. , -1. , -0.5],
           [ 2. , -1. , -0.5]])
    """
    hl, hw, hh = (float(v) / 2 for v in size)
    xy = np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]])
    c = np.concatenate([np.c_[xy, np.full(4, -hh)], np.c_[xy, np.full(4, hh)]])
    return c if pose is None else canonical_to_sensor(c, pose)


def points_in_box(points, size, pose, margin: float = 0.0) -> np.ndarray:
    """Boolean mask of the ``(N, 3)`` sensor-frame points inside a posed box (+ margin, m).

    >>> pose = np.array([10.0, 0.0, 0.0, np.pi / 2])  # length along the sensor's y axis
    >>> points_in_box([[10.0, 1.9, 0.0], [11.9, 0.0, 0.0]], (4.0, 2.0, 1.0), pose)
    array([ True, False])
    """
    local = sensor_to_canonical(np.asarray(points, dtype=np.float64), pose)
    half = np.asarray(size, dtype=np.float64) / 2 + margin
    return np.all(np.abs(local) <= half, axis=1)


def box_surface(n: int, rng: int | np.random.Generator = 0, size=(4.5, 1.8, 1.5), *, pose=None,
                dtype=np.float64) -> np.ndarray:
    """``n`` points uniform over the surface area of a box, shape ``(n, 3)`` (the default size
    is a passenger car's).

    Parameters
    ----------
    n : int
        Number of points.
    rng : int or numpy.random.Generator
        Seed, or a generator to draw from.
    size : array_like, shape (3,)
        Box ``(length, width, height)`` in metres; negative entries count as 0, a box of zero
        area draws its faces uniformly.
    pose : array_like, shape (4,), optional
        ``(x, y, z, yaw)``: return the points in the sensor frame (computed in float64).
    dtype : numpy dtype
        Dtype of the result.

    Returns
    -------
    numpy.ndarray, shape (n, 3)

    Examples
    --------
    >>> p = box_surface(4000, 0, (2.0, 1.0, 1.0))
    >>> on_end = np.isclose(np.abs(p[:, 0]), 1.0)  # the two 1 x 1 end faces: 2 of 10 m^2
    >>> round(float(on_end.mean()), 1)
    0.2
    """
    rng = np.random.default_rng(rng)  # a Generator is passed through unchanged
    size = np.maximum(np.asarray(size, dtype=np.float64), 0.0)
    ln, w, h = size
    areas = np.array([w * h, w * h, ln * h, ln * h, ln * w, ln * w])
    p = areas / areas.sum() if areas.sum() > 0 else np.full(6, 1 / 6)
    face = rng.choice(6, n, p=p)
    u = rng.uniform(-0.5, 0.5, (n, 3)) * size
    for i, (axis, sign) in enumerate(zip([0, 0, 1, 1, 2, 2], [1, -1] * 3, strict=True)):
        u[face == i, axis] = sign * size[axis] / 2
    if pose is not None:
        u = canonical_to_sensor(u, np.asarray(pose, dtype=np.float64))
    return u.astype(dtype)
