"""Griffe extension for the docs site: the docstrings' doctest examples become ``pycon`` code blocks.

The docstrings are plain prose with ``>>>`` examples (run by pytest's ``--doctest-modules``); as
Markdown, an example's output such as ``[3.3, 5.2]`` would read as a link. Loaded by mkdocs.yml.
"""

from __future__ import annotations

import griffe


def fence_doctests(text: str) -> str:
    """Wrap each doctest block (a ``>>>`` line up to the next blank line) in a ``pycon`` fence.

    >>> print(fence_doctests("Example:\\n\\n>>> f(1)\\n[1, 2]\\n\\nMore."))
    Example:
    <BLANKLINE>
    ```pycon
    >>> f(1)
    [1, 2]
    ```
    <BLANKLINE>
    More.
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


class DoctestFences(griffe.Extension):
    def on_instance(self, *, obj: griffe.Object, **kwargs: object) -> None:
        if obj.docstring is not None and ">>>" in obj.docstring.value:
            obj.docstring.value = fence_doctests(obj.docstring.value)
