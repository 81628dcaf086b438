"""Vehicle tracks of real driving logs as a track dataset (``seqshape tracks``, docs/tracks.md).

Layout of the output folder (docs/data-format.md, "Real tracks")::

    OUT/tracks.json              the extraction settings (a rerun must match them)
    OUT/tracks/<track_id>.npz    one Track per file (atomic writes)
    OUT/logs/<dataset>_<log>.json  per log, written after its tracks: its manifest entries
    OUT/manifest.json            (re)written at the end of every run, from all log files

The unit of work, of resume and of sharding is one log: shard ``K/N`` (1-based) takes the
logs ``i`` (sorted names) with ``i % N == K - 1``; a log whose ``logs/`` file exists (and
whose track files all exist) is done and skipped. The split of a track is that of its log:
``val`` when a stable hash of ``dataset:log`` falls below ``val_fraction`` (or every log in
the split forced with ``--split``).
"""

from __future__ import annotations

import hashlib
import importlib
import json
import logging
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from pathlib import Path

from seqshape._io import atomic_write_json
from seqshape._progress import progress
from seqshape._runner import stop_pool, watch_parent
from seqshape.data.crop import CropConfig
from seqshape.data.dataset import check_folder_settings, manifest_entry, write_manifest
from seqshape.data.extract import extract_tracks, track_name
from seqshape.data.odometry import EGO_POSES, with_lidar_odometry
from seqshape.data.reference import accumulated_reference
from seqshape.data.sequence import DATASETS, log_names
from seqshape.data.track import save_track
from seqshape.errors import ConfigError, DataError, SeqshapeError

_log = logging.getLogger(__name__)

CONFIG_FILE = "tracks.json"
LOGS_DIR = "logs"
EXTRACTOR_VERSION = 2  # 2: duplicate annotations left out (keep_duplicates)
SPLITS = ("train", "val")
SPLIT_BY = ("log", "track")


# ----------------------------------------------------------------------------- settings


@dataclass(frozen=True)
class TracksConfig:
    """Everything that determines the content of a real-track folder (saved in tracks.json).

    dataset: the dataset format of ``root`` (a key of DATASETS).
    root: the dataset folder (KITTI tracking training/, an Argoverse 2 split folder such as
        sensor/val, a nuScenes root).
    classes: vehicle classes to keep (VEHICLE_CLASSES names).
    min_points: keep a track when one of its frames has at least this many points after the
        crop.
    margin: metres added to the box on each side.
    ground: ground removal: plane (a local RANSAC plane), box (cut at the box bottom), none.
    reference: store an accumulated reference shape as each track's complete shape.
    reference_points: points of the accumulated reference.
    val_fraction: share of logs (or tracks, see split_by) in the val split, by a stable hash of
        the log name.
    split: put every log into this split instead, e.g. one log to evaluate on (None: by
        val_fraction).
    split_by: what val_fraction splits: whole logs ('log': no vehicle is in both splits, nor
        any log) or single tracks ('track': to fine-tune and evaluate on held-out vehicles of
        the same logs).
    keep_duplicates: keep a vehicle's duplicate annotations (two object ids whose boxes
        coincide) as tracks of their own instead of leaving all but one out
        (seqshape.data.extract, "Duplicate annotations").
    ego_poses: the tracks' ego poses: the log's own (given) or LiDAR odometry of its sweeps
        (lidar: each sweep registered to the one before, seqshape.data.odometry; for logs
        whose poses stretch or jitter, as benchmarks/bm_ego_poses.py shows, or have none;
        about 0.25 s a sweep).
    """

    dataset: str
    root: str
    classes: tuple[str, ...]
    min_points: int = 10
    margin: float = 0.2
    ground: str = "plane"
    reference: bool = True
    reference_points: int = 2048
    val_fraction: float = 0.2
    split: str | None = None
    split_by: str = "log"
    keep_duplicates: bool = False
    ego_poses: str = "given"

    def validate(self) -> None:
        if self.min_points < 0:
            raise ConfigError(f"--min-points must be >= 0, got {self.min_points}")
        if not 0.0 <= self.val_fraction <= 1.0:
            raise ConfigError(f"--val-fraction must be in [0, 1], got {self.val_fraction}")
        if self.split not in (None, *SPLITS):
            raise ConfigError(f"--split must be one of {SPLITS}, got {self.split!r}")
        if self.split_by not in SPLIT_BY:
            raise ConfigError(f"--split-by must be one of {SPLIT_BY}, got {self.split_by!r}")
        if self.ego_poses not in EGO_POSES:
            raise ConfigError(f"--ego-poses must be one of {EGO_POSES}, got {self.ego_poses!r}")
        if self.reference_points < 1:
            raise ConfigError(f"--reference-points must be >= 1, got {self.reference_points}")
        self.crop()  # margin and ground mode

    def crop(self):
        return CropConfig(margin=self.margin, ground=self.ground)

    def to_dict(self) -> dict:
        out = {**asdict(self), "classes": list(self.classes), "crop": self.crop().to_dict(),
               "extractor_version": EXTRACTOR_VERSION}
        if self.ego_poses == "given":  # folders written before the option keep matching
            del out["ego_poses"]
        return out


