"""``seqshape demo``: the whole pipeline on a few generated tracks, in a few minutes on 2 cores.

The demo is a list of steps (:data:`STEPS`), each a :class:`DemoStep` whose function reads and
extends a shared :class:`DemoContext` and may add :class:`Section`s to the report. After the
last step, ``DIR/report.md`` and ``DIR/index.html`` are written from the sections. A later
feature adds itself with ``STEPS.append(DemoStep(...))`` (or ``STEPS.insert``).

Default steps: generate the ``tiny`` synthetic preset into ``DIR/data``; load the shipped
sequential model and baseline; evaluate both on the val split into ``DIR/eval`` (metrics table,
plots, interactive 3D view of one track); label amodal masks on a small KITTI-layout scene
(``seqshape.amodal.demo_step``, into ``DIR/amodal``).
"""

from __future__ import annotations

import argparse
import html
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from seqshape._io import atomic_write_text

HELP = "run the whole pipeline on small generated data and write a report"


@dataclass
class Section:
    """One part of the report: markdown text, images and links (paths relative to DIR)."""

    title: str
    markdown: str = ""
    images: list[tuple[str, str]] = field(default_factory=list)   # (caption, path)
    links: list[tuple[str, str]] = field(default_factory=list)    # (label, path)


@dataclass
class DemoContext:
    """State shared by the steps: the output folder, CLI arguments, what steps produced."""

    out: Path
    args: argparse.Namespace
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
    from seqshape.sim.generate import generate_dataset, preset_config

    ctx.data = ctx.out / "data"
    summary = generate_dataset(preset_config(ctx.args.preset, seed=ctx.args.seed), ctx.data,
                               workers=ctx.args.workers)
    from seqshape.data import TrackDataset

    ds = TrackDataset(ctx.data)
    val = ds.split("val")
    frames = sum(e.get("n_frames", 0) for e in val.entries)
    ctx.sections.append(Section("Data", (
        f"Synthetic preset `{ctx.args.preset}` (seed {ctx.args.seed}): {len(ds)} tracks, "
        f"{len(val)} in the val split ({frames} frames); {summary.n_generated} generated now, "
        f"{summary.n_skipped} found on disk. Folder: `data/`.\n")))


def step_models(ctx: DemoContext) -> None:
    from seqshape.scripts.evaluate import load_estimator

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
    from seqshape.data import TrackDataset
    from seqshape.evaluation.report import metrics_markdown
    from seqshape.scripts.evaluate import evaluate_to

    val = TrackDataset(ctx.data).split("val")
    out = ctx.out / "eval"
    summary = evaluate_to(out, val, ctx.estimators, max_tracks=ctx.args.max_tracks,
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


def step_amodal(ctx: DemoContext) -> None:
    """Amodal mask labelling on a kitti-tiny scene (docs/amodal.md), imported when it runs."""
    from seqshape.amodal.demo_step import step_amodal as amodal

    amodal(ctx)


#: The demo, in order. Append or insert steps to extend it.
STEPS: list[DemoStep] = [
    DemoStep("generate", "generate synthetic tracks", step_generate),
    DemoStep("models", "load the sequential model and the baseline", step_models),
    DemoStep("evaluate", "evaluate shape and pose on the val split", step_evaluate),
    DemoStep("amodal", "label amodal masks on a kitti-tiny scene", step_amodal),
]


def report_markdown(ctx: DemoContext) -> str:
    parts = ["# seqshape demo\n",
             "Sequential joint shape and pose estimation (GRU over PointNet features) beside "
             "the per-frame baseline, on synthetic LiDAR tracks.\n"]
    for s in ctx.sections:
        parts.append(f"## {s.title}\n\n{s.markdown}")
        parts += [f"![{cap}]({path})\n" for cap, path in s.images]
        parts += [f"- [{label}]({path})" for label, path in s.links]
        parts.append("")
    parts.append("## Timings\n")
    parts += [f"- {name}: {sec:.1f} s" for name, sec in ctx.timings]
    return "\n".join(parts) + "\n"


def _md_to_html(text: str) -> str:
    """The small markdown subset the sections use: tables, bullet lists, paragraphs, `code`."""
    out, table, items = [], [], []

    def inline(s: str) -> str:
        s = html.escape(s)
        while s.count("`") >= 2:
            s = s.replace("`", "<code>", 1).replace("`", "</code>", 1)
        return s

    def flush():
        if table:
            rows = [r for r in table if not set(r.replace("|", "").strip()) <= set("-: ")]
            cells = [[inline(c.strip()) for c in r.strip().strip("|").split("|")] for r in rows]
            out.append("<table><tr>" + "".join(f"<th>{c}</th>" for c in cells[0]) + "</tr>"
                       + "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>"
                                 for r in cells[1:]) + "</table>")
            table.clear()
        if items:
            out.append("<ul>" + "".join(f"<li>{inline(i)}</li>" for i in items) + "</ul>")
            items.clear()

    for line in text.splitlines():
        if line.startswith("|"):
            table.append(line)
        elif line.startswith("- "):
            items.append(line[2:])
        else:
            flush()
            if line.strip():
                out.append(f"<p>{inline(line)}</p>")
    flush()
    return "\n".join(out)


