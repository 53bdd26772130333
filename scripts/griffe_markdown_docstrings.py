"""Griffe extension for the docs site: docstrings written for the source read as Markdown.

The docstrings are plain prose with ``>>>`` examples (run by pytest's ``--doctest-modules``) and
Sphinx roles (``:class:`Atlas```). As Markdown an example's output such as ``[3.3, 5.2]`` would read
as a link and a role would show its markup, so examples become ``pycon`` code blocks and roles
plain code. Loaded by mkdocs.yml.
"""

from __future__ import annotations

import re

import griffe

ROLE = re.compile(r":(?:py:)?(?:class|func|meth|mod|data|attr|exc|obj|const):`~?([^`]+)`")


def plain_roles(text: str) -> str:
    """A Sphinx role becomes inline code; ``~`` keeps only the last name, as Sphinx shows it.

    >>> plain_roles("see :class:`~softphantom.estimation.Atlas` and :func:`open_estimator`")
    'see `Atlas` and `open_estimator`'
    """
    return ROLE.sub(lambda m: "`" + (m.group(1).rsplit(".", 1)[-1] if m.group(0).count("~") else m.group(1)) + "`",
                    text)


def fence_doctests(text: str) -> str:
    r"""Wrap each doctest block (a ``>>>`` line up to the next blank line) in a ``pycon`` fence.

    >>> fence_doctests("Example:\n\n>>> f(1)\n[1, 2]\n\nMore.").splitlines()
    ['Example:', '', '```pycon', '>>> f(1)', '[1, 2]', '```', '', 'More.']
    """
    out: list[str] = []
    in_block = False
    for line in text.splitlines():
        if not in_block and line.lstrip().startswith(">>>"):
            indent = line[: len(line) - len(line.lstrip())]
            out.append(f"{indent}```pycon")
            in_block = True
        elif in_block and not line.strip():
            out.append(f"{indent}```")
            in_block = False
        out.append(line)
    if in_block:
        out.append(f"{indent}```")
    return "\n".join(out)


class MarkdownDocstrings(griffe.Extension):
    def on_instance(self, *, obj: griffe.Object, **kwargs: object) -> None:
        if obj.docstring is not None:
            obj.docstring.value = plain_roles(fence_doctests(obj.docstring.value))
