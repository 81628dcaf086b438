"""``seqshape label`` on a KITTI log with its calibration and no images (issue 46): the modes
that need no pixels (gt-accumulation, sc-gt) label it at KITTI's image size or ``--image-size``;
sc-seg, a log without calibration and a wrong root each end in one line saying what is missing."""

from __future__ import annotations

import pytest
from _kitti_fixture import write_box_kitti

from seqshape.amodal.labeler import DEFAULT_IMAGE_SIZES, set_image_size
from seqshape.cli import main
from seqshape.data.kins import read_kins
from seqshape.data.kitti import KittiTrackingSequence
from seqshape.errors import ConfigError


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    """calib, velodyne and label_02 of sequence 0000, no image_02 (the fixture writes none)."""
    root = write_box_kitti(tmp_path_factory.mktemp("kitti") / "training", frames=2)
    assert not (root / "image_02").exists()
    return root


def _label(root, out, *extra, mode="gt-accumulation"):
    return main(["label", "--dataset", "kitti", "--root", str(root), "--sequence", "0000",
                 "--mode", mode, "--out", str(out), *extra])


def test_gt_accumulation_at_kittis_image_size(root, tmp_path):
    assert DEFAULT_IMAGE_SIZES["kitti"] == (1242, 375)
    assert _label(root, tmp_path / "l.json") == 0
    doc = read_kins(tmp_path / "l.json")
    assert [(im["width"], im["height"]) for im in doc["images"]] == [(1242, 375)] * 2
    assert doc["annotations"], "the two box cars project into the image"


def test_sc_gt_and_another_image_size(root, tmp_path):
    out = tmp_path / "sc.json"
    assert _label(root, out, "--image-size", "640", "200", "--backend", "torch",
                  mode="sc-gt") == 0
    doc = read_kins(out)
    assert [(im["width"], im["height"]) for im in doc["images"]] == [(640, 200)] * 2
    for a in doc["annotations"]:
        assert a["a_segm"]["size"] == [200, 640]
    assert doc["info"]["settings"]["image_size"] == [640, 200]


def test_sc_seg_says_it_needs_the_images_masks(root, tmp_path, capsys):
    assert _label(root, tmp_path / "s.json", mode="sc-seg") == 1
    err = capsys.readouterr().err
    assert "instances_2d/0000.json: 2D instance masks not found" in err
    assert "pass --instances FILE" in err and "gt-accumulation and sc-gt need no images" in err


def test_what_is_missing_is_named(root, tmp_path, capsys):
    # the folder above the root: nothing of sequence 0000 there
    assert _label(root.parent, tmp_path / "x.json") == 1
    err = capsys.readouterr().err
    assert "kitti log 0000 has no cameras" in err
    assert f"the calibration file {root.parent / 'calib' / '0000.txt'}, which is missing" in err
    assert "is --root the folder that holds the dataset's folders" in err
    # --image-size is checked
    log = KittiTrackingSequence(root, "0000")
    with pytest.raises(ConfigError, match="must be positive"):
        set_image_size(log, (0, 375))
    assert _label(root, tmp_path / "x.json", "--image-size", "-1", "5") == 1
    assert "--image-size -1 5" in capsys.readouterr().err
