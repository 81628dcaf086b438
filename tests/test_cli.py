"""The ``seqshape`` command: options and defaults as released, every option's help shows its
default, ``export-tracks`` (and the deprecated ``label --export-tracks``)."""

from __future__ import annotations

import argparse
import importlib
import json
from pathlib import Path

import numpy as np
import pytest

from seqshape.camera import kitti_default_calib, write_calib
from seqshape.cli import COMMANDS, HelpFormatter, main
from seqshape.data import TrackDataset
from seqshape.data.kitti import KittiLabel, pose_to_label_fields, write_velodyne
from seqshape.data.kitti import write_labels as write_kitti
from seqshape.geometry import canonical_to_sensor
from seqshape.scripts.scenes import degrade_config
from seqshape.sim.degrade import NO_DEGRADE, DegradeConfig
from seqshape.testing import box_shell

# options added since that release (issue 17: inference backends, labelling workers)
ADDED = {"label": {"backend": "auto", "workers": 1}, "evaluate": {"backend": "auto"}}

# vars(parse_args(argv)) of the release before the options came from the config dataclasses
# (33229e9), plus ADDED; paths as strings
RELEASED = {
    "demo": (["--out", "o"], {
        "baseline": "pretrained", "checkpoint": "pretrained", "emd_every": 1, "max_tracks": None,
        "out": "o", "preset": "tiny", "seed": 0, "workers": 2}),
    "evaluate": (["--data", "d", "--checkpoint", "c", "--out", "o"], {
        "baseline": "pretrained", "batch_tracks": 64, "boxfit": None, "boxfit_method": "lshape",
        "checkpoint": "c", "data": "d", "emd_every": 1, "emd_points": 1024, "floor": "auto",
        "hints": True, "max_tracks": None, "offline": False, "out": "o", "seed": 0,
        "split": "auto", "view": "auto", "workers": 2, **ADDED["evaluate"]}),
    "evaluate+flags": (["--data", "d", "--checkpoint", "c", "--out", "o", "--no-boxfit",
                        "--no-hints", "--offline", "--max-tracks", "3"], {
        "baseline": "pretrained", "batch_tracks": 64, "boxfit": False, "boxfit_method": "lshape",
        "checkpoint": "c", "data": "d", "emd_every": 1, "emd_points": 1024, "floor": "auto",
        "hints": False, "max_tracks": 3, "offline": True, "out": "o", "seed": 0,
        "split": "auto", "view": "auto", "workers": 2, **ADDED["evaluate"]}),
    "label": (["--sequence", "0000"], {
        "align": True, "alpha": None, "camera": None, "checkpoint": "pretrained",
        "dataset": None, "export_tracks": None, "fit_box": False, "fit_box_below": 50,
        "instances": None, "kitti": None, "mask_fallback": True, "max_frames": None,
        "mode": "sc-gt", "observed": True, "online": False, "order": "pixel", "out": None,
        "overlays": None, "polygons": False, "refine": "smooth", "root": None,
        "sequence": "0000", "threads": 1, "trim": 1.0, "val_fraction": 0.2,
        **ADDED["label"]}),
    "label+flags": (["--sequence", "0000", "--no-align", "--no-refine", "--no-observed",
                     "--no-mask-fallback", "--fit-box", "--trim", "2.5", "--instances",
                     "i.json", "--alpha", "0.5"], {
        "align": False, "alpha": 0.5, "camera": None, "checkpoint": "pretrained",
        "dataset": None, "export_tracks": None, "fit_box": True, "fit_box_below": 50,
        "instances": "i.json", "kitti": None, "mask_fallback": False, "max_frames": None,
        "mode": "sc-gt", "observed": False, "online": False, "order": "pixel", "out": None,
        "overlays": None, "polygons": False, "refine": "none", "root": None,
        "sequence": "0000", "threads": 1, "trim": 2.5, "val_fraction": 0.2,
        **ADDED["label"]}),
    "tracks": (["--dataset", "kitti", "--root", "r", "--out", "o"], {
        "classes": "car,van,truck,bus,trailer", "dataset": "kitti", "ground": "plane",
        "margin": 0.2, "min_points": 10, "out": "o", "reference": True,
        "reference_points": 2048, "root": "r", "sequence": None, "shard": "1/1", "split": None,
        "split_by": "log", "val_fraction": 0.2, "workers": 1}),
    "tracks+flags": (["--dataset", "kitti", "--root", "r", "--out", "o", "--no-reference",
                      "--split", "val", "--margin", "0.5"], {
        "classes": "car,van,truck,bus,trailer", "dataset": "kitti", "ground": "plane",
        "margin": 0.5, "min_points": 10, "out": "o", "reference": False,
        "reference_points": 2048, "root": "r", "sequence": None, "shard": "1/1",
        "split": "val", "split_by": "log", "val_fraction": 0.2, "workers": 1}),
}


def _command_parser(name: str) -> argparse.ArgumentParser:
    module = importlib.import_module(f"seqshape.scripts.{COMMANDS[name][0]}")
    parser = argparse.ArgumentParser(prog=f"seqshape {name}", formatter_class=HelpFormatter)
    module.add_arguments(parser)
    return parser


@pytest.mark.parametrize("case", sorted(RELEASED))
def test_options_and_defaults_as_released(case):
    argv, expected = RELEASED[case]
    parsed = vars(_command_parser(case.split("+")[0]).parse_args(argv))
    assert {k: str(v) if isinstance(v, Path) else v for k, v in parsed.items()} == expected


