"""Imports of the optional dependencies (the extras of ``pyproject.toml``).

``import lcs_cvx`` imports none of them; a function that needs one imports it through
:func:`require` when called, and a missing one is reported with the extra that installs it.
"""

from __future__ import annotations

import importlib
from types import ModuleType

__all__ = ["require"]


def require(module: str, extra: str, purpose: str) -> ModuleType:
    """Import and return ``module`` (e.g. ``"dask.distributed"``), the dependency of ``purpose``
    installed by the extra ``extra`` of ``lcs_cvx``.

    Raises:
        ModuleNotFoundError: ``module`` cannot be imported; the message names ``purpose`` and
            the ``pip install 'lcs_cvx[extra]'`` that installs it.
    """
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        top = module.split(".")[0]
        raise ModuleNotFoundError(
            f"{purpose} needs {top} ({module} could not be imported: {exc}): "
            f"pip install 'lcs_cvx[{extra}]'",
            name=module,
        ) from exc
