"""Input validation at the package boundary.

Every public entry point converts its array arguments with :func:`as_batch` /
:func:`as_matrix`, so a wrong shape, a non-finite value or a bad scalar is
stopped with a :class:`LCSInputError` that names the argument, what was
expected and what was received.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

__all__ = ["LCSInputError", "SolverError", "as_batch", "as_matrix", "check_positive"]


class LCSInputError(ValueError):
    """Bad input to an ``lcs_cvx`` function (shape, dtype, value or range)."""


class SolverError(RuntimeError):
    """A solver could not produce a verified solution."""


def _describe(value: Any) -> str:
    if isinstance(value, torch.Tensor):
        return f"tensor of shape {tuple(value.shape)} and dtype {value.dtype}"
    if isinstance(value, np.ndarray):
        return f"array of shape {value.shape} and dtype {value.dtype}"
    return f"{type(value).__name__} {value!r}"


def _to_tensor(name: str, value: Any, dtype: torch.dtype, device: torch.device | None) -> torch.Tensor:
    if isinstance(value, torch.Tensor):
        t = value
    else:
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise LCSInputError(
                f"{name}: expected a real array, received {_describe(value)}"
            ) from exc
        t = torch.from_numpy(arr)
    if t.is_complex() or t.dtype == torch.bool:
        raise LCSInputError(f"{name}: expected a real floating array, received {_describe(value)}")
    if not t.is_floating_point():
        t = t.to(torch.float64)
    if isinstance(value, torch.Tensor) and t.dtype != dtype:
        raise LCSInputError(
            f"{name}: expected dtype {dtype} (the model's), received {t.dtype}; "
            f"convert with .to({dtype})"
        )
    t = t.to(dtype=dtype, device=device)
    # a finite sum proves every entry finite (one reduction); only otherwise look closer
    if not math.isfinite(float(t.detach().sum())) and not bool(torch.isfinite(t).all()):
        bad = int((~torch.isfinite(t)).sum())
        raise LCSInputError(f"{name}: expected finite values, received {bad} NaN/inf entries")
    return t


def as_batch(
    name: str,
    value: Any,
    n: int,
    *,
    dtype: torch.dtype = torch.float64,
    device: torch.device | None = None,
    batch: int | None = None,
) -> torch.Tensor:
    """Return ``value`` as a ``(N, n)`` tensor; a 1-D input of length ``n`` is one sample.

    Raises :class:`LCSInputError` naming ``name`` when the shape, dtype or values are wrong;
    ``batch`` (if given) is the required ``N``.
    """
    t = _to_tensor(name, value, dtype, device)
    received = tuple(t.shape)
    if t.dim() == 1:
        t = t.unsqueeze(0)
    if t.dim() != 2 or t.shape[1] != n:
        raise LCSInputError(
            f"{name}: expected shape (N, {n}) or ({n},), received shape {received}"
        )
    if batch is not None and t.shape[0] != batch:
        raise LCSInputError(
            f"{name}: expected {batch} rows to match the other inputs, received {t.shape[0]}"
        )
    return t


def as_matrix(
    name: str,
    value: Any,
    shape: tuple[int, ...],
    *,
    dtype: torch.dtype = torch.float64,
    device: torch.device | None = None,
) -> torch.Tensor:
    """Return ``value`` as a tensor of exactly ``shape`` (a vector may be given as ``(n,)``)."""
    t = _to_tensor(name, value, dtype, device)
    if tuple(t.shape) != tuple(shape):
        raise LCSInputError(f"{name}: expected shape {tuple(shape)}, received {tuple(t.shape)}")
    return t


def check_positive(name: str, value: Any, *, integer: bool = False, upper: float | None = None) -> Any:
    """Check a positive scalar (``integer`` for counts); return it unchanged."""
    if integer:
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise LCSInputError(f"{name}: expected an integer >= 1, received {value!r}")
        return int(value)
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise LCSInputError(f"{name}: expected a positive number, received {value!r}")
    if not math.isfinite(float(value)) or value <= 0:
        raise LCSInputError(f"{name}: expected a finite number > 0, received {value!r}")
    if upper is not None and value >= upper:
        raise LCSInputError(f"{name}: expected a number < {upper:.6g}, received {value!r}")
    return float(value)
