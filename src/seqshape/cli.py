"""The ``seqshape`` command: one sub-command per module in :mod:`seqshape.scripts`.

Each script module defines ``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> int``.
Modules are imported only when their command runs, so ``seqshape --help`` is instant. Every
option's help shows its default (:class:`HelpFormatter`).

Errors end in one line on stderr and exit status 1, never a traceback: a
:class:`~seqshape.errors.SeqshapeError` (bad data or options), an ``OSError`` such as an
output folder that cannot be written (read-only, permission denied, disk full), which names the
path, an out-of-memory error (``MemoryError``, or an inference runtime's failed allocation),
and any other exception (a bug, or an input no check foresaw): :func:`unexpected_error_line`
names the command, its input options and what to do. ``--debug`` (or ``-v``) adds the
traceback. Ctrl-C exits with 130.
"""

from __future__ import annotations

import argparse
import errno
import importlib
import logging
import sys
import traceback
from types import ModuleType

from seqshape._version import __version__
from seqshape.errors import SeqshapeError

COMMANDS: dict[str, tuple[str, str]] = {
    # name: (module, one-line help)
    "demo": ("demo", "run the whole pipeline on small generated data and write a report"),
    "generate": ("generate", "generate a synthetic LiDAR track dataset"),
    "show": ("show", "plot one track (PNG) and an interactive 3D view (HTML)"),
    "stats": ("stats", "print statistics of a track dataset"),
    "train": ("train", "train the sequential model or the per-frame baseline"),
    "train-refiner": ("train_refiner", "train the placement refiner on the networks' own "
                                       "estimates"),
    "pseudo-label": ("pseudo_label", "label a track dataset with the sequential model's "
                                     "offline estimates, for self-supervised fine-tuning"),
    "evaluate": ("evaluate", "evaluate shape and pose estimates on a dataset's val split"),
    "scenes": ("scenes", "generate camera+LiDAR scenes in the KITTI tracking layout"),
    "show-scene": ("show_scene", "draw one frame of a scene with its amodal ground truth"),
    "tracks": ("tracks", "extract vehicle tracks from real driving logs (KITTI, Argoverse 2, "
                         "nuScenes) as a track dataset"),
    "label": ("label", "produce amodal mask labels for a driving log with cameras"),
    "export-tracks": ("export_tracks", "write one log's tracks for fine-tuning (complete "
                                       "shapes: mirrored accumulations)"),
    "evaluate-masks": ("evaluate_masks", "score amodal mask labels against a reference"),
}


