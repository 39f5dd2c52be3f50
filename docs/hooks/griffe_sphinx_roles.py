"""A griffe extension for the API pages: Sphinx cross-reference roles shown as code.

The docstrings name other objects the Sphinx way (``:func:`open_footage```, ``:class:`~x.Y```);
Markdown has no roles, so each becomes plain inline code of the name (the ``~`` prefix, Sphinx's
"show the last part only", keeps the last part).
"""
from __future__ import annotations

import re

import griffe

ROLE = re.compile(r":(?:py:)?(?:func|meth|class|mod|attr|data|obj|exc|const|ref|term):`(~?)([^`]+)`")


def _code(match: re.Match) -> str:
    name = match.group(2)
    if match.group(1):
        name = name.rsplit(".", 1)[-1]
    return f"`{name}`"


class SphinxRoles(griffe.Extension):
    def on_instance(self, *, node, obj, agent, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = ROLE.sub(_code, obj.docstring.value)
