"""The demo pipeline (seqshape.demo): report writers, old import paths, a recorded run, the
metrics table (flips, CD floor), what fusion over time buys, and the degraded 2D masks."""

from __future__ import annotations

import argparse
import json
import re
import warnings
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from seqshape.demo import (
    DemoConfig,
    DemoContext,
    Section,
    amodal_demo_step,
    fusion,
    pipeline,
    report_html,
    run_demo,
)
from seqshape.demo.amodal_step import masks_note
from seqshape.demo.report import md_to_html
from seqshape.errors import ConfigError, DataError
from seqshape.sim.degrade import NO_DEGRADE, DegradeConfig

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


def _table(markdown: str, first_cell: str) -> tuple[list[str], dict[str, list[str]]]:
    """Header cells and ``{row name: cells}`` of the markdown table whose header starts with
    ``first_cell``."""
    lines = markdown.splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.startswith(f"| {first_cell} |"))
    rows = []
    for ln in lines[start:]:
        if not ln.startswith("|"):
            break
        rows.append([c.strip() for c in ln.strip().strip("|").split("|")])
    return rows[0], {r[0]: r for r in rows[2:]}


def test_small_demo_matches_the_recorded_release(tmp_path):
    """The demo without its amodal step on the old `tiny` set (shipped weights, one val track,
    no EMD; about 6 s): the evaluation's metrics.md equals the release's (tests/data/demo_small),
    and the report's table shows the flips and the CD floor beside the CD, from metrics.json."""
    steps = [s for s in pipeline.STEPS if s.name != "amodal"]
    announced = []
    cfg = DemoConfig(preset="tiny", vehicles=0, tracks_per_vehicle=0, seed=0, max_tracks=1,
                     emd_every=0, workers=1)
    ctx = run_demo(tmp_path, cfg, steps=steps, announce=announced.append)
    assert announced == [f"[{i}/3] {s.description} ..." for i, s in enumerate(steps, 1)]
    assert [name for name, _ in ctx.timings] == ["generate", "models", "evaluate", "total"]
    assert (tmp_path / "eval" / "metrics.md").read_text() == (DATA / "metrics.md").read_text()
    report = (tmp_path / "report.md").read_text()
    assert "12 tracks of 6 vehicles, 4 tracks of 2 vehicles in the val split (80 frames)" in report
    assert "Seed 0 draws the paper preset's own vehicles" in report  # the seed seen in training
    metrics = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    head, rows = _table(report, "Method")
    cd = head.index("CD (cm)")
    assert head[cd + 1] == "CD floor (cm)" and "Flips (% frames)" in head
    for m in ("baseline", "sequential"):
        row = rows[f"{m} (ours)"]
        floor = metrics["floor"]["per_method"][m]["cd_floor_cm"]
        assert row[cd] == f"{metrics[m]['cd_cm']:.2f}" and row[cd + 1] == f"{floor:.2f}"
        assert float(row[cd + 2]) == pytest.approx(metrics[m]["cd_cm"] - floor, abs=0.006)
        flips = metrics["details"][m]["flips"]
        assert row[head.index("Flips (% frames)")] == f"{flips['flip_pct']:.1f}"
        assert row[head.index("Tracks with a flip")] == "0 of 1"
    assert rows["sequential (paper)"][cd:cd + 2] == ["2.30", "not given"]
    assert "fusion over time buys" in report
    assert (tmp_path / "eval" / pipeline.FUSION_PLOT).read_bytes()[:4] == b"\x89PNG"
    page = (tmp_path / "index.html").read_text()
    assert "**" not in page and "<strong>On this demo set, fusion over time buys" in page
    assert "###" not in page and "<h3>Errors by detections so far" in page


def _summary(seq: dict, base: dict, late: tuple = ((0.8, 0.7), (1.0, 1.0)),
             flips: tuple = (0.0, 0.0)) -> dict:
    """A metrics.json-like summary: ``seq``/``base`` hold cd_cm, emd_m, trans_cm, rot_deg;
    ``late`` the (cd, trans) 17+-over-first ratios, ``flips`` the % of flipped frames."""
    out = {"cd_floor_cm": 15.0, "floor": {"n_pred": 1024, "per_method": {
        "sequential": {"cd_floor_cm": 15.0}, "baseline": {"cd_floor_cm": 15.0}}},
        "settings": {"n_tracks": 3, "emd_every": 5, "emd_points": 1024}, "details": {}}
    for m, vals, (r_cd, r_tr), pct in (("sequential", seq, late[0], flips[0]),
                                        ("baseline", base, late[1], flips[1])):
        out[m] = dict(vals)
        out["details"][m] = {
            "n_frames": 40, "rot_deg_without_flips": vals["rot_deg"],
            "flips": {"flip_pct": pct, "flipped_tracks": int(pct > 0), "n_tracks": 3},
            "late_over_first": {"all": {"cd": r_cd, "trans": r_tr}},
            "by_detections": {"all": {"1": {"n_tracks": 3, "cd_cm": vals["cd_cm"] + 2.0},
                                      "17+": {"n_tracks": 2, "cd_cm": vals["cd_cm"] - 1.0}}}}
    return out


