"""The one runner of long commands that write one output per item (tracks, scene sequences).

Six pieces, each usable alone, shared by ``seqshape generate`` and ``seqshape scenes``:

* :func:`check_settings`: one folder, one set of settings. The first run writes a JSON
  settings file; a later run into the same folder must bring equal settings (a resume) or is
  refused with a :class:`~seqshape.errors.ConfigError` naming the file and the fields that
  differ.
* :func:`plan_work`: resume and shards. Items are numbered by their position in the full list;
  shard ``K/N`` (1-based) takes the positions ``j`` with ``j % N == K - 1``, so the shards
  partition the items and their union is the whole run. Items whose output is complete
  (``is_done``) are skipped; the caller writes each item's output atomically (``seqshape._io``)
  so that an interrupted run leaves no half-written item.
* :func:`run_pool`: the worker pool. ``fn`` runs on every unit in this process
  (``workers=1``) or in spawned worker processes (results in completion order), with a
  progress bar. Workers ignore SIGINT: Ctrl-C reaches the parent only, which terminates the
  pool and re-raises :class:`KeyboardInterrupt` (the CLI then says "rerun to resume"). Workers
  die with their parent (:func:`watch_parent`): a ``kill -9`` of the command leaves no worker
  running on.
* :class:`WorkerPool`: the same workers for a parent that hands out tasks as it makes them
  (``seqshape label``: frames of one log are drawn in parallel while the next log is
  completed).
* :func:`watch_parent`: the watchdog every worker pool of seqshape starts in its workers
  (this one, the EMD pool of :mod:`seqshape.evaluation.runner`, the log pool of
  :mod:`seqshape.data.tracks_export`).
* :func:`parse_shard`: the ``--shard K/N`` option.

Every item's output must depend only on the item (seeded per item), never on the worker
count or the shard: then a resumed, sharded or parallel run gives the same bytes as one
serial run.

>>> parse_shard("2/3")
(2, 3)
>>> plan_work(range(8), lambda i: i == 4, shard=(2, 3)).todo
[1, 7]
"""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from seqshape._io import atomic_write_json
from seqshape._progress import progress
from seqshape.errors import ConfigError, DataError


def parse_shard(text: str) -> tuple[int, int]:
    """``"K/N"`` (1 <= K <= N) -> ``(K, N)``; :class:`ConfigError` otherwise."""
    try:
        k, n = (int(p) for p in str(text).split("/"))
    except ValueError:
        raise ConfigError(f"--shard must look like K/N (e.g. 1/4), got {text!r}") from None
    return check_shard((k, n))


def check_shard(shard: tuple[int, int]) -> tuple[int, int]:
    """``shard`` as ``(K, N)`` ints if ``1 <= K <= N``; :class:`ConfigError` otherwise."""
    k, n = (int(x) for x in shard)
    if not 1 <= k <= n:
        raise ConfigError(f"shard {k}/{n}: --shard K/N needs 1 <= K <= N")
    return k, n


def shard_items(items: Iterable, shard: tuple[int, int] = (1, 1)) -> list:
    """The items of shard ``K/N``: positions ``j`` with ``j % N == K - 1`` (module doc)."""
    k, n = check_shard(shard)
    return [x for j, x in enumerate(items) if j % n == k - 1]


@dataclass
class WorkPlan:
    """What one run does: ``items`` of its shard (in order), of which ``done`` are complete
    already and ``todo`` are to be made."""

    items: list
    done: list
    todo: list


def plan_work(items: Iterable, is_done: Callable[[Any], bool],
              shard: tuple[int, int] = (1, 1)) -> WorkPlan:
    """Split this shard's ``items`` into complete (``is_done(item)`` true) and to do."""
    mine = shard_items(items, shard)
    done, todo = [], []
    for x in mine:
        (done if is_done(x) else todo).append(x)
    return WorkPlan(mine, done, todo)


