"""Synthetic LiDAR track datasets: vehicles x trajectories x raycasting -> Track files.

Layout of the output folder (docs/data-format.md)::

    DIR/generate.json        the generation config (a rerun must match it)
    DIR/tracks/<id>.npz      one Track per file (atomic writes)
    DIR/manifest.json        written once every track of the preset exists

Determinism: track ``i`` (``i = vehicle_index * tracks_per_vehicle + j``) draws everything from
``np.random.SeedSequence([seed, i])``, the split permutation and the complete shapes from their
own seed sequences, so the arrays are identical whatever the number of workers or shards.
Shard ``K/N`` (1-based) takes the vehicles with ``index % N == K - 1``.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

import seqshape._runner as _runner
import seqshape.sim._worker as _tracks
from seqshape._deprecated import forward
from seqshape._runner import check_settings, check_shard, plan_work, run_pool, shard_items
from seqshape.data.dataset import MANIFEST, manifest_entry, write_manifest
from seqshape.data.track import Track, load_track
from seqshape.errors import ConfigError, DataError
from seqshape.sim._worker import GENERATOR_VERSION
from seqshape.sim.real import RealConfig
from seqshape.sim.sensors import get_sensor
from seqshape.sim.trajectories import PLACEMENTS, read_trajectory_csv, track_length_location
from seqshape.vehicles import fleet_library, load_vehicle_folder, vehicle_library

log = logging.getLogger(__name__)

#: ``parse_shard`` moved to :mod:`seqshape._runner` (the one runner); the old path warns
__getattr__ = forward(__name__, _runner, ("parse_shard",))

CONFIG_FILE = "generate.json"


@dataclass(frozen=True)
class GenerateConfig:
    """Everything that determines a generated dataset (the output is a function of this)."""

    name: str
    """Preset name, recorded in the manifest."""
    n_vehicles: int = 183
    """Number of procedural vehicles (ignored with ``meshes``: every mesh there is used)."""
    n_val_vehicles: int = 15
    """Vehicles held out for the val split (scaled proportionally for a mesh folder)."""
    tracks_per_vehicle: int = 11
    """Trajectories driven by every vehicle."""
    sensor: str = "vlp16"
    """LiDAR preset: "vlp16", "hdl32" or "hdl64"."""
    noise: bool = False
    """Apply the sensor's range noise and dropout (off: exact first hits)."""
    ground: bool = False
    """The ground plane blocks rays (it never returns points itself)."""
    max_occluders: int = 0
    """Up to this many other vehicles per track that block rays (they return no points)."""
    min_frames: int = 10
    """Shortest track (frames)."""
    max_frames: int = 200
    """Longest track (frames)."""
    mean_frames: float = 70.0
    """Mean track length (frames); lengths are a truncated log-normal."""
    min_distance: float = 3.0
    """No vehicle centre comes closer to the sensor (m)."""
    max_distance: float = 60.0
    """Tracks stay within this distance of the sensor (m)."""
    num_points: int = 2048
    """Points of the complete ground-truth shape per vehicle."""
    seed: int = 0
    """Master seed of vehicles, splits, trajectories and noise."""
    meshes: str | None = None
    """Folder of user meshes (OBJ/PLY/STL/OFF/GLB/GLTF) instead of procedural vehicles."""
    mesh_up: str = "z"
    """Up axis of the user meshes (see seqshape.vehicles.load_vehicle)."""
    mesh_forward: str = "x"
    """Forward axis of the user meshes."""
    mesh_scale: float = 1.0
    """Scale of the user meshes to metres."""
    trajectories: str | None = None
    """A CSV file or folder of CSV files (t,x,y,yaw) driving the vehicles instead of sampling."""
    library: str = "procedural"
    """Vehicle library: "procedural" (the original kinds) or "fleet" (seqshape.vehicles
    fleet_library: every class, per-face materials). Ignored with ``meshes``."""
    real: RealConfig | None = None
    """The real path (seqshape.sim.real): sensor mix and mount, materials, ground and clutter
    returns, mixed edge returns, tracker-box crop. None: the original scan (``sensor``,
    ``noise``, ``ground`` as documented above)."""
    placement: str = "crossing"
    """Where sampled trajectories go (seqshape.sim.trajectories.PLACEMENTS): "crossing" (every
    track crosses the line of sight of a static sensor) or "traffic" (seqshape.sim.traffic:
    lanes through the sensor, a moving ego, same-direction, oncoming, crossing and parked
    vehicles). Ignored with ``trajectories``."""

    def __post_init__(self):
        if isinstance(self.real, dict):  # from generate.json
            object.__setattr__(self, "real", RealConfig(**self.real))

    def validate(self) -> None:
        if self.n_vehicles < 1 and self.meshes is None:
            raise ConfigError("n_vehicles must be >= 1")
        if not 0 <= self.n_val_vehicles < max(self.n_vehicles, 2):
            raise ConfigError("n_val_vehicles must be >= 0 and < n_vehicles")
        if self.tracks_per_vehicle < 1 or self.num_points < 1 or self.max_occluders < 0:
            raise ConfigError("tracks_per_vehicle and num_points must be >= 1, "
                              "max_occluders >= 0")
        if self.min_frames != self.max_frames:
            track_length_location(self.min_frames, self.max_frames, self.mean_frames)
        elif not 1 <= self.min_frames == self.mean_frames:
            raise ConfigError("need 1 <= min_frames <= mean_frames <= max_frames")
        if not 0 < self.min_distance < self.max_distance:
            raise ConfigError("need 0 < min_distance < max_distance")
        if self.seed < 0:
            raise ConfigError(f"seed must be >= 0, got {self.seed}")
        if self.placement not in PLACEMENTS:
            raise ConfigError(f"placement must be one of {PLACEMENTS}, got {self.placement!r}")
        if self.library not in LIBRARIES:
            raise ConfigError(f"library must be one of {LIBRARIES}, got {self.library!r}")
        get_sensor(self.sensor)