def log_split(dataset: str, log: str, val_fraction: float, forced: str | None = None) -> str:
    """``"val"`` when the SHA-1 of ``dataset:log`` (as a fraction of 2**64) is below
    ``val_fraction``, else ``"train"``; ``forced`` wins. Stable across runs and machines.
    With ``--split-by track`` the same rule runs on ``dataset:log:object`` (pass
    ``f"{log}:{object_id}"`` as ``log``).

    >>> log_split("av2", "x", 0.0), log_split("av2", "x", 1.0), log_split("av2", "x", 0.5, "val")
    ('train', 'val', 'val')
    """
    if forced is not None:
        return forced
    h = int.from_bytes(hashlib.sha1(f"{dataset}:{log}".encode()).digest()[:8], "big")
    return "val" if h / 2.0**64 < val_fraction else "train"


def marker_path(out: Path, dataset: str, log: str) -> Path:
    """``OUT/logs/<dataset>_<log>.json`` (the log name made file-name safe)."""
    return Path(out) / LOGS_DIR / f"{track_name(dataset, log)}.json"


def _check_config(out: Path, cfg: dict) -> None:
    """Write ``tracks.json`` or check it matches: one folder, one set of settings."""
    check_folder_settings(out, CONFIG_FILE, cfg, "extracted")


# ----------------------------------------------------------------------------- log selection


def parse_sequences(values: list[str] | None) -> list[str] | None:
    """``--sequence a --sequence b,c`` -> ``["a", "b", "c"]`` (None when not given)."""
    if not values:
        return None
    names = [s.strip() for v in values for s in v.split(",") if s.strip()]
    return list(dict.fromkeys(names)) or None


def select_logs(dataset: str, root: Path, wanted: list[str] | None) -> list[str]:
    """The sorted log names to extract: ``wanted`` (each checked to exist) or every log."""
    if not root.is_dir():
        raise DataError(root, f"no such {dataset} dataset folder (--root)")
    available = sorted(log_names(dataset, root))
    if wanted is None:
        if not available:
            raise DataError(root, f"no {dataset} logs found in this folder")
        return available
    unknown = [w for w in wanted if w not in set(available)]
    if unknown:
        shown = ", ".join(available[:10]) + (" ..." if len(available) > 10 else "")
        raise ConfigError(f"unknown {dataset} log(s) {unknown} in {root}; found "
                          f"{len(available)}: {shown or 'none'}")
    return sorted(wanted)


def read_marker(out: Path, path: Path) -> dict | None:
    """A log's ``logs/`` file if it parses and every track file it lists exists, else None."""
    try:
        marker = json.loads(path.read_text())
        files = [e["file"] for e in marker["tracks"]]
        if not isinstance(marker["log"], str) or not isinstance(marker["dataset"], str):
            raise TypeError("'log' and 'dataset' must be strings")
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
        _log.warning("%s: unreadable log record (%s); the log will be extracted again", path,
                     exc)
        return None
    missing = [f for f in files if not (out / f).is_file()]
    if missing:
        _log.warning("%s: %d track files missing (e.g. %s); the log will be extracted again",
                     path, len(missing), missing[0])
        return None
    return marker


# ----------------------------------------------------------------------------- the work


