"""A griffe extension for the Python API pages: the docstrings' Sphinx roles (:func:`~a.b`,
:class:`X`, ...) become inline code (`b`, `X`), which mkdocstrings would otherwise show as
plain text (its docstring parser reads the ``:param:`` fields, not the roles). The generated
reference tables use the same rule (``docgen.markdown.esc``)."""

from __future__ import annotations

import re
from typing import Any

import griffe

ROLE = re.compile(r":[a-z]+:`(~?)([^`]+)`")
"""A role and its target; ``~`` shows the last name only, as Sphinx does."""


def plain_roles(text: str) -> str:
    """``text`` with each Sphinx role as inline code."""
    return ROLE.sub(lambda m: f"`{m[2].rsplit('.', 1)[-1] if m[1] else m[2]}`", text)


class SphinxRoles(griffe.Extension):
    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = plain_roles(obj.docstring.value)
