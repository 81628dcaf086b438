"""The documentation site builds in strict mode, offline, and its generated references cover
the code (issue 46).

``mkdocs build --strict`` (what ``make docs`` runs) fails on any warning: a link to a missing
page, an anchor that no heading of the target has, a ``::: module.object`` that mkdocstrings
cannot resolve, a page missing from the navigation. It runs here with every proxy pointed at a
closed port, so a build that fetched anything (a theme's fonts, a CDN, an inventory) would fail;
the built pages load only local assets. About 10 s on 2 cores.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "docs" / "_hooks"))

import cli_reference  # noqa: E402 (the hook lives with the docs, not in the package)
import rst_roles  # noqa: E402

from seqshape.cli import COMMANDS, command_parser  # noqa: E402

NO_NETWORK = {k: "http://127.0.0.1:9" for k in ("http_proxy", "https_proxy", "HTTP_PROXY",
                                                 "HTTPS_PROXY", "all_proxy", "ALL_PROXY")}


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, **NO_NETWORK, "NO_PROXY": "", "no_proxy": ""}
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir",
                          str(out)], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-4000:]
    return out


def test_the_site_builds_strictly_offline(site):
    for page in ("index.html", "getting-started.html", "cli.html", "api.html", "results.html",
                 "tutorials/kitti.html", "how-to/cluster.html", "history/model.html"):
        assert (site / page).is_file(), page
    for page in site.rglob("*.html"):
        text = page.read_text(encoding="utf-8")
        remote = re.findall(r'<(?:link|script|img)[^>]+(?:href|src)="(https?:[^"]+)"', text)
        assert not remote, f"{page.relative_to(site)} loads {remote}"


def test_the_results_page_opens_with_the_real_sequences(site):
    text = (ROOT / "docs" / "results.md").read_text(encoding="utf-8")
    headings = re.findall(r"^## (.+)$", text, re.M)
    assert headings[0] == "Real sequences"


def test_the_api_reference_is_generated_from_the_docstrings(site):
    api = (site / "api.html").read_text(encoding="utf-8")
    from seqshape.model.estimator import Estimator

    first_line = Estimator.step.__doc__.strip().splitlines()[0].strip()
    assert 'id="seqshape.model.estimator.Estimator.step"' in api
    assert first_line.split("``")[0][:40] in api
    assert ":func:" not in api and ":class:" not in api  # roles read as code (rst_roles)
    assert rst_roles.plain_roles("see :func:`~a.b` and :class:`C`, not :x:`y`") == (
        "see `a.b` and `C`, not :x:`y`")


def test_the_cli_reference_walks_every_parser(site):
    text = cli_reference.cli_markdown()
    for name in COMMANDS:
        assert f"## `seqshape {name}`" in text
        for action in command_parser(name)[1]._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            for option in action.option_strings:
                assert f"`{option}`" in text, f"seqshape {name} {option}"
    page = (site / "cli.html").read_text(encoding="utf-8")
    assert "cli-reference" not in page and "--image-size" in page
