"""Griffe extension for the API pages: the few reStructuredText habits of twoscale's docstrings.

The docstrings are Google style (``Args:``, ``Returns:``, ``Raises:``) with inline reST: roles
such as ``:func:`fit``` or ``:class:`~twoscale.config.ModelConfig```, ``text::`` before an
indented literal block, and one reST simple table (``twoscale.params``). Markdown would show
the roles verbatim and run the table's rows together, so before mkdocstrings renders a docstring
this extension rewrites, in the text only (the source files are untouched):

- a role ``:kind:`target``` into the code span ``target`` (``~a.b.c`` shows as ``c``);
- ``text::`` at the end of a line into ``text:`` (the indented block that follows is already a
  Markdown code block), and a line that is only ``::`` into nothing;
- a reST simple table (a block framed by ``===  ===`` rules) into a fenced code block;
- a ``Fields:`` section into ``Attributes:`` (the Google name for a class's fields).

Loaded by ``mkdocs.yml`` (``extensions: - docs/_ext/griffe_rst.py``); not part of the package.
"""

from __future__ import annotations

import re

import griffe

_ROLE = re.compile(r":(?:py:)?(?:func|class|mod|meth|data|attr|exc|obj|const):`(~?)([^`]+)`")
_RULE = re.compile(r"^\s*=+(?:\s+=+)+\s*$")


def _role(match: re.Match) -> str:
    short, target = match.group(1), match.group(2)
    return f"`{target.rsplit('.', 1)[-1] if short else target}`"


def _fence_tables(lines: list[str]) -> list[str]:
    """Wrap each reST simple table (three ``===`` rules in one block) in a fenced code block."""
    out: list[str] = []
    i = 0
    while i < len(lines):
        if _RULE.match(lines[i]):
            j = i
            rules = []
            while j < len(lines) and lines[j].strip():
                if _RULE.match(lines[j]):
                    rules.append(j)
                j += 1
            if len(rules) >= 2:
                end = rules[-1] + 1
                indent = lines[i][: len(lines[i]) - len(lines[i].lstrip())]
                out += [f"{indent}```text", *lines[i:end], f"{indent}```"]
                i = end
                continue
        out.append(lines[i])
        i += 1
    return out


def rewrite(text: str) -> str:
    """The docstring ``text`` with its reST habits turned into Markdown (see module doc)."""
    text = _ROLE.sub(_role, text)
    lines = []
    for line in text.splitlines():
        stripped = line.rstrip()
        if stripped.strip() == "::":
            line = ""
        elif stripped.endswith("::") and not stripped.endswith(":::"):
            line = stripped[:-1]
        elif stripped.strip() == "Fields:":
            line = stripped.replace("Fields:", "Attributes:")
        lines.append(line)
    return "\n".join(_fence_tables(lines))


class RestToMarkdown(griffe.Extension):
    """Rewrite each docstring when griffe loads its object."""

    def on_instance(self, *, node, obj, agent, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = rewrite(obj.docstring.value)
