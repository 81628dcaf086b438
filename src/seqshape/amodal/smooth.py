"""Deprecated: the track-level pose smoother moved to :mod:`seqshape.model.smooth`.

The old names keep working for one release with a :class:`DeprecationWarning`.
"""

import seqshape.model.smooth as _smooth
from seqshape._deprecated import forward

__getattr__ = forward(__name__, _smooth, ("axial_mean", "smooth_track_poses"))
