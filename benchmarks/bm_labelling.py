"""Amodal labelling quality and throughput against exact ground truth (docs/amodal.md).

    python benchmarks/bm_labelling.py [--scenes DIR] [--checkpoint PATH|pretrained]
        [--sequences 2] [--frames 40] [--repeats 3] [--modes ...] [--refine ...]

Generates (or reuses) a kitti-like scene set (``seqshape scenes --preset kitti-like``, fixed
seed, default degraded 2D masks), labels the first ``--sequences`` sequences (their first
``--frames`` frames; the sequence is labelled as if it ended there, and only those frames'
reference images are scored) with every mode / refinement, scores
the labels with the evaluator (% miss, mIoU, mIoU with misses = 0; amodal, and visible masks
too) and times the labelling (frames/s: a warm-up run, then the median of ``--repeats`` timed
runs on the first sequence). Rows:

* ``oracle-shape``: each vehicle's true mesh surface at its true pose; the upper bound of the
  projection + alpha shape + occlusion steps (no estimation error);
* ``gt-accumulation``, ``sc-gt``, ``sc-seg`` (the latter two with each ``--refine``);
* ``sc-gt-box``: sc-gt with each estimated shape fitted to its ground-truth box
  (``seqshape label --fit-box``).

Besides all reference instances, every row is also scored over the instances within
``--max-distance`` metres (default 80 m, about KITTI's labelling range) and over those with at
least one LiDAR return inside their box (the only ones any LiDAR-based labeller can reach);
matching always uses every instance. The per-distance breakdown goes into results.json.

The sc-* rows need estimator weights: ``--checkpoint PATH`` or ``pretrained`` (skipped with a
note when they cannot be loaded).

``--end-to-end [--baseline-src OLD/src] [--workers 1 2]``: ``seqshape label --sequence all``
on every log of ``--scenes``, timed from the outside (start-up, estimator load and writing
included), per mode and worker count, old and new alternating ``--repeats`` times: wall
seconds and frames/s (medians), the ratio, whether the files are byte-identical, and each
side's % miss / mIoU against the scenes' reference.

``--density``: only the vehicles per frame of every log of ``--scenes`` (distribution over
frames): ``labelled`` (in ``label_02``: amodal mask in the image), ``visible`` (reference
KINS instances) and ``visible_lidar`` (those with >= 1 LiDAR return in their box). Scenes
generated here take ``--vehicles MIN MAX`` (``seqshape scenes --vehicles``).

``--stages [--baseline-src OLD/src]``: speed only, per stage. Each of ``--modes`` (sc-gt and
sc-seg by default) labels the sequences in a fresh process (``benchmarks/_label_stages.py``),
once with cProfile for the seconds per stage and ``--repeats`` times without it for frames/s,
with this package and, alternating with it in the same run, with the package at
``--baseline-src`` (``PYTHONPATH``): a before/after table with ratios, whether the two label
files are byte-identical, and each one's % miss / mIoU against the scenes' reference.
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

from _bench import bench_parser, print_table, time_it

os.environ.setdefault("SEQSHAPE_PROGRESS", "0")

from seqshape._io import atomic_write_text  # noqa: E402
from seqshape.amodal.accumulate import place_in_frames  # noqa: E402
from seqshape.amodal.align import AlignConfig  # noqa: E402
from seqshape.amodal.evaluate import (  # noqa: E402
    breakdown,
    distances_from_labels,
    evaluate_files,
    summarise,
    within_distance,
)
from seqshape.amodal.labeler import (  # noqa: E402
    LabelConfig,
    clouds_by_frame,
    gt_track_inputs,
    label_sequence,
    open_sequence,
    render_labels,
    write_labels,
)
from seqshape.amodal.refine import REFINE_MODES  # noqa: E402
from seqshape.data.crop import crop_box  # noqa: E402
from seqshape.data.kins import read_kins, write_kins  # noqa: E402
from seqshape.data.kitti import KittiTrackingSequence, label_to_pose  # noqa: E402
from seqshape.sim.degrade import DegradeConfig  # noqa: E402
from seqshape.sim.scene_writer import generate_scenes, load_scene, scene_config  # noqa: E402
from seqshape.sim.scenes import check_vehicle_range  # noqa: E402
from seqshape.vehicles.surface import sample_outer_surface  # noqa: E402


def ensure_scenes(path: Path | None, sequences: int, frames: int, seed: int,
                  vehicles: tuple[int, int] | None = None) -> Path:
    """The scene set folder, generated with ``seqshape scenes`` when absent (``vehicles``:
    ``seqshape scenes --vehicles MIN MAX``, None: the preset's)."""
    if path is None:
        dense = "" if vehicles is None else f"_v{vehicles[0]}-{vehicles[1]}"
        path = Path(tempfile.gettempdir()) / (f"seqshape_bm_labelling_{sequences}x{frames}_"
                                              f"{seed}{dense}")
    if not (path / "scene.json").is_file() or not list((path / "amodal").glob("*.json")):
        print(f"generating kitti-like scenes in {path} ...", flush=True)
        cfg = scene_config("kitti-like", n_sequences=sequences, frames=(frames, frames),
                           n_vehicles=vehicles)
        generate_scenes(path, cfg, seed=seed, workers=1, degrade=DegradeConfig())
    return path


def vehicles_per_frame(root: Path, sequence: str) -> dict[str, list[int]]:
    """Per frame of ``sequence``, how many vehicles are ``labelled`` (``label_02``: amodal
    mask in the image), ``visible`` (a reference KINS instance: visible area >= the scenes'
    ``--min-visible-area``) and ``visible_lidar`` (visible and >= 1 LiDAR return inside its
    box: what a LiDAR-based labeller can label)."""
    seq = KittiTrackingSequence(root, sequence)
    doc = read_kins(root / "amodal" / f"{sequence}.json")
    frame_of = {img["id"]: int(img.get("frame", -1)) for img in doc["images"]}
    boxes = {(lab.frame, str(lab.track_id)): label_to_pose(lab, seq.calib)
             for lab in seq.labels}
    out = {k: [0] * len(seq.frames) for k in ("labelled", "visible", "visible_lidar")}
    index = {f: i for i, f in enumerate(seq.frames)}
    for lab in seq.labels:
        out["labelled"][index[lab.frame]] += 1
    scans: dict[int, object] = {}
    for a in doc["annotations"]:
        frame = frame_of[a["image_id"]]
        out["visible"][index[frame]] += 1
        key = (frame, str(a.get("track_id")))
        if key in boxes:
            if frame not in scans:
                scans[frame] = seq.velodyne(frame)[:, :3]
            out["visible_lidar"][index[frame]] += int(len(crop_box(scans[frame],
                                                                   *boxes[key])) > 0)
    return out


def run_density(root: Path, sequences) -> None:
    """The ``--density`` table: the distribution over frames of :func:`vehicles_per_frame`."""
    import numpy as np  # here only: the rest of the benchmark needs no numpy of its own

    counts: dict[str, list[int]] = {}
    placed = []
    for s in sequences:
        for key, per in vehicles_per_frame(root, s).items():
            counts.setdefault(key, []).extend(per)
        doc = json.loads((root / "scene" / f"{s}.json").read_text())
        placed.append(len(doc["agents"]))
    print(f"scenes: {root} ({len(sequences)} logs, {len(counts['visible'])} frames; "
          f"vehicles placed per log: {placed})")
    rows = []
    for key, per in counts.items():
        q = np.percentile(per, [0, 10, 25, 50, 75, 90, 100])
        rows.append((key, f"{np.mean(per):.1f}", *(f"{x:g}" for x in q),
                     f"{np.mean((np.asarray(per) >= 10) & (np.asarray(per) <= 20)) * 100:.0f}"))
    print_table(("vehicles per frame", "mean", "min", "p10", "p25", "median", "p75", "p90",
                 "max", "% frames 10-20"), rows)


def oracle_labels(root: Path, sequence: str, cfg: LabelConfig, max_frames: int | None = None):
    """Labels from the true meshes at the true poses (upper bound of the mask steps)."""
    seq = open_sequence(root, sequence, max_frames)
    scene, _ = load_scene(root, sequence)
    by_tid = {a.track_id: k for k, a in enumerate(scene.agents)}
    _, inputs = gt_track_inputs(seq, cfg.classes, cfg.crop)
    clouds = []
    for inp in inputs:
        shape = sample_outer_surface(scene.mesh(by_tid[inp.label_id]), n=4096, seed=0)
        clouds.append(place_in_frames(shape, inp.poses))
    return render_labels(seq, clouds_by_frame(inputs, clouds), cfg)


def label_once(root, sequence, name, cfg, estimator, max_frames):
    """The :class:`LabelResult` of one method on one sequence (first ``max_frames`` frames)."""
    if name == "oracle-shape":
        return oracle_labels(root, sequence, cfg, max_frames)
    return label_sequence(root, sequence, cfg, estimator, max_frames=max_frames)


def reference_subset(root: Path, sequence: str, max_frames: int | None, out_dir: Path) -> Path:
    """The reference KINS file of ``sequence``, cut to its first ``max_frames`` frames.

    The copy is written under ``out_dir/reference/amodal``. Each annotation gains the
    ``distance`` of its KITTI label (the copy has no ``label_02`` beside it) and
    ``lidar_points``, the number of LiDAR returns inside its box: instances without any cannot
    be labelled from LiDAR at all, whatever the method.
    """
    full = root / "amodal" / f"{sequence}.json"
    seq = open_sequence(root, sequence, max_frames)
    frames = set(seq.frames)
    doc = read_kins(full)
    images = [img for img in doc["images"] if int(img.get("frame", -1)) in frames]
    ids = {img["id"] for img in images}
    frame_of = {img["id"]: int(img.get("frame", -1)) for img in images}
    dists = distances_from_labels(full)
    boxes = {(lab.frame, str(lab.track_id)): label_to_pose(lab, seq.calib)
             for lab in seq.labels}
    scans: dict[int, object] = {}
    anns = []
    for a in doc["annotations"]:
        if a["image_id"] not in ids:
            continue
        key = (frame_of[a["image_id"]], str(a.get("track_id")))
        extra = {}
        if key in dists:
            extra["distance"] = dists[key]
        if key in boxes:
            if key[0] not in scans:
                scans[key[0]] = seq.velodyne(key[0])[:, :3]
            extra["lidar_points"] = len(crop_box(scans[key[0]], *boxes[key]))
        anns.append({**a, **extra})
    path = out_dir / "reference" / "amodal" / f"{sequence}.json"
    write_kins(path, images, anns, doc.get("categories"))
    return path


def run_method(root, sequences, name, cfg, estimator, out_dir, max_frames=None,
               max_distance=80.0):
    """Label every sequence; returns (amodal metrics, visible metrics, frames, seconds)."""
    pairs, frames, secs = [], 0, 0.0
    for s in sequences:
        t0 = time.perf_counter()
        res = label_once(root, s, name, cfg, estimator, max_frames)
        secs += time.perf_counter() - t0
        frames += len(res.images)
        path = out_dir / name.replace("/", "_") / f"{s}.json"
        write_labels(path, res)
        pairs.append((path, reference_subset(root, s, max_frames, out_dir)))
    results, unmatched = evaluate_files(pairs)
    amodal = summarise(results, unmatched)
    amodal["near"] = summarise(within_distance(results, max_distance))
    amodal["with_lidar"] = summarise([r for r in results if r.lidar_points > 0])
    amodal["breakdown"] = breakdown(results)
    visible = summarise(*evaluate_files(pairs, segm="i_segm"))
    return amodal, visible, frames, secs


def time_method(root, sequence, name, cfg, estimator, repeats, max_frames=None):
    """Frames/s of labelling ``sequence``: (median, (min, max)) over ``repeats`` timed runs.

    No warm-up here: :func:`run_method` has just labelled the same sequence.
    """
    timing = time_it(lambda: label_once(root, sequence, name, cfg, estimator, max_frames),
                     repeats, warmup=0)
    rates = timing.rates(len(timing.result.images))
    return statistics.median(rates), (min(rates), max(rates))


def write_results(out_dir: Path, root: Path, note: str, args, rows: list[dict]) -> None:
    """``out_dir/results.json`` with the rows so far (rewritten after every method)."""
    atomic_write_text(out_dir / "results.json", json.dumps(
        {"scenes": str(root), "note": note, "order": args.order, "sequences": args.sequences,
         "frames": args.frames, "rows": rows}, indent=2))


def _stage_run(src: Path | None, root: Path, sequences, frames, mode: str, checkpoint: str,
               out: Path, profile: bool) -> dict:
    """One labelling run of ``_label_stages.py`` in a fresh process, with the package at
    ``src`` (None: this one); its JSON result."""
    import subprocess

    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = str(src)
    cmd = [sys.executable, str(Path(__file__).with_name("_label_stages.py")), "--scenes",
           str(root), "--sequences", *sequences, "--frames", str(frames), "--mode", mode,
           "--checkpoint", checkpoint, "--out", str(out)] + (["--profile"] if profile else [])
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    if done.returncode:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _scores(out: Path, root: Path, sequences, frames) -> tuple[float, float]:
    """(% miss, mIoU) of the label files in ``out`` against the scenes' reference."""
    pairs = [(out / f"{s}.json", reference_subset(root, s, frames, out)) for s in sequences]
    amodal = summarise(*evaluate_files(pairs))
    return amodal["miss_pct"], amodal["miou"]


def run_stages(root: Path, sequences, args) -> None:
    """The ``--stages`` table (module doc): per mode and stage, seconds per frame before
    (``--baseline-src``) and after, side by side."""
    out_dir = args.out or Path(tempfile.mkdtemp(prefix="bm_labelling_stages_"))
    versions = {"new": None} if args.baseline_src is None else {"old": args.baseline_src,
                                                                "new": None}
    print(f"scenes: {root} ({', '.join(sequences)}, first {args.frames} frames); "
          f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}", flush=True)
    for mode in args.modes:
        runs: dict[str, dict] = {v: {"rates": []} for v in versions}
        for rep in range(max(args.repeats, 0) + 1):  # the first run is profiled
            for v, src in versions.items():
                folder = out_dir / mode / v
                res = _stage_run(src, root, sequences, args.frames, mode, args.checkpoint,
                                 folder, profile=rep == 0)
                if rep == 0:
                    runs[v].update(res)
                else:
                    runs[v]["rates"].append(res["frames"] / res["seconds"])
        names = list(runs["new"]["stages"])
        cols = list(versions)
        rows = []
        for name in names:
            per = [runs[v]["stages"][name] / runs[v]["frames"] * 1e3 for v in cols]
            rows.append((name, *(f"{x:.1f}" for x in per),
                         *([f"{per[0] / per[1]:.2f}" if per[1] > 0 else "-"] if len(cols) > 1
                           else [])))
        tot = [runs[v]["seconds"] / runs[v]["frames"] * 1e3 for v in cols]
        rows.append(("total (profiled)", *(f"{x:.1f}" for x in tot),
                     *([f"{tot[0] / tot[1]:.2f}"] if len(cols) > 1 else [])))
        fps = [statistics.median(runs[v]["rates"]) if runs[v]["rates"] else float("nan")
               for v in cols]
        rows.append(("frames/s (unprofiled, median)", *(f"{x:.2f}" for x in fps),
                     *([f"{fps[1] / fps[0]:.2f}"] if len(cols) > 1 else [])))
        rows.append(("estimator load (s, once)", *(f"{runs[v]['load']:.2f}" for v in cols),
                     *(["-"] if len(cols) > 1 else [])))
        print(f"\n{mode}: ms per frame ({runs['new']['frames']} frames; frames/s over "
              f"{args.repeats} unprofiled runs)")
        print_table(("stage", *(f"{v} (ms/frame)" for v in cols),
                     *(["old / new"] if len(cols) > 1 else [])), rows)
        for v in cols:
            miss, miou = _scores(out_dir / mode / v, root, sequences, args.frames)
            print(f"{v}: % miss {miss:.2f}, mIoU {miou:.4f} against the reference")
        if len(cols) > 1:
            same = all((out_dir / mode / "old" / f"{s}.json").read_bytes()
                       == (out_dir / mode / "new" / f"{s}.json").read_bytes()
                       for s in sequences)
            print(f"label files old vs new: {'byte-identical' if same else 'DIFFERENT'}")
    print(f"labels in {out_dir}")


def _cli_run(src: Path | None, root: Path, mode: str, workers: int, checkpoint: str,
             out: Path) -> tuple[float, float]:
    """(wall, CPU) seconds of one ``seqshape label --sequence all`` in a fresh process
    (start-up included; CPU: user + system of it and its workers), with the package at
    ``src`` (None: this one)."""
    import resource
    import shutil
    import subprocess

    env = dict(os.environ, SEQSHAPE_PROGRESS="0")
    if src is not None:
        env["PYTHONPATH"] = str(src)
    shutil.rmtree(out, ignore_errors=True)
    cmd = [sys.executable, "-m", "seqshape.cli", "label", "--kitti", str(root), "--sequence",
           "all", "--mode", mode, "--workers", str(workers), "--checkpoint", checkpoint,
           "--out", str(out)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    secs = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{done.stderr[-3000:]}")
    return secs, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def run_end_to_end(root: Path, sequences, args) -> None:
    """The ``--end-to-end`` table (module doc): ``seqshape label --sequence all`` per mode and
    worker count, old and new alternating; frames/s, ratios, byte equality, scores."""
    out_dir = args.out or Path(tempfile.mkdtemp(prefix="bm_labelling_e2e_"))
    versions = {"new": None} if args.baseline_src is None else {"old": args.baseline_src,
                                                                "new": None}
    frames = sum(len(KittiTrackingSequence(root, s).frames) for s in sequences)
    print(f"scenes: {root} ({len(sequences)} logs, {frames} frames); "
          f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load "
          f"{os.getloadavg()[0]:.1f}", flush=True)
    rows = []
    for mode in args.modes:
        for workers in args.workers:
            secs: dict[str, list[float]] = {v: [] for v in versions}
            cpu: dict[str, list[float]] = {v: [] for v in versions}
            for _ in range(max(args.repeats, 1)):
                for v, src in versions.items():
                    wall, used = _cli_run(src, root, mode, workers, args.checkpoint,
                                          out_dir / mode / f"{v}{workers}")
                    secs[v].append(wall)
                    cpu[v].append(used)
            fps = {v: frames / statistics.median(x) for v, x in secs.items()}
            row = [f"{mode}, --workers {workers}",
                   *(f"{statistics.median(secs[v]):.1f} s ({statistics.median(cpu[v]):.1f} "
                     f"CPU s), {fps[v]:.2f}" for v in versions)]
            if len(versions) > 1:
                same = all((out_dir / mode / f"old{workers}" / f"{s}.json").read_bytes()
                           == (out_dir / mode / f"new{workers}" / f"{s}.json").read_bytes()
                           for s in sequences)
                row += [f"{fps['new'] / fps['old']:.2f}", "yes" if same else "no"]
            rows.append(tuple(row))
            print(f"  {row}  (load {os.getloadavg()[0]:.1f})", flush=True)
        for v in versions:
            miss, miou = _scores(out_dir / mode / f"{v}{args.workers[0]}", root, sequences,
                                 None)
            print(f"{mode} {v}: % miss {miss:.3f}, mIoU {miou:.5f} against the reference")
    print()
    print_table(("run", *(f"{v} (wall (CPU), frames/s)" for v in versions),
                 *(["new / old", "files equal"] if len(versions) > 1 else [])), rows)
    print(f"labels in {out_dir}")


def main(argv=None) -> int:
    p = bench_parser(__doc__, repeats=3, min_repeats=0,
                     repeats_help="timed runs for frames/s (0: skip)")
    p.add_argument("--scenes", type=Path, default=None, help="scene set (generated if absent)")
    p.add_argument("--skip", type=int, default=0,
                   help="start at the scene set's sequence number SKIP (held-out checks)")
    p.add_argument("--sequences", type=int, default=2,
                   help="evaluate the first N sequences (and generate N when absent)")
    p.add_argument("--frames", type=int, default=40,
                   help="evaluate the first F frames of each (and generate F when absent)")
    p.add_argument("--checkpoint", default="pretrained")
    p.add_argument("--modes", nargs="+",
                   default=["oracle-shape", "gt-accumulation", "sc-gt", "sc-gt-box", "sc-seg"])
    p.add_argument("--max-distance", type=float, default=80.0,
                   help="also score the instances at most this far (m)")
    p.add_argument("--refine", nargs="+", default=list(REFINE_MODES), choices=REFINE_MODES)
    p.add_argument("--fit-box-below", type=int, default=LabelConfig.fit_box_below,
                   help="sc-gt: box-fit tracks that fused fewer points (seqshape label "
                        "--fit-box-below)")
    p.add_argument("--min-visible-area", type=int, default=LabelConfig.min_visible_area,
                   help="label instances with at least this visible area (px)")
    p.add_argument("--no-mask-fallback", dest="mask_fallback", action="store_false",
                   help="sc-seg: no mask-only labels (seqshape label --no-mask-fallback)")
    p.add_argument("--trim", type=float, default=LabelConfig.trim,
                   help="sc-*: trim completed shapes to their robust box (seqshape label --trim)")
    p.add_argument("--no-align", dest="align", action="store_false",
                   help="sc-seg: no mask-guided placement (seqshape label --no-align)")
    p.add_argument("--align-max-points", type=int, default=AlignConfig.max_points,
                   help="sc-seg: move only vehicles with fewer own LiDAR returns (0: all)")
    p.add_argument("--align-min-inside", type=float, default=AlignConfig.min_inside,
                   help="sc-seg: share of a vehicle's own returns kept inside its moved mask")
    p.add_argument("--placement", default="pretrained",
                   help="sc-*: the estimator's placement refiner (seqshape label --placement: "
                        "'pretrained', a refiner file or 'none')")
    p.add_argument("--order", default="pixel", choices=["pixel", "median"])
    p.add_argument("--threads", type=int, default=1,
                   help="torch threads for the estimator (default 1, as `seqshape label`)")
    p.add_argument("--out", type=Path, default=None, help="labels + results.json here")
    p.add_argument("--stages", action="store_true",
                   help="speed per stage only (module doc); --modes default sc-gt sc-seg")
    p.add_argument("--baseline-src", type=Path, default=None,
                   help="--stages, --end-to-end: also run the package at this src folder "
                        "(before/after)")
    p.add_argument("--end-to-end", action="store_true",
                   help="time `seqshape label --sequence all` (start-up included) on every "
                        "log of --scenes (module doc); --modes default sc-gt sc-seg")
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2],
                   help="--end-to-end: the --workers values to time")
    p.add_argument("--vehicles", nargs=2, metavar=("MIN", "MAX"), default=None,
                   help="when the scenes are generated here: non-ego vehicles per sequence "
                        "(seqshape scenes --vehicles; default the kitti-like preset's)")
    p.add_argument("--density", action="store_true",
                   help="only print the vehicles per frame of every log of --scenes "
                        "(labelled, visible, visible with LiDAR returns)")
    args = p.parse_args(argv)

    vehicles = None if args.vehicles is None else check_vehicle_range(args.vehicles,
                                                                      "--vehicles")
    root = ensure_scenes(args.scenes, args.skip + args.sequences, args.frames, args.seed,
                         vehicles)
    sequences = KittiTrackingSequence.sequences(root)[args.skip:args.skip + args.sequences]
    if args.density:
        run_density(root, KittiTrackingSequence.sequences(root))
        return 0
    if args.end_to_end:
        if args.modes == p.get_default("modes"):
            args.modes = ["sc-gt", "sc-seg"]
        run_end_to_end(root, KittiTrackingSequence.sequences(root), args)
        return 0
    if args.stages:
        if args.modes == p.get_default("modes"):
            args.modes = ["sc-gt", "sc-seg"]
        run_stages(root, sequences, args)
        return 0
    out_dir = args.out or Path(tempfile.mkdtemp(prefix="bm_labelling_"))
    estimator, note = None, ""
    if any(m.startswith("sc-") for m in args.modes):
        import torch  # lazy: torch only for the sc-* modes

        from seqshape.model.estimator import Estimator  # lazy: torch

        torch.set_num_threads(args.threads)
        try:
            estimator = Estimator.load(args.checkpoint, refiner=args.placement)
            note = f"checkpoint: {args.checkpoint}, placement refiner: {args.placement}"
        except Exception as exc:  # report and go on with the modes that need no weights
            note = f"sc-* rows skipped: cannot load {args.checkpoint!r} ({exc})"
    print(f"scenes: {root} ({len(sequences)} sequences x first {args.frames} frames); {note}; "
          f"occlusion order {args.order}", flush=True)
    rows = []
    out_dir.mkdir(parents=True, exist_ok=True)
    for mode in args.modes:
        if mode.startswith("sc-") and estimator is None:
            continue
        for refine in (args.refine if mode.startswith("sc-") else ["none"]):
            label_mode = {"oracle-shape": "gt-accumulation", "sc-gt-box": "sc-gt"}.get(mode, mode)
            cfg = LabelConfig(mode=label_mode, refine=refine, order=args.order,
                              checkpoint=args.checkpoint, fit_box=mode == "sc-gt-box",
                              fit_box_below=args.fit_box_below,
                              min_visible_area=args.min_visible_area,
                              mask_fallback=args.mask_fallback, align=args.align,
                              trim=args.trim, placement=args.placement,
                              align_config=AlignConfig(max_points=args.align_max_points,
                                                       min_inside=args.align_min_inside))
            name = mode if not mode.startswith("sc-") else f"{mode}/{refine}"
            a, v, n, secs = run_method(root, sequences, name, cfg, estimator, out_dir,
                                       args.frames, args.max_distance)
            fps, spread = (n / secs, (n / secs, n / secs))
            if args.repeats > 0:
                fps, spread = time_method(root, sequences[0], mode, cfg, estimator, args.repeats,
                                          args.frames)
            rows.append({"method": name, "amodal": a, "visible": v, "fps": fps,
                         "fps_range": spread, "frames": n})
            print(f"  {name}: miss {a['miss_pct']:.2f}%  mIoU {a['miou']:.3f}  (<= "
                  f"{args.max_distance:g} m: {a['near']['miss_pct']:.2f}% {a['near']['miou']:.3f})  "
                  f"visible mIoU {v['miou']:.3f}  {fps:.2f} frames/s ({n} frames)", flush=True)
            write_results(out_dir, root, note, args, rows)
    print()
    near = f"<= {args.max_distance:g} m"
    print_table(("Method", "% Miss", "mIoU", f"% Miss ({near})", f"mIoU ({near})",
                 "% Miss (LiDAR > 0)", "mIoU (LiDAR > 0)",
                 "mIoU (misses = 0)", "visible mIoU", "unmatched preds",
                 "frames/s (median, min-max)"),
                [(r["method"], f"{r['amodal']['miss_pct']:.2f}", f"{r['amodal']['miou']:.3f}",
                  f"{r['amodal']['near']['miss_pct']:.2f}", f"{r['amodal']['near']['miou']:.3f}",
                  f"{r['amodal']['with_lidar']['miss_pct']:.2f}",
                  f"{r['amodal']['with_lidar']['miou']:.3f}",
                  f"{r['amodal']['miou_with_misses']:.3f}", f"{r['visible']['miou']:.3f}",
                  r["amodal"]["unmatched_predictions"],
                  f"{r['fps']:.2f} ({r['fps_range'][0]:.2f}-{r['fps_range'][1]:.2f})")
                 for r in rows])
    instances = rows[0]["amodal"]["n"] if rows else 0
    n_near = rows[0]["amodal"]["near"]["n"] if rows else 0
    n_lidar = rows[0]["amodal"]["with_lidar"]["n"] if rows else 0
    print(f"\n{instances} reference instances ({n_near} within {args.max_distance:g} m, "
          f"{n_lidar} with LiDAR returns), {rows[0]['frames'] if rows else 0} frames; {note}")
    write_results(out_dir, root, note, args, rows)
    print(f"labels and results.json in {out_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