def read_settings(path: str | Path) -> dict | None:
    """The JSON object in ``path``; None when the file does not exist; :class:`DataError`
    when it is unreadable or not a JSON object."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataError(path, f"unreadable settings file ({exc})") from None
    if not isinstance(doc, dict):
        raise DataError(path, "settings file does not hold a JSON object")
    return doc


def check_settings(folder: str | Path, file_name: str, settings: dict, *,
                   keys: Sequence[str] | None = None, made: str = "outputs made",
                   occupied: bool = False, write: bool = True) -> None:
    """Refuse to resume into ``folder`` when its ``file_name`` holds other settings.

    Args:
        folder: the output folder.
        file_name: the settings file inside it (JSON object).
        settings: this run's settings (JSON-normalised: lists, not tuples).
        keys: the fields compared (None: every field of either side).
        made: what the folder holds, for the message ("tracks generated", "scenes generated").
        occupied: the folder already holds outputs; without a settings file that is refused.
        write: write ``settings`` (atomically) when the file does not exist yet.

    Raises:
        ConfigError: the settings differ (the message names the file and every differing
            field with both values), or ``occupied`` without a settings file.
        DataError: the settings file is unreadable.
    """
    path = Path(folder) / file_name
    old = read_settings(path)
    if old is not None:
        names = keys if keys is not None else sorted(set(old) | set(settings))
        diff = [k for k in names if old.get(k) != settings.get(k)]
        if diff:
            detail = ", ".join(f"{k}: {old.get(k)!r} there vs {settings.get(k)!r} now"
                               for k in diff)
            raise ConfigError(f"{folder} holds {made} with other settings ({detail}; recorded "
                              f"in {path}); use another --out folder or rerun with the same "
                              f"options")
        return
    if occupied:
        raise ConfigError(f"{folder} already holds {made} but no {file_name}; use another "
                          f"--out folder")
    if write:
        atomic_write_json(path, settings)


#: seconds between two looks of a worker's watchdog at its parent (:func:`watch_parent`)
PARENT_POLL_S = 0.5
#: exit status of a worker that ended itself because its parent died
ORPHAN_EXIT = 70


def process_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists and has not ended (a zombie, ended but not yet reaped
    by its parent, counts as ended where ``/proc`` tells). Never signals it: on Windows, where
    ``os.kill(pid, 0)`` would end the process, this is always True."""
    if os.name == "nt":  # pragma: no cover - os.kill(pid, 0) terminates there
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by another user
        pass
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:  # no /proc (macOS) or gone meanwhile: trust os.kill
        return True
    return stat.rpartition(")")[2].split()[:1] not in (["Z"], ["X"])


def watch_parent(parent: int | None = None, interval: float = PARENT_POLL_S) -> threading.Thread:
    """Start a daemon thread that ends this (worker) process when its parent is gone.

    Every ``interval`` seconds the thread compares ``os.getppid()`` with its value at the start
    (an orphan is adopted by init or a subreaper, so the value changes when the parent dies)
    and, when ``parent`` (the pid of the process that made the pool) is given, checks that this
    process still exists; the first look is at once. Either way, ``os._exit(ORPHAN_EXIT)``
    ends the worker without unwinding: whatever it was writing goes through
    :mod:`seqshape._io`, so nothing is left half-written. ``prctl(PR_SET_PDEATHSIG)`` is not
    used: on Linux it fires when the parent *thread* that started the worker ends (pools start
    replacement workers from helper threads), and a forkserver worker's parent is the server.

    Call it as a pool's ``initializer`` (with ``initargs=(os.getpid(),)``) or from one.
    """
    ppid = os.getppid()

    def orphaned() -> bool:
        return os.getppid() != ppid or (parent is not None and not process_alive(parent))

    def watch() -> None:
        while not orphaned():
            time.sleep(interval)
        os._exit(ORPHAN_EXIT)

    thread = threading.Thread(target=watch, name="seqshape-parent-watchdog", daemon=True)
    thread.start()
    return thread


