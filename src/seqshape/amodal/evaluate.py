"""Scoring amodal mask labels against a reference (the paper's Table II metrics).

Per image, predicted and reference amodal masks are matched one-to-one by the Hungarian
algorithm on their IoU (``scipy.optimize.linear_sum_assignment``, maximising total IoU). A
reference instance is a **miss** when it has no partner or its partner's IoU is below 0.5
(the paper: "instances that do not have a matching or IoU < 0.5"). Metrics over all reference
instances of all images:

* ``miss_pct``: 100 * misses / reference instances;
* ``miou``: mean IoU over matched instances (those with IoU >= 0.5), as the paper reports it;
* ``miou_with_misses``: mean IoU over all reference instances, misses counted as 0;
* ``unmatched_predictions``: predictions left without a partner with IoU >= 0.5 (false labels).

Each reference instance also carries its occlusion fraction ``1 - i_area / a_area`` and, when
known, its distance (m); the metrics are broken down by :data:`OCCLUSION_BINS` and
:data:`DISTANCE_BINS`.

:func:`write_mask_report` is ``seqshape evaluate-masks``: it scores label files paired by
:func:`resolve_pairs` and writes ``metrics.json``, ``instances.json`` and ``metrics.md``, whose
title says what the labels were compared with (:func:`reference_kind`: the exact ground truth
of a ``seqshape scenes`` folder, or a reference) and whose row is named after the prediction
files (:func:`default_row_name`) unless a name is given.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from seqshape._io import atomic_write_json, atomic_write_text
from seqshape.data.kins import annotation_mask, read_kins
from seqshape.data.kitti import read_labels
from seqshape.errors import ConfigError, DataError
from seqshape.sim.scene_writer import SCENE_FORMAT, SETTINGS_FILE

IOU_THRESHOLD = 0.5
#: occlusion fraction bins (label, low, high): low <= occ < high
OCCLUSION_BINS = (("none (<1%)", 0.0, 0.01), ("partly (1-30%)", 0.01, 0.30),
                  ("largely (30-70%)", 0.30, 0.70), ("heavily (>=70%)", 0.70, 1.01))
#: distance bins in metres
DISTANCE_BINS = (("0-15 m", 0.0, 15.0), ("15-30 m", 15.0, 30.0), ("30-50 m", 30.0, 50.0),
                 ("50-80 m", 50.0, 80.0), (">=80 m", 80.0, np.inf))


@dataclass
class InstanceResult:
    """The outcome for one reference instance."""

    image_id: int | str  # image id, or file name when read from files
    gt_index: int
    pred_index: int  # -1 when unmatched
    iou: float  # IoU with the matched prediction (0 when unmatched)
    occlusion: float  # 1 - visible / amodal area of the reference
    distance: float  # m, NaN when unknown
    track_id: str | None = None
    lidar_points: float = float("nan")  # LiDAR returns on the vehicle, NaN when unknown

    @property
    def missed(self) -> bool:
        return self.pred_index < 0 or self.iou < IOU_THRESHOLD


def mask_iou_matrix(pred: Sequence[np.ndarray], gt: Sequence[np.ndarray]) -> np.ndarray:
    """IoU of every prediction with every reference: ``(P, G)`` from P and G ``(h, w)`` masks."""
    if len(pred) == 0 or len(gt) == 0:
        return np.zeros((len(pred), len(gt)))
    p = np.stack([np.asarray(m, dtype=bool).ravel() for m in pred]).astype(np.float32)
    g = np.stack([np.asarray(m, dtype=bool).ravel() for m in gt]).astype(np.float32)
    inter = p @ g.T  # (P, G)
    union = p.sum(1)[:, None] + g.sum(1)[None, :] - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(union > 0, inter / union, 0.0)


def match_masks(pred: Sequence[np.ndarray], gt: Sequence[np.ndarray]
                ) -> tuple[np.ndarray, np.ndarray]:
    """Hungarian matching maximising total IoU.

    Returns ``(pred_of_gt (G,), iou_of_gt (G,))``: the index of the prediction matched to each
    reference (-1 when none) and their IoU (0 when none). Pairs with zero IoU are not matches.
    """
    iou = mask_iou_matrix(pred, gt)
    pred_of_gt = np.full(len(gt), -1, dtype=np.int64)
    iou_of_gt = np.zeros(len(gt))
    if iou.size == 0:
        return pred_of_gt, iou_of_gt
    rows, cols = linear_sum_assignment(-iou)
    for r, c in zip(rows, cols, strict=True):
        if iou[r, c] > 0:
            pred_of_gt[c], iou_of_gt[c] = r, iou[r, c]
    return pred_of_gt, iou_of_gt


def evaluate_image(image_id: int, pred: Sequence[np.ndarray], gt: Sequence[np.ndarray],
                   gt_visible_area: Sequence[float] | None = None,
                   gt_distance: Sequence[float] | None = None,
                   gt_track_ids: Sequence | None = None) -> tuple[list[InstanceResult], int]:
    """Score one image; returns the per-reference results and the count of unmatched predictions.

    A prediction is "unmatched" when it is not the partner (IoU >= 0.5) of any reference.
    """
    pred_of_gt, iou_of_gt = match_masks(pred, gt)
    out = []
    for g, m in enumerate(gt):
        area = float(np.asarray(m, dtype=bool).sum())
        vis = area if gt_visible_area is None else float(gt_visible_area[g])
        occ = float(np.clip(1.0 - vis / area, 0.0, 1.0)) if area > 0 else 0.0
        dist = float("nan") if gt_distance is None else float(gt_distance[g])
        tid = None if gt_track_ids is None or gt_track_ids[g] is None else str(gt_track_ids[g])
        out.append(InstanceResult(int(image_id), g, int(pred_of_gt[g]), float(iou_of_gt[g]),
                                  occ, dist, tid))
    good = {r.pred_index for r in out if not r.missed}
    return out, len(pred) - len(good)


def summarise(results: Sequence[InstanceResult], unmatched_predictions: int = 0) -> dict:
    """``{"n", "misses", "miss_pct", "miou", "miou_with_misses", "unmatched_predictions"}``."""
    n = len(results)
    ious = np.array([r.iou for r in results], dtype=np.float64)
    missed = np.array([r.missed for r in results], dtype=bool)
    matched = ious[~missed]
    return {"n": n, "misses": int(missed.sum()),
            "miss_pct": float(100.0 * missed.mean()) if n else float("nan"),
            "miou": float(matched.mean()) if matched.size else float("nan"),
            "miou_with_misses": float(np.where(missed, 0.0, ious).mean()) if n else float("nan"),
            "unmatched_predictions": int(unmatched_predictions)}


def within_distance(results: Sequence[InstanceResult], max_distance: float
                    ) -> list[InstanceResult]:
    """The results of reference instances at most ``max_distance`` metres away.

    Instances of unknown distance (NaN) are left out. The matching that produced ``results``
    used every instance, so a far vehicle's prediction never steals a near one's match.
    """
    return [r for r in results if np.isfinite(r.distance) and r.distance <= max_distance]


def breakdown(results: Sequence[InstanceResult]) -> dict[str, dict[str, dict]]:
    """Metrics per occlusion bin and per distance bin (only bins with instances)."""
    out: dict[str, dict[str, dict]] = {"occlusion": {}, "distance": {}}
    for key, bins, attr in (("occlusion", OCCLUSION_BINS, "occlusion"),
                            ("distance", DISTANCE_BINS, "distance")):
        for label, lo, hi in bins:
            sel = [r for r in results if lo <= getattr(r, attr) < hi]
            if sel:
                out[key][label] = summarise(sel)
        if key == "distance":
            unknown = [r for r in results if not np.isfinite(r.distance)]
            if unknown:
                out[key]["unknown"] = summarise(unknown)
    return out


def results_to_records(results: Sequence[InstanceResult]) -> list[dict]:
    """Plain dicts (JSON-ready) of the per-instance results."""
    return [{**asdict(r), "missed": r.missed} for r in results]


def markdown_table(rows: dict[str, dict], title: str = "Amodal masks against the reference"
                   ) -> str:
    """A Table II-style markdown table: one row per method/label set, % miss and mIoU columns."""
    lines = [f"**{title}**", "",
             "| Method | Instances | % Miss | mIoU | mIoU (misses = 0) | Unmatched preds |",
             "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for name, m in rows.items():
        lines.append(f"| {name} | {m['n']} | {m['miss_pct']:.2f} | {m['miou']:.3f} | "
                     f"{m['miou_with_misses']:.3f} | {m['unmatched_predictions']} |")
    return "\n".join(lines) + "\n"


def breakdown_table(bd: dict[str, dict[str, dict]]) -> str:
    """Markdown tables of :func:`breakdown`."""
    parts = []
    for key, rows in bd.items():
        if not rows:
            continue
        parts.append(f"| {key} | Instances | % Miss | mIoU | mIoU (misses = 0) |")
        parts.append("| --- | ---: | ---: | ---: | ---: |")
        for label, m in rows.items():
            parts.append(f"| {label} | {m['n']} | {m['miss_pct']:.2f} | {m['miou']:.3f} | "
                         f"{m['miou_with_misses']:.3f} |")
        parts.append("")
    return "\n".join(parts)


# ----------------------------------------------------------------------------- files


def distances_from_labels(gt_path) -> dict[tuple[int, str], float]:
    """``{(frame, track_id): distance}`` from ``<root>/label_02/SSSS.txt`` beside ``amodal/``.

    The distance is the planar range (m) of the box centre in the velodyne frame. Empty when
    the label file does not exist.
    """
    gt_path = Path(gt_path)
    label_path = gt_path.parent.parent / "label_02" / f"{gt_path.stem}.txt"
    if not label_path.is_file():
        return {}

    out = {}
    for lab in read_labels(label_path):
        out[(int(lab.frame), str(lab.track_id))] = _label_range(lab)
    return out


def _label_range(lab) -> float:
    """Planar distance (m) of a KITTI label's box from the camera (its x, z location)."""
    loc = np.asarray(lab.location, dtype=np.float64)
    return float(np.hypot(loc[0], loc[2]))


