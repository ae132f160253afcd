"""mkdocs hook: the docstrings' Sphinx roles (``:func:`fit```, ``:class:`~lcs_cvx.LCS```) rendered
as links to the API page of the name they give (through mkdocs-autorefs, which resolves them after
this hook; a name it does not know stays plain code), with Sphinx's ``~`` meaning "show the last
component only"; and a docstring's ``.. math::`` directive dropped before its formula."""

import html
import re

_ROLE = re.compile(r":(?:func|class|mod|meth|attr|data|exc|obj):<code>(~?)([\w.]+)</code>")
_MATH = re.compile(r"\.\. math::\s*")


def _link(match: re.Match) -> str:
    tilde, target = match.group(1), match.group(2)
    shown = target.rsplit(".", 1)[-1] if tilde else target
    identifier = target if target.startswith("lcs_cvx") else f"lcs_cvx.{target}"
    return (f'<autoref identifier="{html.escape(identifier)}" optional>'
            f"<code>{html.escape(shown)}</code></autoref>")


def on_page_content(html_text, **kwargs):
    return _MATH.sub("", _ROLE.sub(_link, html_text))
