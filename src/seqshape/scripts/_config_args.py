"""Command-line options from a config dataclass: each option documented once, in the class.

A config dataclass documents its fields in its docstring, one ``field: text`` line each
(continuation lines indented further), as :class:`seqshape.amodal.labeler.LabelConfig` does.
:func:`add_config_arguments` turns chosen fields into ``--field-name`` options whose help is
that text and whose default is the field's default; :func:`config_kwargs` reads them back.

Types come from the annotations: ``int``, ``float``, ``str`` and ``Path`` (or ``X | None``)
take a value; a ``bool`` field that defaults to False is a ``--field`` switch, one that
defaults to True a ``--no-field`` switch, a ``bool | None`` one the pair ``--field`` /
``--no-field`` (so is a plain ``bool`` given ``action=argparse.BooleanOptionalAction``). A
field missing from the docstring, or of another type, raises :class:`TypeError` when the parser
is built: an undocumented option cannot ship.

>>> import argparse
>>> from dataclasses import dataclass
>>> @dataclass
... class Cfg:
...     '''Options.
...
...     size: edge length (m).
...     fast: skip the ``slow`` check.
...     '''
...     size: float = 2.0
...     fast: bool = False
>>> p = argparse.ArgumentParser()
>>> add_config_arguments(p, Cfg, ["size", "fast"])
>>> config_kwargs(p.parse_args(["--size", "3", "--fast"]), ["size", "fast"])
{'size': 3.0, 'fast': True}
>>> field_help(Cfg)["fast"]
'skip the slow check.'
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import re
import sys
import types
import typing
from pathlib import Path
from typing import Any

_FIELD_LINE = re.compile(r"^(\w+): (.*)$")
_ROLE = re.compile(r":\w+:`~?([^`]+)`")
_SIMPLE = (int, float, str, Path)


def field_help(cls) -> dict[str, str]:
    """``field -> text`` from the ``field: text`` lines of ``cls``'s docstring.

    Sphinx roles keep their target (``:func:`~a.b``` -> ``b``), double back-quotes are
    dropped, continuation lines are joined with one space.
    """
    out: dict[str, str] = {}
    name = None
    for line in inspect.cleandoc(cls.__doc__ or "").splitlines():
        match = _FIELD_LINE.match(line)
        if match:
            name = match.group(1)
            out[name] = match.group(2).strip()
        elif name is not None and line.startswith(" ") and line.strip():
            out[name] += " " + line.strip()
        else:
            name = None
    return {k: _plain(v) for k, v in out.items()}


def _plain(text: str) -> str:
    text = _ROLE.sub(lambda m: m.group(1).rsplit(".", 1)[-1] if m.group(0).count("~")
                     else m.group(1), text)
    return text.replace("``", "")


def _annotation(cls, f: dataclasses.Field):
    """The field's type, evaluated in its module when annotations are strings (only this
    field's: others may name types imported for type checking only)."""
    if not isinstance(f.type, str):
        return f.type
    return eval(f.type, dict(vars(sys.modules[cls.__module__])))  # noqa: S307 - own source


def _value_type(cls, name: str, annotation) -> tuple[type, bool]:
    """The argparse type of a field annotated ``annotation`` and whether it may be None."""
    optional = False
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        if len(args) == 1:
            annotation, optional = args[0], True
    if annotation is bool or annotation in _SIMPLE:
        return annotation, optional
    raise TypeError(f"{cls.__name__}.{name}: type {annotation!r} has no command-line form "
                    f"(int, float, str, Path, bool, or one of them | None)")


def add_config_arguments(parser, cls, names: list[str], **overrides: dict[str, Any]) -> None:
    """Add one option per field of ``names`` of the dataclass ``cls`` to ``parser``.

    ``overrides``: per field, extra ``add_argument`` keywords (``choices``, ``metavar``,
    ``type``, ``action``, ``flag`` = another option name); help and default always come from
    ``cls``. The help ends with the default unless the docstring says it in words.
    """
    docs = field_help(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for name in names:
        if name not in fields:
            raise TypeError(f"{cls.__name__} has no field {name!r}")
        if name not in docs:
            raise TypeError(f"{cls.__name__}.{name} is not documented: add a '{name}: text' "
                            f"line to the class docstring")
        f = fields[name]
        if f.default is dataclasses.MISSING:
            raise TypeError(f"{cls.__name__}.{name} has no default to show on the command line")
        kwargs = dict(overrides.get(name, {}))
        given = kwargs.pop("flag", None)
        flag = given or "--" + name.replace("_", "-")
        help_ = docs[name].replace("%", "%%")
        kind, optional = _value_type(cls, name, _annotation(cls, f))
        if kind is bool and (optional or kwargs.get("action") is argparse.BooleanOptionalAction):
            kwargs["action"], shown = argparse.BooleanOptionalAction, str(f.default)
        elif kind is bool and f.default:
            flag = given or "--no-" + name.replace("_", "-")
            kwargs["action"], shown, help_ = "store_false", "on", f"turn off: {help_}"
        elif kind is bool:
            kwargs["action"], shown = "store_true", "off"
        else:
            if kind is not str:  # argparse values are strings already
                kwargs.setdefault("type", kind)
            shown = "%(default)s"
        if "default" not in help_.lower():  # else the docstring says it in words
            help_ = f"{help_.removesuffix('.')} (default: {shown})"
        parser.add_argument(flag, dest=name, default=f.default, help=help_, **kwargs)


def config_kwargs(args: argparse.Namespace, names: list[str]) -> dict[str, Any]:
    """The parsed values of the fields ``names`` (keyword arguments of the config class)."""
    return {name: getattr(args, name) for name in names}