class HelpFormatter(argparse.HelpFormatter):
    """Appends ``(default: X)`` to an option's help unless the help already says its default
    (the options of a config dataclass, or a default in words); a switch (an option without a
    value) shows ``(default: off)``: it is off unless given."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if ("default" in text.lower() or not action.option_strings or action.required
                or isinstance(action, (argparse._HelpAction, argparse._VersionAction))):
            return text
        if action.nargs == 0:
            return text + " (default: off)"
        if action.default in (None, argparse.SUPPRESS):
            return text
        return text + " (default: %(default)s)"


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser: ``--version``, ``-v`` and one sub-parser per command (whose
    options :func:`command_parser` adds when the command runs)."""
    parser = argparse.ArgumentParser(
        prog="seqshape", formatter_class=HelpFormatter,
        description="Sequential joint shape and pose estimation of vehicles from LiDAR, "
                    "and automatic amodal segmentation labels.")
    parser.add_argument("--version", action="version", version=f"seqshape {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="debug logging, and the traceback of any error")
    parser.add_argument("--debug", action="store_true",
                        help="print the traceback of any error (after its one-line message)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, help_) in COMMANDS.items():
        sub.add_parser(name, help=help_, add_help=False)
    return parser


def command_parser(name: str) -> tuple[ModuleType, argparse.ArgumentParser]:
    """The script module of command ``name`` and its parser (its options, help with defaults)."""
    module_name, help_ = COMMANDS[name]
    module = importlib.import_module(f"seqshape.scripts.{module_name}")
    parser = argparse.ArgumentParser(prog=f"seqshape {name}",
                                     description=getattr(module, "HELP", help_),
                                     formatter_class=HelpFormatter)
    module.add_arguments(parser)
    return module, parser


#: what an OSError's errno means for the user, beside the system's own words
_OS_HINTS = {errno.EACCES: "no permission: choose a folder you can write, e.g. another --out",
             errno.EPERM: "no permission: choose a folder you can write, e.g. another --out",
             errno.EROFS: "read-only file system: choose another --out",
             errno.ENOSPC: "the disk is full: free some space or choose another --out, then "
                           "rerun the same command to resume",
             errno.EDQUOT: "disk quota exceeded: free some space or choose another --out"}


def os_error_line(exc: OSError, out: object = None) -> str:
    """One line for an ``OSError``: the path(s), the system's words and what to do.

    A failed ``write`` (a full disk) carries no file name: then the line names ``out``, the
    command's output (its ``--out``), when given.

    >>> import errno
    >>> os_error_line(PermissionError(errno.EACCES, "Permission denied", "out/a.json"))
    'out/a.json: Permission denied (no permission: choose a folder you can write, ...)'
    >>> os_error_line(OSError(errno.ENOSPC, "No space left on device"), out="runs/a")
    'writing to runs/a: No space left on device (the disk is full: ...)'
    """
    words = exc.strerror or str(exc) or type(exc).__name__
    paths = [str(p) for p in (exc.filename, exc.filename2) if p is not None]
    where = (" -> ".join(paths) if paths else f"writing to {out}" if out is not None
             else "")
    hint = _OS_HINTS.get(exc.errno)
    return (f"{where}: " if where else "") + words + (f" ({hint})" if hint else "")


#: options that name a command's input, in the order the one-line error lists them
_INPUT_OPTIONS = ("dataset", "root", "sequence", "data", "track", "trajectories", "meshes",
                  "checkpoint", "baseline", "pred", "gt", "kitti", "config")

#: words of an exception that say an allocation failed (onnxruntime's Fail and
#: RuntimeException, torch's and numpy's errors, C++ std::bad_alloc)
_OOM_WORDS = ("out of memory", "bad_alloc", "failed to allocate", "allocation failed",
              "cannot allocate memory", "unable to allocate", "allocate memory")


def is_out_of_memory(exc: BaseException) -> bool:
    """Is ``exc`` a failed allocation: a ``MemoryError`` or an error whose words say so?

    >>> is_out_of_memory(MemoryError()), is_out_of_memory(RuntimeError("x"))
    (True, False)
    >>> is_out_of_memory(RuntimeError("[ONNXRuntimeError] : 1 : FAIL : bad_alloc"))
    True
    """
    if isinstance(exc, MemoryError):
        return True
    text = str(exc).lower()
    return any(word in text for word in _OOM_WORDS)


def command_inputs(args: argparse.Namespace) -> str:
    """The input options of a parsed command, as the user gave them (``--root R``), for a
    message; ``""`` when it has none.

    >>> command_inputs(argparse.Namespace(root="kitti", out="x", sequence=None))
    '--root kitti'
    """
    given = [(k, getattr(args, k)) for k in _INPUT_OPTIONS
             if getattr(args, k, None) not in (None, "", [], False)]
    return ", ".join(f"--{k.replace('_', '-')} {v}" for k, v in given)


def unexpected_error_line(command: str, exc: BaseException, args: argparse.Namespace) -> str:
    """One line for an exception no check turned into a :class:`SeqshapeError`: the command,
    what went wrong, the input, and what to do.

    >>> import argparse
    >>> unexpected_error_line("stats", ValueError("bad"), argparse.Namespace(dataset="ds"))
    'seqshape stats: error: unexpected ValueError: bad (input: --dataset ds); ...'
    """
    words = " ".join(str(exc).split())[:300] or "(no message)"
    inputs = command_inputs(args)
    where = f" (input: {inputs})" if inputs else ""
    if is_out_of_memory(exc):
        return (f"seqshape {command}: error: out of memory{where}: {type(exc).__name__}: "
                f"{words}; hint: process less at once (fewer --workers, a smaller "
                "--batch-size, fewer tracks or frames per run) or use a machine with more "
                "memory")
    return (f"seqshape {command}: error: unexpected {type(exc).__name__}: {words}{where}; "
            "hint: check that input (rerun with --debug for the traceback) and report it "
            "with that traceback if the input is sound")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    # two-step parse: find the command, then let its module define the arguments
    head, rest = parser.parse_known_args(argv)
    if head.command is None:
        parser.print_help()
        return 2
    module, sub = command_parser(head.command)
    args = sub.parse_args(rest)
    logging.basicConfig(level=logging.DEBUG if head.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(module.run(args) or 0)
    except SeqshapeError as exc:
        error, line = exc, f"seqshape {head.command}: error: {exc}"
    except MemoryError as exc:
        error, line = exc, unexpected_error_line(head.command, exc, args)
    except OSError as exc:  # unwritable output, disk full...: the path, not a traceback
        error = exc
        line = f"seqshape {head.command}: error: {os_error_line(exc, getattr(args, 'out', None))}"
    except KeyboardInterrupt:
        print(f"seqshape {head.command}: interrupted; rerun the same command to resume",
              file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the one top-level handler: no traceback
        error, line = exc, unexpected_error_line(head.command, exc, args)
    if head.debug or head.verbose:
        traceback.print_exception(error, file=sys.stderr)
    print(line, file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
