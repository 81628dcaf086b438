"""An offline interactive 3D view (plotly, ``include_plotlyjs=True``) of one track over time.

A slider (and a play button) steps through the frames from the first to the last detection.
Each frame shows the partial LiDAR points, the ground-truth complete shape and box, and per
method the estimated complete shape and its box. Coordinates are the frame's sensor axes
(x forward, y left, z up) shifted so that the true box centre is at the origin (the vehicle
stays in view while it moves). An estimated box is drawn at the estimated pose, its length,
width and height the extent of the estimated shape seen in that pose's canonical frame.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from seqshape._io import atomic_write_text
from seqshape.data import Track
from seqshape.errors import require
from seqshape.evaluation.metrics import subsample
from seqshape.evaluation.runner import EstimatorLike, predict_track
from seqshape.geometry import box_corners, sensor_to_canonical

COLORS = {"sequential": "#1f77b4", "baseline": "#ff7f0e", "boxfit": "#9467bd"}
#: Share of the page width on the left of the frame slider kept for the play and pause buttons
#: (stacked): 0.1 of a page 700 px wide is 70 px, wider than the "pause" button.
PLAYER_WIDTH = 0.1
_EDGES = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4),
          (0, 4), (1, 5), (2, 6), (3, 7)]


def _box_lines(corners: np.ndarray) -> np.ndarray:
    """Polyline ``(36, 3)`` of a box's 12 edges separated by NaN gaps."""
    out = []
    for a, b in _EDGES:
        out += [corners[a], corners[b], [np.nan] * 3]
    return np.array(out)


def estimated_box(complete: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Corners ``(8, 3)`` (sensor frame) of the box at ``pose`` sized by the shape's extent."""
    local = sensor_to_canonical(np.asarray(complete, np.float64), pose)
    size = local.max(0) - local.min(0) if len(local) else np.zeros(3)
    return box_corners(size, pose)


def _scatter(go, pts: np.ndarray, name: str, color: str, size: float, opacity: float = 1.0):
    pts = np.round(np.asarray(pts, dtype=np.float64).reshape(-1, 3), 3)
    return go.Scatter3d(x=pts[:, 0], y=pts[:, 1], z=pts[:, 2], mode="markers", name=name,
                        marker=dict(size=size, color=color, opacity=opacity))


def _lines(go, pts: np.ndarray, name: str, color: str):
    pts = np.round(pts, 3)
    return go.Scatter3d(x=pts[:, 0], y=pts[:, 1], z=pts[:, 2], mode="lines", name=name,
                        line=dict(color=color, width=4))


def _frame_traces(go, track: Track, t: int, ests: Mapping, max_points: int) -> list:
    pose = track.poses[t]
    if not np.all(np.isfinite(pose)):  # unknown truth: centre on the first method's estimate
        pose = next(iter(ests.values())).pose
    centre = np.asarray(pose[:3])
    traces = [_scatter(go, track.points[t] - centre, f"LiDAR points ({len(track.points[t])})",
                       "black", 3)]
    if track.complete is not None and np.all(np.isfinite(track.poses[t])):
        gt = subsample(track.complete_in_frame(t), min(max_points, len(track.complete)), seed=0)
        ref = track.meta.get("reference")
        label = ("accumulated reference" if isinstance(ref, dict)
                 and ref.get("kind") == "accumulated" else "ground truth shape")
        traces += [_scatter(go, gt - centre, label, "#7f7f7f", 1.5, 0.35),
                   _lines(go, _box_lines(box_corners(track.size, track.poses[t]) - centre),
                          "ground truth box", "#2ca02c")]
    else:
        traces += [_scatter(go, np.zeros((0, 3)), "ground truth shape", "#7f7f7f", 1.5),
                   _lines(go, np.zeros((0, 3)), "ground truth box", "#2ca02c")]
    for i, (name, e) in enumerate(ests.items()):
        color = COLORS.get(name, ["#d62728", "#9467bd", "#8c564b"][i % 3])
        shape = np.asarray(e.complete)
        shape = subsample(shape, min(max_points, len(shape)), seed=1)
        traces += [_scatter(go, shape - centre, f"{name} shape", color, 2, 0.8),
                   _lines(go, _box_lines(estimated_box(e.complete, e.pose)) - centre,
                          f"{name} box", color)]
    return traces


def track_figure(track: Track, predictions: Mapping[str, tuple[range, list]],
                 max_frames: int = 100, max_points: int = 768):
    """A plotly figure with one animation frame per (strided) track frame.

    ``predictions``: method -> ``(frames, estimates)`` as returned by
    :func:`~seqshape.evaluation.runner.predict_track` (all methods over the same frames).
    """
    go = require("plotly.graph_objects", "the HTML track view", "plotly")
    frames, _ = next(iter(predictions.values()))
    stride = max(1, int(np.ceil(len(frames) / max_frames)))
    chosen = list(range(0, len(frames), stride))
    figs = []
    for i in chosen:
        t = frames[i]
        ests = {m: p[1][i] for m, p in predictions.items()}
        figs.append(go.Frame(data=_frame_traces(go, track, t, ests, max_points), name=str(t)))
    half = float(np.max(track.size)) / 2 + 0.8
    axis = dict(range=[-half, half], autorange=False)
    steps = [dict(method="animate", label=f.name,
                  args=[[f.name], dict(mode="immediate", frame=dict(duration=0, redraw=True),
                                       transition=dict(duration=0))]) for f in figs]
    fig = go.Figure(data=figs[0].data, frames=figs)
    fig.update_layout(
        title=f"track {track.track_id}: frames {frames[0]}-{frames[-1]} "
              f"(sensor axes, origin at the true box centre)",
        scene=dict(xaxis=dict(title="x (m)", **axis), yaxis=dict(title="y (m)", **axis),
                   zaxis=dict(title="z (m)", **axis), aspectmode="cube"),
        sliders=[dict(active=0, currentvalue=dict(prefix="frame "), steps=steps,
                      x=PLAYER_WIDTH, len=1.0 - PLAYER_WIDTH, xanchor="left", y=0.0,
                      yanchor="top", pad=dict(t=30, b=10))],
        updatemenus=[dict(type="buttons", showactive=False, direction="down", x=0.0,
                          xanchor="left", y=0.0, yanchor="top", pad=dict(t=30, r=10), buttons=[
            dict(label="play", method="animate",
                 args=[None, dict(frame=dict(duration=150, redraw=True), fromcurrent=True)]),
            dict(label="pause", method="animate",
                 args=[[None], dict(mode="immediate", frame=dict(duration=0, redraw=False))]),
        ])],
        legend=dict(itemsizing="constant"), margin=dict(l=10, r=10, t=40, b=90), height=760)
    return fig


def write_track_html(path: str | Path, track: Track,
                     estimators: Mapping[str, EstimatorLike], max_frames: int = 100,
                     max_points: int = 768) -> Path:
    """Run each estimator over ``track`` and write the standalone HTML view to ``path``."""
    predictions = {name: predict_track(est, track) for name, est in estimators.items()}
    fig = track_figure(track, predictions, max_frames, max_points)
    path = Path(path)
    atomic_write_text(path, fig.to_html(include_plotlyjs=True, full_html=True,
                                        auto_play=False))
    return path
