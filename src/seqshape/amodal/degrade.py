"""Deprecated: the simulated 2D instance-mask degradation moved to :mod:`seqshape.sim.degrade`
(the scene generator writes it; ``sim`` must not import ``amodal``).

The old names keep working for one release with a :class:`DeprecationWarning`.
"""

import seqshape.sim.degrade as _degrade
from seqshape._deprecated import forward

__getattr__ = forward(__name__, _degrade, (
    "DegradeConfig", "NO_DEGRADE", "Instance2D", "erode_dilate", "jitter_boundary",
    "degrade_instances"))