def evaluate_files(pairs: Sequence[tuple], category_ids: Sequence[int] | None = None,
                   segm: str = "a_segm") -> tuple[list[InstanceResult], int]:
    """Score KINS label files ``[(pred_path, gt_path), ...]`` (images matched by file name;
    segmentations RLE or polygons).

    Reference images missing from the prediction count every instance as missed. Distances come
    from an annotation's ``distance`` key when present, else from the KITTI ``label_02`` file of
    the reference's sequence (matched by ``track_id``), else NaN. ``category_ids`` restricts both
    sides to those categories (default: all). ``segm="i_segm"`` scores the visible masks instead
    of the amodal ones (same matching rule).
    """
    if segm not in ("a_segm", "i_segm"):
        raise ValueError(f"segm must be 'a_segm' or 'i_segm', got {segm!r}")

    results: list[InstanceResult] = []
    unmatched = 0
    for pred_path, gt_path in pairs:
        pred_doc, gt_doc = read_kins(pred_path), read_kins(gt_path)
        _check_image_sizes(pred_doc, gt_doc, pred_path, gt_path)
        dists = distances_from_labels(gt_path)

        def keep(a):
            return category_ids is None or a["category_id"] in category_ids

        pred_by_name = {img["file_name"]: [] for img in pred_doc["images"]}
        pid_to_img = {img["id"]: img for img in pred_doc["images"]}
        for a in pred_doc["annotations"]:
            if keep(a):
                img = pid_to_img[a["image_id"]]
                pred_by_name[img["file_name"]].append((a, img))
        gt_anns: dict[int, list[dict]] = {img["id"]: [] for img in gt_doc["images"]}
        for a in gt_doc["annotations"]:
            if keep(a):
                gt_anns[a["image_id"]].append(a)
        for img in gt_doc["images"]:
            anns = gt_anns[img["id"]]
            preds = pred_by_name.get(img["file_name"], [])
            frame = int(img.get("frame", -1))
            dist = [a.get("distance", dists.get((frame, str(a.get("track_id"))), np.nan))
                    for a in anns]
            res, un = evaluate_image(
                img["id"], [annotation_mask(a, segm, pimg) for a, pimg in preds],
                [annotation_mask(a, segm, img) for a in anns],
                [a["i_area"] for a in anns] if segm == "a_segm" else None, dist,
                [a.get("track_id") for a in anns])
            for r, a in zip(res, anns, strict=True):
                r.image_id = img["file_name"]
                r.lidar_points = float(a.get("lidar_points", np.nan))
            results.extend(res)
            unmatched += un
    return results, unmatched