@dataclass
class LogJob:
    """One log to extract, picklable (the reader is named by its ``module:class``)."""

    reader: str
    log: str
    out: str
    config: TracksConfig


@dataclass
class LogResult:
    """What extracting one log gave: its ``logs/`` record, or the error that stopped it."""

    log: str
    marker: dict | None = None
    error: str | None = None
    seconds: float = 0.0
    warnings: list[str] = field(default_factory=list)


def _open(reader: str, root: str, name: str):
    module, cls = reader.split(":")
    return getattr(importlib.import_module(module), cls)(root, name)


def _add_reference(track, n_points: int) -> str | None:
    """Set ``track.complete`` to the accumulated reference; a message when it could not."""
    try:
        complete, info = accumulated_reference(track, n_points=n_points)
    except (ValueError, DataError) as exc:
        track.meta["reference"] = {"kind": None, "error": str(exc)}
        return str(exc) if track.track_id in str(exc) else f"{track.track_id}: {exc}"
    track.complete = complete
    track.meta["reference"] = info
    return None


def extract_log(job: LogJob) -> LogResult:
    """Extract, write and record one log (worker entry point; never raises for a bad log)."""
    t0 = time.perf_counter()
    try:
        return _extract_log(job, t0)
    except SeqshapeError as exc:
        return LogResult(job.log, error=str(exc), seconds=time.perf_counter() - t0)
    except Exception as exc:  # noqa: BLE001 - one broken log must not stop a 700-log job
        _log.debug("log %s failed", job.log, exc_info=True)
        return LogResult(job.log, error=f"{type(exc).__name__}: {exc}",
                         seconds=time.perf_counter() - t0)


def _extract_log(job: LogJob, t0: float) -> LogResult:
    cfg, out = job.config, Path(job.out)
    log = _open(job.reader, cfg.root, job.log)
    if cfg.ego_poses == "lidar":
        with_lidar_odometry(log)
    tracks = extract_tracks(log, cfg.classes, cfg.crop(), cfg.min_points,
                            keep_duplicates=cfg.keep_duplicates)
    split = log_split(cfg.dataset, job.log, cfg.val_fraction, cfg.split)
    entries, warnings, no_ref = [], [], []
    for tr in tracks:
        tr.meta["split"] = split if cfg.split_by == "log" or cfg.split else log_split(
            cfg.dataset, f"{job.log}:{tr.meta['object_id']}", cfg.val_fraction)
        if cfg.reference:
            msg = _add_reference(tr, cfg.reference_points)
            if msg:
                _log.debug("%s", msg)
                no_ref.append(msg)
        file = f"tracks/{tr.track_id}.npz"
        save_track(out / file, tr)
        entries.append({**manifest_entry(tr, file), "class": tr.meta["class"],
                        "dataset": cfg.dataset, "log": job.log,
                        "has_complete": tr.complete is not None})
    if no_ref:
        warnings.append(f"log {job.log}: {len(no_ref)} of {len(tracks)} tracks have no "
                        f"accumulated reference (complete is None), e.g. {no_ref[0]}")
    seconds = time.perf_counter() - t0
    marker = {"dataset": cfg.dataset, "log": job.log, "split": split,
              "n_frames": len(log.frames), "n_points": sum(e["n_points"] for e in entries),
              "n_no_reference": len(no_ref), "seconds": round(seconds, 3), "tracks": entries}
    if cfg.ego_poses == "lidar":
        marker["odometry"] = odo = log.odometry.summary()
        if odo["bridged"] > 0.1 * max(odo["pairs"], 1):
            warnings.append(f"log {job.log}: LiDAR odometry bridged {odo['bridged']} of "
                            f"{odo['pairs']} sweep pairs with the log's own motion (time gaps, "
                            "too few points, or no convergence)")
    atomic_write_json(marker_path(out, cfg.dataset, job.log), marker)
    return LogResult(job.log, marker=marker, seconds=seconds, warnings=warnings)


def _pool(workers: int):
    """A pool of ``workers`` processes (forkserver where available, else spawn) whose workers
    end themselves when this process dies (:func:`seqshape._runner.watch_parent`)."""
    methods = multiprocessing.get_all_start_methods()
    ctx = multiprocessing.get_context("forkserver" if "forkserver" in methods else "spawn")
    return ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=watch_parent,
                               initargs=(os.getpid(),))


