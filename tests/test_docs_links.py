"""Relative links of the markdown docs, and the ``docs/*.md`` pointers of the code, resolve.

Pure Python, no network: a link with a scheme (``https:``, ``mailto:``) is not followed.
Checked: ``[text](target)`` and ``![alt](target)`` outside fenced code blocks in README.md,
CHANGELOG.md, benchmarks/README.md, every page under docs/ and the model card (the file must
exist; a ``#anchor`` must be one of the target's headings, GitHub style), and every
``docs/NAME.md`` (or ``docs/DIR/NAME.md``) mentioned in the package, the benchmarks and the tests
(the file must exist; with a section named right after it, ``docs/x.md, section "Title"`` or
``docs/x.md, "Title"``, a heading of x.md must start with that title). A section of
``docs/x.md`` that moved to the developer journal ``docs/history/x.md`` (issue 46) still
resolves there, so a mention written before the move does not break; new mentions name the
journal. The documentation site's own check (strict MkDocs build) is tests/test_docs_site.py.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MARKDOWN = [ROOT / "README.md", ROOT / "CHANGELOG.md", ROOT / "benchmarks" / "README.md",
            ROOT / "src" / "seqshape" / "pretrained" / "MODEL_CARD.md",
            *sorted((ROOT / "docs").rglob("*.md"))]
SOURCES = sorted({*(ROOT / "src" / "seqshape").rglob("*.py"), *(ROOT / "benchmarks").glob("*.py"),
                  *(ROOT / "tests").glob("*.py"), ROOT / "Makefile"} - {Path(__file__).resolve()})

_FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
_LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_MENTION = re.compile(
    r"(?<![\w/.-])docs/((?:[\w.-]+/)*[\w.-]+\.md)(?:,?\s+(?:section\s+)?\"([^\"]+)\")?")


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def _headings(path: Path) -> list[str]:
    text = _FENCE.sub("", path.read_text(encoding="utf-8"))
    return [m.group(1).strip() for m in re.finditer(r"^#{1,6}\s+(.+?)\s*#*\s*$", text, re.M)]


def dead_links(path: Path) -> list[str]:
    """The relative link targets of markdown file ``path`` that do not resolve."""
    text = _FENCE.sub("", path.read_text(encoding="utf-8"))
    dead = []
    for match in _LINK.finditer(text):
        target = match.group(1)
        if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target):
            continue
        file, _, anchor = target.partition("#")
        dest = (path.parent / file) if file else path
        if not dest.exists():
            dead.append(target)
        elif anchor and dest.suffix == ".md" and anchor not in {_slug(h) for h in _headings(dest)}:
            dead.append(target)
    return dead


def dead_mentions(text: str, docs: Path) -> list[str]:
    """``docs/NAME.md`` mentions in ``text`` whose file or named section is missing."""
    dead = []
    for match in _MENTION.finditer(re.sub(r"\s+", " ", text)):
        name, section = match.groups()
        dest = docs / name
        if not dest.exists():
            dead.append(f"docs/{name}")
        elif section and not any(h.startswith(section) for h in _headings(dest)):
            moved = docs / "history" / name
            if not (moved.exists() and any(h.startswith(section) for h in _headings(moved))):
                dead.append(f'docs/{name}, "{section}"')
    return dead


def _id(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def test_dead_link_finder_on_a_hand_made_tree(tmp_path):
    (tmp_path / "img").mkdir()
    (tmp_path / "img" / "a.png").write_bytes(b"")
    (tmp_path / "other.md").write_text("# Title\n\n## Offline mode (`x`, issue 19)\n")
    page = tmp_path / "page.md"
    page.write_text("![fig](img/a.png) [ok](other.md#offline-mode-x-issue-19) [web](https://x.y)\n"
                    "[gone](missing.md) ![gone](img/b.png) [bad](other.md#nope) [self](#top)\n"
                    "```\n[in code](nowhere.md)\n```\n# Top\n")
    assert dead_links(page) == ["missing.md", "img/b.png", "other.md#nope"]
    text = 'see docs/other.md, section "Offline mode", docs/other.md, "Title", docs/gone.md and\n' \
           '  docs/other.md, "No such"; mydocs/x.md is not a mention'
    assert dead_mentions(text, tmp_path) == ["docs/gone.md", 'docs/other.md, "No such"']
    # a section moved to the journal docs/history/NAME.md resolves there; sub-folders count
    (tmp_path / "history").mkdir()
    (tmp_path / "history" / "other.md").write_text("# Journal\n\n## No such (2026-12-01)\n")
    text += ', docs/history/other.md, "Journal", docs/history/gone.md'
    assert dead_mentions(text, tmp_path) == ["docs/gone.md", "docs/history/gone.md"]


def test_markdown_links_resolve():
    dead = {_id(p): d for p in MARKDOWN if (d := dead_links(p))}
    assert dead == {}


def test_docs_mentions_resolve():
    docs = ROOT / "docs"
    dead = {_id(p): d for p in MARKDOWN + SOURCES
            if (d := dead_mentions(p.read_text(encoding="utf-8"), docs))}
    assert dead == {}