LIBRARIES = ("procedural", "fleet")
#: fields added after the first datasets: left out of generate.json / the manifest while they
#: hold their default, so that the older presets' outputs stay byte-identical
_LATE_FIELDS = {"library": "procedural", "real": None, "placement": "crossing"}

PRESETS: dict[str, GenerateConfig] = {
    # a handful of short tracks, generated in seconds
    "tiny": GenerateConfig("tiny", n_vehicles=6, n_val_vehicles=2, tracks_per_vehicle=2,
                           min_frames=10, max_frames=30, mean_frames=18.0, max_distance=40.0),
    # the paper's synthetic dataset: 183 vehicles, 168/15 split, 11 tracks each, VLP-16 at 2 m
    "paper": GenerateConfig("paper"),
    # paper + ground plane and up to 4 other vehicles as occluders + range noise and dropout
    "realistic": GenerateConfig("realistic", noise=True, ground=True, max_occluders=4),
    # train on what inference sees: the fleet library, a sensor mix (VLP-16, VLP-32C, HDL-64E,
    # OS1-128) at 1.5-2.2 m with +-1.5 deg pitch / roll, glass, dark surfaces, edge mixing,
    # ground and clutter returns, occluders, and the shared crop with a tracker-like box;
    # traffic seen along the line of sight from a moving ego (seqshape.sim.traffic)
    "real": GenerateConfig("real", noise=True, ground=True, max_occluders=4, library="fleet",
                           real=RealConfig(), placement="traffic"),
}


@dataclass
class GenerateSummary:
    """What a run did: tracks of the whole preset, generated now, found done, manifest state."""

    n_tracks: int
    n_generated: int
    n_skipped: int
    manifest_written: bool
    seconds: float
    missing: list[str] = field(default_factory=list)


def config_dict(config: GenerateConfig) -> dict:
    """The config as saved in ``generate.json`` and the manifest (with the generator version).

    Fields of `_LATE_FIELDS` at their default are left out (older datasets stay identical);
    values are JSON-normalised (tuples -> lists) so a reread config compares equal.
    """
    d = asdict(config)
    for k, default in _LATE_FIELDS.items():
        if d.get(k) == default:
            d.pop(k)
    return {**json.loads(json.dumps(d)), "generator_version": GENERATOR_VERSION}


def _check_config(out: Path, cfg: dict) -> None:
    """Write ``generate.json`` or check it matches: one folder, one config (a folder with
    tracks but no ``generate.json`` is refused too)."""
    occupied = (out / MANIFEST).is_file() or any((out / "tracks").glob("*.npz"))
    check_settings(out, CONFIG_FILE, cfg, made="tracks generated", occupied=occupied)


