"""The docs site's docstring extension (scripts/griffe_markdown_docstrings.py): what the strict
build (`make docs`) relies on to render the docstrings' examples and roles."""

import importlib.util
from pathlib import Path

import griffe

spec = importlib.util.spec_from_file_location(
    "griffe_markdown_docstrings", Path(__file__).parents[1] / "scripts" / "griffe_markdown_docstrings.py")
ext = importlib.util.module_from_spec(spec)
spec.loader.exec_module(ext)


def test_doctest_output_is_fenced_not_a_link():
    # an example's output "[3.3, 5.2]" would otherwise be an unresolvable Markdown reference
    text = "Pieces.\n\n    >>> [c for c in x]\n    [3.3, 5.2]\n    >>> y\n    Traceback (most recent call last):\n    ...\n\nEnd."
    lines = ext.fence_doctests(text).splitlines()
    assert lines == ["Pieces.", "", "    ```pycon", "    >>> [c for c in x]", "    [3.3, 5.2]", "    >>> y",
                     "    Traceback (most recent call last):", "    ...", "    ```", "", "End."]
    assert ext.fence_doctests("no example here") == "no example here"
    assert ext.fence_doctests(">>> f()\n1").splitlines()[-1] == "```"  # closed at the end of the text


def test_sphinx_roles_become_code():
    assert ext.plain_roles(":class:`~softphantom.estimation.Atlas`, :func:`open_estimator`, :mod:`a.b`") == \
        "`Atlas`, `open_estimator`, `a.b`"
    assert ext.plain_roles("``literal`` and :term:`kept`") == "``literal`` and :term:`kept`"


def test_extension_rewrites_a_loaded_docstring():
    code = 'def f():\n    """Calls :func:`~m.g`.\n\n    >>> f()\n    [1, 2]\n    """\n'
    mod = griffe.visit("m", Path("m.py"), code, extensions=griffe.load_extensions(ext.MarkdownDocstrings))
    assert mod["f"].docstring.value.splitlines() == ["Calls `g`.", "", "```pycon", ">>> f()", "[1, 2]", "```"]
