"""The documentation is tested: its code runs, its shown output is what the code prints, the
API reference covers the public API and the site builds with ``mkdocs build --strict``.

Code blocks: every fenced ```` ```python ```` block of ``README.md`` and of each
``docs/tutorials/*.md`` page runs; the blocks of one page run in order, in one namespace, in a
fresh temporary working directory (which has a ``studies`` link to the repository's
``studies/``, as a user's checkout has). Markers, each on the line right before a fence:

- ``<!-- skip-test -->`` before a ```` ```python ```` block: the block is not run (for code that
  needs more than seconds; shell commands belong in ```` ```bash ```` blocks, which never run).
- A ```` ```text ```` block right after a python block (blank lines between allowed) is the
  output the block prints; it must match exactly (trailing spaces aside; ``...`` matches any
  text, as in doctest's ELLIPSIS), except for bounds: ``≤ 1e-05`` (or ``≥ 0.5``) in place of
  a number matches any number printed there that satisfies it. Errors of trained models and
  round-off move with the machine's floating-point path and the installed versions, so the
  pages show them as bounds, never as values.
"""

from __future__ import annotations

import contextlib
import inspect
import io
import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", ROOT / "docs" / "index.md", *sorted((ROOT / "docs" / "tutorials").glob("*.md"))]
REFERENCE = ROOT / "docs" / "reference"

SKIP = "<!-- skip-test -->"

#: Modules documented as a whole in the API reference (besides every top-level name).
DOCUMENTED_MODULES = (
    "lcs_cvx.resizing",
    "lcs_cvx.parameter_constraints",
    "lcs_cvx.second_order",
    "lcs_cvx.hessian",
    "lcs_cvx.problems",
    "lcs_cvx.layers",
    "lcs_cvx.io",
    "lcs_cvx.train",
    "lcs_cvx.datasets",
    "lcs_cvx.plot",
    "lcs_cvx.train.log",
    "lcs_cvx.streams",
    "lcs_cvx.recordings",
)

#: Words that narrate how the software was made rather than what it does.
PROCESS_WORDS = re.compile(
    r"\bsession|slow phase|\btoday|this issue|the issue's|commit [0-9a-f]{7}|#1[0-9]",
    re.IGNORECASE,
)


# -- extracting the blocks ----------------------------------------------------------------------
@dataclass(frozen=True)
class Block:
    """One ```` ```python ```` block of a page and the output it is documented to print."""

    path: Path
    line: int  # 1-based line of the opening fence
    code: str
    skip: bool
    expected: str | None

    @property
    def where(self) -> str:
        return f"{self.path.relative_to(ROOT)}:{self.line}"


def _fence(lines: list[str], start: int) -> tuple[str, int]:
    """The body of the fence opening at ``lines[start]`` and the index of its closing line."""
    end = start + 1
    while end < len(lines) and lines[end].strip() != "```":
        end += 1
    if end == len(lines):
        raise AssertionError(f"unclosed code fence opened at line {start + 1}")
    return "\n".join(lines[start + 1 : end]) + "\n", end


def _previous(lines: list[str], i: int) -> str:
    """The nearest non-blank line before ``lines[i]`` ('' if none)."""
    j = i - 1
    while j >= 0 and not lines[j].strip():
        j -= 1
    return lines[j].strip() if j >= 0 else ""


def extract_blocks(path: Path) -> list[Block]:
    """Every ```` ```python ```` block of ``path``, with its markers and documented output."""
    lines = path.read_text(encoding="utf-8").splitlines()
    blocks: list[Block] = []
    i = 0
    while i < len(lines):
        fence = lines[i].strip()
        if not fence.startswith("```") or fence == "```":
            i += 1
            continue
        body, end = _fence(lines, i)
        if fence != "```python":
            i = end + 1
            continue
        skip = _previous(lines, i) == SKIP
        # the documented output: the next fence, if it is ```text
        j = end + 1
        while j < len(lines) and not lines[j].strip():
            j += 1
        expected = None
        if j < len(lines) and lines[j].strip() == "```text":
            expected, out_end = _fence(lines, j)
            end = out_end
        blocks.append(Block(path, i + 1, body, skip, expected))
        i = end + 1
    return blocks


# -- comparing output ---------------------------------------------------------------------------
_NUMBER = r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?"
#: what the documented output may hold besides literal text: ``...`` or a bound ``≤ x``/``≥ x``
_SPECIAL = re.compile(rf"\.\.\.|([≤≥]) ?({_NUMBER})")