def run_jobs(jobs: list[LogJob], workers: int):
    """Run ``jobs`` in-process (``workers == 1``) or in a process pool; yields LogResults as
    they finish, with a progress bar over logs (cumulative frames and frames/s beside it)."""
    bar = progress(total=len(jobs), desc="tracks", unit="log")
    frames, t0 = 0, time.perf_counter()
    try:
        if workers == 1 or len(jobs) == 1:
            results = map(extract_log, jobs)
            pool = None
        else:
            pool = _pool(min(workers, len(jobs)))
            results = (f.result() for f in as_completed([pool.submit(extract_log, j)
                                                         for j in jobs]))
        try:
            for res in results:
                if res.marker is not None:
                    frames += res.marker["n_frames"]
                bar.set_postfix(frames=frames,
                                fps=f"{frames / max(time.perf_counter() - t0, 1e-9):.1f}")
                bar.update(1)
                yield res
        except BaseException:
            if pool is not None:
                stop_pool(pool)
                pool = None
            raise
        finally:
            if pool is not None:
                pool.shutdown(wait=True)
    finally:
        bar.close()


# ----------------------------------------------------------------------------- the run


@dataclass
class TracksSummary:
    """What a run did (this shard's logs) and the state of the folder afterwards."""

    extracted: list[dict]
    skipped: list[dict]
    failed: dict[str, str]
    seconds: float
    n_manifest_tracks: int
    missing_logs: list[str]

    @property
    def markers(self) -> list[dict]:
        return self.extracted + self.skipped


def extract_dataset(config: TracksConfig, out, sequences: list[str] | None = None,
                    shard: tuple[int, int] = (1, 1), workers: int = 1) -> TracksSummary:
    """Extract (or resume) the logs of shard ``shard`` into ``out`` and rewrite the manifest
    from every log recorded in the folder (module doc)."""
    t0 = time.perf_counter()
    config.validate()
    if config.dataset not in DATASETS:
        raise ConfigError(f"unknown dataset {config.dataset!r}: choose from "
                          f"{', '.join(DATASETS)}")
    k, n = shard
    if not 1 <= k <= n:
        raise ConfigError(f"shard {k}/{n}: need 1 <= K <= N")
    if workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {workers}")
    names = select_logs(config.dataset, Path(config.root), sequences)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    cfg = config.to_dict()
    _check_config(out, cfg)

    mine = [name for i, name in enumerate(names) if i % n == k - 1]
    skipped, jobs = [], []
    for name in mine:
        path = marker_path(out, config.dataset, name)
        marker = read_marker(out, path) if path.is_file() else None
        if marker is None:
            jobs.append(LogJob(DATASETS[config.dataset], name, str(out), config))
        else:
            skipped.append(marker)
    _log.info("%s: %d logs in shard %d/%d, %d already done, %d to extract", out, len(mine),
              k, n, len(skipped), len(jobs))
    extracted, failed = [], {}
    for res in run_jobs(jobs, workers):
        for w in res.warnings:
            _log.warning("%s", w)
        if res.error is not None:
            _log.warning("log %s skipped: %s", res.log, res.error)
            failed[res.log] = res.error
        else:
            extracted.append(res.marker)
    n_tracks, missing = write_folder_manifest(out, cfg, names)
    return TracksSummary(extracted, skipped, failed, time.perf_counter() - t0, n_tracks,
                         missing)


def write_folder_manifest(out: Path, cfg: dict, names: list[str]) -> tuple[int, list[str]]:
    """Write the manifest of every complete log recorded in ``out/logs``; returns the number
    of tracks in it and the logs of ``names`` not recorded yet (other shards, failures)."""
    markers = {}
    for path in sorted((out / LOGS_DIR).glob("*.json")):
        m = read_marker(out, path)
        if m is not None and m["dataset"] == cfg["dataset"]:
            markers[m["log"]] = m
    entries = [e for m in markers.values() for e in m["tracks"]]
    missing = [n for n in names if n not in markers]
    write_manifest(out, entries, cfg, kind="real-tracks", logs=sorted(markers),
                   splits={s: sum(e["split"] == s for e in entries) for s in SPLITS})
    return len(entries), missing
