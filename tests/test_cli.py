"""The ``seqshape`` command: options and defaults as released, every option's help shows its
default, output folders that cannot be written, ``export-tracks`` (and the deprecated
``label --export-tracks``)."""

from __future__ import annotations

import argparse
import errno
import json
import os
from pathlib import Path

import numpy as np
import pytest
from _kitti_fixture import write_box_kitti

from seqshape.cli import COMMANDS, build_parser, command_parser, main
from seqshape.data import TrackDataset
from seqshape.scripts.scenes import degrade_config
from seqshape.sim.degrade import NO_DEGRADE, DegradeConfig

# options added since that release (issue 17: inference backends, labelling workers;
# label --resume; evaluate and label --max-points; evaluate --smoothing, --size-scale)
ADDED = {"label": {"backend": "auto-float", "workers": 1, "resume": False,
                   "placement": "pretrained", "max_points": None, "image_size": None,
                   "ego_poses": "given"},
         "evaluate": {"backend": "auto-float", "refiner": "pretrained", "max_points": None,
                      "smoothing": "none", "baseline_refiner": "same", "size_scale": "1",
                      "track_memory": "auto"},
         "tracks": {"ego_poses": "given"}}

# vars(parse_args(argv)) of the release before the options came from the config dataclasses
# (33229e9), plus ADDED; paths as strings
RELEASED = {
    "demo": (["--out", "o"], {
        "baseline": "pretrained", "checkpoint": "pretrained", "emd_every": 20, "max_tracks": None,
        "out": "o", "preset": "paper", "seed": 123, "tracks_per_vehicle": 1, "vehicles": 16,
        "workers": 2}),
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
        "split_by": "log", "val_fraction": 0.2, "workers": 1, "keep_duplicates": False,
        **ADDED["tracks"]}),
    "tracks+flags": (["--dataset", "kitti", "--root", "r", "--out", "o", "--no-reference",
                      "--split", "val", "--margin", "0.5"], {
        "classes": "car,van,truck,bus,trailer", "dataset": "kitti", "ground": "plane",
        "margin": 0.5, "min_points": 10, "out": "o", "reference": False,
        "reference_points": 2048, "root": "r", "sequence": None, "shard": "1/1",
        "split": "val", "split_by": "log", "val_fraction": 0.2, "workers": 1,
        "keep_duplicates": False, **ADDED["tracks"]}),
}


def _command_parser(name: str) -> argparse.ArgumentParser:
    return command_parser(name)[1]


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


def _help_problems(parser: argparse.ArgumentParser) -> list[str]:
    """What the help of ``parser`` lacks: an action without help; an option that is neither
    required nor says its default (a switch: "default: off" or its default in words; a value
    option: its default value itself, or the default in words when the value is None)."""
    formatter = parser._get_formatter()
    problems = []
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._VersionAction,
                               argparse._SubParsersAction)):
            continue
        name = "/".join(action.option_strings) or action.dest
        if not (action.help or "").strip():
            problems.append(f"{name}: no help")
            continue
        if not action.option_strings or action.required:
            continue
        text = " ".join(formatter._expand_help(action).split())
        if "default" not in text.lower():
            problems.append(f"{name}: no default in {text!r}")
        elif action.nargs != 0 and action.default is not None and str(action.default) not in text:
            problems.append(f"{name}: default {action.default!r} not shown in {text!r}")
    return problems


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_option_has_help_that_shows_its_default(name):
    assert _help_problems(command_parser(name)[1]) == []


def test_help_checker_finds_the_gaps():
    parser = argparse.ArgumentParser(formatter_class=argparse.HelpFormatter)
    parser.add_argument("--quiet", action="store_true", help="say less")
    parser.add_argument("--seed", type=int, default=0, help="seed")
    parser.add_argument("--window", type=int, default=None, help="frames per window")
    parser.add_argument("--mode", default="fast", help="the mode (default: slow)")
    parser.add_argument("--lr", type=float)
    assert [p.split(":")[0] for p in _help_problems(parser)] == [
        "--quiet", "--seed", "--window", "--mode", "--lr"]


def test_switches_and_the_top_level_options_show_their_defaults():
    assert _help_problems(build_parser()) == []
    text = " ".join(_command_parser("train").format_help().split())
    assert "write no TensorBoard logs (default: off)" in text
    assert "--model {sequential,baseline} the recurrent model or the per-frame baseline " \
           "(default: sequential)" in text
    assert "--seed SEED seed (default: the preset's)" in text
    assert "--preset PRESET training preset: small (2 CPU cores), paper (GPU), smoke " \
           "(tests) (default: small)" in text


def _scenes(out: Path) -> list[str]:
    return ["scenes", "--out", str(out), "--frames", "2", "--sequences", "1"]


def _one_error_line(capsys, command: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"seqshape {command}: error: "), err
    assert "Traceback" not in err[0]
    return err[0]


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0,
                    reason="root writes into read-only folders")
def test_a_read_only_output_folder_is_one_line_naming_it(tmp_path, capsys):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o500)
    try:
        assert main(_scenes(folder / "scenes")) == 1
        line = _one_error_line(capsys, "scenes")
        assert str(folder / "scenes") in line and "Permission denied" in line
        assert list(folder.iterdir()) == []
    finally:
        folder.chmod(0o700)


def test_an_output_path_through_a_file_is_one_line_naming_it(tmp_path, capsys):
    (tmp_path / "file").write_text("not a folder")
    assert main(_scenes(tmp_path / "file" / "scenes")) == 1
    line = _one_error_line(capsys, "scenes")
    assert str(tmp_path / "file") in line
    assert (tmp_path / "file").read_text() == "not a folder"


def test_a_full_disk_is_one_line_and_leaves_nothing_half_written(tmp_path, capsys,
                                                                  monkeypatch):
    def full(_fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # as write(2) raises it

    monkeypatch.setattr(os, "fsync", full)
    out = tmp_path / "scenes"
    assert main(_scenes(out)) == 1
    line = _one_error_line(capsys, "scenes")
    # the atomic writer names the file it was writing (write(2)'s error names none)
    assert f"{out / 'scene.json'}: {os.strerror(errno.ENOSPC)} (the disk is full" in line
    assert list(out.rglob("*")) == []  # the settings file's temporary copy is gone too


def test_top_level_help_lists_every_command(capsys):
    assert main([]) == 2
    text = capsys.readouterr().out
    assert all(name in text for name in COMMANDS)


def _tiny_kitti(root: Path) -> Path:
    """A hand-built KITTI tracking sequence 0000: two box cars seen from the sensor side."""
    return write_box_kitti(root)


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


def test_train_progress_counts_the_steps_asked(tmp_path, capsys, monkeypatch):
    data = tmp_path / "data"
    assert main(["generate", "--preset", "tiny", "--vehicles", "3", "--out", str(data)]) == 0
    monkeypatch.setenv("SEQSHAPE_PROGRESS", "1")
    capsys.readouterr()
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "run"), "--preset",
                 "smoke", "--stage-steps", "5,2,3", "--no-tensorboard"]) == 0
    bars = capsys.readouterr().err.replace("\r", "\n")
    for stage, steps in ((1, 5), (2, 2), (3, 3)):
        final = [line for line in bars.splitlines() if line.startswith(f"stage {stage}/3")][-1]
        assert f"| {steps}/{steps} [" in final and "step/s" in final and "frames/s=" in final
    assert "‰" not in bars