def output_matches(want: str, got: str) -> bool:
    """``got`` (what a block printed) against ``want`` (the documented output): literal text
    exactly (trailing spaces aside), ``...`` any text, ``≤ x`` / ``≥ x`` a number within the
    bound."""
    want = "\n".join(line.rstrip() for line in want.strip("\n").splitlines())
    got = "\n".join(line.rstrip() for line in got.strip("\n").splitlines())
    pattern, bounds, pos = [], [], 0
    for m in _SPECIAL.finditer(want):
        pattern.append(re.escape(want[pos : m.start()]))
        if m.group() == "...":
            pattern.append(".*?")
        else:
            pattern.append(f"({_NUMBER})")
            bounds.append((m.group(1), float(m.group(2))))
        pos = m.end()
    pattern.append(re.escape(want[pos:]))
    match = re.fullmatch("".join(pattern), got, flags=re.DOTALL)
    if match is None:
        return False
    return all(
        (float(v) <= bound) if sign == "≤" else (float(v) >= bound)
        for v, (sign, bound) in zip(match.groups(), bounds, strict=True)
    )


# -- running a page -----------------------------------------------------------------------------
@pytest.fixture
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def run_page(path: Path, workdir: Path) -> list[tuple[Block, str]]:
    """Run the blocks of ``path`` in ``workdir``, in one namespace; return what each printed."""
    (workdir / "studies").symlink_to(ROOT / "studies", target_is_directory=True)
    namespace: dict = {"__name__": "__docs__"}
    printed = []
    cwd = os.getcwd()
    os.chdir(workdir)
    try:
        for block in extract_blocks(path):
            if block.skip:
                continue
            out = io.StringIO()
            try:
                with contextlib.redirect_stdout(out):
                    exec(compile(block.code, block.where, "exec"), namespace)
            except Exception as exc:
                raise AssertionError(
                    f"the block at {block.where} raised {type(exc).__name__}: {exc}\n"
                    f"it had printed:\n{out.getvalue()}"
                ) from exc
            printed.append((block, out.getvalue()))
    finally:
        os.chdir(cwd)
    return printed


@pytest.mark.parametrize("path", PAGES, ids=[p.name for p in PAGES])
def test_page_code_runs_and_prints_what_is_shown(path, tmp_path, one_thread):
    blocks = extract_blocks(path)
    assert blocks, f"{path.name}: no ```python block found"
    for block, got in run_page(path, tmp_path):
        if block.expected is not None:
            assert output_matches(block.expected, got), (
                f"the block at {block.where} printed\n{got}\ninstead of the documented\n"
                f"{block.expected}"
            )


def test_skipped_blocks_are_few():
    blocks = [b for p in PAGES for b in extract_blocks(p)]
    skipped = [b.where for b in blocks if b.skip]
    assert len(skipped) <= 2, f"too many blocks opt out of the test: {skipped}"


# -- the markers and comparisons themselves -----------------------------------------------------
def test_extract_blocks_reads_markers(tmp_path):
    page = tmp_path / "page.md"
    page.write_text(
        "text\n\n```python\nprint(1)\n```\n\n```text\n1\n```\n\n<!-- skip-test -->\n```python\n"
        "raise SystemExit\n```\n\n```bash\nls\n```\n\n```python\nprint(2.0)\n```\n"
        "```text\n≤ 2.5\n```\n"
    )
    b = extract_blocks(page)
    assert [(x.line, x.skip, x.expected) for x in b] == [
        (3, False, "1\n"), (12, True, None), (20, False, "≤ 2.5\n"),
    ]


def test_output_comparison():
    assert output_matches("a 1\n", "a 1  \n")
    assert not output_matches("a 1\n", "a 2\n")
    assert not output_matches("a 1\n", "a 1\nb\n")
    assert output_matches("e_test ...\n", "e_test 3.2e-07\n")
    assert output_matches("wall time: ... s\nok\n", "wall time: 4.20 s\nok\n")
    # bounds: the number printed there must satisfy them; the words around stay exact
    assert output_matches("e_test = ≤ 1e-05 (n=3)\n", "e_test = 9.1e-08 (n=3)\n")
    assert output_matches("e_test = ≤1e-05\n", "e_test = 1e-05\n")
    assert not output_matches("e_test = ≤ 1e-05\n", "e_test = 4.0e-04\n")
    assert not output_matches("e_test = ≤ 1e-05\n", "e_tst = 4.0e-08\n")
    assert not output_matches("e_test = ≤ 1e-05 (n=3)\n", "e_test = 4.0e-08 (n=4)\n")
    assert not output_matches("e_test = ≤ 1e-05\n", "e_test = nan\n")
    assert output_matches("share ≥ 0.5, H = 1, 5: ≤ 1e-3, ≤ 1e-2\n", "share 0.7, H = 1, 5: 2e-4, 3e-3\n")
    assert not output_matches("share ≥ 0.5\n", "share 0.4\n")
    # every number not written as a bound is exact
    assert not output_matches("modes: 8, e_test = ≤ 1e-05\n", "modes: 9, e_test = 1e-06\n")


