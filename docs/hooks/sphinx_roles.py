"""mkdocs hook: the docstrings' Sphinx roles (``:func:`fit```, ``:class:`LCS```) rendered as the
plain code they name, and a docstring's ``.. math::`` directive dropped before its formula."""

import re

_ROLE = re.compile(r":(?:func|class|mod|meth|attr|data|exc|obj):(?=<code>)")
_MATH = re.compile(r"\.\. math::\s*")


def on_page_content(html, **kwargs):
    return _MATH.sub("", _ROLE.sub("", html))
