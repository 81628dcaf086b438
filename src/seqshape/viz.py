"""Pictures of one Track: a PNG overview (matplotlib) and an offline 3D view (plotly HTML);
and of one scene frame with its amodal ground truth (:func:`draw_scene_frame`).

The PNG has a bird's-eye view of the trajectory with the points of every frame (sensor frame,
coloured by frame), the number of points per frame over time, and the complete ground-truth
shape from the top, the side and the front (canonical frame); each colour scale has a colour
bar. The HTML holds the whole
plotly.js library (it works offline) and shows one frame at a time on a slider: that frame's
points, the complete shape placed with the frame's ground-truth pose, and the trajectory.
The scene figure's image is drawn as the labeller's overlays (:mod:`seqshape.amodal.overlay`:
one colour and one tag per track, a legend), with the same colours and track ids on its
bird's-eye view.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from seqshape._io import atomic_write_bytes, atomic_write_text, check_regular
from seqshape.amodal.overlay import OverlayInstance, draw_overlay, track_colour
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
    """Write the PNG overview of ``track`` (:func:`track_overview`) to ``path``; returns the
    path."""
    import matplotlib.pyplot as plt  # heavy: plotting only

    path = Path(path)
    fig = track_overview(track)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
    return path


def track_overview(track: Track):
    """The matplotlib figure of :func:`plot_track_png` (module doc); every colour scale has a
    colour bar (frame; the coordinate seen end-on in each view of the complete shape)."""
    import matplotlib  # heavy: plotting only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # heavy: plotting only

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
    return fig


def _bev(ax, track: Track) -> None:
    import matplotlib  # heavy: plotting only
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
    frames = matplotlib.cm.ScalarMappable(matplotlib.colors.Normalize(0, n), cmap)
    ax.figure.colorbar(frames, ax=ax, label="frame", fraction=0.04, pad=0.01)


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
        k = 3 - i - j  # the axis seen end-on
        order = np.argsort(c[:, k])  # draw far points first
        dots = ax.scatter(c[order, i], c[order, j], s=2, c=c[order, k], cmap="coolwarm",
                          linewidths=0)
        ax.figure.colorbar(dots, ax=ax, label=f"{labels[k]} (m)", fraction=0.05, pad=0.02)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"{labels[i]} (m)")
    ax.set_ylabel(f"{labels[j]} (m)")
    ax.set_title(f"complete shape, {name}")
    ax.grid(alpha=0.3)


# The HTML view's layout: margins and a slider inset from the sides so that the first and last
# slider labels and the axis titles of the 3D scene are not cut at the page edge.
_HTML_MARGIN = dict(l=40, r=40, t=50, b=40)
_SCENE_DOMAIN = dict(x=[0.02, 0.98], y=[0.08, 1.0])
_SLIDER_PLACE = dict(x=0.06, len=0.88, xanchor="left", y=0.0, yanchor="top")


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
                                 zaxis_title="z (m)", domain=_SCENE_DOMAIN),
                      margin=_HTML_MARGIN)
    atomic_write_text(path, fig.to_html(include_plotlyjs=True, full_html=True))
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
    return dict(active=0, steps=steps, currentvalue=dict(prefix="frame "), pad=dict(t=30),
                **_SLIDER_PLACE)


# ----------------------------------------------------------------------------- scene frames


def _rgb(track) -> np.ndarray:
    """The overlay colour of ``track`` (:func:`seqshape.amodal.overlay.track_colour`) as RGB
    in [0, 1], for matplotlib."""
    b, g, r = track_colour(track)
    return np.array([r, g, b], dtype=np.float64) / 255.0


def _depth(ann: dict) -> float:
    """An annotation's ``depth`` (m), inf when absent or not a finite number."""
    d = ann.get("depth")
    ok = isinstance(d, (int, float)) and not isinstance(d, bool) and np.isfinite(d)
    return float(d) if ok else np.inf