def vehicles_digest(vehicles) -> str:
    """SHA-1 of the vehicles' ids and mesh arrays: a resume with other meshes is refused."""
    h = hashlib.sha1()
    for v in vehicles:
        h.update(v.vehicle_id.encode())
        h.update(np.ascontiguousarray(v.mesh.vertices, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(v.mesh.faces, dtype=np.int64).tobytes())
    return h.hexdigest()


def _trajectories_digest(logs) -> str | None:
    if not logs:
        return None
    h = hashlib.sha1()
    for tr in logs:
        h.update(np.stack([tr.t, tr.x, tr.y, tr.yaw]).tobytes())
    return h.hexdigest()


def _load_vehicles(config: GenerateConfig):
    if config.meshes is not None:
        return load_vehicle_folder(config.meshes, up=config.mesh_up,
                                   forward=config.mesh_forward, scale=config.mesh_scale)
    return library_vehicles(config.library, config.n_vehicles, config.seed)


def library_vehicles(library: str, n: int, seed: int):
    """The ``n`` vehicles of ``library``: the one switch between the procedural library and
    the fleet library (`seqshape.vehicles.fleet_library`)."""
    if library == "fleet":
        return fleet_library(n, seed=seed)
    return vehicle_library(n, seed=seed)


def _load_trajectories(spec: str | None):
    if spec is None:
        return []
    path = Path(spec)
    if path.is_dir():
        files = sorted(path.glob("*.csv"))
        if not files:
            raise DataError(path, "no *.csv trajectory files in this folder")
        return [read_trajectory_csv(f) for f in files]
    return [read_trajectory_csv(path)]


def _splits(n: int, config: GenerateConfig) -> list[str]:
    """Per-vehicle split: a seeded permutation puts ``n_val`` vehicles into "val"."""
    n_val = config.n_val_vehicles
    if config.meshes is not None:  # scale the val share to the folder's size
        n_val = int(round(n * config.n_val_vehicles / max(config.n_vehicles, 1)))
        n_val = min(max(n_val, 1 if n > 1 else 0), n - 1)
    perm = np.random.default_rng(np.random.SeedSequence([config.seed, 0x5B117])).permutation(n)
    val = set(perm[:n_val].tolist())
    return ["val" if i in val else "train" for i in range(n)]


def generate_dataset(config: GenerateConfig, out: str | Path, workers: int = 1,
                     shard: tuple[int, int] = (1, 1)) -> GenerateSummary:
    """Generate (or resume) the dataset ``config`` into ``out``; see the module docstring.

    Tracks already on disk (and loadable) are skipped. The manifest is written when every track
    of the preset exists, by whichever run (shard) completes the set. Settings check, resume,
    shards and the worker pool are :mod:`seqshape._runner`'s; the work unit is one vehicle.
    """
    t0 = time.perf_counter()
    config.validate()
    k, n = check_shard(shard)
    if workers < 1:
        raise ConfigError(f"workers must be >= 1, got {workers}")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    logs = _load_trajectories(config.trajectories)
    vehicles = _load_vehicles(config)
    if not vehicles:
        raise ConfigError(f"no vehicles to generate from (meshes={config.meshes!r})")
    cfg = {**config_dict(config), "vehicles_digest": vehicles_digest(vehicles),
           "trajectories_digest": _trajectories_digest(logs)}
    _check_config(out, cfg)
    splits = _splits(len(vehicles), config)
    plan = _tracks.TrackPlan(config, [v.vehicle_id for v in vehicles], splits)
    entries: dict[str, dict] = {}

    def is_done(i: int) -> bool:
        e = _existing_entry(out, plan.track_id(i))
        if e is not None:
            entries[e["track_id"]] = e
        return e is not None

    todo: dict[int, list[int]] = {}
    for v in shard_items(range(len(vehicles)), (k, n)):
        work = plan_work(plan.track_indices(v), is_done)
        if work.todo:
            todo[v] = work.todo
    n_todo = sum(len(x) for x in todo.values())
    log.info("%s: %d tracks in shard %d/%d, %d already done, %d to generate", out,
             n_todo + len(entries), k, n, len(entries), n_todo)
    if n_todo:
        payload = _tracks.WorkerPayload.build(config, vehicles, splits, logs)
        units = [(v, idx, str(out)) for v, idx in sorted(todo.items())]
        for result in run_pool(_tracks.work_unit, units, workers,
                               initializer=_tracks.init_worker, initargs=(payload,),
                               weight=lambda _u, r: len(r), total=n_todo, desc="generate",
                               unit="track"):
            for e in result:
                entries[e["track_id"]] = e
    manifest_written, missing = _maybe_write_manifest(out, plan, cfg, entries)
    return GenerateSummary(plan.n_tracks, n_todo, len(entries) - n_todo, manifest_written,
                           time.perf_counter() - t0, missing)


def _existing_entry(out: Path, track_id: str) -> dict | None:
    """The manifest entry of a finished track file, or None (missing or unreadable)."""
    file = f"tracks/{track_id}.npz"
    path = out / file
    if not path.is_file():
        return None
    try:
        return manifest_entry(load_track(path), file)
    except DataError as exc:
        log.warning("regenerating %s: %s", path, exc)
        return None


def _maybe_write_manifest(out: Path, plan, cfg: dict, entries: dict[str, dict]):
    """Write the manifest if every track of the preset is on disk; return (written, missing)."""
    missing = []
    for i in range(plan.n_tracks):
        tid = plan.track_id(i)
        if tid in entries:
            continue
        e = _existing_entry(out, tid)
        if e is None:
            missing.append(tid)
        else:
            entries[tid] = e
    if missing:
        log.info("%s: %d of %d tracks still missing (other shards?); manifest not written yet",
                 out, len(missing), plan.n_tracks)
        return False, missing
    write_manifest(out, list(entries.values()), cfg, preset=cfg["name"],
                   splits={s: sum(e["split"] == s for e in entries.values())
                           for s in ("train", "val")})
    return True, []


def _preset(name: str) -> GenerateConfig:
    try:
        return PRESETS[name]
    except KeyError:
        raise ConfigError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}") from None


