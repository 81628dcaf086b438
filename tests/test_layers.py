"""The import structure of docs/architecture.md: layers import downward only, no cycles, no
module imports the package root; and each checker is shown to fail on a package that breaks it.

The layers contract lives in pyproject.toml (``[tool.importlinter]``) and runs through
import-linter's own command; the root-import and cycle rules, which import-linter cannot state,
are checked here on grimp's import graph (the one import-linter builds, function-level imports
included).
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import pytest

grimp = pytest.importorskip("grimp", reason="import-linter (dev extra) is not installed")

ROOT = Path(__file__).resolve().parents[1]


def run_contracts(config: Path, cwd: Path, pythonpath: Path | None = None
                  ) -> subprocess.CompletedProcess:
    """``lint-imports`` of the venv on ``config`` (no cache written), from ``cwd``."""
    env = None
    if pythonpath is not None:
        env = {"PATH": "", "PYTHONPATH": str(pythonpath)}
    code = "import sys; from importlinter.cli import lint_imports_command as c; sys.exit(c())"
    return subprocess.run([sys.executable, "-c", code, "--no-cache", str(config)], cwd=cwd,
                          env=env, capture_output=True, text=True, timeout=120)


def root_importers(package: str) -> set[str]:
    """Modules of ``package`` that import the package root itself (``from pkg import name``
    of a name defined in ``pkg/__init__.py``)."""
    graph = grimp.build_graph(package, cache_dir=None)
    return set(graph.find_modules_that_directly_import(package))


def import_cycles(package: str) -> list[list[str]]:
    """Strongly connected groups (more than one module) of ``package``'s import graph: every
    import cycle, a package ``__init__`` and its own submodules included."""
    graph = grimp.build_graph(package, cache_dir=None)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles = []

    def visit(v: str) -> None:  # Tarjan; the graph has about a hundred modules
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.find_modules_directly_imported_by(v)):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                cycles.append(sorted(group))

    for module in sorted(graph.modules):
        if module not in index:
            visit(module)
    return cycles


# ---------------------------------------------------------------------------- seqshape itself


def test_layers_contract_kept():
    result = run_contracts(ROOT / "pyproject.toml", ROOT)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "0 broken" in result.stdout


def test_no_module_imports_the_package_root():
    assert root_importers("seqshape") == set(), (
        "import seqshape._version (or the defining module), not the package root")


def test_no_import_cycles():
    assert import_cycles("seqshape") == []


def test_moved_names_warn_and_still_work():
    import seqshape.amodal.kins as old_kins
    import seqshape.amodal.smooth as old_smooth
    import seqshape.data.kitti as kitti
    from seqshape.data import crop, kins
    from seqshape.model import smooth

    for old, new, name in ((old_kins, kins, "read_kins"), (old_kins, kins, "KINS_CATEGORIES"),
                           (old_smooth, smooth, "smooth_track_poses"),
                           (kitti, crop, "crop_box")):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            assert getattr(old, name) is getattr(new, name)
        assert [w.category for w in caught] == [DeprecationWarning]
        assert f"{new.__name__}.{name}" in str(caught[0].message)
    with pytest.raises(AttributeError, match="no_such_name"):
        old_kins.no_such_name  # noqa: B018 - the attribute access is the test


def test_one_category_table():
    from seqshape.data import categories, kins, sequence
    from seqshape.vehicles import VEHICLE_CLASSES as VEHICLE_CLASSES_OF_VEHICLES

    # hand-written from the KINS release (car 4, truck 6, van 7) plus seqshape's bus and trailer
    assert categories.CLASS_TO_KINS == {"car": 4, "van": 7, "truck": 6, "bus": 9, "trailer": 10}
    assert categories.KITTI_TYPE_TO_KINS == {"Car": 4, "Van": 7, "Truck": 6}
    assert categories.CLASS_TO_KITTI == {"car": "Car", "van": "Van", "truck": "Truck"}
    assert sequence.CLASS_TO_KINS is categories.CLASS_TO_KINS
    assert sequence.VEHICLE_CLASSES is categories.VEHICLE_CLASSES
    assert kins.KINS_CATEGORIES is categories.KINS_CATEGORIES
    # vehicles sits beside data (neither imports the other): its copy must agree
    assert VEHICLE_CLASSES_OF_VEHICLES == categories.VEHICLE_CLASSES


def test_importing_data_and_the_labeller_does_not_import_torch():
    code = ("import sys, seqshape.data, seqshape.amodal.labeler, seqshape.model.smooth; "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120)
    assert out.stdout.strip() == "False"


# ------------------------------------------------------------------ the checkers can fail


def _write_package(root: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))


TOY_CONFIG = """\
[tool.importlinter]
root_package = "toypkg"

[[tool.importlinter.contracts]]
name = "toy layers"
type = "layers"
containers = ["toypkg"]
layers = ["high", "low"]
"""


def test_contract_fails_on_an_upward_import(tmp_path):
    _write_package(tmp_path, {"toypkg/__init__.py": "", "toypkg/high.py": "X = 1\n",
                              "toypkg/low.py": "from toypkg.high import X\n",
                              "pyproject.toml": TOY_CONFIG})
    result = run_contracts(tmp_path / "pyproject.toml", tmp_path, pythonpath=tmp_path)
    assert result.returncode == 1, result.stdout + result.stderr
    assert "toy layers BROKEN" in result.stdout
    assert "toypkg.low -> toypkg.high" in result.stdout
    # the same package with the import pointing down is kept
    _write_package(tmp_path, {"toypkg/high.py": "from toypkg.low import X\n",
                              "toypkg/low.py": "X = 1\n"})
    result = run_contracts(tmp_path / "pyproject.toml", tmp_path, pythonpath=tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr


def test_root_and_cycle_checks_fail_on_a_bad_package(tmp_path, monkeypatch):
    _write_package(tmp_path, {
        "badpkg/__init__.py": "VERSION = '1'\n",
        "badpkg/a.py": "from badpkg import VERSION\n\n\ndef f():\n    from badpkg import b\n",
        "badpkg/b.py": "import badpkg.a\n",
        "badpkg/c.py": "X = 1\n",
    })
    monkeypatch.syspath_prepend(str(tmp_path))
    assert root_importers("badpkg") == {"badpkg.a"}
    assert import_cycles("badpkg") == [["badpkg.a", "badpkg.b"]]
