"""The ``seqshape`` command: one sub-command per module in :mod:`seqshape.scripts`.

Each script module defines ``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> int``.
Modules are imported only when their command runs, so ``seqshape --help`` is instant. Every
option's help shows its default (:class:`HelpFormatter`).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from seqshape._version import __version__
from seqshape.errors import SeqshapeError

COMMANDS: dict[str, tuple[str, str]] = {
    # name: (module, one-line help)
    "demo": ("demo", "run the whole pipeline on small generated data and write a report"),
    "generate": ("generate", "generate a synthetic LiDAR track dataset"),
    "show": ("show", "plot one track (PNG) and an interactive 3D view (HTML)"),
    "stats": ("stats", "print statistics of a track dataset"),
    "train": ("train", "train the sequential model or the per-frame baseline"),
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
    (the options of a config dataclass, or a default in words); switches have none."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if ("default" in text or action.default in (None, argparse.SUPPRESS) or action.nargs == 0
                or not action.option_strings):
            return text
        return text + " (default: %(default)s)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="seqshape",
        description="Sequential joint shape and pose estimation of vehicles from LiDAR, "
                    "and automatic amodal segmentation labels.")
    parser.add_argument("--version", action="version", version=f"seqshape {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, help_) in COMMANDS.items():
        sub.add_parser(name, help=help_, add_help=False)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    # two-step parse: find the command, then let its module define the arguments
    head, rest = parser.parse_known_args(argv)
    if head.command is None:
        parser.print_help()
        return 2
    module_name, help_ = COMMANDS[head.command]
    module = importlib.import_module(f"seqshape.scripts.{module_name}")
    sub = argparse.ArgumentParser(prog=f"seqshape {head.command}",
                                  description=getattr(module, "HELP", help_),
                                  formatter_class=HelpFormatter)
    module.add_arguments(sub)
    args = sub.parse_args(rest)
    logging.basicConfig(level=logging.DEBUG if head.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(module.run(args) or 0)
    except SeqshapeError as exc:
        print(f"seqshape {head.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"seqshape {head.command}: interrupted; rerun the same command to resume",
              file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