def _check_image_sizes(pred_doc: dict, gt_doc: dict, pred_path, gt_path) -> None:
    """:class:`DataError` when an image (matched by ``file_name``) has another size in the
    prediction than in the reference: masks of different sizes cannot be compared."""
    gt_size = {img["file_name"]: (int(img["width"]), int(img["height"]))
               for img in gt_doc["images"]}
    for img in pred_doc["images"]:
        ref = gt_size.get(img["file_name"])
        size = (int(img["width"]), int(img["height"]))
        if ref is not None and ref != size:
            raise DataError(pred_path, f"image {img['file_name']!r} is {size[0]}x{size[1]} "
                                       f"(width x height) here but {ref[0]}x{ref[1]} in the "
                                       f"reference {gt_path}: predictions and reference must "
                                       "be of the same images")


# ----------------------------------------------------------------------------- report


def reference_kind(gts: Sequence[Path]) -> str:
    """``"exact ground truth"`` when every reference file is ``ROOT/amodal/SSSS.json`` of a
    ``seqshape scenes`` folder (``ROOT/scene.json`` of format ``seqshape-scenes``: its masks
    are rendered, exact), else ``"the reference"``."""
    def is_scenes(gt: Path) -> bool:
        settings = Path(gt).parent.parent / SETTINGS_FILE
        try:
            doc = json.loads(settings.read_text(encoding="utf-8"))
        except (OSError, ValueError):  # no settings file, unreadable or not JSON
            return False
        return Path(gt).parent.name == "amodal" and isinstance(doc, dict) and \
            doc.get("format") == SCENE_FORMAT

    return "exact ground truth" if gts and all(is_scenes(g) for g in gts) else "the reference"


