"""``seqshape demo``: the whole pipeline on a few generated tracks, in a few minutes on 2 cores.

The demo is a list of steps (:data:`STEPS`), each a :class:`DemoStep` whose function reads and
extends a shared :class:`DemoContext` and may add :class:`~seqshape.demo.report.Section`s to
the report. After the last step, ``DIR/report.md`` and ``DIR/index.html`` are written from the
sections. A later feature adds itself with ``STEPS.append(DemoStep(...))`` (or
``STEPS.insert``).

Default steps: generate a small sample of the ``paper`` preset's distribution into
``DIR/data`` (16 vehicles, one track each, 15 of them in the val split; generator seed 123,
vehicles the shipped weights never saw); load the shipped sequential model and baseline;
evaluate both on the val split into ``DIR/eval`` (the table of :mod:`seqshape.demo.fusion`
with the CD floor beside the CD and the flips as their own columns, what fusion over time
buys, plots, an interactive 3D view of one track); label amodal masks on a small KITTI-layout
scene with degraded 2D masks (:mod:`seqshape.demo.amodal_step`, into ``DIR/amodal``).
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
from seqshape.demo.fusion import floor_note, fusion_verdict, headline_table, plot_fusion
from seqshape.demo.report import Section, report_html, report_markdown
from seqshape.errors import ConfigError
from seqshape.evaluation.evaluate import evaluate_to, load_estimator
from seqshape.evaluation.report import detections_markdown
from seqshape.sim.generate import generate_dataset, preset_config

log = logging.getLogger(__name__)


@dataclass
class DemoConfig:
    """Options of the demo (the flags of ``seqshape demo``).

    preset: synthetic generation preset (seqshape generate --preset) whose distribution the
        demo's tracks are drawn from.
    vehicles: vehicles to generate, all but one held out for the val split (0: the preset's
        own counts and split).
    tracks_per_vehicle: tracks each vehicle drives (0: the preset's).
    seed: generation seed (also seeds the evaluation and the amodal scene); 0 would repeat
        the paper preset's own vehicles, most of which the shipped weights were trained on.
    checkpoint: sequential model weights: a checkpoint / model.pt path, or 'pretrained' for
        the shipped ones.
    baseline: per-frame baseline weights: a path, or 'pretrained' for the shipped ones.
    max_tracks: val tracks to evaluate (None: all).
    emd_every: EMD on every K-th frame of each track (0: no EMD).
    workers: processes for generation and EMD.
    """

    preset: str = "paper"
    vehicles: int = 16
    tracks_per_vehicle: int = 1
    seed: int = 123
    checkpoint: str = "pretrained"
    baseline: str = "pretrained"
    max_tracks: int | None = None
    emd_every: int = 20
    workers: int = 2

    def __post_init__(self):
        if self.vehicles == 1 or self.vehicles < 0:
            raise ConfigError(f"--vehicles must be 0 (the preset's) or >= 2 (one train, the "
                              f"rest val), got {self.vehicles}")
        if self.tracks_per_vehicle < 0:
            raise ConfigError(f"--tracks-per-vehicle must be >= 0, got "
                              f"{self.tracks_per_vehicle}")

    def generate_config(self):
        """The :class:`~seqshape.sim.generate.GenerateConfig` of the demo's tracks: the
        preset with ``vehicles`` (all but one in val) and ``tracks_per_vehicle`` (0: the
        preset's own)."""
        sized = {"n_vehicles": self.vehicles, "n_val_vehicles": self.vehicles - 1} \
            if self.vehicles else {}
        return preset_config(self.preset, seed=self.seed, **sized,
                             tracks_per_vehicle=self.tracks_per_vehicle or None)


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
    """Generate the demo's tracks (:meth:`DemoConfig.generate_config`) into ``DIR/data``
    (resumes what is on disk)."""
    ctx.data = ctx.out / "data"
    cfg = ctx.args.generate_config()
    summary = generate_dataset(cfg, ctx.data, workers=ctx.args.workers)
    ds = TrackDataset(ctx.data)
    val = ds.split("val")
    frames = sum(e.get("n_frames", 0) for e in val.entries)
    seen = (" Seed 0 draws the paper preset's own vehicles, most of which the shipped weights "
            "were trained on: these numbers flatter them."
            if cfg.seed == 0 and cfg.library == "procedural" and cfg.meshes is None else "")
    ctx.sections.append(Section("Data", (
        f"Synthetic preset `{ctx.args.preset}` (seed {cfg.seed}): {len(ds)} tracks of "
        f"{cfg.n_vehicles} vehicles, {len(val)} tracks of {cfg.n_val_vehicles} vehicles in the "
        f"val split ({frames} frames), drawn from the preset's distributions of vehicles, "
        f"trajectories and track lengths; {summary.n_generated} generated now, "
        f"{summary.n_skipped} found on disk. Folder: `data/`.{seen}\n")))


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
    """Evaluate the loaded models on the val split into ``DIR/eval``; the section holds the
    table of :func:`~seqshape.demo.fusion.headline_table`, the verdict on fusion over time
    and its plot (``eval/fusion_vs_detections.png``)."""
    val = TrackDataset(ctx.data).split("val")
    summary = evaluate_to(ctx.out / "eval", val, ctx.estimators, max_tracks=ctx.args.max_tracks,
                          emd_every=ctx.args.emd_every, workers=ctx.args.workers,
                          seed=ctx.args.seed)
    ctx.state["metrics"] = summary
    plot_fusion(ctx.out / "eval" / "per_frame.csv", ctx.out / "eval" / FUSION_PLOT,
                summary.get("cd_floor_cm"))
    ctx.sections.append(Section(
        "Shape and pose estimation (val split)", evaluation_markdown(summary),
        images=[("What fusion over time buys: errors against the number of detections so far",
                 f"eval/{FUSION_PLOT}"),
                ("Errors against the distance from the sensor", "eval/errors_vs_distance.png")],
        links=[("Interactive 3D view of one track over time", "eval/track_view.html"),
               ("the full evaluation report", "eval/metrics.md"),
               ("errors against detections, all frames pooled", "eval/errors_vs_detections.png"),
               ("metrics.json", "eval/metrics.json"),
               ("per-frame errors (CSV)", "eval/per_frame.csv")]))


FUSION_PLOT = "fusion_vs_detections.png"


def evaluation_markdown(summary: dict) -> str:
    """The evaluation section's text: the headline table, the CD floor, what fusion over time
    buys, the settings and the errors by detections so far."""
    s = summary.get("settings", {})
    det = summary.get("details", {})
    n_emd = det.get("sequential", {}).get("n_emd_m", "?")
    emd = ("no EMD" if not s.get("emd_every") else
           f"EMD exact on {s.get('emd_points', '?')}-point subsamples of every "
           f"{s['emd_every']}th frame ({n_emd} frames)")
    return (headline_table(summary) + "\n" + floor_note(summary) + "\n"
            + fusion_verdict(summary) + "\n"
            + f"Frame-pooled means over {s.get('n_tracks', '?')} tracks, each run from its first "
              f"to its last detection; {emd}. Flips: frames whose rotation error exceeds 150 "
              f"degrees (the box faces backwards); a flip costs a nearly symmetric car little "
              f"CD but a large rotation error.\n"
            + "\n".join(detections_markdown(det, [m for m in ("baseline", "sequential")
                                                   if m in det])) + "\n")


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
