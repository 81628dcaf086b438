"""OpenBLAS's thread pool in processes whose heavy work runs on other pools.

NumPy's matrix products run on OpenBLAS, which starts a thread per core and keeps them
spinning for a while after each product. In a process whose network passes run on PyTorch's
or ONNX Runtime's own threads (the labeller's workers and its parent), those spinning threads
take the cores the other pools and processes want: `seqshape label --workers 2` on dense logs
spent 44 CPU-seconds for 23 s of wall clock with OpenBLAS's default, 35 for 19 s with one
OpenBLAS thread a process, the labels byte for byte the same (docs/amodal.md); with one
worker, where a core may be free, sc-seg lost (0.85x), so only multi-worker runs set it. The
limit is set with threadpoolctl (scikit-learn's, a dependency), for OpenBLAS only: PyTorch's
and ONNX Runtime's pools are left to their own settings.
"""

from __future__ import annotations

import logging

log = logging.getLogger(__name__)

_limits: list = []  # the threadpoolctl limiters in force (kept alive for the process)


def limit_openblas(threads: int = 1) -> bool:
    """Hold NumPy's OpenBLAS to ``threads`` threads in this process from now on; False when
    threadpoolctl is missing (nothing changes)."""
    try:
        from threadpoolctl import threadpool_info, threadpool_limits
    except ImportError:  # a dependency, but a stripped environment still labels
        log.debug("threadpoolctl missing: OpenBLAS keeps its default threads")
        return False
    import numpy  # noqa: F401  (the library must be loaded for its pool to be found)

    # keys of the limits are library prefixes or user APIs ("blas" would take MKL too)
    prefixes = {p["prefix"] for p in threadpool_info() if p.get("internal_api") == "openblas"}
    if prefixes:
        _limits.append(threadpool_limits(limits=dict.fromkeys(prefixes, int(threads))))
    return True
