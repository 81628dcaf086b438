"""Quality of accumulated reference shapes on synthetic tracks, where the truth is known.

    python benchmarks/bm_reference.py --data DIR [--preset paper|realistic] [--split val]
        [--frames 1 2 5 10 20 50 all] [--limit N] [--repeats 3] [--seed 0]

For every track of ``--split`` of the Track dataset ``DIR`` (generated there first, when DIR
has no manifest, with ``--preset`` shrunk to 30 vehicles of which 15 val, 4 tracks each, seed
``--seed``), the accumulated reference (``seqshape.data.reference.accumulated_reference``) is
built from the track's first ``min(F, T)`` frames for each ``--frames`` F and compared with the
track's true ``complete`` shape: Chamfer distance (``seqshape.evaluation.metrics``, canonical
frame, both clouds with the dataset's number of complete points), and its two halves,
accuracy (reference -> truth) and completeness (truth -> reference). Three variants: the
default (mirrored, outliers removed), without mirroring, without outlier removal. A second
table bins the default references of all (track, F) pairs by the number of accumulated points
(``info["points_used"]``). The CD floor is the CD between the truth and a fresh sampling of the
same mesh surface (procedural vehicles are rebuilt from ``meta["source"]``; other meshes fall
back to ``cd_floor``'s split estimate). The share of the completeness term that comes from the
truth points in the lowest 0.35 m of the box (underside, wheels, sills) is printed for the last
``--frames`` value. Timing: ``accumulated_reference`` on the whole track,
one warm-up then the median of ``--repeats`` runs over the first 10 tracks.
"""

from __future__ import annotations

import os
import statistics
from pathlib import Path

import numpy as np
from _bench import bench_parser, print_table, time_it

os.environ.setdefault("SEQSHAPE_PROGRESS", "0")

from seqshape.data import TrackDataset  # noqa: E402
from seqshape.data.reference import NoReferenceError, accumulated_reference  # noqa: E402
from seqshape.evaluation.metrics import cd_floor, nearest_distances  # noqa: E402
from seqshape.sim.generate import generate_dataset, preset_config  # noqa: E402
from seqshape.vehicles import procedural_vehicle, sample_outer_surface  # noqa: E402

VARIANTS = {"default": {}, "no mirror": {"mirror": False}, "no outlier removal":
            {"outlier_std": None}}
POINT_BINS = (1, 100, 300, 1000, 3000, 10000, 30000)
LOW_BAND = 0.35  # m above the box bottom: underside, wheels and sills


def ensure_dataset(path: Path, preset: str, seed: int) -> None:
    """Generate the shrunk ``preset`` into ``path`` unless a dataset is already there."""
    if (path / "manifest.json").exists():
        return
    cfg = preset_config(preset, n_vehicles=30, n_val_vehicles=15, tracks_per_vehicle=4,
                        seed=seed)
    print(f"generating {preset} (30 vehicles x 4 tracks, seed {seed}) into {path}")
    generate_dataset(cfg, path)


def surface_floor(track, n: int, seed: int) -> tuple[float, str]:
    """CD between ``track.complete`` and a fresh ``n``-point sampling of its surface."""
    source = str(track.meta.get("source", ""))
    resample = None
    if source.startswith("procedural:"):
        _, kind, vseed = source.split(":")
        mesh = procedural_vehicle(kind, int(vseed)).mesh
        resample = lambda k, s: sample_outer_surface(mesh, k, seed=s)  # noqa: E731
    return cd_floor(track.complete, n, seed=seed + 7919, resample=resample)


def score(track, frames: int | None, n: int, seed: int, **kwargs) -> dict | None:
    """CD, accuracy, completeness of the reference from the first ``frames`` frames (or None)."""
    sub = track.slice(0, len(track) if frames is None else min(frames, len(track)))
    try:
        ref, info = accumulated_reference(sub, n_points=n, min_points=1, seed=seed, **kwargs)
    except NoReferenceError:
        return None
    acc = nearest_distances(ref, track.complete).mean()
    d = nearest_distances(track.complete, ref)  # (M,) truth -> reference
    low = track.complete[:, 2] < -track.size[2] / 2 + LOW_BAND
    return {"cd": acc + d.mean(), "acc": acc, "comp": d.mean(), "frames": info["frames_used"],
            "points": info["points_used"], "low_share": low.mean(),
            "low_comp": d[low].sum() / max(d.sum(), 1e-12)}


def cm(values) -> str:
    return f"{np.mean(values) * 100:.1f}" if len(values) else "-"


