"""Old import paths kept for one release: a module ``__getattr__`` that forwards moved names.

A module whose public names moved elsewhere keeps working as a shim::

    import seqshape.model.smooth as _new
    from seqshape._deprecated import forward

    __getattr__ = forward(__name__, _new, ("smooth_track_poses",))

Each access of a moved name through the old path raises a :class:`DeprecationWarning` naming
the new path.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterable
from types import ModuleType
from typing import Any


def forward(old: str, new: ModuleType, names: Iterable[str]) -> Callable[[str], Any]:
    """A module ``__getattr__`` for module ``old`` forwarding ``names`` to module ``new``.

    >>> import types
    >>> target = types.ModuleType("pkg.new")
    >>> target.f = len
    >>> getattr_ = forward("pkg.old", target, ["f"])
    >>> with warnings.catch_warnings(record=True) as caught:
    ...     warnings.simplefilter("always")
    ...     getattr_("f") is len, caught[0].category.__name__
    (True, 'DeprecationWarning')
    """
    moved = frozenset(names)

    def __getattr__(name: str) -> Any:
        if name not in moved:
            raise AttributeError(f"module {old!r} has no attribute {name!r}")
        warnings.warn(f"{old}.{name} moved to {new.__name__}.{name}; the old path will be "
                      f"removed in the next release", DeprecationWarning, stacklevel=2)
        return getattr(new, name)

    return __getattr__
