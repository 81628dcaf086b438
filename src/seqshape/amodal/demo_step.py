"""Deprecated: the demo's amodal step moved to :mod:`seqshape.demo.amodal_step`.

Kept for one release so that old imports work (with a DeprecationWarning). It imports
:mod:`seqshape.demo` only when a moved name is used (an upward import, amodal -> demo, that
must not run when :mod:`seqshape.amodal` loads); the module goes with the next release.
"""

from __future__ import annotations

import importlib
import warnings

_MOVED = ("TITLE", "DemoStepResult", "amodal_demo_step", "step_amodal")


def __getattr__(name: str):
    if name not in _MOVED:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    warnings.warn(f"{__name__}.{name} moved to seqshape.demo.amodal_step.{name}; the old path "
                  f"will be removed in the next release", DeprecationWarning, stacklevel=2)
    return getattr(importlib.import_module("seqshape.demo.amodal_step"), name)
