"""Flips per track and errors by detections so far in the evaluation report (issue 19)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from seqshape.data import Track
from seqshape.evaluation import evaluate_tracks, metrics_markdown, summarize
from seqshape.evaluation.metrics import flip_stats
from seqshape.evaluation.report import DETECTION_LABELS, FLIP_DEG, detection_summary
from seqshape.geometry import canonical_to_sensor
from seqshape.testing import box_shell


def _track(track_id: str, n_frames: int = 10) -> Track:
    """A car driving along x, 1 m per frame, 12 m ahead of the sensor and 3 m to the left."""
    t = np.arange(n_frames, dtype=np.float64)
    poses = np.stack([12.0 + t, np.full_like(t, 3.0), np.full_like(t, -1.2),
                      np.full_like(t, 0.3)], axis=1)
    complete = box_shell(400, 0, (4.0, 1.8, 1.5), dtype=np.float32)
    points = [canonical_to_sensor(complete[:50], p) for p in poses]
    return Track(track_id, points, poses, complete, np.array([4.0, 1.8, 1.5]), t * 0.1,
                 {"split": "val"})


@dataclass
class _Est:
    complete: np.ndarray
    pose: np.ndarray


class _Reverser:
    """Returns the true pose and shape, with the yaw turned by pi on chosen frames."""

    recurrent = False

    def __init__(self, tracks: list[Track], flipped: dict[str, set[int]],
                 yaw_offset: float = 0.0):
        self.tracks = {tr.track_id: tr for tr in tracks}
        self.flipped = flipped
        self.yaw_offset = yaw_offset
        self.frame: dict[str, int] = {}

    def step(self, track_ids, point_lists):
        out = []
        for tid in track_ids:
            t = self.frame.get(tid, 0)
            self.frame[tid] = t + 1
            tr = self.tracks[tid]
            pose = tr.poses[t].copy()
            pose[3] += self.yaw_offset
            if t in self.flipped.get(tid, set()):
                pose[3] += np.pi
            out.append(_Est(tr.complete_in_frame(t), pose))
        return out

    def reset(self, track_id=None):
        self.frame.pop(track_id, None)


def _summary(tracks, flipped):
    res = evaluate_tracks({"sequential": _Reverser(tracks, flipped)}, tracks, emd_every=0,
                          workers=0, floor="split", hints=False)
    return summarize(res)


def test_reversed_in_3_of_10_frames_is_30_percent_and_one_track():
    s = _summary([_track("a")], {"a": {2, 5, 7}})
    f = s["details"]["sequential"]["flips"]
    assert f["n_frames"] == 10 and f["flipped_frames"] == 3
    assert f["flip_pct"] == pytest.approx(30.0)
    assert (f["flipped_tracks"], f["n_tracks"]) == (1, 1)
    assert f["tracks_with_flip_pct"] == pytest.approx(100.0)
    assert f["track_flip_median_pct"] == pytest.approx(30.0)
    md = metrics_markdown(s)
    assert "sequential 30.0 % of frames, 1 of 1 tracks (100.0 %) with a flip" in md


def test_rotation_gain_without_flips_leaves_the_flipped_frames_out():
    tracks = [_track("a")]
    res = evaluate_tracks({"sequential": _Reverser(tracks, {"a": {2, 5, 7}}, yaw_offset=0.1),
                           "baseline": _Reverser(tracks, {}, yaw_offset=0.2)},
                          tracks, emd_every=0, workers=0, floor="split", hints=False)
    s = summarize(res)
    # sequential: 7 frames 0.1 rad off, 3 turned around (pi - 0.1); baseline 0.2 everywhere
    assert s["sequential"]["rot_deg"] == pytest.approx(np.degrees((0.7 + 3 * (np.pi - 0.1)) / 10))
    assert s["above_floor"]["rot_pct"] > 300
    assert s["above_floor"]["rot_noflip_pct"] == pytest.approx(-50.0)
    assert "(without 180-degree flips -50.0 %)" in metrics_markdown(s)


def test_clean_track_has_no_flip_and_median_over_tracks():
    s = _summary([_track("a")], {})
    f = s["details"]["sequential"]["flips"]
    assert f["flipped_frames"] == 0 and f["flipped_tracks"] == 0
    assert f["flip_pct"] == 0.0 and f["tracks_with_flip_pct"] == 0.0
    assert f["track_flip_median_pct"] == 0.0
    # three tracks flipped in 0, 1 and 4 of 10 frames: median track share 10 %
    s = _summary([_track("a"), _track("b"), _track("c")], {"b": {0}, "c": {1, 2, 3, 9}})
    f = s["details"]["sequential"]["flips"]
    assert f["flip_pct"] == pytest.approx(100 * 5 / 30)
    assert (f["flipped_tracks"], f["n_tracks"]) == (2, 3)
    assert f["track_flip_median_pct"] == pytest.approx(10.0)


def test_flip_stats_threshold_and_unknown_poses():
    rot = np.radians([FLIP_DEG + 1.0, FLIP_DEG - 1.0, np.nan, np.nan])
    s = flip_stats(rot, np.array(["a", "a", "a", "b"]), FLIP_DEG)
    assert (s["n_frames"], s["n_tracks"], s["flipped_frames"]) == (2, 1, 1)  # b: no known pose
    assert s["flip_pct"] == 50.0
    with pytest.raises(ValueError, match="equal-length"):
        flip_stats(rot, np.array(["a"]), FLIP_DEG)


def _records(tracks: dict[str, tuple[list[float], list[float], list[float]]]):
    """Records of one method from ``{track: (n_det, distance_m, cd_m)}``; the translation
    error is half the CD and the rotation 0.1 rad."""
    tid, n_det, dist, cd = [], [], [], []
    for name, (n, d, c) in tracks.items():
        tid += [name] * len(n)
        n_det += n
        dist += d
        cd += c
    cd = np.array(cd)
    return {"track_id": np.array(tid), "n_det": np.array(n_det), "distance_m": np.array(dist),
            "cd_m": cd, "trans_m": cd / 2, "rot_rad": np.full(len(cd), 0.1)}


def test_errors_by_detections_moving_and_parked():
    n = list(range(1, 21))  # detections 1..20: bins 1, 2-4, 5-8, 9-16, 17+ hold 1, 3, 4, 8, 4
    moving = (n, [10.0 + 0.5 * k for k in n], [0.4] + [0.3] * 15 + [0.2] * 4)
    parked = (n, [20.0] * 20, [0.3] * 20)
    by_det, ratio = detection_summary(_records({"m": moving, "p": parked}))
    assert list(by_det) == ["all", "moving", "parked"]
    assert list(by_det["moving"]) == list(DETECTION_LABELS)
    assert [by_det["moving"][lab]["n_frames"] for lab in DETECTION_LABELS] == [1, 3, 4, 8, 4]
    assert by_det["moving"]["1"]["cd_cm"] == pytest.approx(40.0)
    assert by_det["moving"]["17+"]["trans_cm"] == pytest.approx(10.0)
    assert by_det["all"]["17+"]["cd_cm"] == pytest.approx(25.0)  # 4 frames at 20, 4 at 30
    assert ratio["moving"]["cd"] == pytest.approx(0.5)
    assert ratio["moving"]["trans"] == pytest.approx(0.5)
    assert ratio["parked"]["cd"] == pytest.approx(1.0)
    assert ratio["all"]["cd"] == pytest.approx(25.0 / 35.0)
    # the ratio compares each track with itself: two parked tracks with constant errors
    # 0.2 m (20 frames) and 0.4 m (40 frames) pool to 36.7 cm at 17+ against 30 cm at 1
    by_det, ratio = detection_summary(_records({
        "p1": (n, [20.0] * 20, [0.2] * 20),
        "p2": (list(range(1, 41)), [9.0] * 40, [0.4] * 40)}))
    assert by_det["parked"]["17+"]["cd_cm"] == pytest.approx((4 * 20 + 24 * 40) / 28)
    assert ratio["parked"]["cd"] == pytest.approx(1.0)
    # a short track never reaches 17 detections: no ratio
    _, ratio = detection_summary(_records({"s": ([1, 2, 3], [5.0, 6.0, 7.0], [0.3] * 3)}))
    assert ratio == {"all": {"cd": None, "trans": None}, "moving": {"cd": None, "trans": None}}


def test_markdown_table_by_detections():
    s = _summary([_track("a", 20)], {"a": {0}})
    d = s["details"]["sequential"]
    assert d["by_detections"]["moving"]["1"]["flip_pct"] == 100.0
    assert d["by_detections"]["moving"]["17+"]["flip_pct"] == 0.0
    assert d["late_over_first"]["moving"]["trans"] is None  # no error at the first: no ratio
    md = metrics_markdown(s)
    assert "### Errors by detections so far" in md
    row = next(line for line in md.splitlines() if line.startswith("| moving | sequential |"))
    cells = [c.strip() for c in row.split("|")]
    assert cells[3] == "1 / 4" and cells[-3:-1] == ["n/a", "n/a"]


def test_late_over_first_above_the_cd_floor():
    """The CD ratio above each track's CD floor, by hand: a moving track whose CD falls from
    40 to 20 cm over a 15 cm floor (ratio 5/25 = 0.2, against 0.5 for the raw CD), and a parked
    one at 30 cm over a 10 cm floor (1.0)."""
    from seqshape.evaluation.report import with_floor
    from seqshape.evaluation.runner import EvalResult

    n = list(range(1, 21))
    rec = _records({"m": (n, [10.0 + 0.5 * k for k in n], [0.4] + [0.3] * 15 + [0.2] * 4),
                    "p": (n, [20.0] * 20, [0.3] * 20)})
    rec["method"] = np.array(["sequential"] * len(rec["cd_m"]))
    floors = {"track_id": np.array(["m", "p"]), "floor_m": np.array([0.15, 0.10]),
              "n_pred": np.array([1024, 1024]), "method": np.array(["split", "split"])}
    result = EvalResult(rec, floors, {"n_pred_points": {"sequential": 1024}})
    above = with_floor(result, "sequential")
    np.testing.assert_allclose(above["cd_above_floor_m"][rec["track_id"] == "m"],
                               rec["cd_m"][rec["track_id"] == "m"] - 0.15)
    _, ratio = detection_summary(above)
    assert ratio["moving"]["cd"] == pytest.approx(0.5)
    assert ratio["moving"]["cd_above_floor"] == pytest.approx(0.05 / 0.25)
    assert ratio["parked"]["cd_above_floor"] == pytest.approx(1.0)


def test_world_travel_by_hand():
    """A car parked at (20, 3) in the fixed frame, seen from an ego driving 1 m per frame along
    x: 0 m of travel although its sensor-frame distance changes; the same track with the car
    moving 0.5 m a frame travels 4.5 m (10 frames); without ego poses on a real track: NaN."""
    from seqshape.evaluation.runner import world_travel

    n = 10
    egos = [np.eye(4) for _ in range(n)]
    for k, e in enumerate(egos):
        e[0, 3] = float(k)  # the sensor at x = k in the fixed frame
    parked = np.array([[20.0 - k, 3.0, -1.0, 0.1] for k in range(n)])  # in each sensor frame
    moving = np.array([[20.0 - k + 0.5 * k, 3.0, -1.0, 0.1] for k in range(n)])
    pts = [np.zeros((5, 3))] * n
    meta = {"split": "val", "ego_poses": [e.tolist() for e in egos]}
    times = np.arange(n) * 0.1
    assert world_travel(Track("p", pts, parked, None, np.ones(3), times, meta)) == \
        pytest.approx(0.0, abs=1e-12)
    assert world_travel(Track("m", pts, moving, None, np.ones(3), times, meta)) == \
        pytest.approx(4.5)
    parked_nan = parked.copy()
    parked_nan[3] = np.nan  # an unknown pose is skipped
    assert world_travel(Track("q", pts, parked_nan, None, np.ones(3), times, meta)) == \
        pytest.approx(0.0, abs=1e-12)
    real = Track("r", pts, parked, None, np.ones(3), times, {"split": "val", "source": "real"})
    assert np.isnan(world_travel(real))


def test_passed_group_and_flips_by_group():
    """"passed": view changing, travel < 1 m in the fixed frame; its flips counted apart."""
    from seqshape.evaluation.report import GROUP_NAMES, flip_groups, motion_groups

    n = list(range(1, 11))
    rec = _records({"drive": (n, [10.0 + k for k in n], [0.3] * 10),
                    "passed": (n, [30.0 - 2 * k for k in n], [0.3] * 10),
                    "still": (n, [15.0] * 10, [0.3] * 10)})
    rec["world_travel_m"] = np.repeat([9.0, 0.2, 0.0], 10)
    rec["rot_rad"] = rec["rot_rad"].copy()
    rec["rot_rad"][10:13] = np.pi  # three frames of the passed track flipped
    g = motion_groups(rec)
    assert list(g) == ["all", "moving", "parked", "passed"]
    assert g["passed"].sum() == 10 and g["passed"][10:20].all()
    assert g["moving"].sum() == 20 and g["parked"].sum() == 10
    flips = flip_groups(rec)
    assert flips["passed"] == pytest.approx(30.0)
    assert flips["moving"] == pytest.approx(15.0)
    assert flips["parked"] == 0.0
    assert flips["all"] == pytest.approx(10.0)
    assert set(GROUP_NAMES) >= set(g)
    del rec["world_travel_m"]  # records of an older version: no passed group
    assert "passed" not in motion_groups(rec)
