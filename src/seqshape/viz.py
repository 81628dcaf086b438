"""Pictures of one Track: a PNG overview (matplotlib) and an offline 3D view (plotly HTML);
and of one scene frame with its amodal ground truth (:func:`draw_scene_frame`).

The PNG has a bird's-eye view of the trajectory with the points of every frame (sensor frame,
coloured by frame), the number of points per frame over time, and the complete ground-truth
shape from the top, the side and the front (canonical frame). The HTML holds the whole
plotly.js library (it works offline) and shows one frame at a time on a slider: that frame's
points, the complete shape placed with the frame's ground-truth pose, and the trajectory.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from seqshape._io import atomic_write_bytes
from seqshape.data.kins import annotations_by_image, read_kins, segm_to_mask
from seqshape.data.kitti import KittiTrackingSequence
from seqshape.data.track import Track
from seqshape.errors import DataError
from seqshape.geometry import box_corners


def _footprint(track: Track, t: int) -> np.ndarray:
    """Closed polygon ``(5, 2)`` of the bounding-box footprint at frame ``t``."""
    c = box_corners(track.size, track.poses[t])[:4, :2]
    return np.vstack([c, c[:1]])


def plot_track_png(track: Track, path: str | Path, dpi: int = 110) -> Path:
    """Write the PNG overview of ``track`` to ``path``; returns the path."""
    import matplotlib  # heavy: plotting only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # heavy: plotting only

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig = plt.figure(figsize=(15, 8.5))
    gs = fig.add_gridspec(2, 3, height_ratios=[1.4, 1.0])
    _bev(fig.add_subplot(gs[0, :2]), track)
    _counts(fig.add_subplot(gs[0, 2]), track)
    views = [("top (x-y)", 0, 1), ("side (x-z)", 0, 2), ("front (y-z)", 1, 2)]
    for k, (name, i, j) in enumerate(views):
        _shape_view(fig.add_subplot(gs[1, k]), track, name, i, j)
    m = track.meta
    fig.suptitle(f"{track.track_id}  |  {m.get('kind', '?')}, {m.get('manoeuvre', '?')}, "
                 f"{m.get('sensor', '?')}, split {m.get('split', '?')}  |  {len(track)} frames,"
                 f" {int(track.num_points.sum())} points")
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def _bev(ax, track: Track) -> None:
    import matplotlib.pyplot as plt  # heavy: plotting only

    known = ~np.isnan(track.poses).any(1)
    cmap = plt.get_cmap("viridis")
    n = max(len(track) - 1, 1)
    for t, p in enumerate(track.points):
        if len(p):
            ax.scatter(p[:, 0], p[:, 1], s=1.5, color=cmap(t / n), linewidths=0)
    if known.any():
        ax.plot(track.poses[known, 0], track.poses[known, 1], "k-", lw=0.8, label="trajectory")
        first, last = np.flatnonzero(known)[[0, -1]]
        ax.plot(*_footprint(track, first).T, color=cmap(0.0), lw=1.2, label="first frame")
        ax.plot(*_footprint(track, last).T, color=cmap(1.0), lw=1.2, label="last frame")
    ax.plot([0], [0], "r^", ms=9, label="sensor")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("bird's-eye view, sensor frame (colour: frame)")
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)


def _counts(ax, track: Track) -> None:
    n = track.num_points
    ax.plot(track.timestamps, n, "-o", ms=2, lw=1)
    empty = n == 0
    if empty.any():
        ax.plot(track.timestamps[empty], n[empty], "rx", ms=5, label=f"{empty.sum()} empty")
        ax.legend(fontsize=8)
    ax2 = ax.twinx()
    dist = np.hypot(track.poses[:, 0], track.poses[:, 1])
    ax2.plot(track.timestamps, dist, color="tab:orange", lw=1)
    ax2.set_ylabel("distance (m)", color="tab:orange")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("points per frame")
    ax.set_title("points per frame and distance")
    ax.grid(alpha=0.3)


def _shape_view(ax, track: Track, name: str, i: int, j: int) -> None:
    labels = "xyz"
    if track.complete is None:
        ax.text(0.5, 0.5, "no complete shape", ha="center", va="center", transform=ax.transAxes)
    else:
        c = track.complete
        order = np.argsort(c[:, 3 - i - j])  # draw far points first
        ax.scatter(c[order, i], c[order, j], s=2, c=c[order, 3 - i - j], cmap="coolwarm",
                   linewidths=0)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"{labels[i]} (m)")
    ax.set_ylabel(f"{labels[j]} (m)")
    ax.set_title(f"complete shape, {name}")
    ax.grid(alpha=0.3)


def track_html(track: Track, path: str | Path, max_frames: int = 100,
               complete_points: int = 1024) -> Path:
    """Write an offline interactive 3D view of ``track`` (plotly, frames on a slider).

    At most ``max_frames`` evenly spaced frames and ``complete_points`` points of the complete
    shape per frame are drawn, to keep the file small (plotly.js itself is ~4 MB).
    """
    import plotly.graph_objects as go  # heavy: the HTML view only

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames = np.unique(np.linspace(0, len(track) - 1, min(len(track), max_frames)).astype(int))
    fig = go.Figure()
    known = ~np.isnan(track.poses).any(1)
    fig.add_trace(go.Scatter3d(x=track.poses[known, 0], y=track.poses[known, 1],
                               z=track.poses[known, 2], mode="lines", name="trajectory",
                               line=dict(color="black", width=2)))
    fig.add_trace(go.Scatter3d(x=[0], y=[0], z=[0], mode="markers", name="sensor",
                               marker=dict(color="red", size=4, symbol="diamond")))
    for k, t in enumerate(frames):
        p = track.points[t]
        fig.add_trace(go.Scatter3d(x=p[:, 0], y=p[:, 1], z=p[:, 2], mode="markers",
                                   name=f"points (frame {t})", visible=k == 0,
                                   marker=dict(size=2, color="royalblue")))
        if track.complete is not None and known[t]:
            c = track.complete_in_frame(t)
            c = c[::max(1, len(c) // complete_points)]
            fig.add_trace(go.Scatter3d(x=c[:, 0], y=c[:, 1], z=c[:, 2], mode="markers",
                                       name="complete (GT pose)", visible=k == 0,
                                       marker=dict(size=1.5, color="orange", opacity=0.5)))
    fig.update_layout(sliders=[_slider(fig, track, frames)], title=f"{track.track_id}",
                      scene=dict(aspectmode="data", xaxis_title="x (m)", yaxis_title="y (m)",
                                 zaxis_title="z (m)"),
                      margin=dict(l=0, r=0, t=40, b=0))
    fig.write_html(str(path), include_plotlyjs=True, full_html=True)
    return path


def _slider(fig, track: Track, frames: np.ndarray) -> dict:
    """A slider whose step ``k`` shows the traces of frame ``frames[k]`` (and the fixed ones)."""
    owner = []  # frame position of every trace, -1 for the always-visible ones
    for tr in fig.data:
        name = tr.name or ""
        if name.startswith("points (frame "):
            owner.append(int(np.searchsorted(frames, int(name[14:-1]))))
        elif name.startswith("complete"):
            owner.append(owner[-1])
        else:
            owner.append(-1)
    owner = np.array(owner)
    steps = [dict(method="update", label=f"{t} ({len(track.points[t])} pts)",
                  args=[{"visible": ((owner == -1) | (owner == k)).tolist()}])
             for k, t in enumerate(frames)]
    return dict(active=0, steps=steps, currentvalue=dict(prefix="frame "), pad=dict(t=30))


# ----------------------------------------------------------------------------- scene frames


def _scene_palette(i: int) -> np.ndarray:
    import matplotlib  # heavy: plotting only

    return np.asarray(matplotlib.colormaps["tab20"](i % 20)[:3])


def _draw_scene_image(ax, image: np.ndarray, anns: list[dict]) -> None:
    import cv2  # heavy: only the scene figure needs OpenCV

    img = image.astype(np.float64) / 255.0
    h, w = image.shape[:2]
    outlines = []
    for ann in anns:
        c = _scene_palette(int(ann.get("track_id", 0)))
        vis = segm_to_mask(ann["i_segm"], h, w)
        img[vis] = 0.45 * img[vis] + 0.55 * c
        amodal = segm_to_mask(ann["a_segm"], h, w).astype(np.uint8)
        contours, _ = cv2.findContours(amodal, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        outlines.append((contours, c, vis, ann))
    ax.imshow(np.clip(img, 0, 1))
    for contours, c, vis, ann in outlines:
        for cnt in contours:
            pts = cnt[:, 0, :]
            ax.plot(np.r_[pts[:, 0], pts[0, 0]], np.r_[pts[:, 1], pts[0, 1]], "-", color=c, lw=1.2)
        rows, cols = np.nonzero(vis)
        if len(rows):
            ax.text(cols.mean(), rows.mean(), f"{ann['oco_id']}.{ann['ico_id']}", color="white",
                    fontsize=8, ha="center", va="center", weight="bold",
                    bbox={"facecolor": c, "alpha": 0.8, "pad": 1, "lw": 0})
    ax.set_axis_off()


def _draw_scene_bev(ax, points: np.ndarray, boxes, camera, extent: float) -> None:
    sel = (points[:, 0] > -10) & (points[:, 0] < extent) & (np.abs(points[:, 1]) < extent * 0.6)
    p = points[sel]
    low = p[:, 2] < np.quantile(p[:, 2], 0.02) + 0.15 if len(p) else np.zeros(0, bool)
    ax.scatter(-p[low, 1], p[low, 0], c="0.75", s=0.1, linewidths=0)
    ax.scatter(-p[~low, 1], p[~low, 0], c=p[~low, 2], s=1.0, cmap="viridis", vmin=-1.8,
               vmax=0.5, linewidths=0)
    for tid, pose, size in boxes:
        c = box_corners(size, pose)[:4]
        ring = np.r_[c, c[:1]]
        col = _scene_palette(tid)
        ax.plot(-ring[:, 1], ring[:, 0], "-", color=col, lw=1.2)
        front = (c[0] + c[3]) / 2
        ax.plot([-pose[1], -front[1]], [pose[0], front[0]], "-", color=col, lw=1.0)
        ax.text(-pose[1], pose[0], str(tid), fontsize=7, color="black", ha="center",
                clip_on=True)
    w = camera.width
    fx, cx = camera.K[0, 0], camera.K[0, 2]
    for u in (0.0, w - 1.0):  # field-of-view rays (velodyne y = -camera x)
        lateral = (cx - u) / fx
        ax.plot([0, -lateral * extent], [0, extent], "--", color="grey", lw=0.8)
    ax.plot(0, 0, "r^", ms=6)
    ax.set_xlim(-extent * 0.6, extent * 0.6)
    ax.set_ylim(-10, extent)
    ax.set_aspect("equal")
    ax.set_xlabel("-y (m, right)")
    ax.set_ylabel("x (m, forward)")


def draw_scene_frame(root: Path, sequence: str, frame: int, out: Path, extent: float = 50.0):
    """Write the PNG figure of ``frame`` of ``sequence`` under ``root`` (``seqshape scenes``).

    Left: the rendered image with every KINS instance's visible mask filled, its amodal
    outline drawn, and ``cluster.order`` (KINS ``oco_id.ico_id``; order 1 is the front of its
    cluster, ``0.0`` an instance that overlaps no other) written on it. Right: the LiDAR sweep
    from above (colour = height) with the label_02 boxes and track ids, and the camera's
    field of view (``extent`` metres ahead).
    """
    import cv2  # heavy: only the scene figure needs OpenCV
    import matplotlib  # heavy: plotting only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # heavy: plotting only

    seq = KittiTrackingSequence(root, sequence)
    if not seq.frames:
        raise DataError(root, f"no sequence {seq.sequence} here (found "
                              f"{KittiTrackingSequence.sequences(root)})")
    if frame not in seq.frames:
        raise DataError(seq.velodyne_path(frame), f"frame {frame} not in sequence {seq.sequence} "
                                                  f"(frames {seq.frames[:1]}..{seq.frames[-1:]})")
    img_path = seq.image_path(frame)
    image = cv2.imread(str(img_path), cv2.IMREAD_COLOR)
    if image is None:
        raise DataError(img_path, "missing or unreadable image")
    kins_path = Path(root) / "amodal" / f"{seq.sequence}.json"
    doc = read_kins(kins_path)
    by_image = annotations_by_image(doc)
    image_id = next((im["id"] for im in doc["images"] if im.get("frame", im["id"]) == frame), None)
    anns = by_image.get(image_id, [])
    boxes = [(int(b.track_id), b.pose, b.size) for b in seq.boxes(frame)]
    fig = plt.figure(figsize=(16, 5.2))
    ax_img = fig.add_axes([0.01, 0.05, 0.70, 0.9])
    ax_bev = fig.add_axes([0.75, 0.08, 0.23, 0.86])
    _draw_scene_image(ax_img, image[:, :, ::-1], anns)
    ax_img.set_title(f"{root.name} sequence {seq.sequence} frame {frame}: visible masks filled, "
                     f"amodal outlines, occlusion cluster.order", fontsize=9)
    _draw_scene_bev(ax_bev, seq.points(frame), boxes, seq.camera(), extent)
    ax_bev.set_title("LiDAR (grey: ground, colour: z) and label_02 boxes", fontsize=9)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(out, buf.getvalue())
