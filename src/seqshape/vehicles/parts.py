"""Closed mesh parts with per-face labels, and their assembly into one labelled mesh.

Every builder returns a `Part`: vertices, faces and one label per face (codes in
`seqshape.vehicles.base.FACE_LABELS`). Each part is closed (every edge shared by exactly two
faces) with outward winding; parts may overlap (a mirror pushed into a door, a wheel in its
arch), so their union, `assemble`, is a watertight mesh in trimesh's sense whose hidden faces
are simply never seen from outside.

The main builder is `loft`: a stack of cross-section rings along x closed at both ends by
`sweep_end`, which sweeps the end ring around a plan-view superellipse to the centre plane
(y = 0), where the left and right halves of the ring meet (no apex, no degenerate faces).
Rings are symmetric in y: ``ring = [half, mirror(half[-2:0:-1])]`` with ``half`` the left half
from the bottom centre to the top centre (both on y = 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from seqshape.vehicles.base import RIM, TYRE


@dataclass
class Part:
    """A closed labelled mesh piece: ``vertices`` (V, 3), ``faces`` (F, 3), ``labels`` (F,).

    ``in_box``: False for parts an annotator leaves out of the box (side mirrors).
    """

    vertices: np.ndarray
    faces: np.ndarray
    labels: np.ndarray
    in_box: bool = True

    def oriented(self) -> Part:
        """This part with its faces wound outwards (positive signed volume)."""
        tri = self.vertices[self.faces]
        vol = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum()
        if vol < 0:
            self.faces = self.faces[:, ::-1].copy()
        return self


def assemble(parts: list[Part]) -> tuple[trimesh.Trimesh, np.ndarray]:
    """Concatenate ``parts`` into one mesh (process=False: order kept) and its (F,) labels."""
    verts, faces, labels, off = [], [], [], 0
    for p in parts:
        verts.append(p.vertices)
        faces.append(p.faces + off)
        labels.append(np.asarray(p.labels, dtype=np.uint8))
        off += len(p.vertices)
    mesh = trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=False)
    return mesh, np.concatenate(labels)


def mirror_ring(half: np.ndarray) -> np.ndarray:
    """(m, d) left half (columns ..., y, z with y at column -2) -> (2m - 2, d) closed ring."""
    right = half[-2:0:-1].copy()
    right[:, -2] *= -1.0
    return np.concatenate([half, right])


def half_index(k: np.ndarray, m: int) -> np.ndarray:
    """Index into the half of ring vertex ``k`` (ring of 2m - 2 vertices)."""
    k = np.asarray(k)
    return np.where(k <= m - 1, k, 2 * m - 2 - k)


def segment_half_index(m: int) -> np.ndarray:
    """(2m - 2,) for ring segment k (vertex k to k + 1): index of the same segment in the half."""
    k = np.arange(2 * m - 2)
    return np.where(k <= m - 2, k, 2 * m - 3 - k)


def sweep_end(ring: np.ndarray, depth: np.ndarray, exponent: float, steps: int,
              sign: float) -> np.ndarray:
    """Rings (steps, K, 3) closing the end of a loft at the planar ring ``ring`` (K, 3).

    Ring vertex k moves along a quarter superellipse of exponent ``exponent`` in its own
    horizontal plane: x grows by up to ``depth[k]`` (times ``sign``: +1 at the front, -1 at the
    rear) while y shrinks to 0. The last ring lies on y = 0 (both halves coincide).
    """
    th = np.linspace(0.0, np.pi / 2, steps + 1)[1:]
    e = 2.0 / exponent
    s = np.sin(th) ** e  # (steps,)
    c = np.cos(th).clip(0.0) ** e
    c[-1] = 0.0
    out = np.repeat(ring[None], steps, axis=0)
    out[:, :, 0] = ring[None, :, 0] + sign * depth[None, :] * s[:, None]
    out[:, :, 1] = ring[None, :, 1] * c[:, None]
    return out


def loft(rings: np.ndarray, labels: np.ndarray) -> Part:
    """Closed part from rings (N, K, 3) whose first and last rings lie on y = 0.

    ``labels`` (N - 1, K): label of the strip between ring i and i + 1 at segment k. The first
    and last rings are collapsed (vertex k and its mirror merged), which closes the surface.
    """
    n, k, _ = rings.shape
    m = (k + 2) // 2
    body = rings[1:-1].reshape(-1, 3)
    verts = np.concatenate([rings[0, :m], body, rings[-1, :m]])
    idx = np.empty((n, k), dtype=np.int64)
    idx[0] = half_index(np.arange(k), m)
    idx[1:-1] = m + np.arange((n - 2) * k).reshape(n - 2, k)
    idx[-1] = m + (n - 2) * k + half_index(np.arange(k), m)
    a, b = idx[:-1], np.roll(idx[:-1], -1, axis=1)
    c, d = idx[1:], np.roll(idx[1:], -1, axis=1)
    faces = np.stack([np.stack([a, b, d], -1), np.stack([a, d, c], -1)], axis=2)  # (N-1,K,2,3)
    lab = np.repeat(np.asarray(labels, dtype=np.uint8)[:, :, None], 2, axis=2)
    return Part(verts, faces.reshape(-1, 3), lab.reshape(-1)).oriented()


def end_closed_loft(rings: np.ndarray, labels: np.ndarray, depth_front: np.ndarray,
                    depth_rear: np.ndarray, exp_front: float, exp_rear: float,
                    steps: int = 6, cap_labels=None) -> Part:
    """Loft of planar body rings (N, K, 3) (x increasing) closed by two `sweep_end` caps.

    ``labels`` (N - 1, K) label the body strips; ``cap_labels(which, rings)`` (``which`` is
    ``"front"`` or ``"rear"``, rings (steps + 1, K, 3) from the body's end ring outwards)
    returns (steps, K) labels of the cap strips; default: the label of the adjacent strip.
    """
    front = sweep_end(rings[-1], depth_front, exp_front, steps, 1.0)
    rear = sweep_end(rings[0], depth_rear, exp_rear, steps, -1.0)
    all_rings = np.concatenate([rear[::-1], rings, front])
    if cap_labels is None:
        lf = np.repeat(labels[-1:], steps, axis=0)
        lr = np.repeat(labels[:1], steps, axis=0)
    else:
        lf = cap_labels("front", np.concatenate([rings[-1:], front]))
        lr = cap_labels("rear", np.concatenate([rings[:1], rear]))
    return loft(all_rings, np.concatenate([lr[::-1], labels, lf]))


def box_part(lo, hi, label: int) -> Part:
    """Axis-aligned closed box from corner ``lo`` to ``hi`` (12 faces)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    m = trimesh.creation.box(extents=hi - lo)
    v = np.asarray(m.vertices) + (lo + hi) / 2.0
    return Part(v, np.asarray(m.faces), np.full(len(m.faces), label, np.uint8)).oriented()


def beam(p0, p1, half: float, label: int) -> Part:
    """Closed square beam of half thickness ``half`` from point ``p0`` to ``p1`` (12 faces)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    d = p1 - p0
    length = float(np.linalg.norm(d))
    m = trimesh.creation.box(extents=(length, 2 * half, 2 * half))
    x = d / length
    ref = np.array([0.0, 0.0, 1.0]) if abs(x[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    y = np.cross(ref, x)
    y /= np.linalg.norm(y)
    rot = np.stack([x, y, np.cross(x, y)], axis=1)  # columns: local axes in the world
    v = np.asarray(m.vertices) @ rot.T + (p0 + p1) / 2.0
    return Part(v, np.asarray(m.faces), np.full(len(m.faces), label, np.uint8)).oriented()


def superellipsoid(centre, half, label: int, power: float = 4.0, n_lat: int = 6,
                   n_lon: int = 12) -> Part:
    """Closed superellipsoid (rounded box for ``power`` > 2, ellipsoid for 2) of half extents."""
    lat = np.linspace(-np.pi / 2, np.pi / 2, n_lat + 1)[1:-1]
    lon = np.linspace(0.0, 2 * np.pi, n_lon, endpoint=False)
    e = 2.0 / power

    def f(t):
        return np.sign(t) * np.abs(t) ** e

    cl, sl = f(np.cos(lat))[:, None], f(np.sin(lat))[:, None]
    x = cl * f(np.cos(lon))[None]
    y = cl * f(np.sin(lon))[None]
    z = np.repeat(sl, n_lon, axis=1)
    ring_v = np.stack([x, y, z], -1).reshape(-1, 3)
    verts = np.concatenate([[[0, 0, -1.0]], ring_v, [[0, 0, 1.0]]])
    verts = verts * np.asarray(half, float) + np.asarray(centre, float)
    faces = []
    nr = len(lat)
    for j in range(n_lon):
        j1 = (j + 1) % n_lon
        faces.append([0, 1 + j1, 1 + j])
        top = 1 + nr * n_lon
        faces.append([top, 1 + (nr - 1) * n_lon + j, 1 + (nr - 1) * n_lon + j1])
        for i in range(nr - 1):
            a, b = 1 + i * n_lon + j, 1 + i * n_lon + j1
            c, d = a + n_lon, b + n_lon
            faces += [[a, b, d], [a, d, c]]
    faces = np.asarray(faces)
    return Part(verts, faces, np.full(len(faces), label, np.uint8)).oriented()


def lathe(profile: np.ndarray, labels: np.ndarray, segments: int) -> Part:
    """Closed surface of revolution about the local y axis.

    ``profile`` (P, 2): (r, a) points of a closed outline whose first and last points lie on
    the axis (r = 0); ``labels`` (P - 1,): label of each profile segment.
    """
    phi = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    verts, index = [], []
    for r, a in profile:
        if r <= 1e-12:
            index.append([len(verts)] * segments)
            verts.append([0.0, a, 0.0])
        else:
            index.append(list(range(len(verts), len(verts) + segments)))
            verts += [[r * np.cos(p), a, r * np.sin(p)] for p in phi]
    faces, lab = [], []
    for i in range(len(profile) - 1):
        i0, i1 = index[i], index[i + 1]
        for j in range(segments):
            j1 = (j + 1) % segments
            tris = [[i0[j], i0[j1], i1[j1]], [i0[j], i1[j1], i1[j]]]
            tris = [t for t in tris if len(set(t)) == 3]
            faces += tris
            lab += [labels[i]] * len(tris)
    return Part(np.asarray(verts), np.asarray(faces), np.asarray(lab, np.uint8)).oriented()


def wheel(centre, radius: float, width: float, side: float, segments: int = 20,
          rim_frac: float = 0.62, dish: float = 0.03) -> Part:
    """Tyre (rounded shoulders) with a recessed rim face on the outer side, axis along y.

    ``side`` = +1 for a wheel on the left (outer face towards +y), -1 on the right.
    """
    r, w = radius, width / 2.0
    rr, sh = rim_frac * radius, min(0.04, 0.3 * w, 0.15 * radius)
    prof = np.array([
        (0.0, w - dish), (rr * 0.95, w - dish), (rr, w - 0.01), (rr + 0.012, w),
        (r - sh, w), (r - 0.3 * sh, w - 0.3 * sh), (r, w - sh), (r, -w + sh),
        (r - 0.3 * sh, -w + 0.3 * sh), (r - sh, -w), (rr, -w), (0.0, -w)])
    labels = np.array([RIM, RIM, RIM, TYRE, TYRE, TYRE, TYRE, TYRE, TYRE, TYRE, RIM])
    part = lathe(prof, labels, segments)
    v = part.vertices.copy()
    v[:, 1] *= side
    part.vertices = v + np.asarray(centre, float)
    part.faces = part.faces if side > 0 else part.faces[:, ::-1].copy()
    return part.oriented()
