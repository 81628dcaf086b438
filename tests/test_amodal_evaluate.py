"""Mask evaluation against hand-computed IoUs and misses."""

import json
from pathlib import Path

import numpy as np
import pytest

from seqshape.amodal.evaluate import (
    breakdown,
    default_row_name,
    evaluate_files,
    evaluate_image,
    mask_iou_matrix,
    match_masks,
    reference_kind,
    resolve_pairs,
    summarise,
    within_distance,
    write_mask_report,
)
from seqshape.cli import main
from seqshape.data.kins import image_entry, kins_annotation, write_kins
from seqshape.errors import ConfigError, DataError


def box(y0, x0, h, w, size=(100, 100)):
    m = np.zeros(size, bool)
    m[y0:y0 + h, x0:x0 + w] = True
    return m


def test_iou_matrix_hand_computed():
    a, b = box(0, 0, 10, 10), box(0, 2, 10, 10)  # overlap 8 x 10 = 80, union 120
    iou = mask_iou_matrix([a, b], [a])
    assert iou.shape == (2, 1)
    assert iou[0, 0] == pytest.approx(1.0) and iou[1, 0] == pytest.approx(80 / 120)
    assert mask_iou_matrix([], [a]).shape == (0, 1)


def test_hungarian_beats_greedy():
    # greedy would give g0 its best (p0, IoU .8) and leave g1 with nothing;
    # the optimum pairs p0-g1 and p1-g0
    g0, g1 = box(0, 0, 10, 10), box(0, 6, 10, 10)
    p0 = box(0, 2, 10, 10)  # IoU(g0) = 80/120, IoU(g1) = 60/140
    p1 = box(0, 0, 10, 6)   # IoU(g0) = 60/100, IoU(g1) = 0
    pred_of_gt, iou = match_masks([p0, p1], [g0, g1])
    assert pred_of_gt.tolist() == [1, 0]
    assert iou == pytest.approx([0.6, 60 / 140])


def test_misses_unmatched_prediction_and_low_iou():
    g = [box(0, 0, 10, 10), box(50, 50, 10, 10), box(80, 80, 10, 10)]
    p = [box(0, 2, 10, 10),          # IoU 2/3 with g0: a match
         box(50, 50, 10, 4),         # IoU 0.4 with g1: a miss
         box(30, 0, 5, 5)]           # overlaps nothing: unmatched prediction; g2: no partner
    res, unmatched = evaluate_image(7, p, g, gt_visible_area=[100, 50, 100],
                                    gt_distance=[10, 20, 60])
    assert [r.missed for r in res] == [False, True, True]
    assert [r.pred_index for r in res] == [0, 1, -1]
    assert unmatched == 2
    m = summarise(res, unmatched)
    assert m["n"] == 3 and m["misses"] == 2
    assert m["miss_pct"] == pytest.approx(200 / 3)
    assert m["miou"] == pytest.approx(2 / 3)
    assert m["miou_with_misses"] == pytest.approx((2 / 3) / 3)
    assert m["unmatched_predictions"] == 2
    assert res[1].occlusion == pytest.approx(0.5)
    bd = breakdown(res)
    assert bd["occlusion"]["none (<1%)"]["n"] == 2
    assert bd["occlusion"]["largely (30-70%)"]["misses"] == 1
    assert bd["distance"]["50-80 m"]["miss_pct"] == pytest.approx(100.0)


def test_empty_image_and_no_predictions():
    res, unmatched = evaluate_image(0, [], [])
    assert res == [] and unmatched == 0
    res, unmatched = evaluate_image(0, [box(0, 0, 3, 3)], [])
    assert unmatched == 1
    res, _ = evaluate_image(0, [], [box(0, 0, 3, 3)])
    assert summarise(res)["miss_pct"] == 100.0 and np.isnan(summarise(res)["miou"])


def test_within_distance_keeps_near_instances_only():
    g = [np.zeros((4, 4), bool) for _ in range(3)]
    for k, m in enumerate(g):
        m[k, :] = True
    res, _ = evaluate_image(0, [g[0]], g, gt_distance=[10.0, 90.0, float("nan")])
    near = within_distance(res, 80.0)
    assert [r.gt_index for r in near] == [0]
    assert summarise(near)["miss_pct"] == 0.0 and summarise(res)["misses"] == 2


