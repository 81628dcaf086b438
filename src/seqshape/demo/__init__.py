"""The ``seqshape demo`` pipeline: steps, their shared context and the report (layer "demo").

:mod:`seqshape.demo.pipeline` holds the steps and :func:`run_demo`,
:mod:`seqshape.demo.fusion` the metrics table, the verdict on fusion over time and its plot,
:mod:`seqshape.demo.amodal_step` the amodal-labelling step, :mod:`seqshape.demo.report` the
report writers (markdown and HTML).
"""

from seqshape.demo.amodal_step import DemoStepResult, amodal_demo_step, masks_note, step_amodal
from seqshape.demo.fusion import fusion_verdict, headline_table, plot_fusion
from seqshape.demo.pipeline import (
    STEPS,
    DemoConfig,
    DemoContext,
    DemoStep,
    run_demo,
    run_steps,
    step_evaluate,
    step_generate,
    step_models,
    write_report,
)
from seqshape.demo.report import Section, md_to_html, report_html, report_markdown

__all__ = ["STEPS", "DemoConfig", "DemoContext", "DemoStep", "DemoStepResult", "Section",
           "amodal_demo_step", "fusion_verdict", "headline_table", "masks_note", "md_to_html",
           "plot_fusion", "report_html", "report_markdown", "run_demo", "run_steps",
           "step_amodal", "step_evaluate", "step_generate", "step_models", "write_report"]
