"""The package version, in the bottom layer so that any module can record it without importing
the package root (``seqshape/__init__.py``)."""

__version__ = "0.2.0"
