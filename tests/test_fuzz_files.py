"""Fuzz tests of the project's own file readers: COCO RLE, KINS / COCO JSON, track dataset
manifests and vehicle meshes (issue 18, item 10), and manifest paths that leave their folder
(item 9).

Each test mutates valid files with a seeded generator and asserts that every input either
raises :class:`DataError` naming the file or reads back as provably valid content (checked
against independent references below); any other exception fails the test.
"""

import json
import os

import numpy as np
import pytest
import trimesh

from seqshape.data import Track, TrackDataset, write_dataset
from seqshape.data.kins import (
    SegmentationError,
    annotation_mask,
    coco_annotation,
    image_entry,
    kins_annotation,
    mask_to_rle,
    read_coco_instances,
    read_kins,
    rle_to_mask,
    write_coco_instances,
    write_kins,
)
from seqshape.errors import DataError
from seqshape.vehicles.io import load_vehicle

# ----------------------------------------------------------------------------- references


def reference_runs(counts) -> list[int]:
    """Run lengths of a COCO compressed RLE string, a line-by-line port of pycocotools'
    ``rleFrString`` (C) with Python's unbounded ints; raises ValueError on a character outside
    the code or an unfinished last run."""
    data = counts.encode("latin-1") if isinstance(counts, str) else bytes(counts)
    runs, p = [], 0
    while p < len(data):
        x, k, more = 0, 0, True
        while more:
            if p >= len(data):
                raise ValueError("unfinished run")
            c = data[p] - 48
            if not 0 <= c <= 63:
                raise ValueError("bad character")
            x |= (c & 0x1F) << 5 * k
            more = bool(c & 0x20)
            p += 1
            k += 1
            if not more and c & 0x10:
                x |= -1 << 5 * k
        if len(runs) > 2:
            x += runs[-2]
        runs.append(x)
    return runs


def reference_mask(runs, h, w) -> np.ndarray:
    """The (h, w) mask of run lengths (column-major, starting with zeros), by a plain loop."""
    flat, value = [], False
    for r in runs:
        flat.extend([value] * r)
        value = not value
    return np.array(flat, dtype=bool).reshape(w, h).T


def valid_rle(rle) -> bool:
    """Is ``rle`` a well-formed RLE by the references (non-negative runs covering h x w)."""
    try:
        h, w = rle["size"]
        counts = rle["counts"]
        if isinstance(counts, list):
            runs = counts
            if not all(isinstance(c, int) and not isinstance(c, bool) for c in runs):
                return False
        elif isinstance(counts, (str, bytes)):
            runs = reference_runs(counts)
        else:
            return False
        ok_size = all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in (h, w))
    except (TypeError, ValueError, KeyError):
        return False
    return ok_size and all(r >= 0 for r in runs) and sum(runs) == h * w


# ----------------------------------------------------------------------------- mutations


def mutate_bytes(data: bytes, rng: np.random.Generator) -> bytes:
    """One random byte-level mutation: truncate, flip bytes, delete or duplicate a span,
    insert non-UTF-8 bytes or empty the file."""
    b = bytearray(data)
    op = int(rng.integers(6))
    if op == 0:
        return bytes(b[:int(rng.integers(0, len(b)))])
    if op == 1:
        for i in rng.integers(0, len(b), int(rng.integers(1, 6))):
            b[int(i)] = int(rng.integers(0, 256))
        return bytes(b)
    i, j = sorted(int(v) for v in rng.integers(0, len(b), 2))
    if op == 2:
        return bytes(b[:i] + b[j:])
    if op == 3:
        return bytes(b[:j] + b[i:j] + b[j:])
    if op == 4:
        return bytes(b[:i] + bytes([0xFF, 0xFE, 0xC3]) + b[i:])
    return b""


#: replacement values that are wrong for most fields
ODD_VALUES = [None, True, -1, 0, 1.5, -3.7, 10**30, float("nan"), float("inf"), "x", "", [],
              [1, 2], {}, {"a": 1}, [[1, 2, 3]], 2**63, -(2**40)]


