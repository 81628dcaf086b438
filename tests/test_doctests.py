"""The docstring examples run, and none is written where the doctest collection cannot see it.

The examples themselves run through pytest's own doctest collection: ``--doctest-modules`` in
``addopts`` and ``src/seqshape`` in ``testpaths`` (``pyproject.toml``), so a plain ``pytest``
(and ``make test``) runs every example of every module. These tests guard that set-up.
"""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = SRC / "seqshape"


def _module_name(path: Path) -> str:
    parts = path.relative_to(SRC).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _files_with_examples() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if ">>> " in p.read_text(encoding="utf-8"))


def _prompts(text: str) -> int:
    """Lines of ``text`` that open a doctest example (``>>> `` after indentation)."""
    return sum(line.lstrip().startswith(">>> ") for line in text.splitlines())


def test_the_doctest_collection_covers_the_package(request):
    assert "--doctest-modules" in " ".join(request.config.getini("addopts")).split()
    testpaths = [Path(p).as_posix().rstrip("/") for p in request.config.getini("testpaths")]
    assert "src/seqshape" in testpaths


def test_prompt_counter_matches_doctest_parser():
    text = ">>> 1 + 1\n2\n\n    >>> x = [1,\n    ...      2]\n\n# >>>not an example\n"
    examples = doctest.DocTestParser().get_examples(text)
    assert _prompts(text) == len(examples) == 2


def test_some_modules_carry_examples():
    names = {_module_name(p) for p in _files_with_examples()}
    assert {"seqshape.geometry", "seqshape.camera", "seqshape.evaluation.metrics"} <= names


@pytest.mark.parametrize("path", _files_with_examples(), ids=_module_name)
def test_every_example_is_reachable(path):
    """Each ``>>>`` line of the file is one example the doctest finder collects: an example in
    a comment, a nested function or a plain string would never run."""
    module = importlib.import_module(_module_name(path))
    found = sum(len(t.examples) for t in doctest.DocTestFinder().find(module))
    assert found == _prompts(path.read_text(encoding="utf-8")), \
        f"{path.relative_to(SRC.parent)}: some '>>>' lines are not in a collected docstring"