# -- the reference and the site -----------------------------------------------------------------
def reference_targets() -> set[str]:
    """The ``::: dotted.name`` targets of the API reference pages."""
    pattern = re.compile(r"^::: ([\w.]+)\s*$")
    return {
        m.group(1)
        for page in REFERENCE.glob("*.md")
        for line in page.read_text(encoding="utf-8").splitlines()
        if (m := pattern.match(line))
    }


def _exists(module: str) -> bool:
    """``module`` (dotted) is a module or package of this checkout."""
    path = ROOT.joinpath(*module.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def test_reference_covers_the_public_api():
    import lcs_cvx
    import lcs_cvx.control
    import lcs_cvx.study

    def public(module) -> set[str]:
        return {
            f"{module.__name__}.{name}"
            for name, value in vars(module).items()
            if not name.startswith("_") and not inspect.ismodule(value)
        }

    wanted = public(lcs_cvx) | public(lcs_cvx.study) | public(lcs_cvx.control)
    wanted |= {m for m in DOCUMENTED_MODULES if _exists(m)}
    missing = sorted(wanted - reference_targets())
    assert not missing, f"names without a '::: name' line in docs/reference/: {missing}"


def test_site_builds_strict(tmp_path):
    pytest.importorskip("mkdocs")
    pytest.importorskip("mkdocstrings")
    pytest.importorskip("material")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "NO_MKDOCS_2_WARNING": "1"}
    run = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT, env=env, capture_output=True, text=True,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    assert (tmp_path / "site" / "reference" / "systems" / "index.html").is_file()
    # the docstrings' Sphinx roles are links to the API pages, with no "~" left showing
    training = (tmp_path / "site" / "reference" / "training" / "index.html").read_text(encoding="utf-8")
    assert 'href="../data/#lcs_cvx.Trajectories"><code>' in training
    pages = [p.read_text(encoding="utf-8") for p in (tmp_path / "site").rglob("*.html")]
    assert not any("~lcs_cvx" in page for page in pages)
    assert not any("<autoref" in page for page in pages)  # every one resolved or dropped
    # the studies' result files a page names are on the site, and the names link to them
    assert (tmp_path / "site" / "results" / "control" / "cartpole_c3.md.html").is_file()
    solver = (tmp_path / "site" / "choosing-a-solver" / "index.html").read_text(encoding="utf-8")
    assert ('<a href="../results/solvers/authors_speed.md.html"><code>studies/results/solvers/authors_speed.md'
            in solver)


def test_sphinx_roles_become_optional_cross_references():
    """The hook turns ``:class:`~lcs_cvx.x.Name``` into a cross-reference showing ``Name`` (Sphinx's
    ``~``), a bare name into one to ``lcs_cvx.name``; mkdocs-autorefs resolves them afterwards."""
    sys.path.insert(0, str(ROOT / "docs" / "hooks"))
    try:
        import sphinx_roles
    finally:
        sys.path.pop(0)
    out = sphinx_roles.on_page_content(
        ":class:<code>~lcs_cvx.trajectories.Trajectories</code> and :func:<code>fit</code>; .. math:: x")
    assert out == ('<autoref identifier="lcs_cvx.trajectories.Trajectories" optional><code>Trajectories</code>'
                   '</autoref> and <autoref identifier="lcs_cvx.fit" optional><code>fit</code></autoref>; x')


# -- what the documents say -----------------------------------------------------------------------
def _documents() -> list[Path]:
    return [ROOT / "README.md", ROOT / "studies" / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def test_documents_do_not_narrate_their_making():
    hits = [
        f"{path.relative_to(ROOT)}:{n}: {line.strip()}"
        for path in _documents()
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if PROCESS_WORDS.search(line)
    ]
    assert not hits, "process wording in the documents:\n" + "\n".join(hits)


def test_readme_quick_start_and_commands():
    from lcs_cvx.cli import COMMANDS

    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 250
    quick = text.split("## Quick start", 1)[1].split("\n## ", 1)[0]
    commands = re.findall(r"^\s*(make \w+)\s*$", quick, flags=re.MULTILINE)
    assert commands == ["make demo", "make test"], commands
    for cmd in COMMANDS:
        assert f"`lcs-cvx {cmd.name}" in text, f"README: the CLI table lacks lcs-cvx {cmd.name}"
