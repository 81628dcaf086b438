"""Command-line options built from a config dataclass (seqshape.scripts._config_args)."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from seqshape.cli import HelpFormatter
from seqshape.scripts._config_args import add_config_arguments, config_kwargs, field_help


@dataclass
class Demo:
    """Options of something.

    size: edge length (m), 100 % of the box.
    name: a name, see :func:`~seqshape.geometry.wrap_angle` and
        :class:`seqshape.data.Track` for ``details``.
    count: how many (None: as many as there are).
    fast: skip the slow check.
    checked: run the check; default on, as measured.
    boxes: draw boxes (None: when there are any).
    path: where to write.
    """

    size: float = 2.0
    name: str = "a"
    count: int | None = None
    fast: bool = False
    checked: bool = True
    boxes: bool | None = None
    path: Path = Path("out")
    extra: int = 0
    items: tuple[int, ...] = ()
    required: int = field(default=1)


ALL = ["size", "name", "count", "fast", "checked", "boxes", "path"]


def _parser(names=ALL, **overrides) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(formatter_class=HelpFormatter)
    add_config_arguments(parser, Demo, names, **overrides)
    return parser


def test_field_help_joins_lines_and_drops_markup():
    docs = field_help(Demo)
    assert docs["name"] == "a name, see wrap_angle and seqshape.data.Track for details."
    assert docs["size"] == "edge length (m), 100 % of the box."
    assert "extra" not in docs and "Options" not in " ".join(docs)


def test_defaults_and_types_come_from_the_fields():
    args = _parser().parse_args([])
    assert config_kwargs(args, ALL) == {"size": 2.0, "name": "a", "count": None, "fast": False,
                                        "checked": True, "boxes": None, "path": Path("out")}
    args = _parser().parse_args(["--size", "3.5", "--count", "4", "--fast", "--no-checked",
                                 "--no-boxes", "--path", "x/y", "--name", "b"])
    assert config_kwargs(args, ALL) == {"size": 3.5, "name": "b", "count": 4, "fast": True,
                                        "checked": False, "boxes": False, "path": Path("x/y")}
    assert _parser().parse_args(["--boxes"]).boxes is True
    with pytest.raises(SystemExit):
        _parser().parse_args(["--count", "many"])


def test_help_is_the_docstring_with_the_default():
    text = " ".join(_parser().format_help().split())
    assert "--size SIZE edge length (m), 100 % of the box (default: 2.0)" in text
    assert "--count COUNT how many (None: as many as there are) (default: None)" in text
    assert "--fast skip the slow check (default: off)" in text
    # the default said in words is not repeated
    assert "--no-checked turn off: run the check; default on, as measured." in text
    assert "--boxes, --no-boxes draw boxes (None: when there are any) (default: None)" in text


def test_overrides_add_choices_flag_and_metavar():
    parser = _parser(["name", "checked"], name={"choices": ("a", "b"), "metavar": "N"},
                     checked={"flag": "--skip-check"})
    assert parser.parse_args(["--skip-check"]).checked is False
    with pytest.raises(SystemExit):
        parser.parse_args(["--name", "c"])
    assert "--name N" in parser.format_help()


@pytest.mark.parametrize("name, message", [
    ("extra", "Demo.extra is not documented"),
    ("items", "Demo.items is not documented"),
    ("missing", "Demo has no field 'missing'"),
])
def test_an_undocumented_or_unknown_field_fails_loudly(name, message):
    with pytest.raises(TypeError, match=message):
        _parser([name])


def test_a_type_without_a_command_line_form_fails_loudly():
    @dataclass
    class Bad:
        """Bad.

        items: some numbers.
        """

        items: tuple[int, ...] = ()

    with pytest.raises(TypeError, match="Bad.items: type"):
        add_config_arguments(argparse.ArgumentParser(), Bad, ["items"])
