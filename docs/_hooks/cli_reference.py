"""MkDocs hook: the CLI reference page (docs/cli.md) generated from seqshape's argparse parsers.

The page holds the marker ``<!-- cli-reference -->``; this hook replaces it, at build time, with
one section per command of :data:`seqshape.cli.COMMANDS`: its description, its usage line and a
table of its options (flags, value, default, help) walked from the parser that
:func:`seqshape.cli.command_parser` builds, the same parser ``seqshape NAME --help`` prints. Nothing
in the page is restated by hand. :func:`cli_markdown` is what tests/test_docs_site.py checks.
"""

from __future__ import annotations

import argparse
import os

MARKER = "<!-- cli-reference -->"


def _cell(text: str) -> str:
    """Markdown table cell: no newlines, pipes escaped."""
    return " ".join(str(text).split()).replace("|", "\\|")


def _value(action: argparse.Action) -> str:
    if action.nargs == 0:
        return ""
    if isinstance(action.metavar, tuple):
        return " ".join(action.metavar)
    if action.metavar:
        return str(action.metavar)
    if action.choices:
        return "{" + ",".join(str(c) for c in action.choices) + "}"
    return action.dest.upper()


def _default(action: argparse.Action) -> str:
    if action.required:
        return "required"
    if action.nargs == 0 or action.default in (None, argparse.SUPPRESS):
        return ""
    return f"`{action.default}`"


def _help(action: argparse.Action) -> str:
    text = action.help or ""
    if "%(" in text:
        try:
            text = text % {**vars(action), "default": action.default, "prog": ""}
        except (KeyError, TypeError, ValueError):
            pass
    return text


def parser_markdown(parser: argparse.ArgumentParser, level: int = 2) -> str:
    """Usage and an options table of ``parser``."""
    os.environ.setdefault("COLUMNS", "100")  # the usage line's width: the same on every machine
    usage = parser.format_usage().strip().removeprefix("usage: ")
    lines = [f"{'#' * level} `{parser.prog}`", "", _cell(parser.description or ""), "",
             "```text", usage, "```", "",
             "| option | value | default | what it does |", "| --- | --- | --- | --- |"]
    for action in parser._actions:
        if (isinstance(action, (argparse._HelpAction, argparse._SubParsersAction))
                or action.help == argparse.SUPPRESS):
            continue
        names = ", ".join(f"`{o}`" for o in action.option_strings) or f"`{action.dest}`"
        lines.append(f"| {names} | {_cell(_value(action))} | {_cell(_default(action))} | "
                     f"{_cell(_help(action))} |")
    return "\n".join(lines) + "\n"


def cli_markdown() -> str:
    """Every command's section, in :data:`seqshape.cli.COMMANDS` order, after the top level."""
    from seqshape.cli import COMMANDS, build_parser, command_parser

    top = build_parser()
    commands = ["| command | what it does |", "| --- | --- |"]
    commands += [f"| [`seqshape {name}`](#seqshape-{name}) | {_cell(help_)} |"
                 for name, (_, help_) in COMMANDS.items()]
    parts = [parser_markdown(top), "Commands:\n", "\n".join(commands) + "\n"]
    for name in COMMANDS:
        parts.append(parser_markdown(command_parser(name)[1]))
    return "\n".join(parts)


def on_page_markdown(markdown: str, page, config, files) -> str:  # noqa: ARG001 (mkdocs hook)
    if MARKER in markdown:
        return markdown.replace(MARKER, cli_markdown())
    return markdown