def preset_config(name: str, **overrides) -> GenerateConfig:
    """The preset ``name`` with fields replaced by the non-None ``overrides``."""
    base = _preset(name)
    overrides = {k: v for k, v in overrides.items() if v is not None}
    if base.real is not None and "sensor" in overrides and "real" not in overrides:
        # one sensor model for the whole dataset instead of the preset's mix
        overrides["real"] = replace(base.real, sensors=(overrides["sensor"],),
                                    sensor_weights=(1.0,))
    cfg = replace(base, **overrides)
    cfg.validate()
    return cfg


def scaled_val_vehicles(base: GenerateConfig, n_vehicles: int) -> int:
    """Val vehicles for ``n_vehicles``: the preset's val share, at least 1 and at most
    ``n_vehicles - 1`` (0 for a single vehicle).

    >>> scaled_val_vehicles(PRESETS["paper"], 50)  # 15 of 183
    4
    """
    share = round(n_vehicles * base.n_val_vehicles / base.n_vehicles)
    return min(max(share, 1), max(n_vehicles - 1, 0))


def track_lengths(base: GenerateConfig, mean_frames: float) -> dict:
    """``mean_frames``, ``min_frames`` and ``max_frames`` for a mean track length: the
    preset's shortest (or the mean if shorter) and the longest capped at 3x the mean (or the
    preset's cap if smaller, but never below the mean).

    >>> track_lengths(PRESETS["paper"], 6)
    {'mean_frames': 6.0, 'min_frames': 6, 'max_frames': 18}
    """
    mean = float(mean_frames)
    return {"mean_frames": mean, "min_frames": min(base.min_frames, int(mean)),
            "max_frames": max(int(mean), min(base.max_frames, int(3 * mean)))}


def scaled_preset_config(name: str, n_vehicles: int | None = None,
                         mean_frames: float | None = None, **overrides) -> GenerateConfig:
    """:func:`preset_config` as ``seqshape generate`` sets it: a vehicle count scales the val
    vehicles with it (:func:`scaled_val_vehicles`), a mean track length sets the length range
    (:func:`track_lengths`); explicit non-None ``overrides`` win over both.
    """
    base = _preset(name)
    derived: dict = {"n_vehicles": n_vehicles}
    if n_vehicles is not None:
        derived["n_val_vehicles"] = scaled_val_vehicles(base, n_vehicles)
    if mean_frames is not None:
        derived.update(track_lengths(base, mean_frames))
    return preset_config(name, **{**derived, **{k: v for k, v in overrides.items()
                                                 if v is not None}})


def make_track_in_process(config: GenerateConfig, vehicles, splits, index: int,
                          logs=()) -> Track:
    """Build one track without writing it (for tests and notebooks)."""
    _tracks.init_worker(_tracks.WorkerPayload.build(config, vehicles, splits, list(logs)))
    return _tracks.make_track(index)
