"""The commands of the tutorials and guides run as written, on fixture logs in the documented
layouts (issue 46): the documentation cannot drift from the code.

Each page of :data:`PAGES` shows its commands in ```` ```bash ```` blocks with a placeholder
root (``/data/kitti/tracking/training``, ...). This test writes a small log of that dataset
(the fixtures of tests/_*_fixture.py) where the placeholder says, runs every ``seqshape``
command of the page in order through :func:`seqshape.cli.main` (in-process: no interpreter
start-up per command) in an empty working folder, and checks each exits 0 and writes the
outputs the page names. A line that is not a ``seqshape`` command (a comment, ``python ...``)
is not run; a page whose blocks hold no command fails, so a renamed block cannot pass by
running nothing.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
from _av2_fixture import write_log
from _kitti_fixture import write_box_kitti
from _nuscenes_fixture import write_nuscenes

from seqshape.cli import main

DOCS = Path(__file__).resolve().parents[1] / "docs"

#: page -> (placeholder root, writer of a fixture log at a path, outputs the commands write)
PAGES = {
    "tutorials/kitti.md": ("/data/kitti/tracking/training",
                           lambda root: write_box_kitti(root, frames=3),
                           ["kitti_tracks/manifest.json", "kitti_eval/metrics.md",
                            "kitti_labels/0000.json"]),
    "tutorials/av2.md": ("/data/av2/sensor/val", lambda root: write_log(root, n_sweeps=3),
                         ["av2_tracks/manifest.json", "av2_eval/metrics.md",
                          "av2_labels/0a1b2c3d-0000-4000-8000-000000000001.json"]),
    "tutorials/nuscenes.md": ("/data/nuscenes", lambda root: write_nuscenes(root),
                              ["nuscenes_tracks/manifest.json", "nuscenes_eval/metrics.md",
                               "nuscenes_labels/scene-0061.json"]),
    "getting-started.md": ("/data/kitti/tracking/training",
                           lambda root: write_box_kitti(root, frames=2),
                           ["kitti_eval/metrics.md", "kitti_labels/0000.json"]),
    "how-to/label-a-dataset.md": ("/data/kitti/tracking/training",
                                  lambda root: write_box_kitti(root, frames=2),
                                  ["labels/0000.json", "labels_gt/0000.json"]),
}

_BLOCK = re.compile(r"^```bash\n(.*?)^```", re.S | re.M)


def shell_commands(markdown: str) -> list[str]:
    """The ``seqshape`` command lines of the page's bash blocks, continuations joined and
    trailing comments dropped (:func:`test_the_command_extractor`)."""
    out = []
    for block in _BLOCK.findall(markdown):
        for line in re.sub(r"\\\n\s*", "", block).splitlines():
            line = line.split(" #", 1)[0].strip()
            if line.startswith("seqshape "):
                out.append(line)
    return out


def test_the_command_extractor():
    text = "x\n```bash\nseqshape a --b c \\\n    --d e   # note\n# x\npython y\n```\n```\nseqshape no\n```\n"
    assert shell_commands(text) == ["seqshape a --b c --d e"]


@pytest.fixture(scope="module")
def graph_cache(tmp_path_factory) -> Path:
    """One ONNX graph cache for the pages, as a user's runs share ~/.cache/seqshape (the
    suite's conftest turns the cache off: each load would export the graphs again)."""
    return tmp_path_factory.mktemp("onnx-cache")


@pytest.mark.parametrize("page", sorted(PAGES))
def test_page_commands_run_on_a_fixture_log(page, tmp_path, monkeypatch, graph_cache):
    placeholder, write, outputs = PAGES[page]
    monkeypatch.setenv("SEQSHAPE_CACHE_DIR", str(graph_cache))
    commands = shell_commands((DOCS / page).read_text(encoding="utf-8"))
    assert commands, f"{page}: no seqshape command in its bash blocks"
    root = tmp_path / "data" / placeholder.strip("/")
    write(root)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    for command in commands:
        argv = shlex.split(command.replace(placeholder, str(root)))[1:]
        assert main(argv) == 0, f"{page}: `{command}` failed"
    for out in outputs:
        assert (work / out).is_file(), f"{page}: {out} not written"