def _kins_file(path, masks, visible, categories, distances=None):
    """A one-image KINS file of the boxes ``masks`` (amodal) and ``visible``."""
    anns = []
    for k, (a, v, c) in enumerate(zip(masks, visible, categories, strict=True)):
        ann = kins_annotation(k + 1, 0, c, a, v, 0, 0, track_id=k)
        if distances is not None:
            ann["distance"] = distances[k]
        anns.append(ann)
    write_kins(path, [image_entry(0, "0000", 0, 100, 100)], anns)
    return path


@pytest.fixture
def label_pair(tmp_path):
    g0, g1 = box(0, 0, 10, 10), box(50, 50, 10, 10)
    gt = _kins_file(tmp_path / "gt.json", [g0, g1], [box(0, 0, 10, 5), g1], [4, 7],
                    distances=[10.0, 40.0])
    # p0: IoU 80/120 with g0 (a match); p1: IoU 40/100 with g1 (a miss, and unmatched)
    pred = _kins_file(tmp_path / "pred.json", [box(0, 2, 10, 10), box(50, 50, 10, 4)],
                      [box(0, 2, 10, 10), box(50, 50, 10, 4)], [4, 7])
    return pred, gt


def test_write_mask_report_hand_computed(label_pair, tmp_path):
    out = tmp_path / "report"
    table = write_mask_report([label_pair], out, name="run", max_distance=20.0)
    m = json.loads((out / "metrics.json").read_text())
    assert (m["n"], m["misses"], m["unmatched_predictions"]) == (2, 1, 1)
    assert m["miss_pct"] == pytest.approx(50.0)
    assert m["miou"] == pytest.approx(2 / 3) and m["miou_with_misses"] == pytest.approx(1 / 3)
    near = m["within_max_distance"]  # g0 only (10 m; g1 is 40 m away)
    assert (near["n"], near["misses"], near["max_distance_m"]) == (1, 0, 20.0)
    assert m["breakdown"]["occlusion"]["largely (30-70%)"]["n"] == 1  # g0: half visible
    assert m["breakdown"]["distance"]["30-50 m"]["misses"] == 1
    assert m["iou_threshold"] == 0.5
    assert m["pairs"] == [[str(label_pair[0]), str(label_pair[1])]]
    records = json.loads((out / "instances.json").read_text())
    assert [r["missed"] for r in records] == [False, True]
    assert [r["iou"] for r in records] == pytest.approx([80 / 120, 0.4])
    assert (out / "metrics.md").read_text() == table
    assert "| run | 2 | 50.00 | 0.667 | 0.333 | 1 |" in table
    assert "| run (<= 20 m) | 1 | 0.00 | 0.667 | 0.667 | 0 |" in table


def test_write_mask_report_categories_and_bad_distance(label_pair, tmp_path):
    write_mask_report([label_pair], tmp_path / "cars", categories=[4])
    m = json.loads((tmp_path / "cars" / "metrics.json").read_text())
    assert (m["n"], m["misses"], m["unmatched_predictions"]) == (1, 0, 0)
    assert "within_max_distance" not in m
    with pytest.raises(ConfigError, match="max-distance must be > 0"):
        write_mask_report([label_pair], tmp_path / "bad", max_distance=0.0)
    assert not (tmp_path / "bad").exists()


def test_resolve_pairs_files_and_directories(label_pair, tmp_path):
    pred, gt = label_pair
    assert resolve_pairs([pred], [gt]) == [(pred, gt)]
    pdir, gdir = tmp_path / "p", tmp_path / "g"
    pdir.mkdir()
    gdir.mkdir()
    for name in ("0001.json", "0000.json"):
        (pdir / name).write_bytes(pred.read_bytes())
        (gdir / name).write_bytes(gt.read_bytes())
    assert resolve_pairs([pdir], [gdir]) == [(pdir / "0000.json", gdir / "0000.json"),
                                             (pdir / "0001.json", gdir / "0001.json")]
    with pytest.raises(ConfigError, match="1 --pred but 2 --gt"):
        resolve_pairs([pred], [gt, gt])
    with pytest.raises(ConfigError, match="pair a file with a file"):
        resolve_pairs([pdir], [gt])
    with pytest.raises(ConfigError, match="no such file"):
        resolve_pairs([tmp_path / "none.json"], [gt])
    (pdir / "0001.json").unlink()
    with pytest.raises(ConfigError, match="missing prediction"):
        resolve_pairs([pdir], [gdir])


