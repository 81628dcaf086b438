"""A disk cache of the ONNX graphs the fast inference backends build at load time.

Building an ONNX engine exports the network with PyTorch's exporter, which imports the ``onnx``
package, and ``"onnx-int8"`` quantises the export as well. That is most of a process's start-up
(measured: importing ``onnx`` 1-2 s, the two exports 0.8 s, against 0.1 s for ONNX Runtime's
sessions; docs/model.md, "Start-up"), paid again by every ``seqshape label`` or ``evaluate``
process and every ``Estimator.load`` in a new process. The graphs are a pure function of the
weights, the configuration, the exporting code and the versions of the tools, so they are kept
on disk under a key made of exactly these, and read back instead of exported.

* Folder: ``$SEQSHAPE_CACHE_DIR``, else ``$XDG_CACHE_HOME/seqshape/onnx``, else
  ``~/.cache/seqshape/onnx``. ``SEQSHAPE_CACHE_DIR=none`` (or ``off``) turns the cache off.
* Key (:func:`graph_key`): SHA-256 of the graph's kind, every weight tensor (name, dtype, shape,
  bytes), the model's kind and configuration, the source of the modules that define the
  exported function (``network.py``, ``engine.py``, ``int8.py``, ``transforms.py``,
  ``placement.py``), and the versions of seqshape, PyTorch, ``onnx`` and ONNX Runtime. A
  change of any of them is a new key, so a stale graph is never read.
* File: ``<key>.onnx`` holding the graph's bytes followed by their SHA-256 digest (32 bytes),
  written atomically (:func:`seqshape._io.atomic_write_bytes`). A file whose digest does not
  match (a damaged disk, a foreign file) is reported with a warning naming it, and the graph is
  built and written again.
* At most :data:`MAX_FILES` graphs and :data:`MAX_BYTES` bytes are kept; writing one removes
  the least recently used beyond that (a read refreshes a file's time), never the one just
  written. Only files named like the cache's own are ever removed (the folder may be one
  the user also keeps other files in).
* A folder that cannot be created or written is not an error: the graph is built as without the
  cache, with one warning per process.

The same folder keeps the verdicts of ``backend="auto"``'s check (:func:`cached_verdict`: does
a fast backend reproduce the reference on this machine?), about 0.1-0.35 s a process
otherwise. A verdict depends on the graph and on the machine's arithmetic, so its key is the
graph's key, the check's own code (``estimator.py``), the CPU (model name and feature flags),
the platform and numpy's version; files ``seqshape-check-<key>.json``, at most
:data:`MAX_VERDICTS`, written atomically; an unreadable one is checked again.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import platform
import warnings
from collections.abc import Callable
from importlib import metadata
from pathlib import Path

from seqshape._io import atomic_write_bytes
from seqshape._version import __version__

log = logging.getLogger(__name__)

#: The environment variable naming the cache folder ("none" or "off": no cache).
ENV = "SEQSHAPE_CACHE_DIR"
#: Graphs kept in the folder (two per model and backend: the batch and one-track graphs)
#: and their total size (a `small` model's graph is about 11 MB, a `paper` one's 65 MB).
MAX_FILES = 24
MAX_BYTES = 1 << 29
FORMAT = b"seqshape-onnx-graph/1"
PREFIX = "seqshape-graph-"  # the cache's file names: PREFIX + key + ".onnx"
_DIGEST = 32
_SOURCES = ("network.py", "engine.py", "int8.py", "transforms.py", "placement.py")
#: Verdicts kept (:func:`cached_verdict`; a few hundred bytes each).
MAX_VERDICTS = 256
VERDICT_PREFIX = "seqshape-check-"
_warned: set[str] = set()


def cache_dir() -> Path | None:
    """The cache folder (module doc), or None when the cache is off."""
    env = os.environ.get(ENV, "").strip()
    if env.lower() in ("none", "off", "0", "false"):
        return None
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME", "").strip()
    base = Path(xdg).expanduser() if xdg else Path.home() / ".cache"
    return base / "seqshape" / "onnx"


def _version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "-"


def _code_digest(sources: tuple[str, ...] = _SOURCES) -> bytes:
    """SHA-256 of the source of the modules that define the exported graphs."""
    h = hashlib.sha256()
    here = Path(__file__).resolve().parent
    for name in sources:
        try:
            h.update((here / name).read_bytes())
        except OSError:  # no source shipped (a frozen install): versions only
            h.update(name.encode())
    return h.digest()


def graph_key(model, kind: str) -> str:
    """The cache key (hex SHA-256, module doc) of graph ``kind`` of ``model``
    (a :class:`~seqshape.model.network.ShapePoseNet`, or a placement refiner's network, which
    has no kind nor configuration beyond its weights' shapes)."""
    h = hashlib.sha256(FORMAT)
    cfg = model.cfg.to_dict() if hasattr(model, "cfg") else {}
    meta = {"kind": kind, "model": getattr(model, "kind", type(model).__name__), "cfg": cfg,
            "versions": [__version__, _version("torch"), _version("onnx"),
                         _version("onnxruntime")]}
    h.update(json.dumps(meta, sort_keys=True, default=str).encode())
    h.update(_code_digest())
    for name, t in model.state_dict().items():
        a = t.detach().cpu().contiguous().numpy()
        h.update(f"{name}:{a.dtype.str}:{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _warn_once(key: str, message: str) -> None:
    if key not in _warned:
        _warned.add(key)
        warnings.warn(message, RuntimeWarning, stacklevel=4)


def _read(path: Path) -> bytes | None:
    """The graph stored at ``path``, None when there is none; a damaged file is reported."""
    try:
        data = path.read_bytes()
    except (FileNotFoundError, NotADirectoryError):  # not cached yet (a folder that is not
        return None  # one is reported when the graph is written)
    except OSError as exc:
        _warn_once(str(path), f"{path}: cannot read the cached ONNX graph ({exc}); exporting")
        return None
    graph, digest = data[:-_DIGEST], data[-_DIGEST:]
    if len(data) <= _DIGEST or hashlib.sha256(graph).digest() != digest:  # short: empty graph
        _warn_once(str(path), f"{path}: cached ONNX graph is damaged (checksum mismatch); "
                              "exporting it again")
        return None
    try:
        os.utime(path)  # least recently used goes first (_prune)
    except OSError:
        pass
    return graph


def _prune(folder: Path, newest: Path) -> None:
    """Remove the least recently used graphs of ``folder`` beyond :data:`MAX_FILES` files or
    :data:`MAX_BYTES` bytes, keeping ``newest``."""
    files = []
    for path in folder.glob(f"{PREFIX}*.onnx"):
        try:
            st = path.stat()
        except OSError:  # removed meanwhile by another process
            continue
        files.append((path != newest, -st.st_mtime, st.st_size, path))
    files.sort(key=lambda f: f[:2])  # the new file first, then the most recently used
    total = 0
    for n, (_, _, size, path) in enumerate(files):
        total += size
        if n == 0 or (n < MAX_FILES and total <= MAX_BYTES):
            continue
        try:
            path.unlink()
        except OSError:
            pass


def cached_graph(model, kind: str, build: Callable[[], bytes]) -> bytes:
    """Graph ``kind`` of ``model``: read from the cache, else ``build()`` and stored."""
    folder = cache_dir()
    if folder is None:
        return build()
    path = folder / f"{PREFIX}{graph_key(model, kind)}.onnx"
    graph = _read(path)
    if graph is not None:
        log.debug("ONNX graph %s read from %s", kind, path)
        return graph
    graph = build()
    if _store(folder, path, graph + hashlib.sha256(graph).digest()):
        _prune(folder, path)
    return graph


def _store(folder: Path, path: Path, data: bytes) -> bool:
    """Write ``data`` to ``path`` atomically; False (with one warning a process) when the
    folder cannot be written."""
    try:
        atomic_write_bytes(path, data)
    except OSError as exc:
        _warn_once(str(folder), f"{folder}: cannot write the ONNX graph cache ({exc}); "
                                f"graphs are exported in every process (set {ENV} to a "
                                "writable folder, or to 'none')")
        return False
    return True


def machine_id() -> str:
    """What a backend check's outcome depends on besides the graph (module doc): the CPU's
    model name and feature flags (``/proc/cpuinfo``, else :func:`platform.processor`), the
    platform and numpy's version."""
    cpu = platform.processor()
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        lines = []
    for field in ("model name", "flags", "Features"):
        value = next((ln.split(":", 1)[1].strip() for ln in lines
                      if ln.split(":", 1)[0].strip() == field and ":" in ln), "")
        cpu += "|" + " ".join(sorted(value.split()))
    return "|".join([platform.machine(), platform.system(), cpu, _version("numpy")])


def verdict_key(model, name: str) -> str:
    """The key of backend ``name``'s check verdict for ``model`` on this machine."""
    h = hashlib.sha256(graph_key(model, f"check:{name}").encode())
    h.update(_code_digest(("estimator.py",)))
    h.update(machine_id().encode())
    return h.hexdigest()


def cached_verdict(model, name: str, run: Callable[[], bool]) -> bool:
    """Backend ``name``'s check of ``model`` (``run()``): read from the cache when this
    machine checked it before (module doc), else run and stored. ``run``'s exceptions (a
    missing runtime) pass through and store nothing."""
    folder = cache_dir()
    if folder is None:
        return run()
    path = folder / f"{VERDICT_PREFIX}{verdict_key(model, name)}.json"
    try:
        stored = json.loads(path.read_text())
        if stored.get("backend") == name and isinstance(stored.get("ok"), bool):
            log.debug("backend check of %s read from %s", name, path)
            return stored["ok"]
    except (OSError, ValueError, AttributeError):
        pass  # not checked yet on this machine, or unreadable: check again
    ok = bool(run())
    if _store(folder, path, json.dumps({"backend": name, "ok": ok}).encode()):
        _prune_verdicts(folder, path)
    return ok


def _prune_verdicts(folder: Path, newest: Path) -> None:
    """Remove the oldest verdicts of ``folder`` beyond :data:`MAX_VERDICTS`."""
    files = []
    for path in folder.glob(f"{VERDICT_PREFIX}*.json"):
        try:
            files.append((path != newest, -path.stat().st_mtime, path))
        except OSError:
            continue
    files.sort(key=lambda f: f[:2])
    for _, _, path in files[MAX_VERDICTS:]:
        try:
            path.unlink()
        except OSError:
            pass