def default_row_name(preds: Sequence[Path]) -> str:
    """The table row of the predictions ``preds`` (files or folders): the name of one file,
    or of one folder (``labels/``); the folder's name for files of one folder; else the names
    joined by ``+``."""
    preds = list(dict.fromkeys(Path(p) for p in preds))
    if len(preds) == 1:
        return preds[0].name + ("/" if preds[0].is_dir() else "")
    parents = {p.parent for p in preds}
    if len(parents) == 1:
        return f"{parents.pop().name}/"
    return " + ".join(p.name for p in preds)


def resolve_pairs(preds: Sequence[Path], gts: Sequence[Path]) -> list[tuple[Path, Path]]:
    """Pair prediction and reference files; directories pair their ``*.json`` by file name.

    ``preds[i]`` goes with ``gts[i]``: two files, or two directories (every reference
    ``*.json`` needs a prediction of the same name). :class:`ConfigError` (naming the
    ``--pred``/``--gt`` options of ``seqshape evaluate-masks``) on a count mismatch, a file
    paired with a directory, or a missing file.
    """
    if len(preds) != len(gts):
        raise ConfigError(f"{len(preds)} --pred but {len(gts)} --gt: give them in pairs")
    pairs = []
    for p, g in zip(preds, gts, strict=True):
        if p.is_dir() != g.is_dir():
            raise ConfigError(f"--pred {p} and --gt {g}: pair a file with a file, or a "
                              "directory with a directory")
        if not p.is_dir():
            for f in (p, g):
                if not f.is_file():
                    raise ConfigError(f"{f}: no such file")
            pairs.append((p, g))
            continue
        gt_files = sorted(g.glob("*.json"))
        if not gt_files:
            raise ConfigError(f"{g}: no *.json reference files")
        for gf in gt_files:
            pf = p / gf.name
            if not pf.is_file():
                raise ConfigError(f"{pf}: missing prediction for reference {gf}")
            pairs.append((pf, gf))
    return pairs