def test_headline_table_puts_the_floor_beside_the_cd_and_flips_in_columns():
    s = _summary({"cd_cm": 20.0, "emd_m": 0.3, "trans_cm": 8.0, "rot_deg": 4.0},
                 {"cd_cm": 21.5, "emd_m": 0.4, "trans_cm": 9.0, "rot_deg": 30.0},
                 flips=(0.0, 12.5))
    head, rows = _table(fusion.headline_table(s), "Method")
    assert head[1:4] == ["CD (cm)", "CD floor (cm)", "CD above floor (cm)"]
    assert rows["baseline (ours)"][1:4] == ["21.50", "15.00", "6.50"]
    assert rows["baseline (ours)"][-2:] == ["12.5", "1 of 3"]
    assert rows["sequential (ours)"][-2:] == ["0.0", "0 of 3"]
    assert list(rows) == ["baseline (ours)", "sequential (ours)", "baseline (paper)",
                          "sequential (paper)"]


def test_verdict_says_when_fusion_buys_nothing():
    worse = _summary({"cd_cm": 21.0, "emd_m": 0.40, "trans_cm": 10.0, "rot_deg": 5.0},
                     {"cd_cm": 21.0, "emd_m": 0.39, "trans_cm": 9.0, "rot_deg": 4.0},
                     late=((1.0, 1.1), (1.0, 1.1)))
    text = fusion.fusion_verdict(worse)
    assert "fusion over time buys nothing" in text
    # CD above the floor 6.0 against 6.0, EMD +3 %: the same; translation +11 %: worse
    assert "within 5 % on CD above the floor (+0 %: 6.00 against 6.00 cm)" in text
    assert "worse on translation error (+11 %: 10.00 against 9.00 cm)" in text
    better = _summary({"cd_cm": 20.0, "emd_m": 0.40, "trans_cm": 9.0, "rot_deg": 4.0},
                      {"cd_cm": 21.0, "emd_m": 0.39, "trans_cm": 9.0, "rot_deg": 4.0},
                      late=((0.8, 1.0), (1.0, 1.0)), flips=(5.0, 0.0))
    text = fusion.fusion_verdict(better)
    assert "buys nothing" not in text
    # CD above the floor 5 against 6: -17 %; CD falls x0.8 against x1.0
    assert ("fusion over time buys a lower CD above the floor and a CD error that falls faster "
            "as detections accumulate**; it costs more 180-degree flips.") in text
    assert "sequential CD x0.80 and translation x1.00; baseline CD x1.00" in text
    assert ("first detection (one frame seen, nothing to fuse yet): sequential 22.00 against "
            "baseline 23.00 cm; at 17 detections and more: 19.00 against 20.00 cm.") in text


def _per_frame_csv(path: Path) -> None:
    """Two tracks, two methods; the sequential rows in another order than the baseline's."""
    header = ("method,track_id,frame,n_det,n_points,distance_m,cd_m,emd_m,trans_m,rot_rad,"
              "cd_true_pose_m,class,radial_m,tangential_m,rot_axis_rad,length_err_m,"
              "width_err_m,ref_to_est_m")
    rows = []
    for m, cd in (("baseline", 0.20), ("sequential", 0.18)):
        frames = [("a", t) for t in range(20)] + [("b", t) for t in range(3)]
        if m == "sequential":
            frames = frames[::-1]
        for tr, t in frames:
            rot = 3.1 if (m == "baseline" and tr == "b") else 0.05  # b flipped by the baseline
            rows.append(f"{m},{tr},{t},{t + 1},50,10,{cd + 0.001 * t},,0.1,{rot},,,,,,,,")
    path.write_text(header + "\n" + "\n".join(rows) + "\n")


def test_fusion_plot_pairs_the_frames_of_both_methods(tmp_path):
    _per_frame_csv(tmp_path / "per_frame.csv")
    rec = fusion.read_per_frame(tmp_path / "per_frame.csv")
    ia, ib = fusion.paired_frames(rec["sequential"], rec["baseline"])
    assert len(ia) == 23
    for k in ("track_id", "frame"):
        assert np.array_equal(rec["sequential"][k][ia], rec["baseline"][k][ib])
    diff = rec["sequential"]["cd_cm"][ia] - rec["baseline"]["cd_cm"][ib]
    assert np.allclose(diff, -2.0)  # 18 + 0.1 t against 20 + 0.1 t cm, frame by frame
    out = fusion.plot_fusion(tmp_path / "per_frame.csv", tmp_path / "f.png", floor_cm=15.0)
    assert out.read_bytes()[:4] == b"\x89PNG"
    which = np.digitize([1, 2, 3, 4, 5, 17, 100], fusion.PLOT_BINS) - 1
    assert which.tolist() == [0, 1, 2, 2, 3, 5, 7]


