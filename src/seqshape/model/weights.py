"""Where the network's weights are: the shipped files and the one resolver of "shipped name
or path". Torch-free (the labeller's parent process names the weights it records without
importing PyTorch); :mod:`seqshape.model.estimator` re-exports these names."""

from __future__ import annotations

from pathlib import Path

from seqshape.errors import ConfigError, DataError

KINDS = ("sequential", "baseline")
PRETRAINED_DIR = Path(__file__).resolve().parent.parent / "pretrained"
#: The spec of the shipped weights of a given kind (``--init pretrained``, ``--checkpoint
#: pretrained``).
PRETRAINED = "pretrained"


def pretrained_path(kind: str) -> Path:
    """The shipped weights ``seqshape/pretrained/<kind>.pt``.

    Raises :class:`ConfigError` for an unknown kind and :class:`DataError` when the file is not
    installed.
    """
    if kind not in KINDS:
        raise ConfigError(f"unknown pretrained model {kind!r}; choose from {KINDS}")
    path = PRETRAINED_DIR / f"{kind}.pt"
    if not path.is_file():
        raise DataError(path, f"shipped {kind} weights are missing from this installation; "
                              f"train them with `seqshape train --model {kind}` and pass the "
                              f"run's model.pt (RUN/model.pt) instead")
    return path


def resolve_weights(spec: str | Path, kind: str = "sequential") -> Path:
    """The weights file named by ``spec``: the one resolver of "shipped name or path".

    ``spec`` is ``"pretrained"`` (the shipped weights of ``kind``), a shipped name
    (``"sequential"`` or ``"baseline"``), or the path of an exported ``model.pt`` or a training
    checkpoint (a :class:`DataError` when there is no such file). The file itself is read and
    checked by :func:`seqshape.model.estimator.read_model_file`.
    """
    name = str(spec)
    if name == PRETRAINED:
        return pretrained_path(kind)
    if name in KINDS:
        return pretrained_path(name)
    path = Path(spec)
    if not path.is_file():
        raise DataError(path, "weights file not found")
    return path
