"""Track dataset folders: ``manifest.json`` plus ``tracks/<track_id>.npz``.

Manifest format ``seqshape-tracks`` version 1 (docs/data-format.md)::

    {"format": "seqshape-tracks", "version": 1,
     "created_by": "seqshape 0.1.0", "config": {...generator config...},
     "tracks": [{"track_id": "...", "split": "train", "file": "tracks/....npz",
                 "n_frames": 70, "n_points": 12345}, ...]}

Reading checks the manifest before any track is opened (:func:`read_manifest`): UTF-8 JSON,
an object of this format with an integer version this code understands, and a list of entries
with a string ``track_id`` and a relative ``file`` that stays inside the dataset folder: no
absolute path, no ``..``, and (checked again when a track is opened) no symlink that resolves
outside the folder. Every refusal is a :class:`~seqshape.errors.DataError` naming the manifest.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from seqshape._io import atomic_write_json, contained_path, read_bytes
from seqshape._version import __version__
from seqshape.data.track import Track, load_track, save_track
from seqshape.errors import ConfigError, DataError

MANIFEST = "manifest.json"
DATASET_FORMAT = "seqshape-tracks"
DATASET_FORMAT_VERSION = 1


class TrackDataset:
    """A folder of tracks: ``len(ds)``, ``ds[i] -> Track``, ``ds.split("train")``.

    Tracks are read from disk on access (nothing is cached), so a dataset of any size opens
    instantly and can be shared by DataLoader workers.
    """

    def __init__(self, path: str | Path, _entries: list[dict] | None = None):
        self.path = Path(path)
        if _entries is not None:
            self.manifest = None
            self.entries = _entries
            return
        if not self.path.is_dir():
            raise DataError(self.path, "no such dataset folder")
        self.manifest = read_manifest(self.path)
        self.entries = list(self.manifest["tracks"])

    def __len__(self) -> int:
        return len(self.entries)

    def __getitem__(self, i: int) -> Track:
        if not -len(self) <= i < len(self):
            raise IndexError(f"track index {i} out of range for {len(self)} tracks")
        entry = self.entries[i]
        file = Path(entry["file"])
        if file.is_absolute():  # made absolute by union(), which checked it inside its folder
            path, source = file, f"its dataset's {MANIFEST}"
        else:
            path, source = _track_path(self.path, file), str(self.path / MANIFEST)
        track = load_track(path)
        if track.track_id != entry["track_id"]:
            raise DataError(path, f"holds track {track.track_id!r}, but {source} lists this "
                                  f"file as track {entry['track_id']!r}: the file was "
                                  "replaced or the manifest edited; make them agree")
        return track

    def __iter__(self) -> Iterator[Track]:
        for i in range(len(self)):
            yield self[i]

    @property
    def track_ids(self) -> list[str]:
        return [e["track_id"] for e in self.entries]

    def index_of(self, track_id: str) -> int:
        for i, e in enumerate(self.entries):
            if e["track_id"] == track_id:
                return i
        raise KeyError(f"{self.path}: no track with id {track_id!r}")

    def get(self, track_id: str) -> Track:
        return self[self.index_of(track_id)]

    def split(self, name: str) -> TrackDataset:
        """The tracks of one split ("train" or "val") as a dataset view."""
        entries = [e for e in self.entries if e.get("split") == name]
        if not entries:
            splits = sorted({str(e.get("split")) for e in self.entries})
            raise DataError(self.path, f"no tracks in split {name!r} (splits here: {splits})")
        return TrackDataset(self.path, _entries=entries)

    @classmethod
    def union(cls, paths, fractions=None) -> TrackDataset:
        """Several dataset folders as one dataset (entries' files made absolute); track ids
        must be unique across them. ``fractions`` (one per path, in (0, 1]) keeps that share of
        each folder's tracks, chosen by a stable hash of the track id (the same tracks on every
        run and machine). One path and no fraction gives that dataset itself."""
        paths = [Path(p) for p in paths]
        fractions = [1.0] * len(paths) if fractions is None else [float(f) for f in fractions]
        if len(fractions) != len(paths) or not all(0.0 < f <= 1.0 for f in fractions):
            raise ValueError(f"need one fraction in (0, 1] per dataset, got {fractions} for "
                             f"{len(paths)} datasets")
        if len(paths) == 1 and fractions[0] == 1.0:
            return cls(paths[0])
        entries, seen = [], {}
        for p, frac in zip(paths, fractions, strict=True):
            for e in cls(p).entries:
                if frac < 1.0 and _unit_hash(e["track_id"]) >= frac:
                    continue
                if e["track_id"] in seen:
                    raise DataError(p, f"track id {e['track_id']!r} is also in {seen[e['track_id']]}"
                                       f": datasets with shared ids cannot be joined")
                seen[e["track_id"]] = p
                entries.append({**e, "file": str(_track_path(p, e["file"]).resolve())})
        return cls(paths[0], _entries=entries)

    def with_complete(self) -> TrackDataset:
        """The tracks that have a complete shape, as a dataset view (manifests of real tracks
        mark the others with ``"has_complete": false``; entries without the key count as
        having one, as every synthetic track does)."""
        return TrackDataset(self.path, _entries=[e for e in self.entries
                                                 if e.get("has_complete", True)])

    def __repr__(self) -> str:
        return f"TrackDataset({str(self.path)!r}, {len(self)} tracks)"


def read_manifest(folder: str | Path) -> dict[str, Any]:
    """The checked ``manifest.json`` of a dataset folder (see the module doc).

    Raises :class:`DataError` naming the manifest when it is missing, not UTF-8 JSON, not an
    object of format ``seqshape-tracks``, of a version that is not an integer in
    ``1..DATASET_FORMAT_VERSION``, or its ``tracks`` is not a list of valid entries
    (:func:`check_entry`).
    """
    mpath = Path(folder) / MANIFEST
    if not mpath.exists():  # a FIFO or a folder in its place is refused by _read_json
        raise DataError(mpath, "missing manifest: not a seqshape track dataset, or its "
                               "generation has not finished (rerun the same command)")
    manifest = _read_json(mpath)
    if not isinstance(manifest, dict):
        raise DataError(mpath, f"expected a JSON object, got {type(manifest).__name__}")
    if manifest.get("format") != DATASET_FORMAT:
        raise DataError(mpath, f"not a {DATASET_FORMAT} manifest (format "
                               f"{manifest.get('format')!r})")
    version = manifest.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise DataError(mpath, f"version must be a positive integer, got {version!r}")
    if version > DATASET_FORMAT_VERSION:
        raise DataError(mpath, f"dataset format version {version} is newer than this seqshape "
                               f"understands; upgrade")
    tracks = manifest.get("tracks")
    if not isinstance(tracks, list):
        raise DataError(mpath, f"'tracks' must be a list of entries, got "
                               f"{type(tracks).__name__}")
    seen: set[str] = set()
    for i, entry in enumerate(tracks):
        check_entry(entry, i, mpath)
        if entry["track_id"] in seen:
            raise DataError(mpath, f"track entry {i}: duplicate track_id {entry['track_id']!r}")
        seen.add(entry["track_id"])
    return manifest


def _read_json(path: Path) -> Any:
    """The JSON value in ``path``; :class:`DataError` for unreadable, non-UTF-8 or bad JSON."""
    data = read_bytes(path, "JSON file", "json")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise DataError(path, f"not UTF-8 text (byte {exc.start}): not a JSON file") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise DataError(path, f"invalid JSON ({exc})") from None
    except (ValueError, RecursionError) as exc:  # digits over Python's limit, deep nesting
        raise DataError(path, f"invalid JSON ({type(exc).__name__}: {exc})") from None


#: optional entry fields: what each must be (``split`` may be null in old manifests)
_ENTRY_FIELDS = {"split": "a string or null", "n_frames": "a non-negative integer",
                 "n_points": "a non-negative integer", "has_complete": "true or false"}


def check_entry(entry: Any, i: int, mpath: Path) -> None:
    """Check manifest entry ``i``: an object with a non-empty string ``track_id``, a ``file``
    that is a relative path inside the folder (:func:`_relative_file`) and optional fields of
    the right types (:data:`_ENTRY_FIELDS`); :class:`DataError` naming ``mpath`` otherwise."""
    where = f"track entry {i}"
    if not isinstance(entry, dict):
        raise DataError(mpath, f"{where}: expected an object, got {type(entry).__name__}")
    if "track_id" not in entry or "file" not in entry:
        raise DataError(mpath, f"{where} lacks 'track_id' or 'file'")
    if not isinstance(entry["track_id"], str) or not entry["track_id"]:
        raise DataError(mpath, f"{where}: track_id must be a non-empty string, got "
                               f"{entry['track_id']!r}")
    _relative_file(entry["file"], f"{where}: file", mpath)
    for key, want in _ENTRY_FIELDS.items():
        if key in entry and not _field_ok(key, entry[key]):
            raise DataError(mpath, f"{where}: {key} must be {want}, got {entry[key]!r}")


def _field_ok(key: str, value: Any) -> bool:
    """Is ``value`` what the optional entry field ``key`` must be (:data:`_ENTRY_FIELDS`)."""
    if key == "split":
        return value is None or isinstance(value, str)
    if key == "has_complete":
        return isinstance(value, bool)
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _relative_file(file: Any, where: str, mpath: Path) -> None:
    """Refuse a manifest ``file`` that is not a plain relative path inside the folder: not a
    string, empty, absolute, holding a ``..`` part or a NUL byte."""
    if not isinstance(file, str) or not file.strip():
        raise DataError(mpath, f"{where} must be a non-empty string, got {file!r}")
    parts = file.replace("\\", "/").split("/")  # either separator, on any system
    if "\0" in file or os.path.isabs(file) or file.startswith(("/", "\\")) or ".." in parts:
        raise DataError(mpath, f"{where} {file!r} leaves the dataset folder: paths must be "
                               "relative to it, without '..'")


def _track_path(folder: Path, file: str | Path) -> Path:
    """``folder / file`` of a manifest entry, refused when it resolves outside the dataset."""
    return contained_path(folder, file, source=Path(folder) / MANIFEST, what="track file",
                          folder_kind="dataset folder")


def check_folder_settings(out: Path, config_file: str, cfg: dict, made: str) -> None:
    """Write ``OUT/config_file`` or check it matches ``cfg``: one folder, one set of settings.

    ``made`` says how the folder's tracks were made, for the message ("generated", "extracted").
    A folder with tracks but no settings file is refused too.
    """
    path = Path(out) / config_file
    if path.is_file():
        old = _read_json(path)
        if not isinstance(old, dict):
            raise DataError(path, f"expected a JSON object of settings, got "
                                  f"{type(old).__name__}")
        diff = sorted(k for k in set(old) | set(cfg) if old.get(k) != cfg.get(k))
        if diff:
            detail = ", ".join(f"{k}: {old.get(k)!r} there vs {cfg.get(k)!r} now" for k in diff)
            raise ConfigError(f"{out} holds tracks {made} with other settings ({detail}); "
                              f"use another --out folder or rerun with the same options")
        return
    if (Path(out) / MANIFEST).is_file() or any((Path(out) / "tracks").glob("*.npz")):
        raise ConfigError(f"{out} already holds tracks but no {config_file}; use another "
                          f"--out folder")
    atomic_write_json(path, cfg)


def _unit_hash(text: str) -> float:
    """A stable number in [0, 1) from ``text`` (first 8 bytes of its SHA-1)."""
    return int.from_bytes(hashlib.sha1(text.encode()).digest()[:8], "big") / 2.0**64


def manifest_entry(track: Track, file: str) -> dict[str, Any]:
    return {"track_id": track.track_id, "split": track.meta.get("split"), "file": file,
            "n_frames": len(track), "n_points": int(track.num_points.sum())}


def write_manifest(path: str | Path, entries: list[dict], config: dict | None = None,
                   **extra: Any) -> None:
    """Write ``manifest.json`` atomically (entries sorted by track id for stable output)."""
    manifest = {"format": DATASET_FORMAT, "version": DATASET_FORMAT_VERSION,
                "created_by": f"seqshape {__version__}", "config": config or {}, **extra,
                "tracks": sorted(entries, key=lambda e: e["track_id"])}
    atomic_write_json(Path(path) / MANIFEST, manifest)


def write_dataset(path: str | Path, tracks: Iterable[Track], config: dict | None = None,
                  **extra: Any) -> TrackDataset:
    """Write tracks and a manifest to a new dataset folder; returns it opened."""
    path = Path(path)
    entries = []
    for tr in tracks:
        file = f"tracks/{tr.track_id}.npz"
        save_track(path / file, tr)
        entries.append(manifest_entry(tr, file))
    write_manifest(path, entries, config, **extra)
    return TrackDataset(path)