def _init_worker(parent: int, initializer: Callable | None, initargs: tuple) -> None:
    """Worker start: die with ``parent`` (:func:`watch_parent`), ignore SIGINT (the parent
    handles Ctrl-C), then the caller's initializer."""
    watch_parent(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if initializer is not None:
        initializer(*initargs)


def run_pool(fn: Callable, units: Sequence, workers: int = 1, *,
             initializer: Callable | None = None, initargs: tuple = (),
             weight: Callable[[Any, Any], int] | None = None, total: int | None = None,
             desc: str = "", unit: str = "item", progress_bar: bool | None = None) -> Iterator:
    """Yield ``fn(u)`` for every unit ``u`` of ``units``.

    ``workers == 1`` (or a single unit): in this process, in order, after
    ``initializer(*initargs)``. Otherwise over ``min(workers, len(units))`` spawned processes,
    each started with ``initializer(*initargs)``, results in completion order (``fn``,
    ``initializer``, the units and results must pickle). The progress bar advances by
    ``weight(u, result)`` per finished unit (1 when None) up to ``total`` (``len(units)`` when
    None); ``progress_bar`` None follows :func:`seqshape._progress.progress`'s default.
    Ctrl-C terminates the workers and re-raises :class:`KeyboardInterrupt`; the workers end
    themselves when this process dies (:func:`watch_parent`).
    """
    if workers < 1:
        raise ConfigError(f"workers must be >= 1, got {workers}")
    units = list(units)
    bar = progress(total=len(units) if total is None else total, desc=desc, unit=unit,
                   disable=None if progress_bar is None else not progress_bar)
    step = weight or (lambda _u, _r: 1)
    try:
        if workers == 1 or len(units) <= 1:
            if initializer is not None and units:
                initializer(*initargs)
            for u in units:
                result = fn(u)
                bar.update(step(u, result))
                yield result
            return
        yield from _pooled(fn, units, min(workers, len(units)), initializer, initargs, bar, step)
    finally:
        bar.close()


def _spawn_pool(workers: int, initializer: Callable | None, initargs: tuple
                ) -> ProcessPoolExecutor:
    """``workers`` spawned processes, each started by :func:`_init_worker`, all at once (a
    no-op task each: the executor would start them one submission at a time)."""
    pool = ProcessPoolExecutor(max_workers=workers,
                               mp_context=multiprocessing.get_context("spawn"),
                               initializer=_init_worker,
                               initargs=(os.getpid(), initializer, initargs))
    for _ in range(workers):
        pool.submit(int)
    return pool


def stop_pool(pool: ProcessPoolExecutor) -> None:
    """End ``pool`` at once after an error or Ctrl-C: queued tasks cancelled, the workers
    killed, its threads joined. (``multiprocessing.Pool.terminate`` could hang here for good:
    its task thread blocked on a full queue that no worker read any more, seen under load.)"""
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in list((getattr(pool, "_processes", None) or {}).values()):
        proc.kill()
    pool.shutdown(wait=True)


def _pooled(fn, units, workers, initializer, initargs, bar, step) -> Iterator:
    pool = _spawn_pool(workers, initializer, initargs)
    try:
        futures = {pool.submit(fn, u): j for j, u in enumerate(units)}
        for fut in as_completed(futures):
            result = fut.result()
            bar.update(step(units[futures[fut]], result))
            yield result
    except BaseException:
        stop_pool(pool)
        raise
    pool.shutdown(wait=True)


class WorkerPool:
    """Spawned worker processes that take tasks as they come, for a parent that makes the
    work while the workers do it (``seqshape label``: the parent completes a log's tracks, the
    workers draw the masks of the logs completed before).

    Workers start at once (so their imports overlap the parent's own start-up), each with
    ``initializer(*initargs)``, ignore SIGINT and end with their parent, as in
    :func:`run_pool`. :meth:`submit` returns a :class:`Task`
    (``ready()``, ``get()``; a task's exception is raised by ``get``). Use it as a context
    manager: leaving it normally waits for the tasks; an exception (Ctrl-C included)
    terminates the workers and goes on.
    """

    def __init__(self, workers: int, initializer: Callable | None = None,
                 initargs: tuple = ()):
        if workers < 1:
            raise ConfigError(f"workers must be >= 1, got {workers}")
        self.workers = workers
        self._pool = _spawn_pool(workers, initializer, initargs)

    def submit(self, fn: Callable, unit: Any) -> Task:
        """Run ``fn(unit)`` in a worker (``fn`` and ``unit`` must pickle)."""
        return Task(self._pool.submit(fn, unit))

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self._pool.shutdown(wait=True)
        else:
            stop_pool(self._pool)


class Task:
    """A task of :class:`WorkerPool`: ``ready()`` (done, or failed) and ``get()`` (its result,
    or its exception raised here; a worker that died raises
    :class:`concurrent.futures.process.BrokenProcessPool`)."""

    def __init__(self, future: Future):
        self._future = future

    def ready(self) -> bool:
        return self._future.done()

    def get(self, timeout: float | None = None) -> Any:
        return self._future.result(timeout)
