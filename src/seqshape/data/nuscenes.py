"""nuScenes (v1.0) scenes as :class:`~seqshape.data.sequence.DrivingLog` s, without the devkit.

The official layout (``DATAROOT/v1.0-mini/*.json`` or ``v1.0-trainval``, ``samples/...``) is
read with the standard library's :mod:`json` and numpy. The tables of one dataset are read and
indexed once per process (:func:`load_tables`, cached per folder and version, reloaded when a
table file changes), so opening the 850 scenes of ``v1.0-trainval`` one after the other reads
its JSON once.

Conventions (those of the nuScenes devkit, fixed once here):

* Quaternions are scalar-first ``[w, x, y, z]``. ``calibrated_sensor`` maps a sensor's points
  into the **ego** frame (x forward, y left, z up, origin at the rear axle):
  ``p_ego = R(rotation) @ p_sensor + translation``; ``ego_pose`` maps the ego frame at the
  ``sample_data``'s timestamp into the **global** frame the same way.
* ``LIDAR_TOP`` points (``samples/LIDAR_TOP/*.pcd.bin``: float32 ``x y z intensity ring``
  per point) are in the LiDAR's own axes, which are rotated by about -90 degrees about z from
  the ego axes (LiDAR x points to the right of the car).
* Boxes (``sample_annotation``) are in the global frame: ``translation`` is the box centre,
  ``size`` is ``[width, length, height]`` (note the order), ``rotation`` turns the box's axes
  (x along its length, forward) into global axes.

Our **sensor frame** of a keyframe: the ego axes with the origin at the ``LIDAR_TOP``
position, i.e. ``p_sensor = R_ego_lidar @ p_lidar`` (rotation only). Boxes go global -> ego
(inverse ego pose of the LiDAR's ``sample_data``) -> minus the LiDAR translation; ``yaw`` is
the heading of the box's x axis projected onto the sensor x-y plane; ``size`` becomes
``(length, width, height)``.

Frames are the scene's keyframes (``sample`` records, ``first_sample_token`` then ``next``),
numbered 0..T-1; a frame's time is its ``LIDAR_TOP`` keyframe timestamp (microseconds) * 1e-6.

:class:`Box3D` fields: ``track_id`` the instance token, ``category`` the category name,
``cls`` from :data:`CATEGORY_TO_CLASS`, ``num_points`` the annotation's ``num_lidar_pts``,
``visibility`` the lower bound of the visibility level's range as a fraction (``"v60-80"`` ->
0.6: at least 60 % of the object is visible in the six images). ``extra``: ``token`` (the
sample_annotation token), ``visibility_level`` (e.g. ``"v60-80"``), ``attributes`` (names),
``num_radar_pts``, ``rotation`` ((3, 3) box axes -> sensor frame, with any roll and pitch).

Errors: a missing or malformed table (not JSON, not a list of records with string tokens, a
missing or wrongly typed field, a dangling token) is a :class:`~seqshape.errors.DataError`
naming the table file; so are a quaternion whose norm is not 1 within 1e-3 (closer ones are
normalised), a non-finite number, a box dimension <= 0 or above 30 m, a box centre more than
1 km from the sensor, a sensor more than 1 km from the ego origin, a pose beyond 10,000 km, a
timestamp that is not a non-negative number, a ``num_lidar_pts`` that is not a non-negative
integer, a camera without positive focal lengths, a keyframe ``filename`` that is absolute
or climbs out of the data root (``..``) and two keyframes of one channel in one sample. A
LiDAR file whose size is not a multiple of 20 bytes is a DataError; its points holding a NaN
or an infinity are dropped with one warning.
"""

from __future__ import annotations

import json
import logging
import re
import threading
from collections import Counter
from pathlib import Path

import numpy as np

from seqshape._io import read_bytes
from seqshape.camera import PinholeCamera
from seqshape.data.sequence import (
    MAX_RANGE,
    MAX_WORLD,
    Box3D,
    DrivingLog,
    box_problems,
    read_sweep,
    unit_quaternions,
)
from seqshape.errors import ConfigError, DataError

