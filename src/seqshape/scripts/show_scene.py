"""``seqshape show-scene``: one frame with its amodal ground truth and a bird's-eye view.

The figure is :func:`seqshape.viz.draw_scene_frame` (its doc says what it shows).
"""

from __future__ import annotations

from pathlib import Path

from seqshape.viz import draw_scene_frame

HELP = "draw one frame of a scene with its amodal ground truth"


def add_arguments(p) -> None:
    p.add_argument("root", help="scene folder (KITTI tracking layout written by seqshape scenes)")
    p.add_argument("--sequence", default="0000", help="sequence name")
    p.add_argument("--frame", type=int, default=0, help="frame number")
    p.add_argument("--out", required=True, help="PNG file to write")
    p.add_argument("--range", type=float, default=50.0, help="bird's-eye extent ahead (m)")


def run(args) -> int:
    draw_scene_frame(Path(args.root), args.sequence, args.frame, Path(args.out), args.range)
    print(f"wrote {args.out}")
    return 0
