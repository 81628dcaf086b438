"""Griffe extension for the API reference: the docstrings' Sphinx cross-reference roles
(``:func:`name```, ``:class:`~pkg.Name```, ``:data:``, ...) rendered as inline code, so the
Markdown pages read ``name`` instead of a literal ``:func:``. Listed under the python
handler's ``extensions`` in mkdocs.yml; the docstrings themselves are unchanged."""

from __future__ import annotations

import re

import griffe

ROLE = re.compile(r":(?:py:)?(?:func|class|meth|mod|data|attr|exc|obj|const|ref|term):"
                  r"`~?([^`]+)`")


def plain_roles(text: str) -> str:
    """``:func:`~a.b``` -> ```a.b```; text without roles is returned unchanged."""
    return ROLE.sub(r"`\1`", text)


class RstRoles(griffe.Extension):
    def on_instance(self, *, obj, **kwargs) -> None:  # noqa: ARG002 (griffe's event signature)
        if obj.docstring is not None:
            obj.docstring.value = plain_roles(obj.docstring.value)
