"""The shipped weights: they load, refuse foreign files, and the sequential model beats the
per-frame baseline on a small fixed val set of vehicles it never saw (seed 123)."""

import numpy as np
import pytest
import torch

from seqshape import Estimator
from seqshape.data import TrackDataset
from seqshape.errors import DataError
from seqshape.evaluation.report import summarize
from seqshape.evaluation.runner import evaluate_tracks
from seqshape.sim.generate import generate_dataset, preset_config


@pytest.fixture(scope="module")
def shipped():
    # the networks' own placement; the refined ones below
    return {k: Estimator.from_pretrained(k, threads=1, refiner="none")
            for k in ("sequential", "baseline")}


@pytest.fixture(scope="module")
def summary(shipped, tmp_path_factory):
    out = tmp_path_factory.mktemp("val123")
    cfg = preset_config("paper", seed=123, n_vehicles=10, n_val_vehicles=5, tracks_per_vehicle=4,
                        mean_frames=40.0, max_frames=80)
    generate_dataset(cfg, out, workers=1)
    val = TrackDataset(out).split("val")
    return summarize(evaluate_tracks(shipped, val, emd_every=0, workers=0, seed=0))


def test_shipped_weights_load_and_run(shipped):
    assert shipped["sequential"].recurrent and not shipped["baseline"].recurrent
    pts = np.random.default_rng(0).normal(size=(200, 3)).astype(np.float32) + [12, 3, -1]
    for est in shipped.values():
        (e,) = est.step(["a"], [pts])
        assert e.complete.shape[1] == 3 and np.isfinite(e.complete).all()
        assert e.pose.shape == (4,) and np.isfinite(e.pose).all()
        est.reset()


def test_sequential_beats_baseline_on_fixed_val_set(summary):
    # The shipped small models (round 9) separate clearly on heading (paper val split, points
    # alone: 14.64 vs 29.39 deg; here 4.59 vs 8.32) and narrowly on CD (24.19 vs 24.76 cm; here
    # 22.03 vs 22.43) and translation (16.48 vs 17.55 cm; here 11.88 vs 12.01). The set and the
    # weights are fixed, so the run is deterministic: the narrow margins are far above
    # numerical noise, and any new weights must keep the sequential model ahead on this set too.
    seq, base = summary["sequential"], summary["baseline"]
    assert seq["rot_deg"] < 0.8 * base["rot_deg"]
    assert seq["cd_cm"] < base["cd_cm"] and seq["trans_cm"] < base["trans_cm"]


def test_the_loaders_place_with_the_shipped_refiner_by_default(tmp_path):
    from seqshape.model.placement import PlacementRefiner

    pts = np.random.default_rng(1).normal(size=(150, 3)).astype(np.float32) * [2, 1, 0.5]
    pts += np.array([14, -4, -1], np.float32)
    for kind in ("sequential", "baseline"):
        default = Estimator.from_pretrained(kind, threads=1, backend="torch")
        assert isinstance(default.refiner, PlacementRefiner)
        assert isinstance(Estimator.load(kind, threads=1, backend="torch").refiner,
                          PlacementRefiner)
        own = Estimator.from_pretrained(kind, threads=1, backend="torch", refiner="none")
        assert own.refiner is None
        # the default step is the refined one: the network's estimate, then the correction
        (a,), (b,) = default.step(["t"], [pts]), own.step(["t"], [pts])
        assert np.abs(a.pose[:2] - b.pose[:2]).max() > 1e-4


def test_foreign_and_corrupt_files_are_clear_errors(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(DataError, match="bad.pt"):
        Estimator.from_checkpoint(bad)
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(DataError, match="foreign.pt"):
        Estimator.from_checkpoint(foreign)


@pytest.fixture(scope="module")
def refined_summary(summary, tmp_path_factory):
    from seqshape.model.placement import load_refiner

    out = next(iter(tmp_path_factory.getbasetemp().glob("val123*")))
    refiner = load_refiner("pretrained")
    ests = {k: Estimator.from_pretrained(k, threads=1, refiner=refiner)
            for k in ("sequential", "baseline")}
    return summarize(evaluate_tracks(ests, TrackDataset(out).split("val"), emd_every=0,
                                     workers=0, seed=0))


def test_shipped_refiner_places_both_networks_better(summary, refined_summary):
    # Vehicles and tracks the refiner never saw (generator seed 123); figures in
    # docs/model.md, "Placement refinement". The set is fixed: deterministic.
    for m in ("sequential", "baseline"):
        assert refined_summary[m]["trans_cm"] < 0.8 * summary[m]["trans_cm"]
        assert refined_summary[m]["cd_cm"] < summary[m]["cd_cm"]
        assert refined_summary[m]["rot_deg"] < 1.05 * summary[m]["rot_deg"]
