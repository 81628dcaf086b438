"""seqshape._runner: settings check, resume, shards and the worker pool, on a toy job; every
worker pool of seqshape ends with its parent (``kill -9``).

The toy job writes one file per item, its bytes drawn from ``default_rng([SEED, item])``, the
way ``generate`` and ``scenes`` seed their items; the references are plain serial runs and
hand-listed shards.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from seqshape._io import atomic_write_bytes
from seqshape._runner import (
    ORPHAN_EXIT,
    WorkerPool,
    check_settings,
    parse_shard,
    plan_work,
    process_alive,
    run_pool,
    shard_items,
)
from seqshape.errors import ConfigError, DataError

SEED = 7
_OFFSET = {"value": 0}


class _Stop(Exception):
    """Raised by the toy job to stop a run part-way (an interrupted run)."""


def _write_item(unit) -> int:
    folder, i = unit
    atomic_write_bytes(Path(folder) / f"{i:03d}.bin", np.random.default_rng([SEED, i]).bytes(97))
    return i


def _write_until(unit) -> int:
    folder, i, stop_at = unit
    if i == stop_at:
        raise _Stop(i)
    return _write_item((folder, i))


def _set_offset(value: int) -> None:
    _OFFSET["value"] = value


def _offset_square(x: int) -> tuple[int, int]:
    return x, x * x + _OFFSET["value"]


def _sigint_ignored(_x) -> bool:
    return signal.getsignal(signal.SIGINT) == signal.SIG_IGN


def _fail_on_three(x: int) -> int:
    if x == 3:
        raise ValueError("item 3 is broken")
    return x


def _is_done(folder: Path):
    return lambda i: (folder / f"{i:03d}.bin").is_file()


def run_job(folder: Path, n: int = 9, shard=(1, 1), workers: int = 1) -> list[int]:
    """The toy job over items ``0..n-1``: settings check, plan, pool; the items it made."""
    folder.mkdir(parents=True, exist_ok=True)
    check_settings(folder, "job.json", {"seed": SEED, "n": n}, made="toy items")
    work = plan_work(range(n), _is_done(folder), shard)
    return sorted(run_pool(_write_item, [(str(folder), i) for i in work.todo], workers))


def folder_bytes(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


# ----------------------------------------------------------------------------- shards


def test_parse_shard():
    assert parse_shard("1/1") == (1, 1)
    assert parse_shard(" 3/4") == (3, 4)
    for bad in ("2", "a/b", "1/2/3", ""):
        with pytest.raises(ConfigError, match="K/N"):
            parse_shard(bad)
    for bad in ("0/2", "3/2", "-1/2"):
        with pytest.raises(ConfigError, match="1 <= K <= N"):
            parse_shard(bad)


def test_shards_partition_the_items():
    items = list("abcdefghij")
    assert shard_items(items, (1, 3)) == ["a", "d", "g", "j"]  # positions 0, 3, 6, 9
    assert shard_items(items, (2, 3)) == ["b", "e", "h"]
    assert shard_items(items, (3, 3)) == ["c", "f", "i"]
    for n in (1, 2, 3, 4, 11):
        parts = [shard_items(items, (k, n)) for k in range(1, n + 1)]
        assert sorted(sum(parts, [])) == items
        assert sum(len(p) for p in parts) == len(items)  # disjoint
    with pytest.raises(ConfigError):
        shard_items(items, (0, 2))


def test_sharded_runs_together_equal_the_full_run(tmp_path):
    made = run_job(tmp_path / "full")
    assert made == list(range(9))
    for k in (1, 2, 3):
        assert run_job(tmp_path / "sharded", shard=(k, 3)) == [i for i in range(9) if i % 3 == k - 1]
    assert folder_bytes(tmp_path / "sharded") == folder_bytes(tmp_path / "full")
    assert run_job(tmp_path / "sharded") == []  # nothing left for an unsharded rerun


# ----------------------------------------------------------------------------- resume


def test_plan_work_skips_done_items():
    work = plan_work(range(10), lambda i: i in (2, 3, 8), shard=(1, 2))
    assert work.items == [0, 2, 4, 6, 8]
    assert work.done == [2, 8]
    assert work.todo == [0, 4, 6]


def test_interrupted_run_resumes_to_the_same_bytes(tmp_path):
    run_job(tmp_path / "once")
    part = tmp_path / "part"
    part.mkdir()
    check_settings(part, "job.json", {"seed": SEED, "n": 9}, made="toy items")
    with pytest.raises(_Stop):
        list(run_pool(_write_until, [(str(part), i, 5) for i in range(9)]))
    assert sorted(p.name for p in part.glob("*.bin")) == [f"{i:03d}.bin" for i in range(5)]
    assert not list(part.glob(".*"))  # atomic writes leave no temporary file
    before = {p.name: p.stat().st_mtime_ns for p in part.glob("*.bin")}
    assert run_job(part) == [5, 6, 7, 8]  # only the missing items are made
    assert {name: (part / name).stat().st_mtime_ns for name in before} == before
    assert folder_bytes(part) == folder_bytes(tmp_path / "once")


# ----------------------------------------------------------------------------- settings


def test_settings_are_written_then_checked(tmp_path):
    check_settings(tmp_path, "s.json", {"seed": 1, "n": [1, 2]}, made="toy items")
    assert json.loads((tmp_path / "s.json").read_text()) == {"seed": 1, "n": [1, 2]}
    check_settings(tmp_path, "s.json", {"seed": 1, "n": [1, 2]})  # a resume: accepted
    with pytest.raises(ConfigError) as info:
        check_settings(tmp_path, "s.json", {"seed": 2, "n": [1, 2]}, made="toy items")
    msg = str(info.value)
    assert "seed: 1 there vs 2 now" in msg and str(tmp_path / "s.json") in msg
    assert "n:" not in msg  # only the fields that differ are listed
    with pytest.raises(ConfigError, match="extra: None there vs 3 now"):
        check_settings(tmp_path, "s.json", {"seed": 1, "n": [1, 2], "extra": 3})


def test_settings_keys_limit_the_comparison(tmp_path):
    (tmp_path / "s.json").write_text(json.dumps({"seed": 1, "generator": "old"}))
    check_settings(tmp_path, "s.json", {"seed": 1, "generator": "new"}, keys=("seed",),
                   write=False)
    with pytest.raises(ConfigError, match="seed"):
        check_settings(tmp_path, "s.json", {"seed": 5, "generator": "old"}, keys=("seed",))
    assert json.loads((tmp_path / "s.json").read_text())["generator"] == "old"


def test_settings_refuse_occupied_and_unreadable_folders(tmp_path):
    with pytest.raises(ConfigError, match="already holds toy items but no s.json"):
        check_settings(tmp_path, "s.json", {"seed": 1}, made="toy items", occupied=True)
    assert not (tmp_path / "s.json").exists()
    check_settings(tmp_path, "s.json", {"seed": 1}, write=False)
    assert not (tmp_path / "s.json").exists()
    for text in ("{not json", "[1, 2]"):
        (tmp_path / "s.json").write_text(text)
        with pytest.raises(DataError) as info:
            check_settings(tmp_path, "s.json", {"seed": 1})
        assert info.value.path == str(tmp_path / "s.json")


def test_run_job_refuses_other_settings(tmp_path):
    run_job(tmp_path, n=3)
    with pytest.raises(ConfigError, match="n: 3 there vs 4 now"):
        run_job(tmp_path, n=4)


# ----------------------------------------------------------------------------- pool


def test_pool_results_equal_the_serial_ones(tmp_path):
    serial = list(run_pool(_offset_square, range(6), 1, initializer=_set_offset,
                           initargs=(10,)))
    assert serial == [(x, x * x + 10) for x in range(6)]  # in order, initializer run here
    pooled = list(run_pool(_offset_square, range(6), 2, initializer=_set_offset,
                           initargs=(10,)))
    assert sorted(pooled) == serial
    run_job(tmp_path / "serial", n=6, workers=1)
    run_job(tmp_path / "pooled", n=6, workers=2)
    assert folder_bytes(tmp_path / "pooled") == folder_bytes(tmp_path / "serial")


def test_pool_workers_leave_ctrl_c_to_the_parent():
    # a run started in the background (nohup, `&` in a script) inherits SIGINT ignored: the
    # parent's own handler is set here, so the check does not depend on how pytest started
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        assert all(run_pool(_sigint_ignored, range(2), 2))
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # still Ctrl-C
    finally:
        signal.signal(signal.SIGINT, before)


def test_pool_errors_reach_the_caller_and_stop_the_pool():
    with pytest.raises(ValueError, match="item 3"):
        list(run_pool(_fail_on_three, range(6), 2))
    with pytest.raises(ValueError, match="item 3"):
        list(run_pool(_fail_on_three, range(6), 1))


def test_worker_pool_runs_tasks_as_they_come():
    with WorkerPool(2, initializer=_set_offset, initargs=(5,)) as pool:
        tasks = [pool.submit(_offset_square, x) for x in range(5)]
        assert [t.get() for t in tasks] == [(x, x * x + 5) for x in range(5)]
        assert all(pool.submit(_sigint_ignored, 0).get() for _ in range(2))
        broken = pool.submit(_fail_on_three, 3)
        with pytest.raises(ValueError, match="item 3"):
            broken.get()
        assert pool.submit(_fail_on_three, 4).get() == 4  # the pool goes on
    with pytest.raises(_Stop), WorkerPool(1) as pool:  # an error in the parent ends the pool
        task = pool.submit(_offset_square, 2)
        raise _Stop(task)
    with pytest.raises(ValueError, match="item 3"), WorkerPool(1) as pool:
        pool.submit(_fail_on_three, 3).get()
    with pytest.raises(ConfigError, match="workers"):
        WorkerPool(0)


def test_pool_progress_weights_and_bad_workers(monkeypatch):
    monkeypatch.setenv("SEQSHAPE_PROGRESS", "0")
    seen = []
    out = list(run_pool(_offset_square, [1, 2, 3], 1, weight=lambda u, r: seen.append(
        (u, r)) or u, total=6))
    assert [r for _, r in seen] == out and [u for u, _ in seen] == [1, 2, 3]
    with pytest.raises(ConfigError, match="workers"):
        list(run_pool(_offset_square, [1], 0))
    assert list(run_pool(_offset_square, [], 3)) == []


# ----------------------------------------------------------------------------- orphans

# A parent that starts one of seqshape's worker pools with two workers; each worker touches
# FOLDER/<its pid> and sleeps. Run as a script: spawned workers import it as __mp_main__.
_PARENT = textwrap.dedent("""
    import os, sys, time
    from pathlib import Path

    def hold(folder):
        Path(folder, str(os.getpid())).touch()
        time.sleep(120)

    if __name__ == "__main__":
        kind, folder = sys.argv[1:]
        if kind == "run_pool":
            from seqshape._runner import run_pool
            list(run_pool(hold, [folder, folder], 2, progress_bar=False))
        elif kind == "emd":
            from seqshape.evaluation.runner import _Collector
            pool = _Collector(2).pool
            [job.result() for job in [pool.submit(hold, folder) for _ in range(2)]]
        elif kind == "tracks":
            from seqshape.data.tracks_export import _pool
            _pool(2).map(hold, [folder, folder], chunksize=1)
