"""glibc's malloc kept from handing freed memory back to the kernel (long labelling runs).

A labelling frame allocates and frees many arrays of 0.1-30 MB (masks, k-NN graphs, point
sets). glibc serves blocks above its mmap threshold with fresh pages from the kernel and
returns them on free, and trims the top of its heap beyond a threshold (twice the mmap
threshold, which it adapts up to 32 MiB): a frame's large arrays freed together go back to the
kernel, and the next frame page-faults them in again, each page zeroed by the kernel (three
20 MB arrays a frame: about 10,000 faults in ten frames, none with the settings;
tests/test_malloc.py). On the dense logs
`seqshape label --mode sc-seg --workers 2` took 1.23 M minor page faults and 13 s of system
time for 160 frames. :func:`keep_freed_memory` raises the mmap threshold to glibc's largest
(32 MiB) and keeps up to 1 GiB of freed heap (docs/history/amodal.md, "Dense logs, fifth round"):
the freed blocks are reused instead. Only the process that calls it, only with glibc (not
musl, macOS or Windows: nothing happens there); the resident memory grows by the largest
transient, not more.
"""

from __future__ import annotations

import ctypes
import logging
import sys

log = logging.getLogger(__name__)

#: ``mallopt`` parameters (glibc's malloc.h) and the values set.
M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3
SETTINGS = ((M_MMAP_THRESHOLD, 32 << 20), (M_TRIM_THRESHOLD, 1 << 30), (M_TOP_PAD, 256 << 20))


def keep_freed_memory() -> bool:
    """Apply :data:`SETTINGS` to this process's malloc; False where there is no glibc."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
        libc.gnu_get_libc_version  # noqa: B018  (glibc's own symbol: not musl)
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    done = all(mallopt(param, value) == 1 for param, value in SETTINGS)
    if not done:
        log.debug("mallopt refused a setting: malloc keeps its defaults in part")
    return done