def mutate_json(doc, rng: np.random.Generator):
    """One random structural mutation of a JSON value (a deep copy): a value replaced by an
    odd one, a key deleted, or a list emptied / truncated."""
    doc = json.loads(json.dumps(doc))
    slots = []

    def walk(node):
        if isinstance(node, dict):
            for k in list(node):
                slots.append((node, k))
                walk(node[k])
        elif isinstance(node, list):
            for k in range(len(node)):
                slots.append((node, k))
                walk(node[k])

    walk(doc)
    if not slots:
        return ODD_VALUES[int(rng.integers(len(ODD_VALUES)))]
    parent, key = slots[int(rng.integers(len(slots)))]
    op = int(rng.integers(4))
    if op == 0 and isinstance(parent, dict):
        del parent[key]
    elif op == 1 and isinstance(parent[key], list) and parent[key]:
        del parent[key][int(rng.integers(len(parent[key]))):]
    else:
        parent[key] = ODD_VALUES[int(rng.integers(len(ODD_VALUES)))]
    return doc


def write_json(path, doc) -> None:
    path.write_text(json.dumps(doc, allow_nan=True))


def mutated_json(path, n: int, rng: np.random.Generator):
    """Overwrite the JSON file ``path`` ``n`` times, alternately with a structural mutation of
    its document and a byte mutation of its text, yielding after each write (the original is
    restored at the end)."""
    good = path.read_bytes()
    doc = json.loads(good)
    for k in range(n):
        if k % 2:
            path.write_bytes(mutate_bytes(good, rng))
        else:
            write_json(path, mutate_json(doc, rng))
        yield k
    path.write_bytes(good)


def expect_data_error_or(path, read, check):
    """``read(path)``: a DataError naming ``path``, or a result that passes ``check``."""
    try:
        out = read(path)
    except DataError as exc:
        assert exc.path == str(path) and str(path) in str(exc), str(exc)
        return None
    check(out)
    return out


# ----------------------------------------------------------------------------- RLE


def _rle_variants(rng):
    """Valid RLEs (compressed and uncompressed) of random masks."""
    h, w = (int(v) for v in rng.integers(1, 12, 2))
    mask = rng.random((h, w)) < rng.random()
    rle = mask_to_rle(mask)
    runs = reference_runs(rle["counts"])
    return mask, rle, {"size": [h, w], "counts": runs}


def _mutate_rle(rle, rng):
    rle = {"size": list(rle["size"]), "counts": rle["counts"]}
    op = int(rng.integers(8))
    counts = rle["counts"]
    if op == 0:
        rle["size"] = [int(v) + int(rng.integers(-2, 3)) for v in rle["size"]]
    elif op == 1:
        rle["size"] = ODD_VALUES[int(rng.integers(len(ODD_VALUES)))]
    elif op == 2:
        rle["counts"] = ODD_VALUES[int(rng.integers(len(ODD_VALUES)))]
    elif op == 3 and isinstance(counts, str):
        rle["counts"] = counts[:int(rng.integers(0, len(counts) + 1))]
    elif op == 4 and isinstance(counts, str) and counts:
        i = int(rng.integers(len(counts)))
        rle["counts"] = counts[:i] + chr(int(rng.integers(32, 256))) + counts[i + 1:]
    elif op == 5 and isinstance(counts, list):
        counts = list(counts)
        counts[int(rng.integers(len(counts)))] = ODD_VALUES[int(rng.integers(len(ODD_VALUES)))]
        rle["counts"] = counts
    elif op == 6 and isinstance(counts, list):
        rle["counts"] = counts[:int(rng.integers(0, len(counts) + 1))]
    elif op == 7:
        del rle["counts" if rng.random() < 0.5 else "size"]
    return rle


def test_fuzz_rle_dicts():
    """rle_to_mask refuses every malformed RLE (SegmentationError, a ValueError) and decodes
    every accepted one exactly as the pixel-loop reference."""
    rng = np.random.default_rng(18)
    accepted = refused = 0
    for _ in range(400):
        mask, compressed, plain = _rle_variants(rng)
        for rle in (compressed, plain):
            bad = _mutate_rle(rle, rng)
            try:
                got = rle_to_mask(bad)
            except SegmentationError:
                refused += 1
                assert not valid_rle(bad), bad
                continue
            accepted += 1
            assert valid_rle(bad), bad
            runs = bad["counts"] if isinstance(bad["counts"], list) else \
                reference_runs(bad["counts"])
            np.testing.assert_array_equal(got, reference_mask(runs, *bad["size"]))
    assert accepted > 50 and refused > 300


def test_the_issue_rle_is_refused():
    with pytest.raises(SegmentationError, match="cover 0 pixels.*has 20"):
        rle_to_mask({"size": [4, 5], "counts": ""})


# ----------------------------------------------------------------------------- KINS / COCO


