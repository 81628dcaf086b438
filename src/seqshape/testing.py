"""Reference shapes, clouds and tolerances shared by the tests and the benchmarks.

One place for the synthetic inputs that the test files and ``benchmarks/bm_*.py`` scripts both
need, so that a benchmark times exactly the clouds a test checks. It sits in the bottom layer
(numpy and :mod:`seqshape.geometry` only) and ships with the package, so a benchmark run as a
plain script imports it without ``tests/`` on the path.

Two box samplers, both in the canonical frame of :mod:`seqshape.geometry` (box centred at the
origin, ``size = (length, width, height)`` along x, y, z), optionally moved by a ``pose``:

* :func:`box_surface` (:func:`seqshape.geometry.box_surface`, re-exported: the box fit uses
  it too): uniform over the surface area (a face is drawn with probability proportional to
  its area), the right reference for Chamfer / EMD floors.
* :func:`box_shell`: a point uniform in the box with one of its three coordinates, drawn
  uniformly, pushed to a face: each pair of opposite faces gets a third of the points whatever
  its area (small faces are denser). The synthetic training tracks use it.

``rng`` is a seed or a :class:`numpy.random.Generator` (passed on, so a test can draw several
clouds from one stream). The draws are fixed: the same seed gives the same cloud on every
version, which the tests' expected numbers rely on.

>>> cloud = box_surface(1000, 0)
>>> cloud.shape, bool(np.all(np.abs(cloud) <= np.array(CAR_SIZE) / 2 + 1e-12))
((1000, 3), True)
>>> on_face = np.isclose(np.abs(box_shell(500, 1, (4.0, 2.0, 1.0))), [2.0, 1.0, 0.5])
>>> bool(on_face.any(axis=1).all())
True
"""

from __future__ import annotations

import numpy as np

from seqshape.geometry import box_surface, canonical_to_sensor

__all__ = ["CAR_SIZE", "TOLERANCES", "assert_close", "box_shell", "box_surface", "tolerance"]

CAR_SIZE = (4.5, 1.8, 1.5)
"""A passenger car's box ``(length, width, height)`` in metres: the default reference shape."""

TOLERANCES: dict[type, tuple[float, float]] = {
    np.float16: (1e-3, 1e-3),
    np.float32: (1e-5, 1e-5),
    np.float64: (1e-9, 1e-9),
}
"""``(rtol, atol)`` for comparing results computed in a dtype (metres, radians): float32
round trips through rotations of vehicle-scale coordinates (tens of metres) stay within 1e-5."""


def box_shell(n: int, rng: int | np.random.Generator = 0, size=CAR_SIZE, *, pose=None,
              dtype=np.float64) -> np.ndarray:
    """``n`` points on a box's faces, a third of them on each pair of opposite faces.

    Each point is uniform in the box, then one coordinate (x, y or z, uniformly) is set to
    ``-size/2`` or ``+size/2`` (equally likely). Parameters as
    :func:`seqshape.geometry.box_surface`.

    Examples
    --------
    >>> p = box_shell(3000, 0, (4.0, 2.0, 1.0))
    >>> top_or_bottom = np.isclose(np.abs(p[:, 2]), 0.5)  # 8 of 28 m^2, but a third of points
    >>> round(float(top_or_bottom.mean()), 1)
    0.3
    """
    rng = np.random.default_rng(rng)  # a Generator is passed through unchanged
    size = np.asarray(size, dtype=np.float64)
    p = rng.uniform(-0.5, 0.5, (n, 3)) * size
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = rng.choice([-1.0, 1.0], n) * size[axis] / 2
    if pose is not None:
        p = canonical_to_sensor(p, np.asarray(pose, dtype=np.float64))
    return p.astype(dtype)


def tolerance(dtype) -> tuple[float, float]:
    """``(rtol, atol)`` of :data:`TOLERANCES` for ``dtype`` (a dtype, type or array).

    >>> tolerance(np.zeros(3, np.float32))
    (1e-05, 1e-05)
    """
    dtype = dtype.dtype if isinstance(dtype, np.ndarray) else np.dtype(dtype)
    try:
        return TOLERANCES[dtype.type]
    except KeyError:
        raise ValueError(f"no tolerance for dtype {dtype}; known: "
                         f"{', '.join(np.dtype(t).name for t in TOLERANCES)}") from None


def assert_close(actual, expected, dtype=None) -> None:
    """``numpy.testing.assert_allclose`` with the tolerance of ``dtype`` (default: the dtype
    of ``actual``, float64 for non-float input).

    >>> assert_close(np.float32(1.0) + np.float32(1e-6), 1.0)
    """
    actual = np.asarray(actual)
    if dtype is None:
        dtype = actual.dtype if actual.dtype.kind == "f" else np.float64
    rtol, atol = tolerance(dtype)
    np.testing.assert_allclose(actual, expected, rtol=rtol, atol=atol)