def report_html(ctx: DemoContext) -> str:
    body = ["<h1>seqshape demo</h1>"]
    for s in ctx.sections:
        body.append(f"<h2>{html.escape(s.title)}</h2>{_md_to_html(s.markdown)}")
        body += [f'<figure><img src="{html.escape(p)}" alt="{html.escape(c)}">'
                 f"<figcaption>{html.escape(c)}</figcaption></figure>" for c, p in s.images]
        if s.links:
            body.append("<ul>" + "".join(f'<li><a href="{html.escape(p)}">{html.escape(t)}</a>'
                                         f"</li>" for t, p in s.links) + "</ul>")
    body.append("<h2>Timings</h2><ul>" + "".join(
        f"<li>{html.escape(n)}: {s:.1f} s</li>" for n, s in ctx.timings) + "</ul>")
    style = ("body{font-family:sans-serif;max-width:1200px;margin:2em auto;padding:0 1em}"
             "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:4px 8px}"
             "img{max-width:100%}code{background:#eee;padding:0 3px}")
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>seqshape demo</title>"
            f"<style>{style}</style></head><body>{''.join(body)}</body></html>\n")


def run_steps(ctx: DemoContext, steps: list[DemoStep]) -> None:
    for i, step in enumerate(steps, 1):
        print(f"[{i}/{len(steps)}] {step.description} ...", flush=True)
        t0 = time.perf_counter()
        step.run(ctx)
        ctx.timings.append((step.name, time.perf_counter() - t0))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--preset", default="tiny", help="generation preset (default tiny)")
    parser.add_argument("--seed", type=int, default=0, help="generation seed")
    parser.add_argument("--checkpoint", default="pretrained",
                        help="sequential model weights (default: the shipped ones)")
    parser.add_argument("--baseline", default="pretrained",
                        help="baseline weights (default: the shipped ones)")
    parser.add_argument("--max-tracks", type=int, default=None, help="val tracks to evaluate")
    parser.add_argument("--emd-every", type=int, default=1, help="EMD every K-th frame")
    parser.add_argument("--workers", type=int, default=2, help="processes (default 2)")


def run(args: argparse.Namespace) -> int:
    ctx = DemoContext(out=Path(args.out), args=args)
    ctx.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    run_steps(ctx, STEPS)
    ctx.timings.append(("total", time.perf_counter() - t0))
    atomic_write_text(ctx.out / "report.md", report_markdown(ctx))
    atomic_write_text(ctx.out / "index.html", report_html(ctx))
    if "metrics" in ctx.state:
        from seqshape.evaluation.report import metrics_markdown

        print(metrics_markdown(ctx.state["metrics"]))
    print(f"report: {ctx.out / 'report.md'} and {ctx.out / 'index.html'} "
          f"({time.perf_counter() - t0:.0f} s)")
    return 0
