"""Reference point clouds shared by the metric and evaluation tests."""

import numpy as np


def box_surface(n: int, seed: int, size=(4.5, 1.8, 1.5), dtype=np.float64) -> np.ndarray:
    """Uniform samples of a box's surface (area-weighted faces), ``(n, 3)`` in ``dtype``."""
    rng = np.random.default_rng(seed)
    size = np.asarray(size, dtype=np.float64)
    ln, w, h = size
    areas = np.array([w * h, w * h, ln * h, ln * h, ln * w, ln * w])
    face = rng.choice(6, n, p=areas / areas.sum())
    u = rng.uniform(-0.5, 0.5, (n, 3)) * size
    for i, (axis, sign) in enumerate(zip([0, 0, 1, 1, 2, 2], [1, -1] * 3, strict=True)):
        u[face == i, axis] = sign * size[axis] / 2
    return u.astype(dtype)


def box_shell(n: int, seed: int, size) -> np.ndarray:
    """Points on a box's surface: uniform in the box, one random axis pushed to a face."""
    rng = np.random.default_rng(seed)
    half = np.asarray(size, dtype=np.float64) / 2
    p = rng.uniform(-half, half, size=(n, 3))
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = np.where(rng.random(n) < 0.5, -1, 1) * half[axis]
    return p