log = logging.getLogger(__name__)

#: tables the reader needs (``DATAROOT/VERSION/<name>.json``).
TABLES = ("scene", "sample", "sample_data", "sample_annotation", "instance", "category",
          "calibrated_sensor", "ego_pose", "sensor", "log")
#: tables read when present (visibility levels and attribute names of the boxes).
OPTIONAL_TABLES = ("visibility", "attribute")

LIDAR = "LIDAR_TOP"
#: nuScenes' camera channels, in the order ``camera_names`` lists them.
CAMERA_ORDER = ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "CAM_BACK", "CAM_BACK_LEFT",
                "CAM_BACK_RIGHT")

#: nuScenes category -> seqshape vehicle class.
CATEGORY_TO_CLASS = {
    "vehicle.car": "car",
    "vehicle.truck": "truck",
    "vehicle.bus.bendy": "bus",
    "vehicle.bus.rigid": "bus",
    "vehicle.trailer": "trailer",
    "vehicle.construction": "truck",
    "vehicle.emergency.ambulance": "van",
    "vehicle.emergency.police": "car",
}
#: known nuScenes categories (by prefix) that are not vehicles: ``cls`` None, no warning.
NON_VEHICLE_PREFIXES = ("vehicle.bicycle", "vehicle.motorcycle", "vehicle.ego", "human.",
                        "animal", "movable_object.", "static_object.", "flat.", "static.",
                        "noise")

_VERSION_DIR = re.compile(r"^v\d+(\.\d+)*-[\w.-]+$")
_VIS_LEVEL = re.compile(r"^v(\d+)-(\d+)$")


def category_to_class(name: str) -> tuple[str | None, bool]:
    """``(cls, known)`` of a nuScenes category: its vehicle class (or None) and whether the
    name is a known nuScenes category.

    >>> category_to_class("vehicle.bus.rigid"), category_to_class("vehicle.bicycle")
    (('bus', True), (None, True))
    >>> category_to_class("vehicle.hovercraft")
    (None, False)
    """
    if name in CATEGORY_TO_CLASS:
        return CATEGORY_TO_CLASS[name], True
    return None, name.startswith(NON_VEHICLE_PREFIXES)


def quaternion_to_matrix(q) -> np.ndarray:
    """(3, 3) rotation matrix of a scalar-first quaternion ``[w, x, y, z]`` (normalised first).

    >>> quaternion_to_matrix([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]).round(6)[:2, :2]
    array([[ 0., -1.],
           [ 1.,  0.]])
    """
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def read_pcd_bin(path) -> np.ndarray:
    """A nuScenes LiDAR file: ``(N, 5)`` float32 ``x, y, z, intensity, ring`` (LiDAR frame).

    A missing file, or a size that is not a multiple of 20 bytes, is a :class:`DataError`;
    points holding a NaN or an infinity are dropped, with one warning naming the file and the
    count.
    """
    return read_sweep(path, 5, "LiDAR file", "x y z intensity ring")


def _rigid(rotation: np.ndarray, translation) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rotation
    m[:3, 3] = translation
    return m


