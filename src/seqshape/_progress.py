"""The one progress helper: a tqdm bar on stderr.

Bars are on by default (updated every 0.5 s on a terminal, every 10 s in a log file), off under
pytest, and ``SEQSHAPE_PROGRESS=0`` / ``=1`` forces them off / on.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterable
from typing import TypeVar

T = TypeVar("T")


def progress(iterable: Iterable[T] | None = None, total: int | None = None, desc: str = "",
             unit: str = "it", disable: bool | None = None, initial: int = 0):
    """Wrap ``iterable`` in a progress bar; use as an iterator or call ``.update(n)``."""
    from tqdm.auto import tqdm

    if disable is None:
        env = os.environ.get("SEQSHAPE_PROGRESS")
        disable = env == "0" if env is not None else "PYTEST_CURRENT_TEST" in os.environ
    tty = sys.stderr.isatty()
    return tqdm(iterable, total=total, desc=desc, unit=unit, disable=disable, initial=initial,
                dynamic_ncols=tty, file=sys.stderr, mininterval=0.5 if tty else 10.0)
