"""``seqshape label --resume``: an interrupted multi-log run, resumed, writes the files an
uninterrupted run writes, without labelling again the logs it had finished; files made with
other settings (or none recorded, or cut short) stop the run before anything is labelled."""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
from pathlib import Path

import pytest
from _kitti_fixture import write_box_kitti

import seqshape.scripts.label as label_cli
from seqshape._version import __version__
from seqshape.amodal.labeler import (
    LabelConfig,
    label_log,
    label_settings,
    read_label_settings,
    settings_differences,
    weights_digest,
    write_labels,
)
from seqshape.cli import main
from seqshape.data.kins import read_kins
from seqshape.data.kitti import KittiTrackingSequence
from seqshape.errors import ConfigError, DataError

LOGS = ("0000", "0001", "0002")
# one pair of box cars per log, so that the logs' files differ
CARS = {"0000": ((8, 2.5, 0.5, 0.2), (14, -3.0, 0.7, -0.1)),
        "0001": ((10, -2.5, 0.4, -0.3), (18, 3.0, 0.6, 0.1)),
        "0002": ((7, 3.5, 0.3, 0.0), (12, -2.0, 0.8, 0.2))}
FRAMES = 2


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    """A KITTI root of three two-frame logs (each written as sequence 0000, then renamed)."""
    root = tmp_path_factory.mktemp("kitti3")
    for name in LOGS:
        one = write_box_kitti(tmp_path_factory.mktemp(f"log{name}"), frames=FRAMES,
                              cars=CARS[name], ground_points=300)
        for sub, suffix in (("calib", ".txt"), ("label_02", ".txt")):
            (root / sub).mkdir(exist_ok=True)
            shutil.copy(one / sub / f"0000{suffix}", root / sub / f"{name}{suffix}")
        shutil.copytree(one / "velodyne" / "0000", root / "velodyne" / name)
    return root


def _cmd(root: Path, out: Path, *extra: str, mode: str = "gt-accumulation") -> list[str]:
    return ["label", "--kitti", str(root), "--sequence", "all", "--mode", mode, "--out",
            str(out), *extra]