# seqshape scenes: the DegradeConfig of argv as the release before the --degrade-* options came
# from DegradeConfig's fields (33229e9: flag by flag, by hand)
RELEASED_DEGRADE = {
    (): DegradeConfig(),
    ("--no-degrade",): NO_DEGRADE,
    ("--no-degrade", "--degrade-dilate", "3"): NO_DEGRADE,
    ("--degrade-jitter", "0.5", "2", "--degrade-dilate", "-2"):
        DegradeConfig(jitter_px=(0.5, 2.0), dilate_px=-2),
    ("--degrade-miss-small", "0.2", "--degrade-miss", "0.1", "--degrade-false", "0.5"):
        DegradeConfig(miss_rate_small=0.2, miss_rate=0.1, false_rate=0.5),
}


@pytest.mark.parametrize("argv", sorted(RELEASED_DEGRADE))
def test_scenes_degrade_options_as_released(argv):
    args = _command_parser("scenes").parse_args(["--out", "o", *argv])
    got = degrade_config(args)
    assert got == RELEASED_DEGRADE[argv]
    assert type(got.jitter_px) is tuple and type(got.dilate_px) is int
    assert all(type(getattr(got, f)) is float
               for f in ("miss_rate_small", "miss_rate", "false_rate"))


def test_scenes_degrade_help_comes_from_the_config():
    text = _command_parser("scenes").format_help()
    for flag in ("--degrade-jitter MIN MAX", "--degrade-dilate DEGRADE_DILATE",
                 "--degrade-miss-small DEGRADE_MISS_SMALL", "--degrade-miss DEGRADE_MISS",
                 "--degrade-false DEGRADE_FALSE", "--no-degrade"):
        assert flag in text
    assert "false instances per true instance (Poisson mean)" in " ".join(text.split())


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_option_has_help_that_shows_its_default(name):
    parser = _command_parser(name)
    formatter = HelpFormatter(parser.prog)
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        assert action.help, f"seqshape {name} {action.option_strings or action.dest}: no help"
        takes_value = action.option_strings and action.nargs != 0 and not action.required
        if takes_value:
            text = formatter._expand_help(action)
            assert "default" in text, f"seqshape {name} {action.option_strings}: {text!r}"


def test_top_level_help_lists_every_command(capsys):
    assert main([]) == 2
    text = capsys.readouterr().out
    assert all(name in text for name in COMMANDS)


def _tiny_kitti(root: Path, frames: int = 4) -> Path:
    """A hand-built KITTI tracking sequence 0000: two box cars seen from the sensor side."""
    size = (4.0, 1.8, 1.5)
    calib = kitti_default_calib()
    write_calib(root / "calib" / "0000.txt", calib)
    labels = []
    for t in range(frames):
        rng = np.random.default_rng(t)
        scan = [np.c_[rng.uniform([3, -10], [40, 10], (1000, 2)), np.full(1000, -1.73)]]
        for k, (x, y, v, yaw) in enumerate([(8, 2.5, 0.5, 0.2), (14, -3.0, 0.7, -0.1)]):
            pose = np.array([x + v * t, y, -1.73 + size[2] / 2, yaw])
            s = canonical_to_sensor(box_shell(3000, rng, size, dtype=np.float32), pose)
            scan.append(s[np.linalg.norm(s[:, :2], axis=1) < np.linalg.norm(pose[:2])])
            labels.append(KittiLabel(frame=t, track_id=k, type="Car", truncated=0, occluded=0,
                                     bbox=[0, 0, 1, 1], **pose_to_label_fields(pose, size, calib)))
        scan = np.vstack(scan).astype(np.float32)
        write_velodyne(root / "velodyne" / "0000" / f"{t:06d}.bin",
                       np.c_[scan, np.zeros(len(scan))])
    write_kitti(root / "label_02" / "0000.txt", labels)
    return root


def test_export_tracks_and_the_deprecated_label_flag_write_the_same(tmp_path, capsys):
    kitti = _tiny_kitti(tmp_path / "kitti")
    new, old = tmp_path / "new", tmp_path / "old"
    assert main(["export-tracks", "--kitti", str(kitti), "--sequence", "0000", "--out",
                 str(new), "--val-fraction", "0.5"]) == 0
    assert "wrote 2 tracks" in capsys.readouterr().out
    assert main(["label", "--kitti", str(kitti), "--sequence", "0000", "--export-tracks",
                 str(old), "--val-fraction", "0.5"]) == 0
    assert "use `seqshape export-tracks`" in capsys.readouterr().err
    a, b = TrackDataset(new), TrackDataset(old)
    assert a.track_ids == b.track_ids == ["0000_0000", "0000_0001"]
    manifest = json.loads((new / "manifest.json").read_text())
    assert sorted(e["split"] for e in manifest["tracks"]) == ["train", "val"]
    for x, y in zip(a, b, strict=True):
        assert x.meta["complete_source"] == "mirrored-accumulation"
        np.testing.assert_array_equal(x.complete, y.complete)
        np.testing.assert_array_equal(x.poses, y.poses)
    assert main(["export-tracks", "--kitti", str(kitti), "--sequence", "0000", "--out",
                 str(tmp_path / "bad"), "--val-fraction", "1"]) == 1
    assert "--val-fraction must be in [0, 1)" in capsys.readouterr().err
