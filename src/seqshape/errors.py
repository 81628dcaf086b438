"""Exceptions raised by seqshape. Every user-facing error names the file and the problem."""

from __future__ import annotations

from pathlib import Path


class SeqshapeError(Exception):
    """Base class of all seqshape errors; the CLI prints these without a traceback."""


class DataError(SeqshapeError):
    """A file could not be read or holds invalid content.

    >>> str(DataError("tracks/a.npz", "missing array poses"))
    'tracks/a.npz: missing array poses'
    >>> str(DataError("labels.txt", "expected 17 columns, got 3", line=12))
    'labels.txt:12: expected 17 columns, got 3'

    It survives pickling (a worker process raises it, the pool re-raises it in the parent):

    >>> import pickle
    >>> str(pickle.loads(pickle.dumps(DataError("a.npz", "bad", line=3))))
    'a.npz:3: bad'
    """

    def __init__(self, path: str | Path, message: str, line: int | None = None):
        self.path = str(path)
        self.line = line
        self.message = message
        where = f"{self.path}:{line}" if line is not None else self.path
        super().__init__(f"{where}: {message}")

    def __reduce__(self):
        # Exception pickles as cls(*self.args): the one formatted string, which this
        # constructor cannot take; rebuild from the parts (worker pools re-raise it here).
        return (type(self), (self.path, self.message, self.line), self.__dict__)


class ConfigError(SeqshapeError):
    """Invalid arguments or configuration values."""


class MissingDependencyError(SeqshapeError, ImportError):
    """An optional dependency is needed for this feature but is not installed."""


def require(module: str, feature: str, pip_name: str | None = None):
    """Import an optional dependency lazily, failing with a clear message.

    >>> require("math", "tests").sqrt(4.0)
    2.0
    """
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise MissingDependencyError(
            f"{feature} needs the optional package '{pip_name or module}': "
            f"pip install {pip_name or module}"
        ) from exc
