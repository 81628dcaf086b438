"""No traceback reaches a user (issue 45): every command run on a broken input ends in one
error line naming the bad file; an exception no check foresaw, and an out-of-memory error
(a ``MemoryError``, onnxruntime's ``Fail`` of a failed allocation), end in one line naming the
command, the input and what to do, with the traceback only under ``--debug``."""

from __future__ import annotations

import contextlib
import io
import json
import os
from pathlib import Path

import numpy as np
import pytest
from _kitti_fixture import write_box_kitti

from seqshape.cli import COMMANDS, main
from seqshape.data import Track, write_dataset
from seqshape.data.kins import image_entry, kins_annotation, write_kins


def run_cli(argv: list[str]) -> tuple[int, str]:
    """``seqshape ARGV`` in this process: (exit status, stderr)."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = main(argv)
    return rc, err.getvalue()


def _track(tid: str, split: str) -> Track:
    return Track(tid, [np.ones((3, 3), np.float32)], np.zeros((1, 4)), None, np.ones(3),
                 np.zeros(1), {"split": split})


@pytest.fixture(scope="module")
def broken(tmp_path_factory) -> dict[str, tuple[list[str], Path]]:
    """Command -> (its arguments, the broken file the error must name)."""
    t = tmp_path_factory.mktemp("broken")
    ds = write_dataset(t / "ds", [_track("a", "train"), _track("b", "val"), _track("c", "val")])
    for name in ("a", "b"):  # a FIFO where a track file belongs: read, it blocked
        (ds.path / "tracks" / f"{name}.npz").unlink()
        os.mkfifo(ds.path / "tracks" / f"{name}.npz")
    fifo_a, fifo_b = ds.path / "tracks" / "a.npz", ds.path / "tracks" / "b.npz"
    float64 = write_box_kitti(t / "float64", frames=2, ground_points=200)
    sweep = float64 / "velodyne" / "0000" / "000000.bin"  # written as float64
    sweep.write_bytes(np.frombuffer(sweep.read_bytes(), "<f4").astype("<f8").tobytes())
    nul = write_box_kitti(t / "nul", frames=2, ground_points=200)
    calib = nul / "calib" / "0000.txt"
    calib.write_text(calib.read_text().replace("P0: ", "P0:\0").replace(" ", "\0", 3))
    digits = write_box_kitti(t / "digits", frames=2, ground_points=200)
    labels = digits / "label_02" / "0000.txt"
    rows = [r.split() for r in labels.read_text().splitlines()]
    rows[0][1] = "7" * 400
    labels.write_text("".join(" ".join(r) + "\n" for r in rows))
    csv = t / "long.csv"
    csv.write_text("t,x,y,yaw\n0," + "9" * 200_000 + ",0,0\n")
    a = np.zeros((8, 8), bool)
    a[2:5, 2:5] = True
    images = [image_entry(0, "0000", 0, 8, 8), image_entry(1, "0000", 1, 8, 8)]
    write_kins(t / "gt.json", images, [kins_annotation(1, 0, 4, a, a, 0, 0)])
    doc = json.loads((t / "gt.json").read_text())
    doc["images"][1]["file_name"] = doc["images"][0]["file_name"]  # one image twice
    (t / "pred.json").write_text(json.dumps(doc))
    (t / "a_file").write_text("not a folder")
    out = str(t / "out")
    return {
        "demo": (["--out", str(t / "a_file")], t / "a_file"),
        "generate": (["--preset", "tiny", "--trajectories", str(csv), "--out", out + "g"], csv),
        "show": ([str(ds.path), "--track", "a", "--out", out + "s"], fifo_a),
        "stats": ([str(ds.path)], fifo_a),
        "train": (["--data", str(ds.path), "--out", out + "t"], fifo_b),
        "train-refiner": (["--data", str(ds.path), "--out", out + "r"], fifo_a),
        "pseudo-label": (["--data", str(ds.path), "--out", out + "p"], fifo_a),
        "evaluate": (["--data", str(ds.path), "--checkpoint", "pretrained", "--out",
                      out + "e"], fifo_b),
        "scenes": (["--out", str(t / "a_file"), "--sequences", "1", "--frames", "2"],
                   t / "a_file"),
        "show-scene": ([str(nul), "--sequence", "0000", "--frame", "0", "--out", out + "w"],
                       nul),
        "tracks": (["--dataset", "kitti", "--root", str(float64), "--out", out + "k"], sweep),
        "label": (["--root", str(nul), "--sequence", "0000", "--out", out + "l", "--mode",
                   "gt-accumulation"], calib),
        "export-tracks": (["--root", str(digits), "--sequence", "0000", "--out", out + "x"],
                          labels),
        "evaluate-masks": (["--pred", str(t / "pred.json"), "--gt", str(t / "gt.json"),
                            "--out", out + "m"], t / "pred.json"),
    }


def test_every_command_has_a_broken_input(broken):
    assert set(broken) == set(COMMANDS)


@pytest.mark.parametrize("command", list(COMMANDS))
def test_a_broken_input_ends_in_one_line_naming_it(broken, command, caplog):
    argv, bad = broken[command]
    rc, err = run_cli([command, *argv])
    text = err + caplog.text  # (tracks logs a skipped log as a warning, then exits 1)
    assert rc == 1, text
    assert "Traceback" not in text, text
    lines = [ln for ln in text.splitlines() if "error" in ln or "skipped" in ln]
    assert len(lines) == 1 and str(bad) in lines[0], text


def _ort_error(name: str, message: str) -> Exception:
    """onnxruntime's exception ``name`` (a stand-in of that name without onnxruntime)."""
    try:
        from onnxruntime.capi import onnxruntime_pybind11_state as ort
        return getattr(ort, name)(message)
    except ImportError:  # pragma: no cover - onnxruntime is a dependency
        return type(name, (Exception,), {})(message)


def _raising(exc: BaseException):
    def run(args):
        raise exc
    return run


@pytest.mark.parametrize("exc, words", [
    (ValueError("a check nobody wrote"), r"unexpected ValueError: a check nobody wrote "
                                         r"\(input: --dataset .*ds\); hint: check that input"),
    (MemoryError(), r"out of memory \(input: --dataset .*ds\): MemoryError"),
    # onnxruntime's RuntimeException of a failed allocation in a forward pass
    (_ort_error("RuntimeException", "[ONNXRuntimeError] : 6 : RUNTIME_EXCEPTION : Non-zero "
                "status code returned while running MatMul node. Status Message: "
                "bfc_arena.cc:376 AllocateRawInternal Failed to allocate memory for requested "
                "buffer of size 4294967296"),
     r"out of memory .*RuntimeException: .*hint: process less"),
    (_ort_error("Fail", "[ONNXRuntimeError] : 1 : FAIL : std::bad_alloc"),
     r"out of memory .*Fail: .*bad_alloc; hint: process less"),
])
def test_an_unexpected_error_is_one_line_with_the_input_and_a_hint(monkeypatch, broken, exc,
                                                                   words):
    import re

    import seqshape.scripts.stats as stats

    monkeypatch.setattr(stats, "run", _raising(exc))
    argv = broken["stats"][0]
    rc, err = run_cli(["stats", *argv])
    assert rc == 1 and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith("seqshape stats: error: ") and re.search(words, err), err
    rc, err = run_cli(["--debug", "stats", *argv])  # the traceback, then the same line
    assert rc == 1 and err.startswith("Traceback") and type(exc).__name__ in err
    assert err.strip().splitlines()[-1].startswith("seqshape stats: error: ")