def cm_median(values) -> str:
    return f"{np.median(values) * 100:.1f}" if len(values) else "-"


def frames_table(results, frame_list, n_tracks: int) -> None:
    rows = []
    for f in frame_list:
        d = [r for r in results[("default", f)] if r]
        nm = [r["cd"] for r in results[("no mirror", f)] if r]
        ns = [r["cd"] for r in results[("no outlier removal", f)] if r]
        rows.append(("all" if f is None else str(f), f"{len(d)}/{n_tracks}",
                     f"{np.mean([r['frames'] for r in d]):.1f}" if d else "-",
                     f"{np.median([r['points'] for r in d]):.0f}" if d else "-",
                     cm([r["cd"] for r in d]), cm_median([r["cd"] for r in d]),
                     cm([r["acc"] for r in d]), cm([r["comp"] for r in d]), cm(nm),
                     cm_median(nm), cm(ns)))
    print_table(("first F frames", "tracks", "frames used", "median points", "CD mean (cm)",
                 "CD median", "accuracy", "completeness", "no mirror: CD mean",
                 "no mirror: median", "no outlier removal: CD mean"), rows)


def points_table(results, frame_list) -> None:
    pairs = [r for f in frame_list for r in results[("default", f)] if r]
    rows = []
    for lo, hi in zip(POINT_BINS, (*POINT_BINS[1:], None), strict=True):
        b = [r for r in pairs if r["points"] >= lo and (hi is None or r["points"] < hi)]
        label = f"{lo}-{hi - 1}" if hi is not None else f">= {lo}"
        rows.append((label, len(b), cm([r["cd"] for r in b]), cm_median([r["cd"] for r in b]),
                     cm([r["acc"] for r in b]), cm([r["comp"] for r in b])))
    print_table(("accumulated points", "references", "CD mean (cm)", "CD median",
                 "accuracy", "completeness"), rows)


def main() -> None:
    ap = bench_parser(__doc__, repeats=3)
    ap.add_argument("--data", type=Path, required=True, help="Track dataset (made if absent)")
    ap.add_argument("--preset", default="paper", choices=("paper", "realistic"),
                    help="preset generated into --data when it has no dataset (default paper)")
    ap.add_argument("--split", default="val", help="split to score, or 'all' (default val)")
    ap.add_argument("--frames", nargs="+", default=["1", "2", "5", "10", "20", "50", "all"],
                    help="numbers of leading frames to accumulate ('all': the whole track)")
    ap.add_argument("--limit", type=int, default=None, help="score only the first N tracks")
    args = ap.parse_args()
    ensure_dataset(args.data, args.preset, args.seed)
    ds = TrackDataset(args.data)
    ds = ds if args.split == "all" else ds.split(args.split)
    tracks = [t for t in ds if t.complete is not None][:args.limit]
    if not tracks:
        raise SystemExit(f"{args.data}: no track with a complete shape in split {args.split}")
    frame_list = [None if f == "all" else int(f) for f in args.frames]
    n = len(tracks[0].complete)
    results = {(v, f): [score(t, f, n, args.seed, **kw) for t in tracks]
               for v, kw in VARIANTS.items() for f in frame_list}
    floors = [surface_floor(t, n, args.seed) for t in tracks]
    timing = time_it(lambda: [accumulated_reference(t, n_points=n, min_points=1)
                              for t in tracks[:10]], args.repeats)
    lengths = [len(t) for t in tracks]
    print(f"{args.data} ({args.split}): {len(tracks)} tracks, {statistics.median(lengths)} "
          f"frames median (min {min(lengths)}, max {max(lengths)}), {n} points per shape")
    frames_table(results, frame_list, len(tracks))
    print()
    points_table(results, frame_list)
    methods = sorted({m for _, m in floors})
    print(f"\nCD floor (truth vs a fresh {n}-point sampling, {'/'.join(methods)}): "
          f"{np.mean([f for f, _ in floors]) * 100:.1f} cm mean")
    whole = [r for r in results[("default", frame_list[-1])] if r]
    print(f"truth points in the lowest {LOW_BAND} m (underside, wheels, sills), F = "
          f"{args.frames[-1]}: {np.mean([r['low_share'] for r in whole]) * 100:.0f}% of the "
          f"points, {np.mean([r['low_comp'] for r in whole]) * 100:.0f}% of the completeness "
          f"term")
    per_track = timing.median / min(10, len(tracks))
    print(f"accumulated_reference, whole track: {per_track * 1e3:.0f} ms per track "
          f"(median of {args.repeats} runs over {min(10, len(tracks))} tracks)")


if __name__ == "__main__":
    main()
