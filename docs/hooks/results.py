"""mkdocs hook: the studies' result files on the site. Every ``studies/results/**/*.md`` is
published as ``results/**/*.html`` (its Markdown rendered, tables included, with its figures
beside it), and a page's ``studies/results/...`` file names (``.md``, ``.png``) become links to
them, so that a reader of the site can open the tables a page cites."""

from __future__ import annotations

import html
import re
from pathlib import Path

import markdown
from mkdocs.structure.files import File, InclusionLevel
from mkdocs.utils import get_relative_url

RESULTS = Path(__file__).resolve().parents[2] / "studies" / "results"
_NAME = re.compile(r"<code>studies/results/([\w./-]+\.(?:md|png))</code>")
_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>{title}</title>
<style>body{{font-family:sans-serif;max-width:72rem;margin:2rem auto;padding:0 1rem;line-height:1.5}}
table{{border-collapse:collapse;font-size:.85rem}}td,th{{border:1px solid #ccc;padding:.2rem .5rem}}
code,pre{{font-size:.85rem}}img{{max-width:100%}}</style></head>
<body><p><code>studies/results/{title}</code></p>
{body}
</body></html>
"""


def _published(rel: str) -> str:
    return f"results/{rel}.html" if rel.endswith(".md") else f"results/{rel}"


def on_files(files, config, **kwargs):
    for path in sorted(RESULTS.rglob("*")):
        rel = path.relative_to(RESULTS).as_posix()
        if path.suffix == ".md":
            body = markdown.markdown(path.read_text(encoding="utf-8"), extensions=["tables", "fenced_code"])
            content = _PAGE.format(title=html.escape(rel), body=body)
            files.append(File.generated(config, _published(rel), content=content,
                                        inclusion=InclusionLevel.NOT_IN_NAV))
        elif path.suffix == ".png":
            files.append(File.generated(config, _published(rel), abs_src_path=str(path),
                                        inclusion=InclusionLevel.NOT_IN_NAV))
    return files


def on_page_content(html_text, page, **kwargs):
    def link(match: re.Match) -> str:
        rel = match.group(1)
        if not (RESULTS / rel).is_file():
            return match.group(0)
        return f'<a href="{get_relative_url(_published(rel), page.url)}">{match.group(0)}</a>'

    return _NAME.sub(link, html_text)
