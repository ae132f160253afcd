"""Where a physics study's numbers come from: the code (git commit and the library files changed
since), the machine and library versions, and the JSON form of the results."""

from __future__ import annotations

import os
import platform
import subprocess
from typing import Any

import numpy as np

__all__ = ["code_version", "machine", "json_default"]

_ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def code_version() -> dict[str, Any]:
    """The git commit the study ran on and the files of ``lcs_cvx/`` changed since (the fit
    recipes evolve: the results belong to this snapshot); None where git is not available."""

    def git(*args: str) -> str | None:
        try:
            out = subprocess.run(["git", "-C", _ROOT, *args], capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.SubprocessError):
            return None
        return out.stdout if out.returncode == 0 else None

    commit = git("rev-parse", "--short", "HEAD")
    dirty = git("status", "--porcelain", "--", "lcs_cvx")  # lines "XY path"
    return {"commit": None if commit is None else commit.strip(),
            "lcs_cvx_changed": None if dirty is None else [ln[3:] for ln in dirty.splitlines() if ln]}


def machine() -> str:
    """Architecture, CPUs and the versions of Python, torch and MuJoCo, in one line."""
    import mujoco
    import torch

    return (f"{platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, "
            f"torch {torch.__version__}, mujoco {mujoco.__version__}")


def json_default(o: Any) -> Any:
    """``json.dump``'s ``default``: numpy arrays and scalars as Python values."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")