def _files(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative path -> bytes)."""
    return {str(p.relative_to(folder)): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _count_labelled(monkeypatch) -> list[str]:
    """The names of the logs that ``label`` labels from now on, in order."""
    names: list[str] = []
    start = label_cli.start_labels

    def counting(log, *args, **kwargs):
        names.append(log.name)
        return start(log, *args, **kwargs)

    monkeypatch.setattr(label_cli, "start_labels", counting)
    return names


def _interrupt_after(monkeypatch, k: int) -> None:
    """``label`` is interrupted (a Ctrl-C: KeyboardInterrupt) when it is about to write its
    (k+1)-th label file: k files are complete."""
    write = label_cli.write_labels
    written = []

    def failing(path, result, settings=None):
        if len(written) == k:
            raise KeyboardInterrupt
        written.append(path)
        write(path, result, settings)

    monkeypatch.setattr(label_cli, "write_labels", failing)


@pytest.fixture(scope="module")
def uninterrupted(root, tmp_path_factory) -> Path:
    """The files of one uninterrupted run over the three logs, with overlays (one worker:
    the files do not depend on it, tests/test_amodal_labeler.py)."""
    full = tmp_path_factory.mktemp("full")
    assert main(_cmd(root, full / "labels", "--overlays", str(full / "overlays"))) == 0
    assert sorted(_files(full / "labels")) == [f"{n}.json" for n in LOGS]
    assert len(_files(full / "overlays")) == len(LOGS) * FRAMES
    return full


@pytest.mark.parametrize("workers", [1, 2])
def test_interrupted_run_resumed_writes_what_one_run_writes(root, uninterrupted, tmp_path,
                                                            monkeypatch, capsys, workers):
    extra = ["--workers", str(workers), "--overlays"]
    full = uninterrupted
    part = tmp_path / "part"
    cmd = _cmd(root, part / "labels", *extra, str(part / "overlays"))
    with monkeypatch.context() as m:
        _interrupt_after(m, 1)
        assert main(cmd) == 130
    # the first log is complete, the second's label file was never written (overlays first)
    assert sorted(_files(part / "labels")) == ["0000.json"]
    assert "rerun with --resume to label only the others" in capsys.readouterr().err

    labelled = _count_labelled(monkeypatch)
    assert main([*cmd, "--resume"]) == 0
    out = capsys.readouterr().out
    assert labelled == ["0001", "0002"]  # the finished log is not labelled again
    assert "resume: 0000 skipped" in out and "resume: 1 of 3 logs skipped, 2 to label" in out
    assert "0001 skipped" not in out
    assert _files(part / "labels") == _files(full / "labels")
    assert _files(part / "overlays") == _files(full / "overlays")

    # everything done: a third run labels nothing and changes nothing
    labelled.clear()
    assert main([*cmd, "--resume"]) == 0
    assert labelled == [] and "resume: 3 of 3 logs skipped, 0 to label" in capsys.readouterr().out
    assert _files(part / "labels") == _files(full / "labels")


def test_files_record_their_settings_and_without_resume_are_overwritten(root, tmp_path,
                                                                        capsys):
    out = tmp_path / "labels"
    assert main(_cmd(root, out, "--max-frames", "1")) == 0
    doc = json.loads((out / "0001.json").read_text())
    assert list(doc) == ["info", "images", "categories", "annotations"]
    settings = doc["info"]["settings"]
    assert read_kins(out / "0001.json")["info"]["settings"] == settings  # a valid KINS file
    assert {k: settings[k] for k in ("seqshape", "dataset", "log", "camera", "max_frames",
                                     "mode", "weights", "inference", "polygons")} == {
        "seqshape": __version__, "dataset": "kitti", "log": "0001", "camera": "image_02",
        "max_frames": 1, "mode": "gt-accumulation", "weights": None, "inference": None,
        "polygons": False}
    assert settings["crop.margin"] == 0.2 and "checkpoint" not in settings
    assert len(doc["images"]) == 1
    # the labels themselves are the library's (write_labels without settings: no info)
    seq = KittiTrackingSequence(root, "0001").restrict(1)
    write_labels(tmp_path / "lib.json", label_log(seq, LabelConfig(mode="gt-accumulation")))
    lib = json.loads((tmp_path / "lib.json").read_text())
    assert "info" not in lib and {**lib, "info": doc["info"]} == doc
    # without --resume, other settings overwrite the files, as before
    assert main(_cmd(root, out, "--polygons")) == 0
    doc = json.loads((out / "0001.json").read_text())
    assert doc["info"]["settings"]["polygons"] is True and len(doc["images"]) == FRAMES
    assert isinstance(doc["annotations"][0]["a_segm"], list)


def test_other_settings_stop_the_run_before_it_labels(root, tmp_path, monkeypatch, capsys):
    out = tmp_path / "labels"
    assert main(_cmd(root, out, "--sequence", "0000,0001")) == 0
    before = _files(out)
    capsys.readouterr()
    labelled = _count_labelled(monkeypatch)
    # --sequence all: 0002 has no file; 0000 and 0001 were made without --polygons
    assert main([*_cmd(root, out, "--polygons"), "--resume"]) == 1
    err = capsys.readouterr().err
    assert str(out / "0000.json") in err and "polygons: False there vs True now" in err
    assert "use another --out folder, or run without --resume" in err
    assert labelled == [] and _files(out) == before
    # --max-frames changes the labels: a setting too
    with pytest.raises(ConfigError, match=r"max_frames: None there vs 1 now"):
        label_cli.run(_parse(_cmd(root, out, "--max-frames", "1", "--resume")))
    # the same settings: the two logs skipped, the third labelled
    assert main([*_cmd(root, out), "--resume"]) == 0
    assert labelled == ["0002"] and _files(out) == {**before, "0002.json": (out / "0002.json")
                                                    .read_bytes()}


def _parse(argv: list[str]):
    """The options of ``seqshape label`` (``argv`` without the command)."""
    parser = argparse.ArgumentParser()
    label_cli.add_arguments(parser)
    return parser.parse_args(argv[1:])


def test_a_cut_short_or_foreign_file_is_refused_naming_it(root, tmp_path, capsys):
    out = tmp_path / "labels"
    assert main(_cmd(root, out, "--sequence", "0000,0001")) == 0
    text = (out / "0001.json").read_bytes()
    (out / "0001.json").write_bytes(text[: len(text) // 2])  # a user cut it short
    with pytest.raises(DataError, match=r"0001\.json: invalid JSON .*delete it to label"):
        label_cli.run(_parse([*_cmd(root, out, "--sequence", "0000,0001"), "--resume"]))
    (out / "0001.json").write_text('{"images": []}')  # JSON, but not a label file
    with pytest.raises(DataError, match=r"0001\.json: no KINS images, categories and annot"):
        label_cli.run(_parse([*_cmd(root, out, "--sequence", "0000,0001"), "--resume"]))
    # a KINS file without settings (an older seqshape, another tool)
    seq = KittiTrackingSequence(root, "0001")
    write_labels(out / "0001.json", label_log(seq, LabelConfig(mode="gt-accumulation")))
    assert read_label_settings(out / "0001.json") is None
    assert main([*_cmd(root, out, "--sequence", "0000,0001"), "--resume"]) == 1
    assert f"{out / '0001.json'} records no settings" in capsys.readouterr().err


def test_one_log_and_several_cameras(root, tmp_path, monkeypatch, capsys):
    # one log (--sequence 0001): --out is its file
    one = tmp_path / "one.json"
    cmd = ["label", "--kitti", str(root), "--sequence", "0001", "--mode", "gt-accumulation",
           "--out", str(one)]
    assert main(cmd) == 0
    data = one.read_bytes()
    labelled = _count_labelled(monkeypatch)
    assert main([*cmd, "--resume"]) == 0
    assert labelled == [] and one.read_bytes() == data
    assert "resume: 0001 skipped" in capsys.readouterr().out
    # the other camera writes another file at the same path: a setting (camera)
    with pytest.raises(ConfigError, match="camera: 'image_02' there vs 'image_03' now"):
        label_cli.run(_parse([*cmd, "--camera", "image_03", "--resume"]))
    # several cameras: OUT/<log>/<camera>.json; a log with one camera's file missing is
    # labelled again (both files: the same bytes)
    out = tmp_path / "cams"
    cams = [*_cmd(root, out, "--sequence", "0000,0001"), "--camera", "all"]
    assert main(cams) == 0
    full = _files(out)
    assert sorted(full) == [f"{n}/image_0{c}.json" for n in ("0000", "0001") for c in (2, 3)]
    (out / "0001" / "image_03.json").unlink()
    labelled.clear()
    capsys.readouterr()
    assert main([*cams, "--resume"]) == 0
    assert labelled == ["0001"] and _files(out) == full
    assert (f"resume: 0001 labelled again ({out / '0001' / 'image_03.json'} missing)"
            in capsys.readouterr().out)


def test_overlays_asked_for_on_resume_relabel_logs_without_them(root, tmp_path, monkeypatch,
                                                                capsys):
    out, overlays = tmp_path / "labels", tmp_path / "overlays"
    assert main(_cmd(root, out, "--sequence", "0000,0001")) == 0
    labels = _files(out)
    labelled = _count_labelled(monkeypatch)
    assert main([*_cmd(root, out, "--sequence", "0000,0001", "--overlays", str(overlays)),
                 "--resume"]) == 0
    assert labelled == ["0000", "0001"] and _files(out) == labels
    assert sorted(_files(overlays)) == [f"{n}/{n}_{f:06d}.png" for n in ("0000", "0001")
                                        for f in range(FRAMES)]
    (overlays / "0001" / "0001_000001.png").unlink()
    labelled.clear()
    capsys.readouterr()
    assert main([*_cmd(root, out, "--sequence", "0000,0001", "--overlays", str(overlays)),
                 "--resume"]) == 0
    assert labelled == ["0001"] and (overlays / "0001" / "0001_000001.png").is_file()
    assert "resume: 0001 labelled again (1 of its overlays missing in" in capsys.readouterr().out


def test_settings_of_the_estimator(root, tmp_path):
    """The weights count by their content (sha256), the backend only as float32 or int8."""
    from seqshape.model.estimator import pretrained_path

    shipped = pretrained_path("sequential")
    digest = "sha256:" + hashlib.sha256(shipped.read_bytes()).hexdigest()
    assert weights_digest("pretrained") == weights_digest(None) == digest
    copy = tmp_path / "model.pt"
    shutil.copy(shipped, copy)
    assert weights_digest(str(copy)) == digest  # the same weights under another name
    assert weights_digest("baseline") != digest
    with pytest.raises(DataError, match="weights file not found"):
        weights_digest(str(tmp_path / "none.pt"))

    log = KittiTrackingSequence(root, "0000")

    def settings(**kw):
        cfg = LabelConfig(**{"mode": "sc-gt", **kw})
        return label_settings(cfg, log, "image_02", weights=digest)

    base = settings()
    assert base["weights"] == digest and base["inference"] == "float32"
    for backend in ("auto-float", "torch", "onnx", "torch-lean"):
        assert settings(backend=backend) == base
    assert settings_differences(base, settings(backend="onnx-int8")) == [
        "inference: 'float32' there vs 'int8' now"]
    with pytest.raises(ConfigError, match="'auto' may run int8 or float32"):
        settings(backend="auto")  # unresolved: the label command records what it chose
    assert settings_differences(base, settings(trim=2.0)) == ["trim: 1.0 there vs 2.0 now"]
    assert settings_differences(base, settings(max_points=128)) == [
        "max_points: None there vs 128 now"]  # fewer points per frame: other estimates
    with pytest.raises(ConfigError, match="max_points"):
        LabelConfig(mode="sc-gt", max_points=0)
    other = label_settings(LabelConfig(mode="sc-gt"), log, "image_02", weights="sha256:0")
    assert settings_differences(base, other) == [f"weights: {digest!r} there vs 'sha256:0' now"]
    with pytest.raises(ConfigError, match="digest"):
        label_settings(LabelConfig(mode="sc-gt"), log, "image_02")
    # no network, no weights: gt-accumulation records neither
    gt = label_settings(LabelConfig(mode="gt-accumulation"), log, "image_02")
    assert gt["weights"] is None and gt["inference"] is None
    assert settings_differences({**base, "old": 1}, base) == [
        "old: 1 there vs '(not recorded)' now"]


def test_sc_gt_resume_with_the_shipped_weights(root, tmp_path, monkeypatch, capsys):
    """An sc-gt run records the shipped weights' digest; another float backend resumes,
    int8 or other weights are refused (before any estimator is loaded)."""
    out = tmp_path / "labels"
    cmd = [*_cmd(root, out, "--sequence", "0000,0001", "--max-frames", "1", mode="sc-gt"),
           "--backend", "torch"]
    monkeypatch.setattr(label_cli, "_ESTIMATOR", {})  # this process's estimator: ours
    assert main(cmd) == 0
    recorded = read_label_settings(out / "0000.json")
    assert recorded["weights"] == weights_digest("pretrained", "pretrained")
    assert recorded["placement"] == "pretrained"
    before = _files(out)
    capsys.readouterr()
    labelled = _count_labelled(monkeypatch)
    label_cli._ESTIMATOR.clear()
    assert main([*cmd[:-1], "torch-lean", "--resume"]) == 0
    assert labelled == [] and "resume: 2 of 2 logs skipped" in capsys.readouterr().out
    assert main([*cmd[:-1], "onnx-int8", "--resume"]) == 1
    assert "inference: 'float32' there vs 'int8' now" in capsys.readouterr().err
    assert main([*cmd, "--checkpoint", "baseline", "--resume"]) == 1
    assert "weights: 'sha256:" in capsys.readouterr().err
    assert main([*cmd, "--max-points", "128", "--resume"]) == 1
    assert "max_points: None there vs 128 now" in capsys.readouterr().err
    assert labelled == [] and label_cli._ESTIMATOR == {} and _files(out) == before
    # "auto" is recorded as what it chose here: int8 (refused against float32 labels) where
    # its check passes, else a float32 backend (resumed); either way nothing is relabelled
    code = main([*cmd[:-1], "auto", "--resume"])
    chosen = label_cli._ESTIMATOR["est"].backend
    assert code == (1 if chosen == "onnx-int8" else 0), chosen
    if chosen == "onnx-int8":
        assert "inference: 'float32' there vs 'int8' now" in capsys.readouterr().err
    assert labelled == [] and _files(out) == before


def test_placement_refiner_counts_by_its_content(tmp_path):
    """``--placement FILE`` adds the refiner file's digest to the recorded weights."""
    torch = pytest.importorskip("torch")
    from seqshape.model import placement as P

    torch.manual_seed(0)
    P.PlacementRefiner(P.build_net()).save(tmp_path / "a.pt")
    torch.manual_seed(1)
    P.PlacementRefiner(P.build_net()).save(tmp_path / "b.pt")
    shutil.copy(tmp_path / "a.pt", tmp_path / "a_copy.pt")
    net = weights_digest("pretrained")
    a = weights_digest("pretrained", str(tmp_path / "a.pt"))
    digest = "sha256:" + hashlib.sha256((tmp_path / "a.pt").read_bytes()).hexdigest()
    assert a == f"{net} placement {digest}"
    assert weights_digest("pretrained", str(tmp_path / "a_copy.pt")) == a
    assert weights_digest("pretrained", str(tmp_path / "b.pt")) != a
    assert weights_digest("pretrained", "none") == net
    with pytest.raises(DataError, match="missing.pt"):
        weights_digest("pretrained", str(tmp_path / "missing.pt"))


def test_max_points_reaches_the_estimator(monkeypatch):
    """``label --max-points N``: the process's estimator cuts frames to N points."""
    monkeypatch.setattr(label_cli, "_ESTIMATOR", {})
    est = label_cli._estimator("sc-gt", "pretrained", "torch", "none", 96)
    assert est.max_points == 96 and label_cli._estimator("sc-gt", None, "torch") is est
