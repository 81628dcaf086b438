"""``seqshape show-scene``: one frame with its amodal ground truth and a bird's-eye view.

Left: the rendered image with every KINS instance's visible mask filled, its amodal outline
drawn, and ``cluster.order`` (KINS ``oco_id.ico_id``; order 1 is the front of its cluster,
``0.0`` an instance that overlaps no other) written on it. Right: the LiDAR sweep from above (colour = height) with the label_02 boxes and
track ids, and the camera's field of view.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

HELP = "draw one frame of a scene with its amodal ground truth"


def add_arguments(p) -> None:
    p.add_argument("root", help="scene folder (KITTI tracking layout written by seqshape scenes)")
    p.add_argument("--sequence", default="0000", help="sequence name, e.g. 0000")
    p.add_argument("--frame", type=int, default=0)
    p.add_argument("--out", required=True, help="PNG file to write")
    p.add_argument("--range", type=float, default=50.0, help="bird's-eye extent ahead (m)")


def _palette(i: int) -> np.ndarray:
    import matplotlib

    return np.asarray(matplotlib.colormaps["tab20"](i % 20)[:3])


def _draw_image(ax, image: np.ndarray, anns: list[dict]) -> None:
    import cv2

    from seqshape.amodal.kins import segm_to_mask

    img = image.astype(np.float64) / 255.0
    h, w = image.shape[:2]
    outlines = []
    for ann in anns:
        c = _palette(int(ann.get("track_id", 0)))
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


def _draw_bev(ax, points: np.ndarray, boxes, camera, extent: float) -> None:
    from seqshape.geometry import box_corners

    sel = (points[:, 0] > -10) & (points[:, 0] < extent) & (np.abs(points[:, 1]) < extent * 0.6)
    p = points[sel]
    low = p[:, 2] < np.quantile(p[:, 2], 0.02) + 0.15 if len(p) else np.zeros(0, bool)
    ax.scatter(-p[low, 1], p[low, 0], c="0.75", s=0.1, linewidths=0)
    ax.scatter(-p[~low, 1], p[~low, 0], c=p[~low, 2], s=1.0, cmap="viridis", vmin=-1.8,
               vmax=0.5, linewidths=0)
    for tid, pose, size in boxes:
        c = box_corners(size, pose)[:4]
        ring = np.r_[c, c[:1]]
        col = _palette(tid)
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
    """Write the figure (see the module doc) of ``frame`` of ``sequence`` under ``root``."""
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from seqshape._io import atomic_write_bytes
    from seqshape.amodal.kins import annotations_by_image, read_kins
    from seqshape.data.kitti import KittiTrackingSequence
    from seqshape.errors import DataError

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
    _draw_image(ax_img, image[:, :, ::-1], anns)
    ax_img.set_title(f"{root.name} sequence {seq.sequence} frame {frame}: visible masks filled, "
                     f"amodal outlines, occlusion cluster.order", fontsize=9)
    _draw_bev(ax_bev, seq.points(frame), boxes, seq.camera(), extent)
    ax_bev.set_title("LiDAR (grey: ground, colour: z) and label_02 boxes", fontsize=9)
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(out, buf.getvalue())


def run(args) -> int:
    draw_scene_frame(Path(args.root), args.sequence, args.frame, Path(args.out), args.range)
    print(f"wrote {args.out}")
    return 0
