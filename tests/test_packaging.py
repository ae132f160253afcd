"""The package's declared dependencies, and that importing it needs none of the extras.

The core dependencies are the solver stack (numba for the compiled loss kernels); Dask,
matplotlib, MuJoCo, PARC (pyparc) and the solver study's extra solvers come with the extras
``studies``, ``physics``, ``baselines`` and ``solvers`` and are imported only by the functions
that need them, which name the extra when it is missing.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())

CORE = {"torch", "numpy", "scipy", "cvxpy", "cvxpylayers", "clarabel", "diffcp", "threadpoolctl",
        "tqdm", "numba"}
EXTRAS = {
    "studies": {"dask", "matplotlib"},
    "plot": {"matplotlib", "tensorboard"},
    "logs": {"mcap", "mcap-ros2-support", "h5py", "pyarrow"},
    "physics": {"mujoco"},
    "docs": {"mkdocs-material", "mkdocstrings"},
    "dev": {"pytest", "hypothesis", "ruff", "pytest-timeout", "pytest-xdist"},
    "baselines": {"pyparc", "pypoman", "pycddlib", "mip", "faiss-cpu", "scikit-learn"},
    "control": {"pyscipopt"},
    "solvers": {"piqp", "proxsuite", "daqp", "ecos", "casadi"},
}
# (not pyscipopt, the control extra's SCIP: CVXPY itself imports every solver it finds installed)
OPTIONAL_MODULES = ("dask", "distributed", "mujoco", "matplotlib", "pyparc", "sklearn", "faiss",
                    "mip", "pypoman", "cdd", "casadi", "qpth", "pydrake", "tensorboard", "mcap",
                    "mcap_ros2", "h5py", "pyarrow")


def _name(requirement: str) -> str:
    """The distribution name of a PEP 508 requirement (``"dask[distributed]>=2024.1"`` ->
    ``"dask"``)."""
    match = re.match(r"[A-Za-z0-9][A-Za-z0-9._-]*", requirement.strip())
    assert match is not None, f"requirement {requirement!r} has no name"
    return match.group(0).lower()


def test_core_dependencies_are_the_solver_stack():
    names = [_name(r) for r in PYPROJECT["project"]["dependencies"]]
    assert sorted(names) == sorted(CORE)


def test_extras_hold_the_rest():
    extras = PYPROJECT["project"]["optional-dependencies"]
    assert {k: {_name(r) for r in v} for k, v in extras.items()} == EXTRAS
    assert any(r.startswith("dask[distributed]") for r in extras["studies"])
    assert any(r.startswith("mkdocstrings[python]") for r in extras["docs"])


def test_license_is_an_spdx_expression():
    # a table ({text = ...}) is deprecated by setuptools in favour of an SPDX string
    assert PYPROJECT["project"]["license"] == "MIT"


# every module of the package: what --doctest-modules imports to collect the examples
EVERY_MODULE = (
    "import lcs_cvx, pkgutil, importlib\n"
    "for m in pkgutil.walk_packages(lcs_cvx.__path__, 'lcs_cvx.'):\n"
    "    if not m.name.endswith('__main__'):\n"
    "        importlib.import_module(m.name)"
)


@pytest.mark.parametrize("module", ["lcs_cvx", "lcs_cvx.cli", "lcs_cvx.study", "every module"])
def test_import_loads_no_optional_dependency(module):
    """In a fresh interpreter, importing the package (and its command line, its studies, every
    module) leaves Dask, distributed, MuJoCo, matplotlib and PARC's stack unimported."""
    code = (
        "import json, sys\n"
        + (EVERY_MODULE if module == "every module" else f"import {module}") + "\n"
        + f"print(json.dumps(sorted({{m.split('.')[0] for m in sys.modules}} & {set(OPTIONAL_MODULES)!r})))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         check=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []


def test_public_subpackages_are_reached_from_the_package():
    """After a bare ``import lcs_cvx``, ``lcs_cvx.datasets.cube_tosses()`` (and the other public
    subpackages) work without importing them by name, and reaching them imports no optional
    dependency; a name that is not there is still an AttributeError."""
    code = (
        "import json, sys, lcs_cvx\n"
        "n = len(lcs_cvx.datasets.cube_tosses())\n"
        "names = [lcs_cvx.control.C3.__name__, lcs_cvx.study.__name__, lcs_cvx.cli.__name__,\n"
        "         lcs_cvx.bench.__name__]\n"
        "try:\n    lcs_cvx.no_such_name\n    missing = False\nexcept AttributeError:\n    missing = True\n"
        f"opt = sorted({{m.split('.')[0] for m in sys.modules}} & {set(OPTIONAL_MODULES)!r})\n"
        "print(json.dumps([n, names, missing, 'datasets' in dir(lcs_cvx), opt]))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         check=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    n, names, missing, listed, optional = json.loads(out.stdout.strip().splitlines()[-1])
    assert n == 550 and names == ["C3", "lcs_cvx.study", "lcs_cvx.cli", "lcs_cvx.bench"]
    assert missing and listed and optional == []


def test_dask_scheduler_without_dask_names_the_extra(monkeypatch):
    from lcs_cvx.study.executors import dask_cluster

    monkeypatch.setitem(sys.modules, "dask.distributed", None)  # as if not installed
    with pytest.raises(ModuleNotFoundError, match=re.escape(
            "lcs-cvx study run --scheduler needs dask")) as info:
        with dask_cluster([], "local", 1):
            pass
    assert "pip install 'lcs_cvx[studies]'" in str(info.value)


def test_report_figures_without_matplotlib_name_the_extra(monkeypatch):
    from lcs_cvx.study.report import plot

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # as if not installed
    with pytest.raises(ModuleNotFoundError, match=re.escape(
            "lcs-cvx study report (the figures) needs matplotlib")) as info:
        plot({}, {}, "unused")
    assert "pip install 'lcs_cvx[studies]'" in str(info.value)
