"""The package's layers: imports point one way (no cycle between the package's modules, counting
imports inside functions), no module reaches into another module's private names, every public
module declares ``__all__``, and the architecture list of the docs names every module once."""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "lcs_cvx"
ARCHITECTURE = ROOT / "docs" / "architecture.md"


def module_name(path: Path, package: Path) -> str:
    parts = list(path.relative_to(package.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def module_imports(package: Path) -> tuple[dict[str, set[str]], list[str]]:
    """Every module of ``package`` -> the package's modules it imports (at the top or inside a
    function), and the private names imported from another module (``module: name from other``)."""
    paths = {module_name(p, package): p for p in package.rglob("*.py")}
    edges: dict[str, set[str]] = {}
    private: list[str] = []
    for name, path in paths.items():
        base = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                deps |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    target = ".".join(base[: len(base) - node.level + 1] + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                for alias in node.names:
                    sub = f"{target}.{alias.name}"
                    if sub in paths:
                        deps.add(sub)
                        continue
                    deps.add(target)
                    dunder = alias.name.startswith("__") and alias.name.endswith("__")
                    if target in paths and alias.name.startswith("_") and not dunder:
                        private.append(f"{name}: {alias.name} from {target}")
        edges[name] = {d for d in deps if d in paths and d != name}
    return edges, private


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(edges[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return found


def test_the_checks_find_a_cycle_and_a_private_import(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("from .a import f\n")
    (pkg / "a.py").write_text("from .b import g\n\ndef f():\n    return g()\n")
    (pkg / "b.py").write_text("def g():\n    from .sub.c import _h\n    return _h()\n")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "c.py").write_text("def _h():\n    from .. import a\n    return a\n")
    edges, private = module_imports(pkg)
    assert cycles(edges) == [["pkg.a", "pkg.b", "pkg.sub.c"]]
    assert private == ["pkg.b: _h from pkg.sub.c"]
    (pkg / "sub" / "c.py").write_text("def h():\n    return 1\n")
    (pkg / "b.py").write_text("from .sub.c import h as g\n")
    edges, private = module_imports(pkg)
    assert cycles(edges) == [] and private == []


def test_no_import_cycle_between_the_package_modules():
    edges, _ = module_imports(PACKAGE)
    assert len(edges) > 40
    assert cycles(edges) == []


def test_no_module_imports_another_modules_private_names():
    _, private = module_imports(PACKAGE)
    assert private == []


def _public_modules() -> list[str]:
    names = [module_name(p, PACKAGE) for p in PACKAGE.rglob("*.py")]
    return sorted(n for n in names if not any(part.startswith("_") for part in n.split(".")))


@pytest.mark.parametrize("name", _public_modules())
def test_public_modules_declare_all(name):
    module = importlib.import_module(name)
    exported = getattr(module, "__all__", None)
    assert exported is not None, f"{name} has no __all__"
    missing = [n for n in exported if not hasattr(module, n)]
    assert not missing, f"{name}.__all__ names what the module lacks: {missing}"


def test_architecture_list_names_every_module_once():
    text = ARCHITECTURE.read_text(encoding="utf-8")
    listed = re.findall(r"^\s*- `([\w/]+\.py)`", text, flags=re.MULTILINE)
    files = sorted(str(p.relative_to(ROOT)) for p in PACKAGE.rglob("*.py"))
    assert sorted(listed) == sorted(set(listed)), "a module is listed twice"
    assert sorted(listed) == files, (
        f"not listed: {sorted(set(files) - set(listed))}; "
        f"listed but absent: {sorted(set(listed) - set(files))}"
    )
