"""OpenBLAS held to one thread (seqshape._threads), checked in a fresh process."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytest.importorskip("threadpoolctl")

PROBE = """
import json, numpy
from threadpoolctl import threadpool_info
from seqshape._threads import limit_openblas
before = [p["num_threads"] for p in threadpool_info() if p["internal_api"] == "openblas"]
ok = limit_openblas(1)
after = [p["num_threads"] for p in threadpool_info() if p["internal_api"] == "openblas"]
a = numpy.ones((300, 300)); assert (a @ a)[0, 0] == 300  # products still work
print(json.dumps({"ok": ok, "before": before, "after": after}))
"""


def test_limit_openblas_sets_one_thread_in_this_process():
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True,
                         check=True, env={"OPENBLAS_NUM_THREADS": "2", "PATH": ""})
    res = json.loads(out.stdout.strip().splitlines()[-1])
    if not res["before"]:
        pytest.skip("NumPy is not built on OpenBLAS here")
    assert res["ok"] and res["before"] == [2] * len(res["before"])
    assert res["after"] == [1] * len(res["before"])
