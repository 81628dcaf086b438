"""The demo report: sections of markdown, images and links, written as markdown and as HTML.

:func:`md_to_html` converts the small markdown subset the sections use (``###`` headings,
tables, bullet lists, paragraphs, ``code``, ``**bold**``); there is no markdown dependency.

>>> md_to_html("| a | b |\\n|---|---|\\n| 1 | `x` |")
'<table><tr><th>a</th><th>b</th></tr><tr><td>1</td><td><code>x</code></td></tr></table>'
>>> md_to_html("**Title** and `a**b`")
'<p><strong>Title</strong> and <code>a**b</code></p>'
>>> md_to_html("### Errors by `k`\\ntext")
'<h3>Errors by <code>k</code></h3>\\n<p>text</p>'
"""

from __future__ import annotations

import html
import re
from dataclasses import dataclass, field


@dataclass
class Section:
    """One part of the report: markdown text, images and links (paths relative to DIR)."""

    title: str
    markdown: str = ""
    images: list[tuple[str, str]] = field(default_factory=list)   # (caption, path)
    links: list[tuple[str, str]] = field(default_factory=list)    # (label, path)


def _bold(s: str) -> str:
    """``**text**`` -> ``<strong>text</strong>`` (pairs only; a lone ``**`` stays)."""
    parts = s.split("**")
    if len(parts) < 3:
        return s
    out = parts[0]
    for i in range(1, len(parts)):
        if i % 2 == 1 and i + 1 < len(parts):
            out += "<strong>" + parts[i]
        elif i % 2 == 0:
            out += "</strong>" + parts[i]
        else:
            out += "**" + parts[i]
    return out


def _inline(s: str) -> str:
    """Escaped HTML of one line: ``code`` spans, and ``**bold**`` outside them."""
    pieces = html.escape(s).split("`")
    n_code = len(pieces) - 1 - (len(pieces) - 1) % 2  # back-quotes that pair up
    out = []
    for i, piece in enumerate(pieces):
        if i % 2 == 1 and i <= n_code:
            out.append(f"<code>{piece}</code>")
        else:
            out.append(("`" if i > n_code else "") + _bold(piece))
    return "".join(out)


def _table_html(lines: list[str]) -> str:
    rows = [r for r in lines if not set(r.replace("|", "").strip()) <= set("-: ")]
    cells = [[_inline(c.strip()) for c in r.strip().strip("|").split("|")] for r in rows]
    return ("<table><tr>" + "".join(f"<th>{c}</th>" for c in cells[0]) + "</tr>"
            + "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in cells[1:])
            + "</table>")


#: an ATX heading line: 1-6 ``#``, a space, the title (closing ``#`` dropped)
_HEADING = re.compile(r"^(#{1,6})\s+(.*?)(?:\s+#+)?\s*$")


def md_to_html(text: str) -> str:
    """HTML of the markdown subset the sections use: ``#``-``######`` headings, tables, bullet
    lists, paragraphs, `code`, **bold**."""
    out: list[str] = []
    table: list[str] = []
    items: list[str] = []

    def flush():
        if table:
            out.append(_table_html(table))
            table.clear()
        if items:
            out.append("<ul>" + "".join(f"<li>{_inline(i)}</li>" for i in items) + "</ul>")
            items.clear()

    for line in text.splitlines():
        if line.startswith("|"):
            table.append(line)
        elif line.startswith("- "):
            items.append(line[2:])
        elif heading := _HEADING.match(line):
            flush()
            level = len(heading.group(1))
            out.append(f"<h{level}>{_inline(heading.group(2))}</h{level}>")
        else:
            flush()
            if line.strip():
                out.append(f"<p>{_inline(line)}</p>")
    flush()
    return "\n".join(out)


def report_markdown(sections: list[Section], timings: list[tuple[str, float]]) -> str:
    """``report.md``: a fixed introduction, every section, then the step timings (s)."""
    parts = ["# seqshape demo\n",
             "Sequential joint shape and pose estimation (GRU over PointNet features) beside "
             "the per-frame baseline, on synthetic LiDAR tracks.\n"]
    for s in sections:
        parts.append(f"## {s.title}\n\n{s.markdown}")
        parts += [f"![{cap}]({path})\n" for cap, path in s.images]
        parts += [f"- [{label}]({path})" for label, path in s.links]
        parts.append("")
    parts.append("## Timings\n")
    parts += [f"- {name}: {sec:.1f} s" for name, sec in timings]
    return "\n".join(parts) + "\n"


_STYLE = ("body{font-family:sans-serif;max-width:1200px;margin:2em auto;padding:0 1em}"
          "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:4px 8px}"
          "img{max-width:100%}code{background:#eee;padding:0 3px}")


def _section_html(s: Section) -> list[str]:
    body = [f"<h2>{html.escape(s.title)}</h2>{md_to_html(s.markdown)}"]
    body += [f'<figure><img src="{html.escape(p)}" alt="{html.escape(c)}">'
             f"<figcaption>{html.escape(c)}</figcaption></figure>" for c, p in s.images]
    if s.links:
        body.append("<ul>" + "".join(f'<li><a href="{html.escape(p)}">{html.escape(t)}</a>'
                                     f"</li>" for t, p in s.links) + "</ul>")
    return body


def report_html(sections: list[Section], timings: list[tuple[str, float]]) -> str:
    """``index.html``: the same content as :func:`report_markdown`, one self-contained page."""
    body = ["<h1>seqshape demo</h1>"]
    for s in sections:
        body += _section_html(s)
    body.append("<h2>Timings</h2><ul>" + "".join(
        f"<li>{html.escape(n)}: {sec:.1f} s</li>" for n, sec in timings) + "</ul>")
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>seqshape demo</title>"
            f"<style>{_STYLE}</style></head><body>{''.join(body)}</body></html>\n")
