"""``seqshape._malloc.keep_freed_memory``: freed blocks are reused, not faulted in again."""

from __future__ import annotations

import subprocess
import sys

import pytest

CHILD = """
import resource, sys
import numpy as np
from seqshape._malloc import keep_freed_memory
ok = keep_freed_memory() if sys.argv[1] == "on" else None
def frame():  # three 20 MB arrays alive at once, then freed (a labelling frame's pattern)
    arrays = [np.ones(20 << 17) for _ in range(3)]
    del arrays
frame()  # warm-up: the heap grows once
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    frame()
print(ok, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(mode: str) -> tuple[str, int]:
    out = subprocess.run([sys.executable, "-c", CHILD, mode], capture_output=True, text=True,
                         check=True).stdout.split()
    return out[0], int(out[1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc only")
def test_freed_arrays_are_reused_without_page_faults():
    """Ten frames of three 20 MB arrays alive at once: glibc's defaults hand the freed heap
    top back to the kernel (measured: about 10,000 pages faulted in again over the ten), with
    the settings the freed blocks are reused."""
    ok, on = _faults("on")
    if ok != "True":
        pytest.skip("not glibc: keep_freed_memory does nothing here")
    _, off = _faults("off")
    assert off > 5000  # the kernel zeroes pages of the freed arrays again
    assert on < 500, (on, off)