def _kins_doc(rng):
    h, w = 12, 16
    images = [image_entry(i, "0000", i, h, w) for i in range(2)]
    anns = []
    for k in range(3):
        a = np.zeros((h, w), bool)
        y, x = (int(v) for v in rng.integers(0, 6, 2))
        a[y:y + 5, x:x + 7] = True
        v = a & (rng.random((h, w)) < 0.8)
        anns.append(kins_annotation(k + 1, k % 2, 4, a, v, 0, 0, track_id=k,
                                    polygons=k == 2))
    return images, anns


def _check_kins(doc):
    """Everything an accepted KINS / COCO document promises its users."""
    sizes = {img["id"]: img for img in doc["images"]}
    for ann in doc["annotations"]:
        img = sizes[ann["image_id"]]
        for key in ("a_segm", "i_segm", "segmentation"):
            if key in ann:
                m = annotation_mask(ann, key, img)
                assert m.shape == (img["height"], img["width"]) and m.dtype == bool
                if isinstance(ann[key], dict):
                    assert valid_rle(ann[key])


@pytest.mark.parametrize("reader", ["kins", "coco"])
def test_fuzz_kins_and_coco_json(tmp_path, reader):
    rng = np.random.default_rng(7 if reader == "kins" else 8)
    images, anns = _kins_doc(rng)
    path = tmp_path / "labels.json"
    if reader == "kins":
        write_kins(path, images, anns)
        read = read_kins
    else:
        coco = [coco_annotation(a["id"], a["image_id"], 4, annotation_mask(
            a, "a_segm", images[a["image_id"]]), score=0.5) for a in anns]
        write_coco_instances(path, images, coco)
        read = read_coco_instances
    accepted = 0
    for _ in mutated_json(path, 300, rng):
        accepted += expect_data_error_or(path, read, _check_kins) is not None
    assert 0 < accepted < 200


def test_kins_top_level_and_encoding_errors(tmp_path):
    path = tmp_path / "k.json"
    for content, message in ((b"[1, 2]", "got a JSON array"), (b"\xff\xfe{}", "not UTF-8"),
                             (b"", "invalid JSON"), (b"[" * 100000, "invalid JSON"),
                             (b'{"images": 3}', "non-list top-level key 'images'")):
        path.write_bytes(content)
        with pytest.raises(DataError, match=message) as info:
            read_kins(path)
        assert info.value.path == str(path)


# ----------------------------------------------------------------------------- manifests


def _track(tid):
    return Track(tid, [np.full((2, 3), 1.0, np.float32)], np.zeros((1, 4)), None, np.ones(3),
                 np.zeros(1), {"split": "train"})


def _check_dataset(ds):
    root = ds.path.resolve()
    for e in ds.entries:
        assert isinstance(e["track_id"], str) and e["track_id"]
        assert (root / e["file"]).resolve().is_relative_to(root)


def test_fuzz_manifests(tmp_path):
    rng = np.random.default_rng(9)
    ds = write_dataset(tmp_path / "ds", [_track("a"), _track("b")])
    mpath = ds.path / "manifest.json"
    accepted = 0
    for _ in mutated_json(mpath, 300, rng):
        out = expect_data_error_or(mpath, lambda p: TrackDataset(p.parent), _check_dataset)
        if out is not None:
            accepted += 1
            for i in range(len(out)):  # the files named may be missing: DataError, not more
                expect_data_error_or(out.path / out.entries[i]["file"],
                                     lambda p, ds=out, i=i: ds[i], lambda tr: None)
    assert 0 < accepted < 200


@pytest.mark.parametrize("file", ["../outside.npz", "tracks/../../outside.npz",
                                  "/etc/passwd", "../../../../etc/passwd", "", "tracks/\0.npz"])
def test_manifest_paths_must_stay_inside_the_folder(tmp_path, file):
    ds = write_dataset(tmp_path / "ds", [_track("a")])
    write_dataset(tmp_path / "other", [_track("a")])
    (tmp_path / "outside.npz").write_bytes((tmp_path / "other" / "tracks" / "a.npz").read_bytes())
    mpath = ds.path / "manifest.json"
    doc = json.loads(mpath.read_text())
    doc["tracks"][0]["file"] = file
    mpath.write_text(json.dumps(doc))
    with pytest.raises(DataError, match="file") as info:
        TrackDataset(ds.path)
    assert info.value.path == str(mpath)


