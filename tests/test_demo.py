"""The demo pipeline (seqshape.demo): report writers, old import paths, a recorded run."""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import pytest

from seqshape.demo import DemoConfig, DemoContext, Section, pipeline, run_demo

DATA = Path(__file__).parent / "data" / "demo_small"

SECTIONS = [Section("Data", "Some `code` & <tag>.\n\n| a | b |\n|---|---:|\n| 1 | `x` |\n"
                            "- item `y`\n- two\ntext after\n",
                    images=[("A & B", "eval/a.png")], links=[("m.json", "eval/m.json")]),
            Section("Empty")]
TIMINGS = [("generate", 1.25), ("total", 2.0)]

# report_markdown(ctx) / report_html(ctx) of the release before the move (33229e9) on the
# context above
RELEASE_MD = (
    "# seqshape demo\n\nSequential joint shape and pose estimation (GRU over PointNet features) "
    "beside the per-frame baseline, on synthetic LiDAR tracks.\n\n## Data\n\nSome `code` & "
    "<tag>.\n\n| a | b |\n|---|---:|\n| 1 | `x` |\n- item `y`\n- two\ntext after\n\n"
    "![A & B](eval/a.png)\n\n- [m.json](eval/m.json)\n\n## Empty\n\n\n\n## Timings\n\n"
    "- generate: 1.2 s\n- total: 2.0 s\n")
RELEASE_HTML_BODY = (
    "<body><h1>seqshape demo</h1><h2>Data</h2><p>Some <code>code</code> &amp; &lt;tag&gt;.</p>"
    "\n<table><tr><th>a</th><th>b</th></tr><tr><td>1</td><td><code>x</code></td></tr></table>"
    "\n<ul><li>item <code>y</code></li><li>two</li></ul>\n<p>text after</p><figure><img "
    "src=\"eval/a.png\" alt=\"A &amp; B\"><figcaption>A &amp; B</figcaption></figure><ul><li>"
    "<a href=\"eval/m.json\">m.json</a></li></ul><h2>Empty</h2><h2>Timings</h2><ul><li>"
    "generate: 1.2 s</li><li>total: 2.0 s</li></ul></body></html>\n")


def test_report_writers_match_the_release():
    from seqshape.demo import report_html, report_markdown

    assert report_markdown(SECTIONS, TIMINGS) == RELEASE_MD
    page = report_html(SECTIONS, TIMINGS)
    assert page.startswith("<!DOCTYPE html><html><head><meta charset='utf-8'><title>")
    assert page.endswith(RELEASE_HTML_BODY)


@pytest.mark.parametrize("module, name", [
    ("seqshape.scripts.demo", "Section"),
    ("seqshape.scripts.demo", "STEPS"),
    ("seqshape.scripts.demo", "_md_to_html"),
    ("seqshape.amodal.demo_step", "amodal_demo_step"),
    ("seqshape.scripts.evaluate", "evaluate_to"),
    ("seqshape.scripts.evaluate", "load_estimator"),
    ("seqshape.scripts.tracks", "log_split"),
])
def test_moved_names_still_import_with_a_warning(module, name):
    import importlib

    mod = importlib.import_module(module)
    with pytest.warns(DeprecationWarning, match=f"{name} moved to"):
        value = getattr(mod, name)
    assert value is not None
    with pytest.raises(AttributeError):
        mod.no_such_name  # noqa: B018


def test_old_report_functions_take_a_context():
    from seqshape.scripts import demo as old

    ctx = DemoContext(out=Path("x"), args=argparse.Namespace(), sections=SECTIONS,
                      timings=TIMINGS)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        assert old.report_markdown(ctx) == RELEASE_MD
        assert old.report_html(ctx).endswith(RELEASE_HTML_BODY)


def test_small_demo_matches_the_recorded_release(tmp_path):
    """The demo without its amodal step, shipped weights, one val track, no EMD (about 6 s):
    the report and the metrics table equal those the release wrote (tests/data/demo_small)."""
    steps = [s for s in pipeline.STEPS if s.name != "amodal"]
    announced = []
    ctx = run_demo(tmp_path, DemoConfig(max_tracks=1, emd_every=0, workers=1), steps=steps,
                   announce=announced.append)
    assert announced == [f"[{i}/3] {s.description} ..." for i, s in enumerate(steps, 1)]
    assert [name for name, _ in ctx.timings] == ["generate", "models", "evaluate", "total"]
    report = (tmp_path / "report.md").read_text()
    assert report.split("## Timings")[0] == (DATA / "report.md").read_text()
    assert (tmp_path / "eval" / "metrics.md").read_text() == (DATA / "metrics.md").read_text()
