"""Camera + LiDAR scenes: exact masks, KINS / COCO files, labels, tracks, degradations."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace

import cv2
import numpy as np
import pytest
import trimesh

import seqshape.sim.generate as gen
import seqshape.sim.render as render
from seqshape._runner import parse_shard
from seqshape.camera import kitti_default_calib, project_points
from seqshape.cli import command_parser
from seqshape.data.kins import annotations_by_image, occlusion_order, read_kins, rle_to_mask
from seqshape.data.kitti import KittiTrackingSequence, extract_tracks, read_velodyne
from seqshape.errors import ConfigError, SeqshapeError
from seqshape.geometry import wrap_angle
from seqshape.sim.degrade import (
    NO_DEGRADE,
    DegradeConfig,
    Instance2D,
    degrade_instances,
    erode_dilate,
)
from seqshape.sim.raycast import cast_posed
from seqshape.sim.render import GROUND, camera_rays, render_camera
from seqshape.sim.scene_writer import (
    PRESETS,
    SceneConfig,
    _rng,
    generate_scenes,
    generate_sequence,
    load_scene,
    make_scene,
    occlusion_level,
    render_frame,
    scene_to_json,
)
from seqshape.sim.scenes import (
    LayoutConfig,
    Road,
    build_scene,
    check_no_overlap,
    check_vehicle_range,
)
from seqshape.sim.sensors import get_sensor
from seqshape.vehicles import vehicle_library

SMALL = SceneConfig("kitti-tiny", 1, (6, 6), (5, 6))
SEED = 0


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("scenes")
    result = generate_sequence(root, SMALL, SEED, 0, NO_DEGRADE, return_tracks=True)
    return root, result


def _frames(root):
    doc = read_kins(root / "amodal" / "0000.json")
    return doc, annotations_by_image(doc)


def test_amodal_contains_visible_and_visible_disjoint(scene_dir):
    root, _ = scene_dir
    doc, by_image = _frames(root)
    assert len(doc["annotations"]) > 0
    for anns in by_image.values():
        count = np.zeros((375, 1242), np.int64)
        for ann in anns:
            a, v = rle_to_mask(ann["a_segm"]), rle_to_mask(ann["i_segm"])
            assert not (v & ~a).any()
            assert v.sum() == ann["i_area"] and a.sum() == ann["a_area"]
            assert ann["i_area"] >= SMALL.min_visible_area
            count += v
        assert count.max() <= 1  # visible masks are disjoint


def test_unoccluded_vehicles_have_equal_masks(scene_dir):
    root, _ = scene_dir
    doc, _ = _frames(root)
    free = [a for a in doc["annotations"] if not a["occluded_by"]]
    hidden = [a for a in doc["annotations"] if a["occluded_by"]]
    assert free and hidden
    for a in free:
        assert np.array_equal(rle_to_mask(a["a_segm"]), rle_to_mask(a["i_segm"]))
    for a in hidden:
        assert a["i_area"] < a["a_area"]


def test_written_files_match_a_rerender(scene_dir):
    """Determinism + RLE round trip: re-render frame 2 from scene/0000.json."""
    root, _ = scene_dir
    scene, meta = load_scene(root, "0000")
    calib = kitti_default_calib()
    pts, owner, cam = render_frame(scene, 2, calib, get_sensor("hdl64"), _rng(SEED, 0, 1, 2))
    assert np.array_equal(read_velodyne(root / "velodyne/0000/000002.bin"), pts)
    png = cv2.imread(str(root / "image_02/0000/000002.png"))[:, :, ::-1]
    assert np.array_equal(png, cam.image)
    _, by_image = _frames(root)
    for ann in by_image[2]:
        k = ann["track_id"]
        assert np.array_equal(rle_to_mask(ann["a_segm"]), cam.amodal[k])
        assert np.array_equal(rle_to_mask(ann["i_segm"]), cam.visible[k])
    assert (owner == GROUND).sum() > 0.5 * len(owner)


def test_tracks_read_back_match_generator(scene_dir):
    root, result = scene_dir
    tracks = {t.track_id: t for t in extract_tracks(KittiTrackingSequence(root, "0000"))}
    own = {t.track_id: t for t in result.tracks}
    ground_z = -load_scene(root, "0000")[1]["sensor_height"]  # the scenes' flat road
    assert set(tracks) == set(own) and own
    for tid, mine in own.items():
        read = tracks[tid]
        assert read.meta["frames"] == mine.meta["frames"]
        assert np.allclose(read.poses[:, :3], mine.poses[:, :3], atol=1e-4)
        assert np.allclose(wrap_angle(read.poses[:, 3] - mine.poses[:, 3]), 0, atol=1e-4)
        for t in range(len(mine)):
            # extract_tracks (seqshape.data.crop) drops what lies less than 0.2 m above a
            # ground plane fitted around the box: with range noise on the road returns, every
            # vehicle return 0.3 m above the road is kept, none below 0.1 m, and nothing else
            # than the vehicle's own returns comes in
            height = mine.points[t][:, 2] - ground_z
            got = read.points[t]
            rows = {tuple(r) for r in got.tolist()}
            assert rows <= {tuple(r) for r in mine.points[t].tolist()}
            assert {tuple(r) for r in mine.points[t][height >= 0.3].tolist()} <= rows
            assert np.all(got[:, 2] - ground_z >= 0.1)


def test_labels_and_levels(scene_dir):
    root, _ = scene_dir
    seq = KittiTrackingSequence(root, "0000")
    assert seq.labels and all(lab.type in ("Car", "Van") for lab in seq.labels)
    assert all(0 <= lab.truncated <= 1 and lab.occluded in (0, 1, 2, 3) for lab in seq.labels)
    assert occlusion_level(100, 100) == 0 and occlusion_level(60, 100) == 1
    assert occlusion_level(10, 100) == 2 and occlusion_level(0, 100) == 3
    assert seq.ego_poses is not None and len(seq.ego_poses) == 6


def _box(length=4.0, width=1.8, height=1.5):
    return trimesh.creation.box(extents=(length, width, height))


def test_occlusion_order_two_vehicles():
    """A car 10 m ahead hides part of one 20 m ahead, 1 m to the side."""
    calib = kitti_default_calib()
    meshes = [_box(), _box()]
    z = -1.73 + 0.75
    poses = np.array([[20.0, -1.0, z, 0.0], [10.0, 0.0, z, 0.0]])  # far first
    cam = render_camera(meshes, poses, np.full((2, 3), 0.5), camera_rays(calib), -1.73)
    far, near = 0, 1
    assert np.array_equal(cam.amodal[near], cam.visible[near])
    assert (cam.visible[far] & ~cam.amodal[far]).sum() == 0
    hidden = cam.amodal[far] & ~cam.visible[far]
    assert hidden.sum() > 100 and np.all(cam.owner[hidden] == near)
    assert cam.nearest[near] < cam.nearest[far]
    oco, ico = occlusion_order(cam.nearest, cam.amodal)
    assert oco[0] == oco[1] and ico[near] == 1 and ico[far] == 2
    # the near box alone: its visible mask equals its amodal mask and the depths agree
    depth = cam.depth[cam.visible[near]]
    assert np.all(depth < cam.nearest[far])


def test_pixel_rays_project_to_their_pixels():
    calib = kitti_default_calib()
    rays = camera_rays(calib)
    mesh = _box(4, 30, 10)
    tri, rng, _ = cast_posed(mesh, np.array([15.0, 0.0, 0.0, 0.3]), rays.origin, rays.dirs)
    hit = np.flatnonzero(tri >= 0)
    assert len(hit) > 10000
    uv, depth = project_points(rays.origin + rays.dirs[hit] * rng[hit, None], calib)
    expect = np.c_[hit % rays.width, hit // rays.width]
    assert np.abs(uv - expect).max() < 1e-6 and np.all(depth > 0)


def test_scene_layout_has_no_overlap_and_road_round_trip():
    vehicles = vehicle_library(20, seed=1)
    for seed in range(5):
        scene = build_scene(LayoutConfig(n_frames=60, n_vehicles=(10, 20)), vehicles,
                            np.random.default_rng(seed), 1.73)
        assert 5 <= len(scene.agents) <= 20
        z = scene.sensor_poses(0)[:, 2]
        assert np.allclose(z, -1.73 + np.array([scene.size(k)[2] / 2
                                                for k in range(len(scene.agents))]))
    scene.agents[1].world = scene.agents[0].world.copy()
    with pytest.raises(SeqshapeError):
        check_no_overlap(scene)
    road = Road(kappa=1 / 250)
    s, d = np.array([5.0, 80.0]), np.array([-4.0, 3.0])
    assert np.allclose(road.to_road(*road.to_world(s, d)), (s, d))


def test_resume_and_settings_check(tmp_path):
    cfg = SceneConfig("kitti-tiny", 1, (2, 2), (5, 5))
    assert len(generate_scenes(tmp_path, cfg, seed=1, progress_bar=False)) == 1
    assert generate_scenes(tmp_path, cfg, seed=1, progress_bar=False) == []
    with pytest.raises(ConfigError, match="seed: 1 there vs 2 now"):
        generate_scenes(tmp_path, cfg, seed=2, progress_bar=False)


def _tree(root) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file()}


def test_shards_and_workers_give_the_files_of_one_run(tmp_path):
    cfg = SceneConfig("kitti-tiny", 3, (1, 1), (3, 3))
    full = [r.sequence for r in generate_scenes(tmp_path / "one", cfg, seed=4,
                                                 degrade=NO_DEGRADE)]
    assert full == ["0000", "0001", "0002"]
    first = generate_scenes(tmp_path / "sh", cfg, seed=4, degrade=NO_DEGRADE, shard=(1, 2))
    assert [r.sequence for r in first] == ["0000", "0002"]
    second = generate_scenes(tmp_path / "sh", cfg, seed=4, degrade=NO_DEGRADE, shard=(2, 2),
                             workers=2)
    assert [r.sequence for r in second] == ["0001"]
    assert _tree(tmp_path / "sh") == _tree(tmp_path / "one")
    with pytest.raises(ConfigError, match="1 <= K <= N"):
        generate_scenes(tmp_path / "sh", cfg, seed=4, degrade=NO_DEGRADE, shard=(3, 2))


def test_old_import_paths_warn():
    import seqshape.amodal.degrade as old_degrade  # the old paths under test

    with pytest.warns(DeprecationWarning, match="seqshape.sim.degrade"):
        assert old_degrade.DegradeConfig is DegradeConfig
    with pytest.warns(DeprecationWarning, match="cast_posed"):
        assert render.cast_vehicle is cast_posed
    with pytest.warns(DeprecationWarning, match="seqshape._runner"):
        assert gen.parse_shard is parse_shard
    with pytest.raises(AttributeError):
        render.no_such_name  # noqa: B018


def _instances(n, size, rng, shape=(120, 200)):
    out = []
    for i in range(n):
        m = np.zeros(shape, bool)
        r, c = rng.integers(0, shape[0] - size), rng.integers(0, shape[1] - size)
        m[r:r + size, c:c + size] = True
        out.append(Instance2D(m, 1.0, 4, i))
    return out


def test_degrade_identity_and_morphology():
    rng = np.random.default_rng(0)
    inst = _instances(5, 20, rng)
    same = degrade_instances(inst, NO_DEGRADE, rng)
    assert [i.track_id for i in same] == list(range(5))
    assert all(np.array_equal(a.mask, b.mask) for a, b in zip(inst, same, strict=True))
    m = inst[0].mask
    assert erode_dilate(m, 1).sum() == 20 * 20 + 4 * 20  # cross element grows each side by 1
    assert erode_dilate(m, -1).sum() == 18 * 18


def test_degrade_rates_change_instance_counts():
    rng = np.random.default_rng(1)
    images, n = 300, 8
    cfg = DegradeConfig(miss_rate_small=0.25, miss_rate=0.0, jitter_px=(0.0, 0.0),
                        false_rate=0.5)
    small = [len([i for i in degrade_instances(_instances(n, 10, rng), cfg, rng)
                  if i.track_id >= 0]) for _ in range(images)]
    false = [len([i for i in degrade_instances(_instances(n, 40, rng), cfg, rng)
                  if i.track_id < 0]) for _ in range(images)]
    big_kept = [len([i for i in degrade_instances(_instances(n, 40, rng), cfg, rng)
                     if i.track_id >= 0]) for _ in range(20)]
    # small boxes (100 px) are missed at 25%: mean kept 6 +- 4 sigma of the mean
    assert abs(np.mean(small) - n * 0.75) < 4 * np.sqrt(n * 0.25 * 0.75 / images)
    assert abs(np.mean(false) - n * 0.5) < 4 * np.sqrt(n * 0.5 / images)
    assert all(k == n for k in big_kept)  # 1600 px >= small_area: never missed


# ------------------------------------------------------------------ denser scenes (--vehicles)

#: sha256 of ``scene_to_json(make_scene(preset, seed 0, sequence i))`` (sorted keys, every
#: float rounded to 1e-6) as the release before ``--vehicles`` made them: without the option a
#: preset's scenes stay the same. Rounded because the exact bytes depend on the CPU: numpy's
#: sin/cos/exp take SIMD code paths (SVML with AVX-512) that differ from libm in the last bit,
#: and a sequence's poses integrate them (kitti-tiny sequence 1 differed between an AVX-512
#: machine and an AMD EPYC without it; sequence 0 did not).
PRESET_SCENES = {
    ("kitti-tiny", 0): "79ba796604a0e48144108daa117c2b9ee9731db4e85235c0c504aeaaac036d73",
    ("kitti-tiny", 1): "e314dbdb43d4c1419d68794a8f8dc61d49e2f22951ca1d3c8d48e0dfba41c017",
    ("kitti-like", 0): "47f134b1c49248ec23717f369fee2bab4498eb6d29e33ea1827a8d199b59069b",
    ("kitti-like", 1): "e149c2fcdf1dbd2dfdb8e52e4e17afb078d82775f01bde70dbd7b7e88ae0fe12",
}


def _rounded(value):
    """``value`` (a JSON document) with every float rounded to 1e-6 (and -0.0 made 0.0)."""
    if isinstance(value, float):
        return round(value, 6) + 0.0
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_rounded(v) for v in value]
    return value


def scene_digest(doc: dict) -> str:
    """The sha256 of :func:`_rounded` ``doc`` as sorted-key JSON (:data:`PRESET_SCENES`)."""
    return hashlib.sha256(json.dumps(_rounded(doc), sort_keys=True).encode()).hexdigest()


def _cli_scene_config(monkeypatch, argv):
    """The SceneConfig ``seqshape scenes --out o ARGV`` generates with (its run(), up to the
    call of generate_scenes)."""
    import seqshape.scripts.scenes as script

    seen = {}

    def capture(out, cfg, **_kw):
        seen["cfg"] = cfg
        return []

    monkeypatch.setattr(script, "generate_scenes", capture)
    script.run(command_parser("scenes")[1].parse_args(["--out", "o", *argv]))
    return seen["cfg"]


@pytest.mark.parametrize("preset", ["kitti-tiny", "kitti-like"])
def test_presets_make_the_scenes_of_the_release_before(monkeypatch, preset):
    cfg = _cli_scene_config(monkeypatch, ["--preset", preset])
    assert cfg == PRESETS[preset]  # no --vehicles: the preset's range, untouched
    for index in (0, 1):
        doc = scene_to_json(make_scene(cfg, 0, index), f"{index:04d}", {})
        assert scene_digest(doc) == PRESET_SCENES[preset, index], (preset, index)


def test_vehicles_option_overrides_the_preset_range(monkeypatch):
    cfg = _cli_scene_config(monkeypatch, ["--preset", "kitti-like", "--vehicles", "30", "40"])
    assert cfg == replace(PRESETS["kitti-like"], n_vehicles=(30, 40))
    assert _cli_scene_config(monkeypatch, ["--vehicles", "0", "0"]).n_vehicles == (0, 0)


@pytest.mark.parametrize("values, match", [
    (["3", "a"], "be two integers MIN MAX, got '3' 'a'"),
    (["2.5", "4"], "be two integers"),
    (["+-3", "4"], "be two integers"),
    (["5", "3"], "satisfy 0 <= MIN <= MAX, got 5 3"),
    (["-1", "3"], "satisfy 0 <= MIN <= MAX, got -1 3"),
])
def test_vehicles_option_is_checked(monkeypatch, values, match):
    with pytest.raises(ConfigError, match="--vehicles must " + match):
        _cli_scene_config(monkeypatch, ["--vehicles", *values])


def test_vehicle_range_check():
    assert check_vehicle_range((np.int64(2), 7)) == (2, 7)
    for bad in [(1,), (1, 2, 3), None, (True, 2), (1.0, 2), (3, 1), (-2, -1)]:
        with pytest.raises(ConfigError, match="n_vehicles"):
            check_vehicle_range(bad)
    with pytest.raises(ConfigError, match=r"LayoutConfig.n_vehicles must satisfy"):
        LayoutConfig(n_vehicles=(8, 4))


def _in_view(scene, t, calib, max_range=80.0):
    """Agents whose box centre is within ``max_range`` and projects into the image."""
    poses = scene.sensor_poses(t)
    uv, depth = project_points(poses[:, :3], calib)
    inside = ((depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < calib.width) & (uv[:, 1] >= 0)
              & (uv[:, 1] < calib.height) & (np.hypot(poses[:, 0], poses[:, 1]) < max_range))
    return int(inside.sum())


def test_more_vehicles_fill_the_road_without_overlaps():
    calib = kitti_default_calib()
    vehicles = vehicle_library(40, seed=3)
    preset, dense = [], []
    for seed in range(3):
        for n, out in (((10, 20), preset), ((30, 40), dense)):
            scene = build_scene(LayoutConfig(n_frames=60, n_vehicles=n), vehicles,
                                np.random.default_rng(seed), 1.73)  # checks the overlaps
            assert len(scene.agents) <= n[1]
            out.append((len(scene.agents), np.mean([_in_view(scene, t, calib)
                                                   for t in range(0, 60, 5)])))
    # denser roads: more vehicles placed, and more of them in the camera's view
    assert all(d[0] > p[0] for p, d in zip(preset, dense, strict=True))
    assert np.mean([d[1] for d in dense]) > 1.5 * np.mean([p[1] for p in preset])
    empty = build_scene(LayoutConfig(n_frames=5, n_vehicles=(0, 0)), vehicles,
                        np.random.default_rng(0), 1.73)
    assert empty.agents == [] and empty.sensor_poses(0).shape == (0, 4)


def test_a_scene_without_vehicles_is_written(tmp_path):
    cfg = SceneConfig("kitti-tiny", 1, (2, 2), (0, 0))
    (result,) = generate_scenes(tmp_path, cfg, seed=0, degrade=NO_DEGRADE)
    assert (result.n_frames, result.n_labels, result.n_kins) == (2, 0, 0)
    assert read_velodyne(tmp_path / "velodyne" / "0000" / "000001.bin").shape[0] > 1000