def test_evaluate_masks_command_prints_the_report(label_pair, tmp_path, capsys):
    out = tmp_path / "cli"
    assert main(["evaluate-masks", "--pred", str(label_pair[0]), "--gt", str(label_pair[1]),
                 "--out", str(out), "--name", "run"]) == 0
    text = capsys.readouterr().out
    assert text == (out / "metrics.md").read_text() + f"\nwrote {out / 'metrics.json'}\n"


# ----------------------------------------------------------------------------- issue 18


def test_predictions_of_another_image_size_name_both_files_and_sizes(label_pair, tmp_path):
    _, gt = label_pair
    small = tmp_path / "small.json"
    write_kins(small, [image_entry(0, "0000", 0, 50, 80)],
               [kins_annotation(1, 0, 4, box(0, 0, 10, 10, (50, 80)),
                                box(0, 0, 10, 10, (50, 80)), 0, 0)])
    with pytest.raises(DataError) as info:
        evaluate_files([(small, gt)])
    assert info.value.path == str(small)
    message = str(info.value)
    assert "'0000/000000.png' is 80x50 (width x height) here but 100x100" in message
    assert str(gt) in message


def _scenes_folder(root, pred_source):
    """A ``seqshape scenes``-like folder: scene.json of format seqshape-scenes and
    amodal/0000.json; returns the reference file."""
    (root / "amodal").mkdir(parents=True)
    (root / "scene.json").write_text(json.dumps({"format": "seqshape-scenes", "version": 1}))
    gt = root / "amodal" / "0000.json"
    gt.write_bytes(pred_source.read_bytes())
    return gt


def test_report_title_and_row_say_what_was_compared(label_pair, tmp_path):
    pred, gt = label_pair
    table = write_mask_report([(pred, gt)], tmp_path / "ref")
    assert table.startswith("**Amodal masks against the reference**")
    assert "| pred.json | 2 | 50.00 | 0.667 | 0.333 | 1 |" in table
    assert f"Compared: `{pred}` against `{gt}`." in table
    truth = _scenes_folder(tmp_path / "scenes", gt)
    table = write_mask_report([(pred, truth)], tmp_path / "truth")
    assert table.startswith("**Amodal masks against exact ground truth**")
    assert "| pred.json | 2 | 50.00 | 0.667 | 0.333 | 1 |" in table  # the same numbers
    assert json.loads((tmp_path / "truth" / "metrics.json").read_text())["n"] == 2
    # a scene.json of another format is no ground truth
    (tmp_path / "scenes" / "scene.json").write_text('{"format": "other"}')
    assert reference_kind([truth]) == "the reference"
    (tmp_path / "scenes" / "scene.json").write_bytes(b"\xff")
    assert reference_kind([truth]) == "the reference"


def test_default_row_names():
    assert default_row_name([Path("a/sc-gt.json")]) == "sc-gt.json"
    assert default_row_name([Path("labels/0000.json"), Path("labels/0001.json")]) == "labels/"
    assert default_row_name([Path("x/a.json"), Path("y/b.json")]) == "a.json + b.json"


def test_evaluate_masks_command_names_the_row_after_the_predictions(label_pair, tmp_path,
                                                                      capsys):
    out = tmp_path / "cli"
    assert main(["evaluate-masks", "--pred", str(label_pair[0]), "--gt", str(label_pair[1]),
                 "--out", str(out)]) == 0
    assert "| pred.json | 2 |" in capsys.readouterr().out


def test_evaluate_masks_command_names_a_folder_row_after_the_folder(label_pair, tmp_path,
                                                                      capsys):
    pdir, gdir = tmp_path / "sc-gt", tmp_path / "gt"
    pdir.mkdir()
    gdir.mkdir()
    (pdir / "0000.json").write_bytes(label_pair[0].read_bytes())
    (gdir / "0000.json").write_bytes(label_pair[1].read_bytes())
    assert main(["evaluate-masks", "--pred", str(pdir), "--gt", str(gdir),
                 "--out", str(tmp_path / "cli")]) == 0
    assert "| sc-gt/ | 2 | 50.00 | 0.667 | 0.333 | 1 |" in capsys.readouterr().out
