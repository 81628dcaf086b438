"""How well the 2D instance masks of a scene set fit the exact amodal masks of the reference
cars without LiDAR returns: the best IoU of a raw mask and of its convex hull (the mask-only
labels of sc-seg, docs/amodal.md). No timing; not part of ``make bench``.

Run: ``python benchmarks/analyse_masks.py SCENES OUT/reference/amodal``, where OUT is a
``bm_labelling.py --out`` folder: its reference copy is cut to the benchmark's frames and
gives each instance its ``lidar_points``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from _bench import print_table

from seqshape.amodal.fallback import convex_fill
from seqshape.data.kins import read_coco_instances, read_kins, rle_to_mask


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", type=Path, help="scene set (its instances_2d/)")
    ap.add_argument("reference", type=Path, help="bm_labelling's OUT/reference/amodal")
    args = ap.parse_args()
    raw, hull = [], []
    for path in sorted(args.reference.glob("*.json")):
        ref = read_kins(path)
        ins = read_coco_instances(args.scenes / "instances_2d" / path.name)
        names = {im["id"]: im["file_name"] for im in ins["images"]}
        by_name: dict[str, list[np.ndarray]] = {}
        for a in ins["annotations"]:
            by_name.setdefault(names[a["image_id"]], []).append(rle_to_mask(a["segmentation"]))
        for im in ref["images"]:
            for a in ref["annotations"]:
                if a["image_id"] != im["id"] or a.get("lidar_points", 1) > 0:
                    continue
                gt = rle_to_mask(a["a_segm"])
                masks = by_name.get(im["file_name"], [])
                raw.append(max((_iou(m, gt) for m in masks), default=0.0))
                hull.append(max((_iou(convex_fill(m), gt) for m in masks), default=0.0))
    raw_a, hull_a = np.array(raw), np.array(hull)
    print(f"{len(raw_a)} reference instances without LiDAR returns")
    print_table(["2D mask", "IoU >= 0.5 (count)", "median IoU", "mean IoU"],
                [[name, str(int((v >= 0.5).sum())), f"{np.median(v):.3f}", f"{v.mean():.3f}"]
                 for name, v in (("raw", raw_a), ("convex hull", hull_a))])


if __name__ == "__main__":
    main()
