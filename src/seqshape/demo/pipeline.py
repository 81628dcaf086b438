"""``seqshape demo``: the whole pipeline on a few generated tracks, in a few minutes on 2 cores.

The demo is a list of steps (:data:`STEPS`), each a :class:`DemoStep` whose function reads and
extends a shared :class:`DemoContext` and may add :class:`~seqshape.demo.report.Section`s to
the report. After the last step, ``DIR/report.md`` and ``DIR/index.html`` are written from the
sections. A later feature adds itself with ``STEPS.append(DemoStep(...))`` (or
``STEPS.insert``).

Default steps: generate the ``tiny`` synthetic preset into ``DIR/data``; load the shipped
sequential model and baseline; evaluate both on the val split into ``DIR/eval`` (metrics table,
plots, interactive 3D view of one track); label amodal masks on a small KITTI-layout scene
(:mod:`seqshape.demo.amodal_step`, into ``DIR/amodal``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from seqshape._io import atomic_write_text
from seqshape.data import TrackDataset
from seqshape.demo.amodal_step import step_amodal
from seqshape.demo.report import Section, report_html, report_markdown
from seqshape.evaluation.evaluate import evaluate_to, load_estimator
from seqshape.evaluation.report import metrics_markdown
from seqshape.sim.generate import generate_dataset, preset_config

log = logging.getLogger(__name__)


@dataclass
class DemoConfig:
    """Options of the demo (the flags of ``seqshape demo``).

    preset: synthetic generation preset (seqshape generate --preset).
    seed: generation seed (also seeds the evaluation and the amodal scene).
    checkpoint: sequential model weights: a checkpoint / model.pt path, or 'pretrained' for
        the shipped ones.
    baseline: per-frame baseline weights: a path, or 'pretrained' for the shipped ones.
    max_tracks: val tracks to evaluate (None: all).
    emd_every: EMD on every K-th frame of each track (0: no EMD).
    workers: processes for generation and EMD.
    """

    preset: str = "tiny"
    seed: int = 0
    checkpoint: str = "pretrained"
    baseline: str = "pretrained"
    max_tracks: int | None = None
    emd_every: int = 1
    workers: int = 2


@dataclass
class DemoContext:
    """State shared by the steps: the output folder, the options, what steps produced.

    ``args`` holds the :class:`DemoConfig` (the command's options; steps read
    ``ctx.args.seed`` and so on).
    """

    out: Path
    args: Any
    data: Path | None = None
    estimators: dict[str, Any] = field(default_factory=dict)
    sections: list[Section] = field(default_factory=list)
    timings: list[tuple[str, float]] = field(default_factory=list)
    state: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class DemoStep:
    name: str
    description: str
    run: Callable[[DemoContext], None]


def step_generate(ctx: DemoContext) -> None:
    """Generate the synthetic preset into ``DIR/data`` (resumes what is on disk)."""
    ctx.data = ctx.out / "data"
    summary = generate_dataset(preset_config(ctx.args.preset, seed=ctx.args.seed), ctx.data,
                               workers=ctx.args.workers)
    ds = TrackDataset(ctx.data)
    val = ds.split("val")
    frames = sum(e.get("n_frames", 0) for e in val.entries)
    ctx.sections.append(Section("Data", (
        f"Synthetic preset `{ctx.args.preset}` (seed {ctx.args.seed}): {len(ds)} tracks, "
        f"{len(val)} in the val split ({frames} frames); {summary.n_generated} generated now, "
        f"{summary.n_skipped} found on disk. Folder: `data/`.\n")))


def step_models(ctx: DemoContext) -> None:
    """Load the sequential model and the baseline into ``ctx.estimators``."""
    ctx.estimators = {"sequential": load_estimator(ctx.args.checkpoint, "sequential"),
                      "baseline": load_estimator(ctx.args.baseline, "baseline")}
    lines = []
    for name, spec in (("sequential", ctx.args.checkpoint), ("baseline", ctx.args.baseline)):
        est = ctx.estimators[name]
        cfg = getattr(est, "config", None)
        k = getattr(cfg, "num_complete", "?")
        lines.append(f"- {name}: {'shipped weights' if spec == 'pretrained' else spec} "
                     f"({k} output points)")
    ctx.sections.append(Section("Models", "\n".join(lines) + "\n"))


def step_evaluate(ctx: DemoContext) -> None:
    """Evaluate the loaded models on the val split into ``DIR/eval``."""
    val = TrackDataset(ctx.data).split("val")
    summary = evaluate_to(ctx.out / "eval", val, ctx.estimators, max_tracks=ctx.args.max_tracks,
                          emd_every=ctx.args.emd_every, workers=ctx.args.workers,
                          seed=ctx.args.seed)
    ctx.state["metrics"] = summary
    ctx.sections.append(Section(
        "Shape and pose estimation (val split)", metrics_markdown(summary),
        images=[("Errors against the number of detections so far",
                 "eval/errors_vs_detections.png"),
                ("Errors against the distance from the sensor", "eval/errors_vs_distance.png")],
        links=[("Interactive 3D view of one track over time", "eval/track_view.html"),
               ("metrics.json", "eval/metrics.json"), ("per-frame errors (CSV)",
                                                       "eval/per_frame.csv")]))


#: The demo, in order. Append or insert steps to extend it.
STEPS: list[DemoStep] = [
    DemoStep("generate", "generate synthetic tracks", step_generate),
    DemoStep("models", "load the sequential model and the baseline", step_models),
    DemoStep("evaluate", "evaluate shape and pose on the val split", step_evaluate),
    DemoStep("amodal", "label amodal masks on a kitti-tiny scene", step_amodal),
]


def run_steps(ctx: DemoContext, steps: list[DemoStep],
              announce: Callable[[str], None] = log.info) -> None:
    """Run ``steps`` in order, announcing each, and record their timings in ``ctx``."""
    for i, step in enumerate(steps, 1):
        announce(f"[{i}/{len(steps)}] {step.description} ...")
        t0 = time.perf_counter()
        step.run(ctx)
        ctx.timings.append((step.name, time.perf_counter() - t0))


def write_report(ctx: DemoContext) -> None:
    """``DIR/report.md`` and ``DIR/index.html`` from the context's sections and timings."""
    atomic_write_text(ctx.out / "report.md", report_markdown(ctx.sections, ctx.timings))
    atomic_write_text(ctx.out / "index.html", report_html(ctx.sections, ctx.timings))


def run_demo(out, config: DemoConfig | None = None, steps: list[DemoStep] | None = None,
             announce: Callable[[str], None] = log.info) -> DemoContext:
    """Run the demo (``steps``, default :data:`STEPS` as it is at call time) into ``out`` and
    write its report; returns the context (sections, timings with a ``total``, state)."""
    ctx = DemoContext(out=Path(out), args=DemoConfig() if config is None else config)
    ctx.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    run_steps(ctx, STEPS if steps is None else steps, announce)
    ctx.timings.append(("total", time.perf_counter() - t0))
    write_report(ctx)
    return ctx
