"""Fusion ablations: what the recurrent model takes from a track's past frames (issue 19).

Every row runs the project's own evaluation (:func:`seqshape.evaluation.evaluate_tracks`) on
the val split, the networks fed the points alone (``hints=False``: no heading step, so every
row is the network itself), one method per call:

* ``baseline``: the per-frame model; ``sequential``: the recurrent model as shipped;
* ``seq, heading step``: the sequential model told the (identity) ego poses, so that its
  heading post-processing runs, as ``seqshape evaluate`` does by default (only the yaw moves);
* ``seq, state reset``: the recurrent model with its state dropped before every frame
  (:class:`ResetEachFrame`): the GRU's contribution is what it loses here;
* ``seq, shuffled``: the frames with points permuted within each track (points, poses and
  timestamps together, empty frames left in place), each frame scored against its own truth
  (:class:`ShuffledTracks`): what the order of the frames is worth;
* ``oracle -> baseline`` and ``oracle -> seq, reset``: the input at frame t is every point of
  frames <= t moved into frame t with the TRUE poses (sensor t <- canonical <- sensor s),
  a uniform random subset of the model's ``num_points`` of them, as the model would draw
  (:class:`OracleTracks`): a perfect track memory, the bound on what fusion could give.

Printed: CD, CD of the shape alone at the true pose, translation, rotation, flips (% of
frames, % of tracks with one), the error at 17+ detections over the first's, and CD and
translation by detections so far (``seqshape.evaluation.report.DETECTION_BINS``) for moving
and parked tracks (``report.motion_groups``). EMD is off unless ``--emd-every K``.

    python benchmarks/bm_fusion.py --data /work/data/paper            # all 165 val tracks
    python benchmarks/bm_fusion.py --data DATA --limit 20             # quick look
    python benchmarks/bm_fusion.py --data DATA --checkpoint RUN/model.pt --baseline B/model.pt

No timing: the quantity measured is accuracy. ``--json PATH`` keeps the numbers.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from inspect import signature
from pathlib import Path

import numpy as np
from _bench import print_table

from seqshape._io import atomic_write_json
from seqshape.data import Track, TrackDataset
from seqshape.errors import ConfigError
from seqshape.evaluation import detection_span, evaluate_tracks
from seqshape.evaluation.metrics import flip_stats
from seqshape.evaluation.report import (
    DETECTION_LABELS,
    FLIP_DEG,
    detection_summary,
    floor_summary,
    method_summary,
)
from seqshape.geometry import canonical_to_sensor, sensor_to_canonical
from seqshape.model.estimator import Estimator

#: Row keys (``--rows``) and their names in the tables.
ROWS = {"baseline": "baseline", "sequential": "sequential", "heading": "seq, heading step",
        "reset": "seq, state reset", "shuffled": "seq, shuffled",
        "oracle-baseline": "oracle -> baseline", "oracle-reset": "oracle -> seq, reset"}


class ResetEachFrame:
    """An estimator whose inner estimator's state is dropped before every step: a recurrent
    model run as a per-frame one."""

    recurrent = False

    def __init__(self, inner):
        self.inner = inner

    def step(self, track_ids: Sequence[str], point_lists: Sequence[np.ndarray],
             timestamps: Sequence[float] | None = None, **hints):
        for t in track_ids:
            self.inner.reset(t)
        # the runner passes timestamps to a ``step`` that names them; forward them if the
        # inner estimator takes them too (a model with motion inputs)
        if timestamps is not None and "timestamps" in signature(self.inner.step).parameters:
            hints["timestamps"] = timestamps
        return self.inner.step(track_ids, point_lists, **hints)

    def reset(self, track_id: str | None = None) -> None:
        self.inner.reset(track_id)


def shuffle_track(track: Track, rng: np.random.Generator) -> tuple[Track, np.ndarray]:
    """``track`` with its frames that hold points permuted among themselves (points, poses,
    timestamps together; empty frames keep their place, so the scored span is unchanged).
    Returns the track and ``order`` (T,): new frame i holds old frame ``order[i]``."""
    order = np.arange(len(track))
    det = np.flatnonzero(track.num_points > 0)
    order[det] = rng.permutation(det)
    return Track(track.track_id, [track.points[i] for i in order], track.poses[order],
                 track.complete, track.size, track.timestamps[order], dict(track.meta)), order


def accumulate_track(track: Track, num_points: int, rng: np.random.Generator) -> Track:
    """The oracle input (module doc): frame t holds a uniform random subset of at most
    ``num_points`` of the points of frames <= t, moved into frame t with the true poses.

    Frames after the last detection stay empty (the scored span is the original one), frames
    with an unknown pose neither give nor receive points (they keep their own points).
    """
    span = detection_span(track)
    known = np.all(np.isfinite(track.poses), axis=1)
    canon = [sensor_to_canonical(p, track.poses[t]) if known[t] else np.zeros((0, 3))
             for t, p in enumerate(track.points)]
    pool = np.concatenate(canon).astype(np.float64)  # (sum N_t, 3), in frame order
    ends = np.cumsum([len(c) for c in canon])  # (T,) points of frames <= t
    points = []
    for t in range(len(track)):
        if span is None or t >= span[1] or not known[t] or ends[t] == 0:
            points.append(track.points[t] if span is None or t < span[1] else np.zeros((0, 3)))
            continue
        idx = rng.choice(ends[t], size=min(num_points, ends[t]), replace=False)
        points.append(canonical_to_sensor(pool[np.sort(idx)], track.poses[t]).astype(np.float32))
    return Track(track.track_id, points, track.poses, track.complete, track.size,
                 track.timestamps, dict(track.meta))


def restore_counts(rec: dict[str, np.ndarray], tracks: list[Track]) -> None:
    """Set ``n_det`` and ``n_points`` of oracle records to the original tracks' (the oracle
    frames all hold points, so the runner counts every frame as a detection)."""
    by_id = {tr.track_id: tr for tr in tracks}
    n_det = {tid: np.cumsum(tr.num_points > 0) for tid, tr in by_id.items()}
    for i, (tid, f) in enumerate(zip(rec["track_id"], rec["frame"], strict=True)):
        rec["n_det"][i] = n_det[tid][f]
        rec["n_points"][i] = by_id[tid].num_points[f]


def run_rows(tracks: list[Track], seq, base, rows: Sequence[str], emd_every: int,
             workers: int, seed: int) -> dict[str, dict]:
    """Evaluate each row of :data:`ROWS` whose key is in ``rows``; ``{row name: {"rec",
    "floor_cm", "seconds"}}``."""
    out = {}
    for key in rows:
        name = ROWS[key]
        est, hints = {"baseline": (base, False), "sequential": (seq, False),
                      "heading": (seq, True), "reset": (ResetEachFrame(seq), False),
                      "shuffled": (seq, False), "oracle-baseline": (base, False),
                      "oracle-reset": (ResetEachFrame(seq), False)}[key]
        data = tracks
        if key == "shuffled":
            data = [shuffle_track(tr, np.random.default_rng([seed, i]))[0]
                    for i, tr in enumerate(tracks)]
        elif key.startswith("oracle"):
            k = (base if key == "oracle-baseline" else seq).config.num_points
            data = [accumulate_track(tr, k, np.random.default_rng([seed, i]))
                    for i, tr in enumerate(tracks)]
        t0 = time.perf_counter()
        res = evaluate_tracks({name: est}, data, emd_every=emd_every, workers=workers,
                              hints=hints, seed=seed)
        rec = res.of(name)
        if key.startswith("oracle"):
            restore_counts(rec, tracks)
        out[name] = {"rec": rec, "floor_cm": floor_summary(res, name)["cd_floor_cm"],
                     "seconds": time.perf_counter() - t0}
        print(f"{name}: {len(rec['frame'])} frames in {out[name]['seconds']:.0f} s",
              file=sys.stderr, flush=True)
    return out


def _f(v, digits: int = 2) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


def summarise(results: dict[str, dict]) -> dict[str, dict]:
    """Per row: the report's method summary, flips, detection groups and the share of frames
    whose rotation error lies between 90 degrees and the flip threshold."""
    out = {}
    for name, r in results.items():
        rec = r["rec"]
        table, details = method_summary(rec)
        by_det, ratios = detection_summary(rec)
        rot = np.degrees(rec["rot_rad"][np.isfinite(rec["rot_rad"])])
        out[name] = {**table, "shape_cd_cm": details.get("shape_cd_cm"),
                     "flips": flip_stats(rec["rot_rad"], rec["track_id"], FLIP_DEG),
                     "wrong_way_pct": float(100 * (rot > 90.0).mean()) if len(rot) else None,
                     "by_detections": by_det, "late_over_first": ratios,
                     "floor_cm": r["floor_cm"], "n_frames": int(len(rec["frame"])),
                     "n_tracks": int(len(np.unique(rec["track_id"]))),
                     "seconds": r["seconds"]}
    return out


def print_tables(summary: dict[str, dict]) -> None:
    head = ["row", "CD (cm)", "shape CD (cm)", "transl. (cm)", "rot. (deg)",
            f"flips > {FLIP_DEG:.0f} deg (%)", "> 90 deg (%)", "tracks with a flip (%)",
            "CD 17+/1", "transl. 17+/1"]
    rows = []
    for name, s in summary.items():
        f, r = s["flips"], s["late_over_first"].get("all", {})
        rows.append([name, _f(s["cd_cm"]), _f(s["shape_cd_cm"]), _f(s["trans_cm"]),
                     _f(s["rot_deg"]), _f(f["flip_pct"], 1), _f(s["wrong_way_pct"], 1),
                     _f(f["tracks_with_flip_pct"], 1), _f(r.get("cd")), _f(r.get("trans"))])
    print_table(head, rows)
    first = next(iter(summary.values()))
    print(f"\nAll frames, {first['n_tracks']} tracks, {first['n_frames']} frames per row; "
          f"CD floor {_f(first['floor_cm'])} cm.\n")
    labels = DETECTION_LABELS
    groups = [g for g in ("moving", "parked") if g in first["by_detections"]] or ["all"]
    for g in groups:
        per = first["by_detections"][g]
        rows = [["frames", *[str(per.get(lab, {}).get("n_frames", 0)) for lab in labels],
                 "", ""]]
        for name, s in summary.items():
            per = s["by_detections"].get(g, {})
            r = s["late_over_first"].get(g, {})
            rows.append([name, *[_f(per.get(lab, {}).get("cd_cm")) for lab in labels],
                         _f(r.get("cd")), ""])
            rows.append(["", *[_f(per.get(lab, {}).get("trans_cm")) for lab in labels],
                         "", _f(r.get("trans"))])
        print(f"{g} tracks: CD (first line) and translation (second line, cm) by detections "
              f"so far")
        print_table([f"{g}", *labels, "CD 17+/1", "transl. 17+/1"], rows)
        print()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, required=True,
                    help="track dataset folder (e.g. one made by seqshape generate --preset paper)")
    ap.add_argument("--split", default="val", help="split to evaluate (default val)")
    ap.add_argument("--checkpoint", default="pretrained", help="sequential model")
    ap.add_argument("--baseline", default="pretrained", help="per-frame baseline model")
    ap.add_argument("--limit", type=int, default=None, help="first N tracks of the split")
    ap.add_argument("--rows", default=",".join(ROWS),
                    help="comma-separated row keys, of: " + ", ".join(ROWS))
    ap.add_argument("--emd-every", type=int, default=0, help="EMD every K frames (0: off)")
    ap.add_argument("--workers", type=int, default=1, help="EMD processes")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    ap.add_argument("--seed", type=int, default=0, help="shuffle and oracle subsets")
    ap.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    args = ap.parse_args()
    rows = [r.strip() for r in args.rows.split(",") if r.strip()]
    unknown = [r for r in rows if r not in ROWS]
    if unknown:
        sys.exit(f"unknown rows {unknown}; choose from {', '.join(ROWS)}")
    split = TrackDataset(args.data).split(args.split)
    n = len(split) if args.limit is None else min(args.limit, len(split))
    tracks = [split[i] for i in range(n)]
    tracks = [tr for tr in tracks if detection_span(tr) is not None]
    try:
        seq = Estimator.load(args.checkpoint, kind="sequential", threads=args.threads)
        base = Estimator.load(args.baseline, kind="baseline", threads=args.threads)
    except ConfigError as exc:  # a wrong or missing model: say so without a traceback
        sys.exit(str(exc))
    summary = summarise(run_rows(tracks, seq, base, rows, args.emd_every, args.workers,
                                 args.seed))
    print_tables(summary)
    if args.json:
        atomic_write_json(args.json, {"settings": {k: str(v) for k, v in vars(args).items()},
                                      "rows": summary})
    return 0


if __name__ == "__main__":
    sys.exit(main())
