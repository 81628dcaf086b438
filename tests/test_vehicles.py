"""Tests of seqshape.vehicles: procedural bodies, user-mesh loading, outer-surface sampling."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import trimesh

from seqshape.errors import ConfigError, DataError
from seqshape.vehicles import (
    BODY,
    CLASS_MIX,
    DEFAULT_MIX,
    FACE_LABELS,
    FLEET_KINDS,
    GLASS,
    GRILLE,
    HEADLAMP,
    INTERIOR,
    KINDS,
    LAMP,
    TYRE,
    VEHICLE_CLASSES,
    fleet_library,
    fleet_vehicle,
    kind_quotas,
    load_vehicle,
    load_vehicle_folder,
    procedural_vehicle,
    sample_outer_surface,
    vehicle_from_source,
    vehicle_library,
)
from seqshape.vehicles.fleet_stats import dimension_bounds
from seqshape.vehicles.io import canonical_rotation

# ---------------------------------------------------------------- procedural bodies


@pytest.mark.parametrize("kind", KINDS)
def test_every_kind_is_closed_realistic_and_centred(kind):
    for seed in (0, 1, 2):
        v = procedural_vehicle(kind, seed)
        m = v.mesh
        assert m.is_watertight and m.is_winding_consistent
        assert m.volume > 0  # outward normals
        length, width, height = v.size
        assert 3.6 <= length <= 5.8 and 1.6 <= width <= 2.1 and 1.3 <= height <= 2.2
        np.testing.assert_allclose(m.bounds.mean(axis=0), 0.0, atol=1e-9)
        assert 2000 <= len(m.faces) <= 10000
        assert v.kind == kind and v.source == f"procedural:{kind}:{seed}"
        # wheels touch the ground: the lowest points lie near the axles, not under the body ends
        low = m.vertices[m.vertices[:, 2] < m.bounds[0, 2] + 1e-6]
        assert np.all(np.abs(low[:, 0]) < length / 2 - 0.5)


def test_body_shape_depends_on_kind():
    # vans are taller than sedans; the roof of a sedan is shorter than its body
    sedan, van = procedural_vehicle("sedan", 3), procedural_vehicle("van", 3)
    assert van.size[2] > sedan.size[2] + 0.2
    top = sedan.mesh.vertices[sedan.mesh.vertices[:, 2] > sedan.mesh.bounds[1, 2] - 0.05]
    assert np.ptp(top[:, 0]) < 0.5 * sedan.size[0]


def test_library_is_deterministic_distinct_and_mixed():
    a, b = vehicle_library(25, seed=7), vehicle_library(25, seed=7)
    assert [v.vehicle_id for v in a] == [v.vehicle_id for v in b]
    for va, vb in zip(a, b, strict=True):
        np.testing.assert_array_equal(va.mesh.vertices, vb.mesh.vertices)
    assert len({v.vehicle_id for v in a}) == 25
    sizes = np.array([v.size for v in a])
    assert len(np.unique(sizes.round(6), axis=0)) == 25
    assert a[7].vehicle_id == "proc-0007-" + a[7].kind
    assert {v.kind for v in a} == set(KINDS)
    c = vehicle_library(25, seed=8)
    assert not np.allclose(sizes, np.array([v.size for v in c]))
    # the source rebuilds the same vehicle
    kind, seed = a[3].source.split(":")[1:]
    np.testing.assert_array_equal(procedural_vehicle(kind, int(seed)).mesh.vertices,
                                  a[3].mesh.vertices)
    only = vehicle_library(6, seed=0, kinds=["van", "pickup"])
    assert {v.kind for v in only} == {"van", "pickup"}
    with pytest.raises(ConfigError):
        vehicle_library(3, kinds=["tank"])


# ---------------------------------------------------------------- outer surface


def _box_in_box():
    outer = trimesh.creation.box(extents=(4.0, 2.0, 1.5))
    inner = trimesh.creation.box(extents=(1.0, 0.8, 0.6))
    inner.apply_translation((0.5, 0.1, -0.1))
    return outer, inner, trimesh.util.concatenate([outer, inner])


def test_outer_surface_drops_a_closed_mesh_inside_another():
    outer, inner, both = _box_in_box()
    pts = sample_outer_surface(both, n=6000, seed=3)
    assert pts.shape == (6000, 3) and pts.dtype == np.float32
    # every point is on the outer box: |coordinate| equals the half extent on some axis
    half = np.array([2.0, 1.0, 0.75])
    dist = np.min(np.abs(np.abs(pts) - half), axis=1)
    assert dist.max() < 1e-5
    # none on the inner box (which is strictly inside the outer one)
    assert np.all(np.any(np.abs(pts) > half - 0.1, axis=1))
    # uniform by area: counts per face pair (±x, ±y, ±z) and per face follow the areas
    face_axis = np.argmin(np.abs(np.abs(pts) - half), axis=1)
    face_id = face_axis * 2 + (np.take_along_axis(pts, face_axis[:, None], 1)[:, 0] > 0)
    counts = np.bincount(face_id, minlength=6)
    areas = np.repeat([2.0 * 1.5, 4.0 * 1.5, 4.0 * 2.0], 2)
    expected = 6000 * areas / areas.sum()
    assert np.all(np.abs(counts - expected) < 4 * np.sqrt(expected) + 5)
    # within a face, uniform too: the x coordinate on the top face is flat
    top = pts[face_id == 5]
    hist = np.histogram(top[:, 0], bins=4, range=(-2, 2))[0]
    assert np.all(np.abs(hist - len(top) / 4) < 4 * np.sqrt(len(top) / 4))


def test_outer_surface_is_deterministic_and_on_the_mesh():
    v = procedural_vehicle("suv", 5)
    a = sample_outer_surface(v.mesh, n=1000, seed=1)
    np.testing.assert_array_equal(a, sample_outer_surface(v.mesh, n=1000, seed=1))
    assert not np.array_equal(a, sample_outer_surface(v.mesh, n=1000, seed=2))
    _, dist, _ = trimesh.proximity.closest_point(v.mesh, a)
    assert dist.max() < 1e-5
    # the points cover the whole body: front, back, roof and both sides
    lo, hi = a.min(axis=0), a.max(axis=0)
    np.testing.assert_allclose(lo, v.mesh.bounds[0], atol=0.05)
    np.testing.assert_allclose(hi, v.mesh.bounds[1], atol=0.05)


def test_outer_surface_rejects_bad_arguments():
    with pytest.raises(ConfigError):
        sample_outer_surface(trimesh.creation.box(), n=0)
    with pytest.raises(ConfigError):
        sample_outer_surface(trimesh.Trimesh(), n=10)


# ---------------------------------------------------------------- user meshes


def _to_file_convention(mesh, up, forward, scale):
    """Inverse of the loader's normalisation: canonical mesh -> a file's axes and units."""
    rot = canonical_rotation(up, forward)
    return trimesh.Trimesh(mesh.vertices @ rot / scale, mesh.faces, process=False)


@pytest.mark.parametrize("ext,up,forward,scale", [
    ("obj", "y", "-z", 0.01),    # ShapeNet-like axes, centimetres
    ("ply", "-x", "y", 1.0),
    ("stl", "z", "-y", 0.001),   # millimetres
    ("glb", "y", "x", 2.0),
    ("off", "-z", "-x", 1.0),
])
def test_round_trip_through_files_with_other_axes_and_units(tmp_path, ext, up, forward, scale):
    v = procedural_vehicle("pickup", 4)
    moved = _to_file_convention(v.mesh, up, forward, scale)
    moved.apply_translation([3.0, -7.0, 11.0])  # files need not be centred
    path = tmp_path / f"car.{ext}"
    moved.export(path)
    w = load_vehicle(path, up=up, forward=forward, scale=scale)
    assert w.kind == "user" and w.vehicle_id == "user-car" and w.source == str(path)
    assert w.mesh.is_watertight
    np.testing.assert_allclose(w.mesh.bounds, v.mesh.bounds, atol=1e-5)
    np.testing.assert_allclose(w.size, v.size, atol=1e-5)
    # same vertex set (formats may reorder vertices)
    a = np.unique(v.mesh.vertices.round(4), axis=0)
    b = np.unique(w.mesh.vertices.round(4), axis=0)
    assert a.shape == b.shape
    np.testing.assert_allclose(a, b, atol=2e-4)
    assert abs(w.mesh.volume - v.mesh.volume) < 1e-4 * v.mesh.volume


def test_target_length_and_axis_errors(tmp_path):
    box = trimesh.creation.box(extents=(1.0, 4.0, 2.0))  # long along y
    path = tmp_path / "box.stl"
    box.export(path)
    v = load_vehicle(path, up="z", forward="y", target_length=5.0)
    np.testing.assert_allclose(v.size, [5.0, 1.25, 2.5], atol=1e-9)
    with pytest.raises(ConfigError):
        load_vehicle(path, up="z", forward="-z")
    with pytest.raises(ConfigError):
        load_vehicle(path, up="w")
    with pytest.raises(ConfigError):
        load_vehicle(path, scale=0.0)


@pytest.mark.parametrize("name,content", [
    ("garbage.obj", bytes(np.random.default_rng(0).integers(0, 256, 4000, dtype=np.uint8))),
    ("empty.obj", b""),
    ("empty.stl", b""),
    ("broken.ply", b"ply\nformat ascii 1.0\nelement vertex many\nend_header\n1 2 3\n"),
    ("points.ply", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n"
                   b"property float y\nproperty float z\nend_header\n0 0 0\n1 1 1\n"),
    ("text.glb", b"this is not a glb file"),
    ("notes.obj", b"# just a comment\nv 0 0 0\n"),
])
def test_malformed_files_raise_data_error_naming_the_file(tmp_path, name, content):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(DataError) as info:
        load_vehicle(path)
    assert name in str(info.value) and info.value.path == str(path)


_TETRA = "v 0 0 0\nv 4 0 0\nv 0 2 0\nv 0 0 1.5\n"
_TETRA_FACES = "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def _ply(vertices, faces) -> bytes:
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(vertices)}\nproperty float x\n"
            f"property float y\nproperty float z\nelement face {len(faces)}\n"
            "property list uchar int vertex_indices\nend_header\n")
    body = "".join(" ".join(map(str, v)) + "\n" for v in vertices)
    body += "".join(f"3 {a} {b} {c}\n" for a, b, c in faces)
    return (head + body).encode()


@pytest.mark.parametrize("name,content,message", [
    ("beyond.obj", _TETRA + _TETRA_FACES + "f 1 2 9\n", r"beyond\.obj:9: face vertex index 9"),
    ("zero.obj", _TETRA + _TETRA_FACES + "f 0 1 2\n", "index 0 is out of range"),
    ("back.obj", _TETRA + _TETRA_FACES + "f -1 -2 -5\n", "index -5 is out of range"),
    ("nan.obj", _TETRA.replace("1.5", "nan") + _TETRA_FACES, "NaN or infinite"),
    ("flat.obj", _TETRA.replace("1.5", "0") + _TETRA_FACES, "flat: no extent along the file's z"),
    ("line.obj", "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", "no faces with non-zero area"),
    ("faces.ply", _ply([[0, 0, 0], [4, 0, 0], [0, 2, 0], [0, 0, 1.5]], [[0, 2, 1], [0, 1, 7]]),
     "out of range"),
    ("flat.ply", _ply([[0, 0, 0], [4, 0, 0], [0, 2, 0], [4, 2, 0]], [[0, 2, 1], [1, 2, 3]]),
     "flat"),
])
def test_broken_meshes_are_refused_naming_the_file(tmp_path, name, content, message):
    path = tmp_path / name
    path.write_bytes(content.encode() if isinstance(content, str) else content)
    with pytest.raises(DataError, match=message) as info:
        load_vehicle(path)
    assert info.value.path == str(path)
    assert load_vehicle_from_text(tmp_path, _TETRA + _TETRA_FACES).size.tolist() == [4, 2, 1.5]


def load_vehicle_from_text(folder, text):
    """The valid tetrahedron the broken cases start from, loaded (the checks let it through)."""
    path = folder / "ok.obj"
    path.write_text(text)
    return load_vehicle(path)


def test_missing_and_unsupported_files(tmp_path):
    with pytest.raises(DataError, match="no such file"):
        load_vehicle(tmp_path / "nope.obj")
    (tmp_path / "car.fbx").write_bytes(b"x")
    with pytest.raises(DataError, match="unsupported"):
        load_vehicle(tmp_path / "car.fbx")


def test_open_mesh_loads_with_a_warning(tmp_path, caplog):
    box = trimesh.creation.box(extents=(4.0, 2.0, 1.5))
    box.update_faces(np.arange(len(box.faces) - 2))  # remove the two triangles of one side
    path = tmp_path / "open.obj"
    box.export(path)
    with caplog.at_level(logging.WARNING, logger="seqshape.vehicles"):
        v = load_vehicle(path)
    assert not v.mesh.is_watertight
    assert any("not watertight" in r.message and "open.obj" in r.message for r in caplog.records)
    np.testing.assert_allclose(v.size, [4.0, 2.0, 1.5])
    pts = sample_outer_surface(v.mesh, n=500, seed=0)  # still usable
    assert pts.shape == (500, 3)


def test_folder_loading(tmp_path):
    with pytest.raises(DataError, match="no mesh files"):
        load_vehicle_folder(tmp_path)
    with pytest.raises(DataError, match="not a folder"):
        load_vehicle_folder(tmp_path / "missing")
    # ShapeNet-like layout: same file name in different model folders, y-up, facing -z
    for i, kind in enumerate(["sedan", "van"]):
        v = procedural_vehicle(kind, i)
        path = tmp_path / f"model{i}" / "models" / "model_normalized.obj"
        path.parent.mkdir(parents=True)
        _to_file_convention(v.mesh, "y", "-z", 1.0).export(path)
    (tmp_path / "model0" / "readme.txt").write_text("not a mesh")
    vehicles = load_vehicle_folder(tmp_path, up="y", forward="-z", target_length=4.5)
    assert [v.vehicle_id for v in vehicles] == ["user-model0-models-model_normalized",
                                                "user-model1-models-model_normalized"]
    for v in vehicles:
        assert abs(v.size[0] - 4.5) < 1e-9 and v.size[2] < v.size[0]


# ---------------------------------------------------------------- the fleet (issue 15)

# sha256 of the rounded vertices and faces of vehicle_library(6, seed=0), computed before the
# fleet generator was added: the original procedural meshes must never change.
_LIBRARY_HASH = "7c1407a5e0bab5faf110a65f17f46dc9346f925455030ab35b4616702edaefd8"


def test_original_library_meshes_are_unchanged():
    import hashlib

    h = hashlib.sha256()
    lib = vehicle_library(6, seed=0)
    for v in lib:
        h.update(np.round(v.mesh.vertices, 9).tobytes())
        h.update(v.mesh.faces.astype(np.int64).tobytes())
    assert h.hexdigest() == _LIBRARY_HASH
    # they now carry a class and body / tyre labels too (no glass)
    for v in lib:
        assert v.cls == ("van" if v.kind == "van" else "car")
        assert v.face_labels.shape == (len(v.mesh.faces),)
        assert set(np.unique(v.face_labels)) == {BODY, TYRE}
        assert v.mesh.metadata["face_labels"] is v.face_labels


def test_vehicle_classes_match_the_data_package():
    from seqshape.data.sequence import VEHICLE_CLASSES as DATA_CLASSES

    assert VEHICLE_CLASSES == DATA_CLASSES
    assert set(FLEET_KINDS.values()) == set(VEHICLE_CLASSES)


@pytest.mark.parametrize("kind", list(FLEET_KINDS))
def test_every_fleet_kind_is_closed_labelled_and_in_its_real_size_range(kind):
    lo, hi = dimension_bounds(kind)
    for seed in (0, 1):
        v = fleet_vehicle(kind, seed)
        m = v.mesh
        assert m.is_watertight and m.is_winding_consistent and m.volume > 0
        np.testing.assert_allclose(m.bounds.mean(axis=0), 0.0, atol=1e-9)
        assert (500 if kind == "car_trailer" else 2000) <= len(m.faces) <= 20000
        assert v.kind == kind and v.cls == FLEET_KINDS[kind]
        assert v.source == f"fleet:{kind}:{seed}"
        # the annotator's box (mirrors excluded) lies in the range of the listed real models
        length, width, height = v.box_size
        assert lo[0] - 0.05 <= length <= hi[0] + 0.05, (length, lo[0], hi[0])
        assert lo[1] - 0.04 <= width <= hi[1] + 0.04, (width, lo[1], hi[1])
        assert lo[2] - 0.05 <= height <= hi[2] + 0.05, (height, lo[2], hi[2])
        # and it is the drawn size (roof rails included in the height)
        p = m.metadata["params"]
        drawn = p["height"] + (0.06 if p.get("roof_rails") else 0.0)
        np.testing.assert_allclose([length, height], [p["length"], drawn], atol=0.03)
        assert np.all(v.box_size <= v.size + 1e-9) and v.size[1] < width + 0.8
        # one label per face, valid codes, tyres everywhere, glass on cars, vans and buses
        assert v.face_labels.dtype == np.uint8 and v.face_labels.shape == (len(m.faces),)
        assert set(np.unique(v.face_labels)) <= set(FACE_LABELS)
        assert m.metadata["face_labels"] is v.face_labels
        assert np.any(v.face_labels == TYRE)
        if v.cls in ("car", "van", "bus"):
            assert np.any(v.face_labels == GLASS)
        # the wheels stand on the ground: the lowest vertices are tyres
        low = m.triangles_center[:, 2] < m.bounds[0, 2] + 0.03
        assert np.all(v.face_labels[low] == TYRE)


def test_fleet_vehicles_are_deterministic_and_rebuilt_from_their_source():
    a, b = fleet_vehicle("estate", 5), fleet_vehicle("estate", 5)
    np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
    np.testing.assert_array_equal(a.face_labels, b.face_labels)
    c = fleet_vehicle("estate", 6)
    assert not np.allclose(a.size, c.size)
    r = vehicle_from_source(a.source)
    np.testing.assert_array_equal(r.mesh.vertices, a.mesh.vertices)
    old = vehicle_from_source("procedural:van:3")
    np.testing.assert_array_equal(old.mesh.vertices, procedural_vehicle("van", 3).mesh.vertices)
    # a class picks a kind of that class from the seed, and the source names the fine kind
    t = fleet_vehicle("truck", 11)
    assert t.cls == "truck" and t.kind in ("box_truck", "tractor", "flatbed")
    np.testing.assert_array_equal(vehicle_from_source(t.source).mesh.vertices,
                                  t.mesh.vertices)
    for bad in ("procedural:sedan", "fleet:sedan:x", "/some/file.obj", "fleet:tank:1"):
        with pytest.raises(ConfigError):
            vehicle_from_source(bad)
    with pytest.raises(ConfigError):
        fleet_vehicle("tank", 0)
    with pytest.raises(ConfigError):
        fleet_vehicle("sedan", -1)


def _first_hit_label(v, origin, direction):
    from seqshape.vehicles.surface import ray_intersector

    isect = ray_intersector(v.mesh)
    tri = isect.intersects_first(np.array([origin], float), np.array([direction], float))[0]
    assert tri >= 0, "the ray missed the vehicle"
    return int(v.face_labels[tri])


@pytest.mark.parametrize("kind,seed", [("sedan", 2), ("suv", 4), ("hatchback", 1),
                                       ("panel_van", 3), ("pickup", 0)])
def test_car_glass_is_above_the_beltline_and_in_the_side_windows(kind, seed):
    v = fleet_vehicle(kind, seed)
    p, t = v.mesh.metadata["params"], v.mesh.metadata["build_to_canonical"]
    centres = v.mesh.triangles_center - t  # build frame: z up from the ground
    glass = centres[v.face_labels == GLASS]
    assert glass[:, 2].min() > p["belt"] - 0.06  # the windshield's base meets the cowl
    assert glass[:, 2].max() < p["height"] + 0.01
    # a ray from the left at mid-window height through the first side window hits glass;
    # the same ray 25 cm below the beltline hits the painted door
    a, b = p["windows"][0]
    x = p["length"] - 0.5 * (a + b) + t[0]
    z_win = p["belt"] + 0.12 + t[2]
    assert _first_hit_label(v, [x, 10.0, z_win], [0, -1, 0]) == GLASS
    assert _first_hit_label(v, [x, 10.0, p["belt"] - 0.25 + t[2]], [0, -1, 0]) == BODY
    # looking down the windshield from ahead and above hits glass, the hood below it paint
    s_ws = p["hood_len"] + 0.25 * (p["height"] - p["belt"]) / np.tan(np.radians(p["ws_deg"]))
    xw = p["length"] - s_ws + t[0]
    assert _first_hit_label(v, [xw, 0.0, 10.0], [0, 0, -1]) == GLASS
    assert _first_hit_label(v, [p["length"] - p["hood_len"] * 0.5 + t[0], 0.0, 10.0],
                            [0, 0, -1]) == BODY


@pytest.mark.parametrize("kind,seed", [("sedan", 2), ("suv", 4), ("hatchback", 1),
                                       ("panel_van", 3), ("pickup", 0), ("city_car", 5)])
def test_car_nose_grille_radiator_and_headlamps(kind, seed):
    from seqshape.vehicles.surface import ray_intersector

    v = fleet_vehicle(kind, seed)
    lab, c = v.face_labels, v.mesh.triangles_center
    # headlamps at the front, tail lamps at the rear, the grille across the nose
    assert (lab == HEADLAMP).any() and (c[lab == HEADLAMP, 0] > 0).all()
    assert (lab == LAMP).any() and (c[lab == LAMP, 0] < 0).all()
    grille = np.flatnonzero(lab == GRILLE)
    assert len(grille) and (c[grille, 0] > v.mesh.bounds[1, 0] - 0.7).all()
    # the radiator / engine bay block: the INTERIOR faces ahead of the cowl (the dashboard
    # behind it is the next interior part)
    p, t = v.mesh.metadata["params"], v.mesh.metadata["build_to_canonical"]
    inner = np.flatnonzero(lab == INTERIOR)
    rad = inner[c[inner, 0] > p["length"] - p["hood_len"] + t[0]]
    corners = v.mesh.triangles[rad].reshape(-1, 3)
    lo, hi = corners.min(0), corners.max(0)
    assert len(rad) == 12 and (hi - lo).min() > 0.07  # one closed box
    # looking at the middle of the nose from ahead: the grille, then the radiator behind it
    mid = grille[(c[grille, 2] > lo[2]) & (c[grille, 2] < hi[2])]
    assert len(mid) > len(grille) // 2  # the block covers most of the grille's height
    g = mid[np.argmin(np.abs(c[mid, 1]))]
    isect = ray_intersector(v.mesh)
    start, back = np.array([c[g, 0] + 5.0, c[g, 1], c[g, 2]]), np.array([-1.0, 0.0, 0.0])
    first = isect.intersects_first(start[None], back[None])[0]
    assert lab[first] == GRILLE
    hits, rays, tris = isect.intersects_location(start[None], back[None], multiple_hits=True)
    order = np.argsort(-hits[:, 0])
    behind = [(float(hits[i, 0]), int(lab[tris[i]])) for i in order][1:]
    assert behind and behind[0][1] == INTERIOR and c[g, 0] - behind[0][0] < 0.75
    # the radiator is closed inside the body: from its faces every axis ray meets the body
    for d in np.vstack([np.eye(3), -np.eye(3)]):
        o = c[rad] + d * 1e-3
        assert (isect.intersects_first(o, np.tile(d, (len(o), 1))) >= 0).all()
    # and it is no part of the complete (outside) shape
    pts = sample_outer_surface(v.mesh, 4000, seed=0)
    assert not np.all((pts > lo + 1e-4) & (pts < hi - 1e-4), axis=1).any()


def test_bus_glass_sits_above_the_floor_and_the_windshield_faces_forward():
    v = fleet_vehicle("city_bus", 2)
    p, t = v.mesh.metadata["params"], v.mesh.metadata["build_to_canonical"]
    c = v.mesh.triangles_center - t
    n = v.mesh.face_normals
    glass = v.face_labels == GLASS
    side = glass & (np.abs(n[:, 1]) > 0.9)
    assert side.sum() > 50 and c[side, 2].min() > p["belt"] - 0.02
    front = glass & (n[:, 0] > 0.7)
    assert front.sum() > 5 and c[front, 2].min() > p["windshield_bottom"] - 0.02
    assert c[front, 0].min() > p["length"] - 0.5  # the windshield is at the front end
    assert _first_hit_label(v, [20.0, 0.0, p["windshield_bottom"] + 0.5 + t[2]],
                            [-1, 0, 0]) == GLASS


@pytest.mark.parametrize("kind,seed", [("sedan", 2), ("suv", 4), ("hatchback", 1)])
def test_car_cabin_is_open_above_the_seat_backs(kind, seed):
    # real seats: backs end a few cm above the beltline, headrests sit over the outer seats,
    # a gap between the front seats; a ray along the car's axis just above the seat backs
    # crosses the whole cabin, one through a headrest does not, one below the belt does not
    v = fleet_vehicle(kind, seed)
    p, t = v.mesh.metadata["params"], v.mesh.metadata["build_to_canonical"]
    inner = v.mesh.submesh([np.flatnonzero(v.face_labels == INTERIOR)], append=True)
    isect = trimesh.ray.ray_triangle.RayMeshIntersector(inner)

    def hits(y, z):
        o = np.array([[p["length"] + 1.0, y, z]]) + t
        return bool(isect.intersects_any(o, np.array([[-1.0, 0.0, 0.0]]))[0])

    top = p["belt"] + p["belt_rise"]
    assert not hits(0.0, top + 0.12)
    assert hits(0.37, p["belt"] + 0.2)       # the driver's headrest
    assert hits(0.0, p["belt"] - 0.15)       # the rear bench back


@pytest.mark.parametrize("kind", ["mpv", "city_bus", "box_truck"])
def test_interior_is_hidden_from_the_outer_surface(kind):
    v = fleet_vehicle(kind, 1)
    assert np.any(v.face_labels == INTERIOR)
    pts = sample_outer_surface(v.mesh, n=1500, seed=0)
    _, _, tri = trimesh.proximity.closest_point(v.mesh, pts)
    assert not np.any(v.face_labels[tri] == INTERIOR)


def test_fleet_library_mix_quotas_and_determinism():
    q = kind_quotas(1000)
    assert sum(q.values()) == 1000
    for kind, share in DEFAULT_MIX.items():
        assert abs(q[kind] - 1000 * share) <= 1
    per_class = {c: sum(n for k, n in q.items() if FLEET_KINDS[k] == c) for c in CLASS_MIX}
    assert abs(per_class["car"] - 780) <= 2 and abs(per_class["bus"] - 30) <= 2
    a, b = fleet_library(12, seed=3), fleet_library(12, seed=3)
    assert [v.vehicle_id for v in a] == [v.vehicle_id for v in b]
    for va, vb in zip(a, b, strict=True):
        np.testing.assert_array_equal(va.mesh.vertices, vb.mesh.vertices)
    assert a[4].vehicle_id == f"fleet-s3-0004-{a[4].kind}"
    # seed 0 keeps the plain ids; other seeds name theirs apart, so libraries can be joined
    zero = fleet_library(12, seed=0)
    assert zero[4].vehicle_id == f"fleet-0004-{zero[4].kind}"
    assert not {v.vehicle_id for v in zero} & {v.vehicle_id for v in a}
    quotas = kind_quotas(12)
    for kind, count in quotas.items():
        assert sum(v.kind == kind for v in a) == count
    only = fleet_library(6, seed=0, mix={"bus": 1.0, "car_trailer": 1.0})
    assert {v.cls for v in only} == {"bus", "trailer"}
    assert sum(v.kind == "car_trailer" for v in only) == 3
    us, eu = kind_quotas(1000, "us"), kind_quotas(1000, "eu")
    assert us["pickup"] > 5 * eu["pickup"] and eu["hatchback"] > 4 * us["hatchback"]
    assert sum(us.values()) == sum(eu.values()) == 1000
    with pytest.raises(ConfigError):
        fleet_library(3, mix="mars")
    with pytest.raises(ConfigError):
        fleet_library(3, mix={"tank": 1.0})
    with pytest.raises(ConfigError):
        fleet_library(3, mix={"car": -1.0})
    assert fleet_library(0) == []
