"""Shared pieces of the ``benchmarks/bm_*.py`` scripts: timing loop, markdown table, argparse.

The scripts import this module as ``from _bench import ...``; that works because Python puts the
script's own folder (``benchmarks/``) first on ``sys.path`` when a script is run as
``python benchmarks/bm_x.py``. See ``benchmarks/README.md`` for the rules every benchmark follows.
Synthetic inputs shared with the tests (box clouds, reference sizes) come from
:mod:`seqshape.testing`, so a benchmark times the clouds a test checks.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Timing:
    """Wall times of the timed runs of one function.

    ``runs``: seconds per timed run, in order; ``result``: the return value of the last call
    (the warm-up's when there were no timed runs).
    """

    runs: tuple[float, ...]
    result: Any = None

    @property
    def median(self) -> float:
        """Median seconds per run."""
        return statistics.median(self.runs)

    @property
    def min(self) -> float:
        return min(self.runs)

    @property
    def max(self) -> float:
        return max(self.runs)

    @property
    def iqr(self) -> float:
        """Interquartile range in seconds (75th - 25th percentile, linear interpolation)."""
        q25, q75 = np.percentile(self.runs, [25, 75])
        return float(q75 - q25)

    def rates(self, work: float) -> list[float]:
        """``work`` units per second for each run (e.g. frames/s), in run order."""
        return [work / t for t in self.runs]


def time_it(fn: Callable[[], Any], repeats: int, warmup: int = 1,
            setup: Callable[[], Any] | None = None) -> Timing:
    """Call ``fn()`` ``warmup`` times untimed, then ``repeats`` times timed (``perf_counter``).

    ``setup``, when given, is called (untimed) before every timed run, e.g. to reset state.
    Raises ``ValueError`` when ``repeats < 1`` or ``warmup < 0``.
    """
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    if warmup < 0:
        raise ValueError(f"warmup must be >= 0, got {warmup}")
    result = None
    for _ in range(warmup):
        result = fn()
    runs = []
    for _ in range(repeats):
        if setup is not None:
            setup()
        t0 = time.perf_counter()
        result = fn()
        runs.append(time.perf_counter() - t0)
    return Timing(tuple(runs), result)


def machine_gflops(threads: int, rows: int = 8192, size: int = 512, repeats: int = 5) -> float:
    """The machine's float32 matrix-product speed right now (GFLOP/s, best of ``repeats``) on
    ``threads`` PyTorch threads: a (rows x size) by (size x size) product, the shape of the
    encoders' per-point layers. Printed beside speed tables so that figures taken on different
    days (this machine's speed moves by 2x from day to day) can be put side by side."""
    import torch  # lazy: not every benchmark needs it

    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        gen = torch.Generator().manual_seed(0)
        a = torch.rand(rows, size, generator=gen)
        b = torch.rand(size, size, generator=gen)
        best = min(time_it(lambda: a @ b, repeats, warmup=1).runs)
    finally:
        torch.set_num_threads(old)
    return 2.0 * rows * size * size / best / 1e9


def machine_line() -> str:
    """One line naming this run's :func:`machine_gflops` on 1 and 2 threads."""
    return (f"machine now: float32 matrix product {machine_gflops(1):.0f} GFLOP/s on 1 thread, "
            f"{machine_gflops(2):.0f} on 2")


def print_table(headers: Sequence[str], rows: Sequence[Sequence[Any]],
                align: str | None = None) -> None:
    """Print a markdown table, columns padded to a common width.

    Cells are printed with ``str()``: format numbers before passing them. ``align`` holds one
    letter per column, ``l`` or ``r`` (default: first column left, the others right).
    """
    n = len(headers)
    align = align or "l" + "r" * (n - 1)
    if len(align) != n or set(align) - {"l", "r"}:
        raise ValueError(f"align must be {n} letters 'l'/'r', got {align!r}")
    cells = [[str(c) for c in row] for row in rows]
    for row in cells:
        if len(row) != n:
            raise ValueError(f"row has {len(row)} cells, expected {n}: {row}")
    widths = [max([len(headers[j]), 3, *(len(r[j]) for r in cells)]) for j in range(n)]

    def line(row: Sequence[str]) -> str:
        return "| " + " | ".join(c.ljust(w) if a == "l" else c.rjust(w)
                                 for c, w, a in zip(row, widths, align, strict=True)) + " |"

    print(line(headers))
    print("| " + " | ".join("-" * w if a == "l" else "-" * (w - 1) + ":"
                            for w, a in zip(widths, align, strict=True)) + " |")
    for row in cells:
        print(line(row))


def _count(minimum: int) -> Callable[[str], int]:
    def parse(text: str) -> int:
        value = int(text)
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        return value
    return parse


def bench_parser(doc: str | None, repeats: int, seed: int = 0, min_repeats: int = 1,
                 repeats_help: str | None = None) -> argparse.ArgumentParser:
    """An argument parser with the common ``--repeats`` and ``--seed`` options.

    The description is the first line of ``doc`` (the script's ``__doc__``).
    """
    ap = argparse.ArgumentParser(description=(doc or "").splitlines()[0] if doc else None)
    ap.add_argument("--repeats", type=_count(min_repeats), default=repeats,
                    help=repeats_help or f"timed runs after the warm-up (default {repeats})")
    ap.add_argument("--seed", type=int, default=seed,
                    help=f"base random seed of the inputs (default {seed})")
    return ap
