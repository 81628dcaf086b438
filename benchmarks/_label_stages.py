"""One labelling run, timed per stage: the worker of ``bm_labelling.py --stages``.

    python benchmarks/_label_stages.py --scenes DIR --sequences 0000 0001 --frames 40 \
        --mode sc-gt --out DIR [--profile]

Labels the first ``--frames`` frames of each sequence (``seqshape.amodal.labeler.label_log``,
then ``write_labels`` to ``OUT/<sequence>.json``, as ``seqshape label`` does) and prints one
JSON object: frames, seconds (labelling and writing; the estimator is loaded once before, its
time is ``load``) and, with ``--profile``, seconds per stage from cProfile's cumulative times.
It imports only the labeller's stable API, so that it runs against any version of the package
(``PYTHONPATH=OLD/src``): the before/after table times both in one run.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import sys
import time
from pathlib import Path

os.environ.setdefault("SEQSHAPE_PROGRESS", "0")

# stage -> the functions (file suffix, name) whose cumulative time it is; no function of one
# stage runs inside another's, except the estimator steps inside ``complete_tracks`` (online
# mode), taken out of the refinement, and the sweep ground planes the crop fits (gt modes),
# taken out of the crop.
STAGES = {
    "tracks (crop by box)": [("data/extract.py", "extract_tracks")],
    "estimation": [("model/offline.py", "estimate_track"), ("model/estimator.py", "step")],
    "refinement": [("amodal/refine.py", "complete_tracks"), ("amodal/labeler.py", "add_observed")],
    "ground plane (sweep)": [("data/ground.py", "ground_plane")],
    "diffusion (segment frames)": [("amodal/association.py", "segment_frame")],
    "association": [("amodal/association.py", "associate")],
    "mask-only labels": [("amodal/labeler.py", "mask_only_labels")],
    "projection": [("amodal/masks.py", "project_cloud"), ("amodal/masks.py", "project_clouds")],
    "alpha shape": [("amodal/alpha.py", "alpha_shape_mask")],
    "occlusion order": [("amodal/masks.py", "resolve_occlusion")],
    "alignment": [("amodal/align.py", "align_instances")],
    "KINS records": [("data/kins.py", "kins_annotation"), ("amodal/kins.py", "kins_annotation"),
                     ("data/kins.py", "occlusion_order"), ("amodal/kins.py", "occlusion_order")],
    "writing": [("amodal/labeler.py", "write_labels")],
}


def stage_seconds(prof: cProfile.Profile, total: float) -> dict[str, float]:
    """Seconds per stage of :data:`STAGES` (``other``: the rest of ``total``)."""
    cum: dict[tuple[str, str], float] = {}
    for (path, _line, name), row in pstats.Stats(prof).stats.items():
        key = (path.replace(os.sep, "/"), name)
        cum[key] = cum.get(key, 0.0) + row[3]

    def of(suffix: str, name: str) -> float:
        return sum(v for (p, n), v in cum.items() if n == name and p.endswith(suffix))

    out = {stage: sum(of(s, n) for s, n in funcs) for stage, funcs in STAGES.items()}
    out["refinement"] -= of("model/estimator.py", "step")  # online: steps run inside
    if out["tracks (crop by box)"] > 0:  # sc-gt: the sweep planes are fitted inside the crop
        out["tracks (crop by box)"] -= out["ground plane (sweep)"]
    out["other"] = total - sum(out.values())
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", type=Path, required=True)
    p.add_argument("--sequences", nargs="+", required=True)
    p.add_argument("--frames", type=int, default=None)
    p.add_argument("--mode", default="sc-gt")
    p.add_argument("--checkpoint", default="pretrained")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--profile", action="store_true")
    args = p.parse_args(argv)

    import torch  # lazy: only the sc-* modes need it

    from seqshape.amodal.labeler import (
        LabelConfig,
        label_log,
        load_estimator,
        open_sequence,
        write_labels,
    )

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    est = None if args.mode == "gt-accumulation" else load_estimator(args.checkpoint)
    load = time.perf_counter() - t0
    cfg = LabelConfig(mode=args.mode, checkpoint=args.checkpoint)
    prof = cProfile.Profile() if args.profile else None
    frames, secs = 0, 0.0
    for seq in args.sequences:
        log = open_sequence(args.scenes, seq, args.frames)
        t0 = time.perf_counter()
        if prof is not None:
            prof.enable()
        res = label_log(log, cfg, estimator=est)
        write_labels(args.out / f"{seq}.json", res)
        if prof is not None:
            prof.disable()
        secs += time.perf_counter() - t0
        frames += len(res.images)
    out = {"frames": frames, "seconds": secs, "load": load}
    if prof is not None:
        out["stages"] = stage_seconds(prof, secs)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
