"""Viewers and their output names: safe_stem / contained_path, `seqshape show` (names from the
data stay inside --out, colour bars), `show-scene` (one label and colour per car in both
panels), and the plotly layouts (buttons beside the slider, margins)."""

import json
import os
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from seqshape._io import MAX_STEM, contained_path, safe_stem
from seqshape.amodal.overlay import draw_overlay, track_colour
from seqshape.camera import kitti_default_calib, project_points, write_calib
from seqshape.cli import main
from seqshape.data.dataset import write_dataset
from seqshape.data.kins import image_entry, kins_annotation, occlusion_order, write_kins
from seqshape.data.kitti import KittiLabel, pose_to_label_fields, write_velodyne
from seqshape.data.kitti import write_labels as write_kitti
from seqshape.data.track import Track, save_track
from seqshape.errors import DataError
from seqshape.geometry import box_corners
from seqshape.testing import box_shell

SIZE = np.array([4.2, 1.8, 1.5])


@pytest.mark.parametrize("name, stem", [
    ("../x", "_x"), ("/etc/passwd", "_etc_passwd"), ("", "_"), ("..", "_"), (".", "_"),
    ("...hidden", "hidden"), ("a/../../b", "a_.._.._b"), ("Straße_7", "Stra_e_7"),
    ("車", "_"), ("a\\b\x00c d", "a_b_c_d"), ("kitti_0000_3", "kitti_0000_3"),
    ("7fab2350-7eaf.x", "7fab2350-7eaf.x"), (42, "42"),
])
def test_safe_stem_cases(name, stem):
    assert safe_stem(name) == stem
    assert safe_stem(safe_stem(name)) == stem  # a safe name stays as it is


def test_safe_stem_bounds_long_names_and_keeps_them_apart():
    a, b = "x" * 500 + "a", "x" * 500 + "b"
    sa, sb = safe_stem(a), safe_stem(b)
    assert len(sa) == len(sb) == MAX_STEM and sa != sb and sa == safe_stem(a)
    assert len(safe_stem("é" * 300, max_length=20)) == 20
    with pytest.raises(ValueError):
        safe_stem("x", max_length=3)


def test_contained_path_refuses_leaving_the_folder(tmp_path):
    out = tmp_path / "out"
    assert contained_path(out, "a.png") == out / "a.png"
    for bad in ("../a.png", "/etc/passwd", "", "x/../../a.png"):
        with pytest.raises(DataError, match="outside"):
            contained_path(out, bad)
    out.mkdir()
    os.symlink(tmp_path / "elsewhere.png", out / "link.png")
    with pytest.raises(DataError, match="outside"):
        contained_path(out, "link.png")


def tiny_track(track_id, n=4):
    rng = np.random.default_rng(0)
    pts = [rng.normal([8.0 + t, 2.0, -0.8], 0.5, (50, 3)).astype(np.float32) for t in range(n)]
    poses = np.array([[8.0 + t, 2.0, -0.8, 0.1] for t in range(n)])
    return Track(track_id, pts, poses, box_shell(300, 1, SIZE).astype(np.float32), SIZE,
                 np.arange(n) * 0.1, {"split": "val"})


def _retitle(data, track_id):
    """Store track ``track_id`` in ``data``'s one track file, and in its manifest."""
    save_track(data / "tracks" / "t0.npz", tiny_track(track_id))
    doc = json.loads((data / "manifest.json").read_text())
    doc["tracks"][0]["track_id"] = track_id
    (data / "manifest.json").write_text(json.dumps(doc))