@pytest.mark.parametrize("text", ["", "method,track_id\nsequential,a\n",
                                  "method,track_id,frame,n_det,cd_m,trans_m,rot_rad\n"
                                  "sequential,a,x,1,0.1,0.1,0.1\n"])
def test_a_malformed_per_frame_file_is_a_data_error(tmp_path, text):
    path = tmp_path / "per_frame.csv"
    path.write_text(text)
    with pytest.raises(DataError, match="per_frame.csv"):
        fusion.plot_fusion(path, tmp_path / "f.png")


def test_markdown_bold_renders_as_html():
    assert md_to_html("**Amodal masks** vs `a**b`") == (
        "<p><strong>Amodal masks</strong> vs <code>a**b</code></p>")
    assert md_to_html("a ** b") == "<p>a ** b</p>"


def test_report_headings_render_as_html():
    """The evaluation section's ``###`` headings are HTML headings on the demo's page, never a
    literal ``###`` (issue 46)."""
    assert md_to_html("## Two\n### Three (cm) ##\n#not a heading") == (
        "<h2>Two</h2>\n<h3>Three (cm)</h3>\n<p>#not a heading</p>")
    s = _summary({"cd_cm": 20.0, "emd_m": 0.3, "trans_cm": 8.0, "rot_deg": 4.0},
                 {"cd_cm": 21.5, "emd_m": 0.4, "trans_cm": 9.0, "rot_deg": 30.0})
    text = pipeline.evaluation_markdown(s)
    assert "### Errors by detections so far" in text
    page = report_html([Section("Shape and pose estimation", text)], [("total", 1.0)])
    assert "###" not in page
    assert "<h3>Errors by detections so far (frame-pooled means, cm)</h3>" in page


def test_demo_config_sizes_and_seed():
    cfg = DemoConfig().generate_config()
    assert (cfg.name, cfg.seed, cfg.n_vehicles, cfg.n_val_vehicles, cfg.tracks_per_vehicle) == (
        "paper", 123, 16, 15, 1)
    assert (cfg.mean_frames, cfg.max_distance, cfg.sensor) == (70.0, 60.0, "vlp16")  # paper's
    tiny = DemoConfig(preset="tiny", vehicles=0, tracks_per_vehicle=0).generate_config()
    assert (tiny.n_vehicles, tiny.n_val_vehicles, tiny.tracks_per_vehicle) == (6, 2, 2)
    for bad in ({"vehicles": 1}, {"vehicles": -2}, {"tracks_per_vehicle": -1}):
        with pytest.raises(ConfigError):
            DemoConfig(**bad)


def test_sc_seg_uses_the_degraded_masks(tmp_path):
    """The amodal step on a 2-frame kitti-tiny scene: the scene's 2D masks are degraded as
    `seqshape scenes` degrades them by default, and the report says which masks sc-seg used."""
    from seqshape.model.estimator import Estimator
    from seqshape.scripts.demo import terminal_summary

    res = amodal_demo_step(tmp_path, estimator=Estimator.load("sequential"), frames=2,
                           overlay_frames=1)
    settings = json.loads((tmp_path / "scenes" / "scene.json").read_text())
    assert settings["degrade"] == json.loads(json.dumps(asdict(DegradeConfig())))
    assert "sc-seg used degraded 2D instance masks" in res.markdown
    assert "outlines moved by 1-3 px, 5 % of small instances missed" in res.markdown
    assert re.search(r"\| sc-seg \| \d+ \|", res.table)
    assert res.table in res.markdown
    assert res.table in terminal_summary({"amodal_table": res.table})
    assert masks_note(NO_DEGRADE).startswith("sc-seg used the exact visible 2D masks")


@pytest.mark.parametrize("seq, base, verdict", [(10.0, 12.0, "better"), (12.0, 12.5, "same"),
                                                (-0.2, -0.1, "better"), (0.3, -0.5, "worse"),
                                                (0.0, 0.0, "same"), (0.1, 0.0, "worse")])
def test_comparison_verdicts_by_hand(seq, base, verdict):
    """Relative change against a positive baseline; by the sign of the difference when the
    baseline is not positive (a CD below the floor)."""
    assert fusion.Comparison("CD above the floor", "cm", seq, base).verdict == verdict