def scene_instances(anns: list[dict], height: int, width: int
                    ) -> tuple[list[OverlayInstance], list[int | None]]:
    """The KINS annotations of one image as
    :class:`~seqshape.amodal.overlay.OverlayInstance` (``order``: rank of the annotation's ``depth``, 0 = nearest; annotations without a depth
    come last, in file order) and their ``track_id`` (None when absent)."""
    depth = [_depth(a) for a in anns]
    ranks = np.empty(len(anns), dtype=np.int64)
    ranks[np.argsort(depth, kind="stable")] = np.arange(len(anns))
    insts = []
    for a, r in zip(anns, ranks, strict=True):
        insts.append(OverlayInstance(str(a.get("track_id", "")),
                                     segm_to_mask(a["a_segm"], height, width),
                                     segm_to_mask(a["i_segm"], height, width), int(r)))
    return insts, [a.get("track_id") for a in anns]


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
        col = _rgb(tid)
        ax.plot(-ring[:, 1], ring[:, 0], "-", color=col, lw=1.2)
        front = (c[0] + c[3]) / 2
        ax.plot([-pose[1], -front[1]], [pose[0], front[0]], "-", color=col, lw=1.0)
        ax.text(-pose[1], pose[0], str(tid), fontsize=7, color="black", ha="center",
                va="center", clip_on=True,
                bbox={"facecolor": col, "alpha": 0.85, "pad": 1, "lw": 0})
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
    """Write the PNG figure of ``frame`` of ``sequence`` under ``root`` (``seqshape scenes``)
    to ``out``: :func:`scene_figure`."""
    import matplotlib.pyplot as plt  # heavy: plotting only

    fig = scene_figure(root, sequence, frame, extent)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(out, buf.getvalue())


def scene_figure(root: Path, sequence: str, frame: int, extent: float = 50.0):
    """The matplotlib figure of ``frame`` of ``sequence`` under ``root`` (``seqshape scenes``).

    Left: the rendered image drawn as the labeller's overlays
    (:func:`seqshape.amodal.overlay.draw_overlay`): every KINS instance's visible mask filled
    and its amodal outline drawn in its track's colour, tagged with its ``track_id``, and a
    legend under the image with each instance's depth rank (0 = nearest, from the annotation's
    ``depth``). Right: the LiDAR sweep from above (colour = height) with the label_02 boxes,
    each in the same colour and with the same track id as in the image, and the camera's field
    of view (``extent`` metres ahead).
    """
    import cv2  # heavy: only the scene figure needs OpenCV
    import matplotlib  # heavy: plotting only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # heavy: plotting only

    root = Path(root)
    seq = KittiTrackingSequence(root, sequence)
    if not seq.frames:
        raise DataError(root, f"no sequence {seq.sequence} here (found "
                              f"{KittiTrackingSequence.sequences(root)})")
    if frame not in seq.frames:
        raise DataError(seq.velodyne_path(frame), f"frame {frame} not in sequence {seq.sequence} "
                                                  f"(frames {seq.frames[:1]}..{seq.frames[-1:]})")
    img_path = seq.image_path(frame)
    if img_path.exists():  # a FIFO or a folder there: refused, not opened (cv2 would block)
        check_regular(img_path, "image", "image")
    image = cv2.imread(str(img_path), cv2.IMREAD_COLOR)
    if image is None:
        raise DataError(img_path, "missing or unreadable image")
    doc = read_kins(root / "amodal" / f"{seq.sequence}.json")
    image_id = next((im["id"] for im in doc["images"] if im.get("frame", im["id"]) == frame), None)
    anns = annotations_by_image(doc).get(image_id, [])
    boxes = [(_box_track(b.track_id), b.pose, b.size) for b in seq.boxes(frame)]
    insts, tracks = scene_instances(anns, *image.shape[:2])
    fig = plt.figure(figsize=(16, 5.2))
    ax_img = fig.add_axes([0.01, 0.05, 0.70, 0.9])
    ax_bev = fig.add_axes([0.75, 0.08, 0.23, 0.86])
    ax_img.imshow(draw_overlay(image, insts, tracks)[:, :, ::-1])  # BGR -> RGB
    ax_img.set_axis_off()
    ax_img.set_title(f"{root.name} sequence {seq.sequence} frame {frame}: visible masks filled, "
                     f"amodal outlines, tag = track id (legend below)", fontsize=9)
    _draw_scene_bev(ax_bev, seq.points(frame), boxes, seq.camera(), extent)
    ax_bev.set_title("LiDAR (grey: ground, colour: z) and label_02 boxes (track id)",
                     fontsize=9)
    return fig


def _box_track(track_id: str) -> int | str:
    """A label_02 track id as the KINS files store it (an integer when it is one)."""
    return int(track_id) if track_id.lstrip("-").isdigit() else track_id