def _invert(m: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = m[:3, :3].T
    out[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return out


# ---------------------------------------------------------------------------------------------
# tables


def find_version(root, version: str | None = None) -> tuple[Path, str]:
    """``(dataroot, version)`` of a nuScenes folder.

    ``version`` given: ``root/version`` must exist. Otherwise ``root`` may be the table folder
    itself (holding ``scene.json``; its parent is the data root) or the data root holding
    exactly one table folder (``v1.0-mini``, ``v1.0-trainval``, ...); several is an error
    asking for ``version``.
    """
    root = Path(root)
    if version:
        if not (root / version).is_dir():
            raise DataError(root / version, "nuScenes table folder not found")
        return root, version
    if (root / "scene.json").is_file():
        return root.parent, root.name
    if not root.is_dir():
        raise DataError(root, "no such nuScenes folder")
    found = sorted(p.name for p in root.iterdir() if p.is_dir()
                   and (_VERSION_DIR.match(p.name) or (p / "scene.json").is_file()))
    if not found:
        raise DataError(root, "no nuScenes table folder (v1.0-mini/, v1.0-trainval/, ...) here")
    if len(found) > 1:
        raise DataError(root, f"several nuScenes table folders {found}: pass version=... or "
                              "give the table folder itself (e.g. ROOT/v1.0-mini) as the root")
    return root, found[0]


def _read_table(path: Path) -> list[dict]:
    """One JSON table: a list of records, each a dict with a string ``token``."""
    data = read_bytes(path, "nuScenes table", "json")
    try:
        records = json.loads(data)
    except json.JSONDecodeError as exc:
        raise DataError(path, f"malformed JSON: {exc.msg}", line=exc.lineno) from None
    except (OSError, UnicodeDecodeError, ValueError, RecursionError, MemoryError) as exc:
        # ValueError: an integer of more than 4300 digits; RecursionError: absurd nesting
        raise DataError(path, f"unreadable nuScenes table ({type(exc).__name__}: "
                              f"{str(exc)[:200]})") from None
    if not isinstance(records, list):
        raise DataError(path, f"expected a JSON list of records, got {type(records).__name__}")
    return records


def _by_token(records: list, path: Path) -> dict[str, dict]:
    """``{token: record}``; a record that is not an object with a non-empty string
    ``token``, or a token twice, is a :class:`DataError` naming the table."""
    out: dict[str, dict] = {}
    for i, rec in enumerate(records):
        token = _token(rec, i, path)
        if out.setdefault(token, rec) is not rec:
            raise DataError(path, f"record {i}: token {token!r} appears twice (each record "
                                  "needs its own token)")
    return out


def _all_numbers(value) -> bool:
    """Is ``value`` a (nested) JSON list of numbers only (a boolean is not a number)?"""
    if not isinstance(value, list):
        return False
    return all(_all_numbers(x) if isinstance(x, list) else
               isinstance(x, (int, float)) and not isinstance(x, bool) for x in value)


def _token(rec, i: int, path: Path) -> str:
    """The record's ``token``: a non-empty string, else a DataError naming the table."""
    if not isinstance(rec, dict):
        raise DataError(path, f"record {i} is not an object with a string 'token'")
    token = rec.get("token")
    if not isinstance(token, str) or not token:
        raise DataError(path, f"record {i} is not an object with a string 'token' "
                              f"(token {token!r})")
    return token


class NuScenesTables:
    """The indexed tables of one nuScenes version (use :func:`load_tables`, which caches).

    Keeps every scene, sample, annotation, instance, category and sensor record, but only the
    keyframe ``sample_data`` records and their ego poses (the sweeps between keyframes are
    not read by :class:`NuScenesLog`): ``keyframes[sample_token][channel]``.
    """

    def __init__(self, dataroot: Path, version: str):
        self.dataroot = Path(dataroot)
        self.version = version
        self.table_dir = self.dataroot / version
        raw = {name: _read_table(self.path(name)) for name in TABLES}
        for name in OPTIONAL_TABLES:
            raw[name] = _read_table(self.path(name)) if self.path(name).exists() else []
        for name in ("scene", "sample", "instance", "category", "calibrated_sensor", "sensor",
                     "log", *OPTIONAL_TABLES):
            setattr(self, name, _by_token(raw[name], self.path(name)))
        self.scene_by_name = {}
        for token, rec in self.scene.items():
            self.scene_by_name[self.field(rec, "name", "scene", str)] = token
        self.channels = self._index_channels()
        self.keyframes = self._index_keyframes(raw["sample_data"])
        self.ego_pose = self._keep_ego_poses(_by_token(raw["ego_pose"], self.path("ego_pose")))
        self.annotations = self._index_annotations(raw["sample_annotation"])

    def path(self, table: str) -> Path:
        return self.table_dir / f"{table}.json"

    def field(self, rec: dict, key: str, table: str, kind=None):
        """``rec[key]`` (of type ``kind``; a bool is not a number), or a DataError naming the
        table and record."""
        value = rec.get(key)
        if key not in rec or (kind is not None and (
                not isinstance(value, kind) or (isinstance(value, bool) and kind is not bool))):
            what = "missing" if key not in rec else f"not a {getattr(kind, '__name__', kind)}"
            raise DataError(self.path(table), f"record {rec.get('token')!r}: field {key!r} "
                                              f"{what}")
        return rec[key]

    def get(self, table: str, token, referrer: str = "") -> dict:
        """The record ``token`` of ``table``; a missing one is a DataError."""
        rec = getattr(self, table).get(token) if isinstance(token, str) else None
        if rec is None:
            by = f" (referenced by {referrer})" if referrer else ""
            raise DataError(self.path(table), f"no record with token {token!r}{by}")
        return rec

    def vector(self, rec: dict, key: str, table: str, shape) -> np.ndarray:
        """``rec[key]`` as a finite float64 array of ``shape`` (a JSON list of numbers; a
        boolean is not a number), or a DataError."""
        value = self.field(rec, key, table)
        try:
            if not _all_numbers(value):
                raise TypeError(key)
            v = np.asarray(value, dtype=np.float64).reshape(shape)
        except (TypeError, ValueError, OverflowError):
            raise DataError(self.path(table), f"record {rec.get('token')!r}: field {key!r} "
                                              f"must be {shape} numbers") from None
        if not np.all(np.isfinite(v)):
            raise DataError(self.path(table), f"record {rec.get('token')!r}: field {key!r} "
                                              "has a non-finite value")
        return v

    def rotation(self, rec: dict, table: str) -> np.ndarray:
        """(3, 3) of the record's ``rotation`` quaternion (normalised when its norm is within
        1e-3 of 1, else a DataError)."""
        q = self.vector(rec, "rotation", table, 4)
        unit_quaternions(q, self.path(table), f"record {rec.get('token')!r}: rotation")
        return quaternion_to_matrix(q)  # normalises, exactly as before the check

    def translation(self, rec: dict, table: str, limit: float) -> np.ndarray:
        """(3,) the record's ``translation``; a coordinate beyond ``limit`` m is a DataError."""
        t = self.vector(rec, "translation", table, 3)
        if np.abs(t).max() > limit:
            raise DataError(self.path(table), f"record {rec.get('token')!r}: translation "
                                              f"{t.tolist()} is beyond {limit:g} m")
        return t

    def transform(self, rec: dict, table: str) -> np.ndarray:
        """(4, 4) of a ``calibrated_sensor`` or ``ego_pose`` record (rotation, translation):
        a sensor within :data:`MAX_RANGE` of the ego origin, an ego pose within
        :data:`MAX_WORLD` of the global origin."""
        limit = MAX_RANGE if table == "calibrated_sensor" else MAX_WORLD
        return _rigid(self.rotation(rec, table), self.translation(rec, table, limit))

    def _index_channels(self) -> dict[str, tuple[str, str]]:
        out = {}
        for token, rec in self.calibrated_sensor.items():
            sensor = self.get("sensor", rec.get("sensor_token"), f"calibrated_sensor {token}")
            out[token] = (self.field(sensor, "channel", "sensor", str),
                          self.field(sensor, "modality", "sensor", str))
        return out

    def _index_keyframes(self, records: list) -> dict[str, dict[str, dict]]:
        path, out = self.path("sample_data"), {}
        for i, rec in enumerate(records):
            if not isinstance(rec, dict):
                raise DataError(path, f"record {i} is not an object")
            if not self.field(rec, "is_key_frame", "sample_data", bool):
                continue
            for key in ("token", "sample_token", "calibrated_sensor_token", "ego_pose_token",
                        "filename"):
                self.field(rec, key, "sample_data", str)
            _timestamp_us(self, rec)
            _relative_file(rec["filename"], path, rec["token"])
            channel = self.channels.get(rec["calibrated_sensor_token"])
            if channel is None:
                raise DataError(path, f"record {rec['token']!r}: calibrated_sensor_token "
                                      f"{rec['calibrated_sensor_token']!r} not in "
                                      "calibrated_sensor.json")
            other = out.setdefault(rec["sample_token"], {}).setdefault(channel[0], rec)
            if other is not rec:
                raise DataError(path, f"sample {rec['sample_token']!r} has two {channel[0]} "
                                      f"keyframes ({other['token']!r}, {rec['token']!r})")
        return out

    def _keep_ego_poses(self, ego: dict[str, dict]) -> dict[str, dict]:
        needed = {rec["ego_pose_token"] for per in self.keyframes.values() for rec in per.values()}
        return {t: ego[t] for t in needed if t in ego}

    def _index_annotations(self, records: list) -> dict[str, list[dict]]:
        """Annotations by sample; a record without a string token, sample_token and
        instance_token, a token twice, or an instance annotated twice in one sample is a
        :class:`DataError` naming sample_annotation.json."""
        path, out = self.path("sample_annotation"), {}
        tokens: dict[str, int] = {}
        seen: dict[tuple[str, str], str] = {}
        for i, rec in enumerate(records):
            token = _token(rec, i, path)
            if not isinstance(rec.get("sample_token"), str):
                raise DataError(path, f"record {i} is not an object with a 'sample_token'")
            first = tokens.setdefault(token, i)
            if first != i:
                raise DataError(path, f"records {first} and {i}: token {token!r} appears "
                                      "twice")
            instance = self.field(rec, "instance_token", "sample_annotation", str)
            self.get("instance", instance, f"sample_annotation {token}")
            other = seen.setdefault((rec["sample_token"], instance), token)
            if other != token:
                raise DataError(path, f"records {other!r} and {token!r}: instance "
                                      f"{instance!r} annotated twice in sample "
                                      f"{rec['sample_token']!r}")
            out.setdefault(rec["sample_token"], []).append(rec)
        return out

    def scene_samples(self, scene: dict) -> list[str]:
        """Sample tokens of a scene in time order (``first_sample_token``, then ``next``)."""
        token = self.field(scene, "first_sample_token", "scene", str)
        tokens: list[str] = []
        while token:
            if token in tokens or len(tokens) > len(self.sample):
                raise DataError(self.path("sample"), f"scene {scene.get('name')!r}: the "
                                                     f"'next' chain loops at sample {token!r}")
            rec = self.get("sample", token, f"scene {scene.get('name')!r}")
            tokens.append(token)
            token = rec.get("next", "")
        if not tokens:
            raise DataError(self.path("scene"), f"scene {scene.get('name')!r} has no samples")
        return tokens

    def category_name(self, ann: dict) -> str:
        inst = self.get("instance", ann.get("instance_token"),
                        f"sample_annotation {ann.get('token')}")
        cat = self.get("category", inst.get("category_token"), f"instance {inst['token']}")
        return self.field(cat, "name", "category", str)


_CACHE: dict[tuple[str, str], tuple[tuple, NuScenesTables]] = {}
_CACHE_LOCK = threading.Lock()


def _signature(table_dir: Path) -> tuple:
    out = []
    for name in TABLES + OPTIONAL_TABLES:
        try:
            st = (table_dir / f"{name}.json").stat()
            out.append((name, st.st_mtime_ns, st.st_size))
        except OSError:
            out.append((name, None, None))
    return tuple(out)


def load_tables(root, version: str | None = None) -> NuScenesTables:
    """The indexed tables of a nuScenes folder (see :func:`find_version`), read once per
    process and folder; read again only when a table file changed (size or mtime)."""
    dataroot, version = find_version(root, version)
    key = (str(dataroot.resolve()), version)
    sig = _signature(dataroot / version)
    with _CACHE_LOCK:
        hit = _CACHE.get(key)
        if hit is not None and hit[0] == sig:
            return hit[1]
        tables = NuScenesTables(dataroot, version)
        _CACHE[key] = (sig, tables)
        return tables


def clear_cache() -> None:
    """Forget every cached table set (frees their memory)."""
    with _CACHE_LOCK:
        _CACHE.clear()


# ---------------------------------------------------------------------------------------------
# the log


class NuScenesLog(DrivingLog):
    """One nuScenes scene (e.g. ``"scene-0061"``) of the dataset folder ``root``.

    ``root`` holds one table folder (``v1.0-mini/`` or ``v1.0-trainval/``; ``version`` picks
    one when there are several) or is the table folder itself. ``points`` gives ``(N, 5)``
    float32: x, y, z in the sensor frame, intensity (0-255) and ring index (0-31).
    ``unknown_categories`` counts the scene's boxes whose category nuScenes does not define
    (``cls`` None; one warning per scene).
    """

    dataset = "nuscenes"
    sensor = "hdl32e"

    def __init__(self, root, name: str, version: str | None = None):
        self.tables = t = load_tables(root, version)
        self.root = t.dataroot
        self.version = t.version
        self.name = str(name)
        if self.name not in t.scene_by_name:
            some = ", ".join(sorted(t.scene_by_name)[:5])
            raise DataError(t.path("scene"), f"no scene named {self.name!r} "
                                             f"({len(t.scene_by_name)} scenes: {some}, ...)")
        self.scene = t.scene[t.scene_by_name[self.name]]
        self.sample_tokens = t.scene_samples(self.scene)
        self.frames = list(range(len(self.sample_tokens)))
        self._lidar = [self._keyframe(s, LIDAR) for s in self.sample_tokens]
        self._times = [self._timestamp_us(sd) for sd in self._lidar]
        self._sensor_to_global = [self._lidar_pose(sd) for sd in self._lidar]
        self._lidar_rotation = [self._calib(sd)[:3, :3] for sd in self._lidar]
        self.camera_names = self._find_cameras()
        self.default_camera = ("CAM_FRONT" if "CAM_FRONT" in self.camera_names
                               else (self.camera_names[0] if self.camera_names else None))
        self.unknown_categories = self._check_categories()

    # --- indexing helpers

    def _keyframe(self, sample_token: str, channel: str) -> dict:
        rec = self.tables.keyframes.get(sample_token, {}).get(channel)
        if rec is None:
            raise DataError(self.tables.path("sample_data"), f"scene {self.name}: sample "
                                                             f"{sample_token!r} has no {channel} "
                                                             "keyframe")
        return rec

    def _timestamp_us(self, sd: dict) -> int:
        return _timestamp_us(self.tables, sd)

    def _calib(self, sd: dict) -> np.ndarray:
        t = self.tables
        rec = t.get("calibrated_sensor", sd["calibrated_sensor_token"],
                    f"sample_data {sd['token']}")
        return t.transform(rec, "calibrated_sensor")

    def _ego(self, sd: dict) -> np.ndarray:
        t = self.tables
        rec = t.get("ego_pose", sd["ego_pose_token"], f"sample_data {sd['token']}")
        return t.transform(rec, "ego_pose")

    def _lidar_pose(self, sd: dict) -> np.ndarray:
        """(4, 4) our sensor frame (ego axes, LiDAR origin) -> global."""
        return self._ego(sd) @ _rigid(np.eye(3), self._calib(sd)[:3, 3])

    def _index(self, frame: int) -> int:
        if not isinstance(frame, (int, np.integer)) or not 0 <= frame < len(self.sample_tokens):
            raise ConfigError(f"nuScenes {self.name}: no frame {frame!r} (frames 0.."
                              f"{len(self.sample_tokens) - 1})")
        return int(frame)

    def _find_cameras(self) -> tuple[str, ...]:
        present = set()
        for s in self.sample_tokens:
            for channel, sd in self.tables.keyframes.get(s, {}).items():
                if self.tables.channels[sd["calibrated_sensor_token"]][1] == "camera":
                    present.add(channel)
        known = [c for c in CAMERA_ORDER if c in present]
        return tuple(known + sorted(present - set(known)))

    def _check_categories(self) -> Counter:
        unknown: Counter = Counter()
        for s in self.sample_tokens:
            for ann in self.tables.annotations.get(s, []):
                name = self.tables.category_name(ann)
                if not category_to_class(name)[1]:
                    unknown[name] += 1
        if unknown:
            log.warning("nuScenes %s: %d boxes of unknown categories %s get no vehicle class",
                        self.name, sum(unknown.values()), dict(unknown))
        return unknown

    # --- the protocol

    def sample_token(self, frame: int) -> str:
        return self.sample_tokens[self._index(frame)]

    def timestamp(self, frame: int) -> float:
        return self._times[self._index(frame)] * 1e-6

    def lidar_path(self, frame: int) -> Path:
        return self.root / self._lidar[self._index(frame)]["filename"]

    def points(self, frame: int) -> np.ndarray:
        i = self._index(frame)
        raw = read_pcd_bin(self.lidar_path(i))  # (N, 5) LiDAR frame
        out = raw.copy()
        out[:, :3] = (raw[:, :3].astype(np.float64) @ self._lidar_rotation[i].T).astype(np.float32)
        return out

    def boxes(self, frame: int) -> list[Box3D]:
        i = self._index(frame)
        global_to_sensor = _invert(self._sensor_to_global[i])
        return [self._box(ann, global_to_sensor)
                for ann in self.tables.annotations.get(self.sample_tokens[i], [])]

    def _box(self, ann: dict, global_to_sensor: np.ndarray) -> Box3D:
        t, table = self.tables, "sample_annotation"
        category = t.category_name(ann)
        centre = global_to_sensor[:3, :3] @ t.translation(ann, table, MAX_WORLD) \
            + global_to_sensor[:3, 3]
        rotation = global_to_sensor[:3, :3] @ t.rotation(ann, table)
        width, length, height = t.vector(ann, "size", table, 3)
        bad, why = box_problems(centre, (length, width, height))
        if bad[0]:
            raise DataError(t.path(table), f"record {ann.get('token')!r}: {why[0]} (size is "
                                           "[width, length, height])")
        level = self._visibility_level(ann)
        extra = {"token": ann.get("token"), "visibility_level": level,
                 "attributes": self._attributes(ann), "num_radar_pts": ann.get("num_radar_pts"),
                 "rotation": rotation}
        return Box3D(track_id=ann["instance_token"], category=category,
                     cls=category_to_class(category)[0], centre=centre,
                     size=(length, width, height),
                     yaw=float(np.arctan2(rotation[1, 0], rotation[0, 0])),
                     num_points=self._point_count(ann),
                     visibility=_visibility_fraction(level), extra=extra)

    def _point_count(self, ann: dict) -> int | None:
        """``num_lidar_pts`` (a non-negative integer; None when absent)."""
        n = ann.get("num_lidar_pts")
        if n is None:
            return None
        valid = not isinstance(n, bool) and isinstance(n, (int, float))
        if not (valid and n >= 0 and float(n).is_integer()):
            path = self.tables.path("sample_annotation")
            raise DataError(path, f"record {ann.get('token')!r}: num_lidar_pts {n!r} is not a "
                                  "non-negative integer")
        return int(n)

    def _attributes(self, ann: dict) -> list[str]:
        tokens = ann.get("attribute_tokens")
        if tokens is None:
            return []
        if not isinstance(tokens, list) or not all(isinstance(a, str) for a in tokens):
            raise DataError(self.tables.path("sample_annotation"),
                            f"record {ann.get('token')!r}: attribute_tokens must be a list "
                            f"of token strings, got {tokens!r:.80}")
        if not self.tables.attribute:
            return []
        return [str(self.tables.get("attribute", a, f"sample_annotation {ann.get('token')}")
                    .get("name")) for a in tokens]

    def _visibility_level(self, ann: dict) -> str | None:
        token = ann.get("visibility_token")
        if not token or not self.tables.visibility:
            return None
        rec = self.tables.get("visibility", token, f"sample_annotation {ann.get('token')}")
        level = rec.get("level")
        return level if isinstance(level, str) else None

    def ego_pose(self, frame: int) -> np.ndarray:
        i = self._index(frame)
        return _invert(self._sensor_to_global[0]) @ self._sensor_to_global[i]

    def _camera_name(self, name: str | None) -> str:
        name = name or self.default_camera
        if name is None:
            raise ConfigError(f"nuScenes {self.name} has no camera keyframes")
        if name not in self.camera_names:
            raise ConfigError(f"nuScenes {self.name}: no camera {name!r} (cameras: "
                              f"{', '.join(self.camera_names)})")
        return name

    def camera(self, name: str | None = None, frame: int | None = None) -> PinholeCamera:
        """Camera ``name`` at its keyframe image of ``frame`` (default: the first frame).

        ``T_cam_sensor`` follows the devkit's ``map_pointcloud_to_image``: sensor -> global
        with the LiDAR's ego pose, global -> ego with the camera's own ego pose (at the image
        time), ego -> camera with its calibration.
        """
        t, name = self.tables, self._camera_name(name)
        i = self._index(self.frames[0] if frame is None else frame)
        sd = self._keyframe(self.sample_tokens[i], name)
        calib = t.get("calibrated_sensor", sd["calibrated_sensor_token"])
        K = t.vector(calib, "camera_intrinsic", "calibrated_sensor", (3, 3))
        if not (K[0, 0] > 0 and K[1, 1] > 0 and K[2, 2] != 0):
            raise DataError(t.path("calibrated_sensor"), f"record {calib['token']!r}: "
                                                         f"camera_intrinsic {K.tolist()} has no "
                                                         "positive focal lengths")
        size = (t.field(sd, "width", "sample_data", int), t.field(sd, "height", "sample_data", int))
        if min(size) <= 0:
            raise DataError(t.path("sample_data"), f"record {sd['token']!r}: image size {size}")
        cam_to_global = self._ego(sd) @ self._calib(sd)
        return PinholeCamera.from_intrinsics(
            K, _invert(cam_to_global) @ self._sensor_to_global[i], size, name=name)

    def image_path(self, frame: int, camera: str | None = None) -> Path | None:
        if not self.camera_names:
            return None
        name = self._camera_name(camera)
        sd = self.tables.keyframes.get(self.sample_tokens[self._index(frame)], {}).get(name)
        if sd is None:
            return None
        path = self.root / sd["filename"]
        return path if path.is_file() else None

    @classmethod
    def log_names(cls, root, version: str | None = None) -> list[str]:
        """The scene names of the dataset (sorted)."""
        return sorted(load_tables(root, version).scene_by_name)


def _timestamp_us(tables: NuScenesTables, sd: dict) -> int:
    """A ``sample_data`` record's timestamp (us): a finite number in [0, 1e17]."""
    ts = tables.field(sd, "timestamp", "sample_data", (int, float))
    if not (isinstance(ts, int) or np.isfinite(ts)) or ts < 0 or ts > 1e17:
        raise DataError(tables.path("sample_data"), f"record {sd.get('token')!r}: timestamp "
                                                    f"{ts!r} is not a time in microseconds")
    return int(ts)


def _relative_file(name: str, table: Path, token) -> None:
    """Refuse a data file name that could leave the data root (absolute, ``..``, empty)."""
    parts = name.replace("\\", "/").split("/")
    if not name or name.startswith("/") or ":" in parts[0] or ".." in parts or "\0" in name:
        raise DataError(table, f"record {token!r}: filename {name!r} is not a path inside the "
                               "data root")


def _visibility_fraction(level: str | None) -> float | None:
    """``"v60-80"`` -> 0.6 (the lower bound of the visible fraction), else None."""
    m = _VIS_LEVEL.match(level) if level else None
    return int(m.group(1)) / 100.0 if m else None
