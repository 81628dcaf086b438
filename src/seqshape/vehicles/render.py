"""Orthographic views of labelled vehicle meshes (side, top, front, rear, 3/4) for the docs.

A view rotates the canonical mesh (x forward, y left, z up) so that the camera looks along -z'
of the rotated frame, sorts the faces back to front (painter's algorithm) and fills them with
the colour of their label, shaded by the angle between the face and the viewing direction.
Glass is drawn opaque, so INTERIOR faces are not drawn. Matplotlib is imported lazily.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from seqshape._io import atomic_open
from seqshape.vehicles.base import FACE_LABELS, INTERIOR
from seqshape.vehicles.fleet import fleet_vehicle

#: RGB colour of each face label in the renders.
LABEL_COLOURS = {0: (0.80, 0.25, 0.20), 1: (0.35, 0.65, 0.95), 2: (0.12, 0.12, 0.12),
                 3: (0.70, 0.70, 0.72), 4: (0.30, 0.30, 0.32), 5: (1.00, 0.85, 0.30),
                 6: (0.55, 0.45, 0.35), 7: (0.60, 0.50, 0.30), 8: (0.18, 0.18, 0.22),
                 9: (0.92, 0.95, 1.00)}

# view name -> (azimuth, elevation) in degrees: the camera's direction from the vehicle
VIEWS = {"side": (90.0, 0.0), "top": (0.0, 90.0), "front": (0.0, 0.0), "rear": (180.0, 0.0),
         "3/4": (40.0, 22.0), "3/4 rear": (220.0, 22.0)}


def view_rotation(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """(3, 3) rotation: rows are the screen right, screen up and towards-camera axes."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    to_cam = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    up = np.array([0.0, 0.0, 1.0]) if abs(np.sin(el)) < 0.99 else np.array([0.0, 1.0, 0.0])
    right = np.cross(up, to_cam)
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(to_cam, right), to_cam])


def draw_view(ax, mesh, labels, view: str = "3/4", offset=(0.0, 0.0)) -> None:
    """Draw ``mesh`` (labels (F,) or None) seen from ``view`` on the matplotlib axes ``ax``."""
    from matplotlib.collections import PolyCollection

    rot = view_rotation(*VIEWS[view])
    v = np.asarray(mesh.vertices) @ rot.T  # (V, 3)
    tri = v[np.asarray(mesh.faces)]        # (F, 3, 3)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True).clip(1e-12)
    lab = np.zeros(len(tri), int) if labels is None else np.asarray(labels, int)
    facing = (n[:, 2] > 0) & (lab != INTERIOR)  # glass is drawn opaque: hide what is behind it
    order = np.argsort(tri[:, :, 2].mean(axis=1))
    order = order[facing[order]]
    base = np.array([LABEL_COLOURS.get(int(c), (0.5, 0.5, 0.5)) for c in range(len(FACE_LABELS))])
    light = np.array([0.35, 0.55, 0.76])
    shade = 0.45 + 0.55 * np.clip(n @ light, 0.0, 1.0)
    col = base[lab.clip(0, len(base) - 1)] * shade[:, None]
    polys = tri[order][:, :, :2] + np.asarray(offset)
    ax.add_collection(PolyCollection(polys, facecolors=col[order], edgecolors="none",
                                     antialiased=False))


def contact_sheet(vehicles, path, views=("side", "top", "front", "3/4", "3/4 rear"),
                  cell: float = 1.3, dpi: int = 70) -> None:
    """One row per vehicle (each at its own scale), one column per view; saved as PNG ``path``.

    ``vehicles``: `Vehicle` objects (their ``face_labels`` colour the faces; legend below).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(vehicles), len(views), squeeze=False,
                             figsize=(cell * len(views) * 1.6, cell * len(vehicles)))
    for i, v in enumerate(vehicles):
        span = float(np.max(v.mesh.extents)) * 1.08  # each row at its own scale
        for j, view in enumerate(views):
            ax = axes[i, j]
            draw_view(ax, v.mesh, v.face_labels, view)
            ax.set_xlim(-span / 2, span / 2)
            ax.set_ylim(-span / 3.2, span / 3.2)
            ax.set_aspect("equal")
            ax.axis("off")
            if i == 0:
                ax.set_title(view, fontsize=8)
        box = v.size if v.box_size is None else v.box_size  # mirrors excluded
        size = "x".join(f"{s:.2f}" for s in box)
        axes[i, 0].text(-span / 2, span / 3.4, f"{v.kind}  {size} m", fontsize=6,
                        va="top")
    shown = [c for c in FACE_LABELS if c != INTERIOR]
    handles = [plt.Rectangle((0, 0), 1, 1, color=LABEL_COLOURS[c]) for c in shown]
    fig.legend(handles, [FACE_LABELS[c] for c in shown], loc="lower center", ncol=len(shown),
               fontsize=7, frameon=False)
    fig.subplots_adjust(left=0.01, right=0.99, top=0.97, bottom=0.04, wspace=0.02,
                        hspace=0.05)
    with atomic_open(path) as fh:  # a full disk leaves no half-written PNG
        fig.savefig(fh, format="png", dpi=dpi)
    plt.close(fig)


#: the contact sheets of docs/vehicles.md: file name -> fine kinds, one row each
DOC_SHEETS = {
    "cars_1.png": ("city_car", "hatchback", "sedan", "estate", "coupe"),
    "cars_2.png": ("mpv", "crossover", "suv", "pickup"),
    "vans_trucks.png": ("panel_van", "high_roof_van", "box_truck", "tractor", "flatbed"),
    "buses_trailers.png": ("city_bus", "coach", "semi_trailer", "car_trailer"),
}


def render_doc_sheets(out_dir, seed: int = 0) -> list:
    """Write the `DOC_SHEETS` contact sheets of fleet vehicles (seed ``seed``) to ``out_dir``.

    ``python -c "from seqshape.vehicles.render import render_doc_sheets as r;
    r('docs/img/vehicles')"`` regenerates the images of docs/vehicles.md.
    """

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, kinds in DOC_SHEETS.items():
        vehicles = [fleet_vehicle(k, seed) for k in kinds]
        contact_sheet(vehicles, out / name, views=("side", "top", "front", "rear", "3/4"),
                      cell=1.6, dpi=72)
        paths.append(out / name)
    return paths