def test_show_names_files_from_the_track_id_inside_out(tmp_path, capsys):
    """The track is ``../escaped``: the files land in --out as ``_escaped``."""
    data = tmp_path / "data"
    write_dataset(data, [tiny_track("t0")])
    _retitle(data, "../escaped")
    out = tmp_path / "sub" / "out"
    assert main(["show", str(data), "--track", "../escaped", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["_escaped.html", "_escaped.png"]
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == ["out"]
    assert not list(tmp_path.glob("escaped*")) and not list(tmp_path.glob("*/escaped*"))
    _retitle(data, "/tmp/abs")
    assert main(["show", str(data), "--track", "/tmp/abs", "--out", str(out), "--no-html"]) == 0
    assert (out / "_tmp_abs.png").is_file()
    # a track file whose own id disagrees with the manifest is refused (issue 45)
    save_track(data / "tracks" / "t0.npz", tiny_track("t1"))
    assert main(["show", str(data), "--track", "/tmp/abs", "--out", str(out)]) == 1
    assert "holds track 't1', but" in capsys.readouterr().err


def test_show_refuses_a_link_out_of_the_folder(tmp_path, capsys):
    data = tmp_path / "data"
    write_dataset(data, [tiny_track("t0")])
    out = tmp_path / "out"
    out.mkdir()
    os.symlink(tmp_path / "victim.png", out / "t0.png")
    assert main(["show", str(data), "--track", "t0", "--out", str(out), "--no-html"]) == 1
    assert "outside" in capsys.readouterr().err and not (tmp_path / "victim.png").exists()


def test_show_png_has_colour_bars():
    import matplotlib.pyplot as plt

    from seqshape.viz import track_overview

    fig = track_overview(tiny_track("t"))
    bars = sorted(ax.get_ylabel() for ax in fig.axes if ax.get_label() == "<colorbar>")
    plt.close(fig)
    assert bars == ["frame", "x (m)", "y (m)", "z (m)"]  # BEV frames; top, side, front views


def test_show_html_is_not_cut_at_the_edges(tmp_path):
    from seqshape.viz import track_html

    path = track_html(tiny_track("t"), tmp_path / "t.html")
    text = path.read_text()
    assert '"margin":{"l":40,"r":40,"t":50,"b":40}' in text.replace(" ", "")
    assert '"x":0.06' in text and '"len":0.88' in text  # slider inset: first label not cut


def test_track_view_buttons_beside_the_slider():
    from seqshape.evaluation.html import PLAYER_WIDTH, track_figure

    track = tiny_track("t", n=3)
    ests = [SimpleNamespace(complete=track.complete_in_frame(i), pose=track.poses[i])
            for i in range(3)]
    fig = track_figure(track, {"sequential": (range(3), ests)})
    slider, menu = fig.layout.sliders[0], fig.layout.updatemenus[0]
    assert menu.xanchor == "left" and slider.xanchor == "left"
    assert menu.direction == "down"  # stacked: about one button wide
    assert menu.x + PLAYER_WIDTH <= slider.x and slider.x + slider.len <= 1.0 + 1e-9
    assert PLAYER_WIDTH * 700 > 60  # room for "pause" on a 700 px page


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """One KITTI frame with two box cars, label_02 track ids 3 and 12, KINS masks."""
    root = tmp_path_factory.mktemp("scene")
    calib = kitti_default_calib()
    write_calib(root / "calib" / "0000.txt", calib)
    poses = {3: np.array([10.0, 1.0, -0.98, 0.2]), 12: np.array([18.0, -1.5, -0.98, 0.0])}
    write_velodyne(root / "velodyne" / "0000" / "000000.bin",
                   np.random.default_rng(0).normal([15, 0, -1.7], 3, (500, 3)))
    (root / "image_02" / "0000").mkdir(parents=True)
    cv2.imwrite(str(root / "image_02" / "0000" / "000000.png"),
                np.full((calib.height, calib.width, 3), 100, np.uint8))
    amodal = {}
    for k, pose in poses.items():
        uv, _ = project_points(box_corners(SIZE, pose), calib)
        m = np.zeros((calib.height, calib.width), np.uint8)
        cv2.fillConvexPoly(m, cv2.convexHull(np.round(uv).astype(np.int32)), 1)
        amodal[k] = m.astype(bool)
    visible = {3: amodal[3], 12: amodal[12] & ~amodal[3]}
    oco, ico = occlusion_order([10.0, 18.0], [amodal[3], amodal[12]])
    anns = []
    for (k, pose), o, i in zip(poses.items(), oco, ico, strict=True):
        ann = kins_annotation(len(anns) + 1, 0, 4, amodal[k], visible[k], o, i, k)
        ann["depth"] = float(pose[0])
        anns.append(ann)
    write_kins(root / "amodal" / "0000.json", [image_entry(0, "0000", 0, calib.height,
                                                           calib.width)], anns)
    write_kitti(root / "label_02" / "0000.txt", [
        KittiLabel(frame=0, track_id=k, type="Car", truncated=0, occluded=0, bbox=[0, 0, 1, 1],
                   **pose_to_label_fields(p, SIZE, calib)) for k, p in poses.items()])
    return root, anns, calib


def test_show_scene_same_label_and_colour_in_both_panels(scene, tmp_path):
    import matplotlib.pyplot as plt

    from seqshape.viz import _rgb, scene_figure, scene_instances

    root, anns, calib = scene
    insts, tracks = scene_instances(anns, calib.height, calib.width)
    assert tracks == [3, 12] and [m.order for m in insts] == [0, 1]  # depth rank, 0 = nearest
    fig = scene_figure(root, "0000", 0)
    ax_img, ax_bev = fig.axes
    shown = ax_img.images[0].get_array()
    image = np.full((calib.height, calib.width, 3), 100, np.uint8)
    assert np.array_equal(shown, draw_overlay(image, insts, tracks)[:, :, ::-1])
    assert sorted(t.get_text() for t in ax_bev.texts) == ["12", "3"]
    for t in ax_bev.texts:  # the bird's-eye tag has the track's overlay colour
        want = np.array(track_colour(int(t.get_text()))[::-1]) / 255
        assert np.allclose(t.get_bbox_patch().get_facecolor()[:3], want, atol=1e-6)
        assert np.allclose(_rgb(int(t.get_text())), want)
    plt.close(fig)
    out = tmp_path / "f.png"
    assert main(["show-scene", str(root), "--frame", "0", "--out", str(out)]) == 0
    assert out.read_bytes()[:4] == b"\x89PNG"