def test_manifest_symlinks_out_of_the_folder_are_refused(tmp_path):
    ds = write_dataset(tmp_path / "ds", [_track("a"), _track("b")])
    write_dataset(tmp_path / "other", [_track("x")])
    link = ds.path / "tracks" / "b.npz"
    link.unlink()
    os.symlink(tmp_path / "other" / "tracks" / "x.npz", link)  # a file link out
    os.symlink(tmp_path / "other" / "tracks", ds.path / "away")  # a folder link out
    opened = TrackDataset(ds.path)
    assert opened.get("a").track_id == "a"  # the files inside still read
    with pytest.raises(DataError, match="outside the dataset folder") as info:
        opened.get("b")
    assert info.value.path == str(ds.path / "manifest.json")
    mpath = ds.path / "manifest.json"
    doc = json.loads(mpath.read_text())
    doc["tracks"][0]["file"] = "away/x.npz"
    mpath.write_text(json.dumps(doc))
    with pytest.raises(DataError, match="outside the dataset folder"):
        TrackDataset(ds.path)[0]
    with pytest.raises(DataError, match="outside the dataset folder"):
        TrackDataset.union([ds.path, tmp_path / "other"], [1.0, 1.0])
    # a link that stays inside the folder is followed; the file it reaches must hold the
    # track the manifest names (issue 45: it was loaded under the file's own id)
    (ds.path / "tracks" / "b.npz").unlink()
    os.symlink(ds.path / "tracks" / "a.npz", ds.path / "tracks" / "b.npz")
    doc["tracks"][0]["file"] = "tracks/a.npz"
    mpath.write_text(json.dumps(doc))
    assert TrackDataset(ds.path).get("a").track_id == "a"
    with pytest.raises(DataError, match="holds track 'a', but .*manifest.json lists this file "
                                        "as track 'b'") as info:
        TrackDataset(ds.path).get("b")
    assert info.value.path == str(ds.path / "tracks" / "b.npz")


# ----------------------------------------------------------------------------- meshes


def _obj_text() -> str:
    box = trimesh.creation.box(extents=(4.0, 1.8, 1.5))
    lines = [f"v {x:.3f} {y:.3f} {z:.3f}" for x, y, z in box.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in box.faces]
    return "\n".join(lines) + "\n"


_OBJ_TOKENS = ["nan", "inf", "-inf", "1e308", "-1e308", "0", "-0", "9", "99", "-99", "1.5",
               "x", "", "1/2/3", "1e400", "-9"]


def _mutate_obj(text: str, rng) -> bytes:
    lines = text.splitlines()
    op = int(rng.integers(5))
    if op == 0:  # a token replaced
        i = int(rng.integers(len(lines)))
        parts = lines[i].split()
        parts[int(rng.integers(1, len(parts)))] = _OBJ_TOKENS[int(rng.integers(len(_OBJ_TOKENS)))]
        lines[i] = " ".join(parts)
    elif op == 1:  # lines dropped
        keep = rng.random(len(lines)) > rng.random() * 0.5
        lines = [ln for ln, k in zip(lines, keep, strict=True) if k]
    elif op == 2:  # every z (or y, x) set to one value: a flat mesh
        axis = int(rng.integers(1, 4))
        lines = [" ".join(p[:axis] + ["0.5"] + p[axis + 1:]) if p[0] == "v" else ln
                 for ln, p in ((ln, ln.split()) for ln in lines)]
    elif op == 3:  # a face line with a wrong token count
        lines.append("f " + " ".join(str(int(v)) for v in rng.integers(-3, 12, rng.integers(1, 6))))
    else:
        return mutate_bytes(("\n".join(lines) + "\n").encode(), rng)
    return ("\n".join(lines) + "\n").encode()


def _check_vehicle(v):
    verts, faces = np.asarray(v.mesh.vertices), np.asarray(v.mesh.faces)
    assert np.all(np.isfinite(verts)) and len(faces) > 0
    assert faces.min() >= 0 and faces.max() < len(verts)
    assert np.all(np.ptp(verts, axis=0) > 0) and v.mesh.area > 0


def test_fuzz_obj_meshes(tmp_path):
    rng = np.random.default_rng(11)
    text = _obj_text()
    path = tmp_path / "car.obj"
    accepted = 0
    for _ in range(250):
        path.write_bytes(_mutate_obj(text, rng))
        accepted += expect_data_error_or(path, load_vehicle, _check_vehicle) is not None
    assert 0 < accepted < 200