def write_mask_report(pairs: Sequence[tuple[Path, Path]], out: str | Path,
                      name: str | None = None, categories: Sequence[int] | None = None,
                      max_distance: float | None = None) -> str:
    """Score ``pairs`` (:func:`evaluate_files`) and write the report under ``out``.

    ``out/metrics.json``: :func:`summarise` of every reference instance, ``breakdown``
    (:func:`breakdown`), ``iou_threshold`` and ``pairs``; with ``max_distance`` (m, > 0) also
    ``within_max_distance``, the metrics over the reference instances at most that far
    (:func:`within_distance`; the matching still uses every instance).
    ``out/instances.json``: :func:`results_to_records`. ``out/metrics.md``: the markdown
    tables, also returned: titled "Amodal masks against exact ground truth" or "... against
    the reference" (:func:`reference_kind`), a row ``name`` (default
    :func:`default_row_name` of the prediction files) and ``name (<= M m)`` with
    ``max_distance``, a line under the table naming the files compared, the breakdowns.
    ``categories`` restricts the scoring to those category ids (default: all).
    """
    if max_distance is not None and not max_distance > 0:
        raise ConfigError(f"--max-distance must be > 0, got {max_distance}")
    out = Path(out)
    name = name or default_row_name([p for p, _ in pairs])
    results, unmatched = evaluate_files(pairs, categories)
    metrics = summarise(results, unmatched)
    bd = breakdown(results)
    rows = {name: metrics}
    extra = {}
    if max_distance is not None:
        near = within_distance(results, max_distance)
        extra["within_max_distance"] = {**summarise(near), "max_distance_m": max_distance}
        rows[f"{name} (<= {max_distance:g} m)"] = extra["within_max_distance"]
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "metrics.json",
                      {**metrics, **extra, "breakdown": bd, "iou_threshold": IOU_THRESHOLD,
                       "pairs": [[str(p), str(g)] for p, g in pairs]})
    atomic_write_json(out / "instances.json", results_to_records(results), indent=None)
    table = (markdown_table(rows, title=f"Amodal masks against {_kind(pairs)}")
             + "\n" + _compared(pairs) + "\n" + breakdown_table(bd))
    atomic_write_text(out / "metrics.md", table)
    return table


def _kind(pairs: Sequence[tuple[Path, Path]]) -> str:
    """What the predictions of ``pairs`` were compared with, for the title."""
    return reference_kind([Path(g) for _, g in pairs])


def _compared(pairs: Sequence[tuple[Path, Path]]) -> str:
    """A line naming the files compared (the first three pairs, then a count)."""
    shown = [f"`{p}` against `{g}`" for p, g in pairs[:3]]
    more = f" and {len(pairs) - 3} more pairs" if len(pairs) > 3 else ""
    return "Compared: " + "; ".join(shown) + more + ".\n"
