"""``seqshape demo``: the whole pipeline on a few generated tracks, in a few minutes on 2 cores.

The pipeline (steps, context, report) is :mod:`seqshape.demo`; the options are the fields of
:class:`seqshape.demo.DemoConfig`.
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import seqshape.demo as _demo
from seqshape.demo import DemoConfig, run_demo
from seqshape.demo.fusion import fusion_verdict, headline_table
from seqshape.scripts._config_args import add_config_arguments, config_kwargs

HELP = "run the whole pipeline on small generated data and write a report"
FIELDS = ["preset", "vehicles", "tracks_per_vehicle", "seed", "checkpoint", "baseline",
          "max_tracks", "emd_every", "workers"]
_MOVED = {"Section": "Section", "DemoContext": "DemoContext", "DemoStep": "DemoStep",
          "STEPS": "STEPS", "step_generate": "step_generate", "step_models": "step_models",
          "step_evaluate": "step_evaluate", "step_amodal": "step_amodal",
          "run_steps": "run_steps", "_md_to_html": "md_to_html"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    add_config_arguments(parser, DemoConfig, FIELDS)


def _announce(text: str) -> None:
    print(text, flush=True)


def run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    ctx = run_demo(args.out, DemoConfig(**config_kwargs(args, FIELDS)), announce=_announce)
    print(terminal_summary(ctx.state))
    print(f"report: {ctx.out / 'report.md'} and {ctx.out / 'index.html'} "
          f"({time.perf_counter() - t0:.0f} s)")
    return 0


def terminal_summary(state: dict) -> str:
    """What the terminal shows after the run: the metrics table, what fusion over time buys
    and the mask table (each when its step ran)."""
    parts = []
    if "metrics" in state:
        parts += [headline_table(state["metrics"]), fusion_verdict(state["metrics"])]
    if state.get("amodal_table"):
        parts.append(state["amodal_table"])
    return "\n".join(parts)


def _report_markdown(ctx) -> str:
    return _demo.report_markdown(ctx.sections, ctx.timings)


def _report_html(ctx) -> str:
    return _demo.report_html(ctx.sections, ctx.timings)


def __getattr__(name: str):
    """The pipeline that lived here, for one release (moved to :mod:`seqshape.demo`)."""
    if name in _MOVED or name in ("report_markdown", "report_html"):
        warnings.warn(f"seqshape.scripts.demo.{name} moved to seqshape.demo "
                      f"({_MOVED.get(name, name)})", DeprecationWarning, stacklevel=2)
        if name in _MOVED:
            return getattr(_demo, _MOVED[name])
        return _report_markdown if name == "report_markdown" else _report_html
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