""")


def _ended(pid: int) -> bool:
    """Whether ``pid`` has ended (gone, or a zombie nobody reaps), read from /proc."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return True
    return stat.rpartition(")")[2].split()[0] in ("Z", "X")


@pytest.mark.skipif(not Path("/proc/self/stat").is_file(), reason="needs /proc")
def test_workers_of_every_pool_end_when_their_parent_is_killed(tmp_path):
    script = tmp_path / "parent.py"
    script.write_text(_PARENT)
    kinds = ("run_pool", "emd", "tracks")
    env = {**os.environ, "SEQSHAPE_PROGRESS": "0"}
    parents = {}
    for kind in kinds:
        (tmp_path / kind).mkdir()
        parents[kind] = subprocess.Popen([sys.executable, str(script), kind,
                                          str(tmp_path / kind)], env=env)
    workers: dict[str, list[int]] = {}
    try:
        deadline = time.monotonic() + 60
        while len(workers) < len(kinds) and time.monotonic() < deadline:
            for kind in kinds:
                pids = [int(p.name) for p in (tmp_path / kind).iterdir()]
                if len(pids) == 2:
                    workers[kind] = pids
            time.sleep(0.1)
        assert sorted(workers) == sorted(kinds), "the workers did not start"
        for proc in parents.values():
            proc.kill()  # SIGKILL: no cleanup in the parent
            proc.wait()
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not all(
                _ended(pid) for pids in workers.values() for pid in pids):
            time.sleep(0.1)
        alive = {k: [p for p in pids if not _ended(p)] for k, pids in workers.items()}
        assert alive == {k: [] for k in kinds}
    finally:
        for proc in parents.values():
            proc.kill()
            proc.wait()
        for pid in (p for pids in workers.values() for p in pids):
            if not _ended(pid):
                os.kill(pid, signal.SIGKILL)


def test_process_alive():
    assert process_alive(os.getpid())
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    assert not process_alive(proc.pid)  # reaped: gone


def test_watch_parent_ends_a_process_whose_parent_is_gone():
    """A child told that its parent is a process that has ended exits at once with
    ORPHAN_EXIT; one whose parent lives goes on."""
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    code = ("import sys, time; from seqshape._runner import watch_parent; "
            "watch_parent(int(sys.argv[1]), interval=0.05); print('watching', flush=True); "
            "time.sleep(30)")
    orphan = subprocess.run([sys.executable, "-c", code, str(gone.pid)], timeout=30)
    assert orphan.returncode == ORPHAN_EXIT
    child = subprocess.Popen([sys.executable, "-c", code, str(os.getpid())],
                             stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline() == "watching\n"
        time.sleep(0.5)  # ten looks at a living parent
        assert child.poll() is None
    finally:
        child.kill()
        child.wait()
