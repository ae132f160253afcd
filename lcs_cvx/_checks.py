"""Input validation at the package boundary, and the package's errors and warnings.

Every public entry point converts its array arguments with :func:`as_batch` /
:func:`as_matrix` (:func:`as_transitions` for a batch of ``(x, u, x')``), so a wrong shape, a
non-finite value or a bad scalar is stopped with a :class:`LCSInputError` that names the
argument, what was expected and what was received. A solver that cannot verify its answer says
so: :class:`SolverError`, or a warning (:class:`FallbackWarning`, :class:`LayerAccuracyWarning`)
when another solver took over or the answer is reported inaccurate.
"""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np
import torch

__all__ = [
    "LCSInputError",
    "SolverError",
    "FallbackWarning",
    "LayerAccuracyWarning",
    "as_batch",
    "as_matrix",
    "as_transitions",
    "check_positive",
    "report_unconverged",
]


class LCSInputError(ValueError):
    """Bad input to an ``lcs_cvx`` function (shape, dtype, value or range)."""


class SolverError(RuntimeError):
    """A solver could not produce a verified solution."""


class FallbackWarning(RuntimeWarning):
    """The fast solver did not converge on some samples; a reference solver solved them."""


class PlanGapWarning(RuntimeWarning):
    """A controller's plan is not what its model does: the model's own rollout under the plan's
    inputs (``Plan.x_model``) ends far from the planned states (``Plan.x``)."""


class LayerAccuracyWarning(RuntimeWarning):
    """A cvxpylayers solve came back inaccurate (diffcp does not check its cone solver's status)."""


def report_unconverged(n_bad: int, total: int, what: str, max_iter: int, fallback: bool,
                       reference: str) -> None:
    """Say that ``n_bad`` of ``total`` samples did not converge in ``max_iter`` pivoting sweeps:
    a :class:`FallbackWarning` naming the ``reference`` that solves them instead if ``fallback``,
    else :class:`SolverError` (a silent fallback would hide the slower, less exact answers)."""
    msg = f"{what} pivoting did not converge on {n_bad} of {total} samples in {max_iter} sweeps"
    if not fallback:
        raise SolverError(msg)
    # stacklevel 3: the caller of the public solver that called this
    warnings.warn(f"{msg}; solved them with {reference}", FallbackWarning, stacklevel=3)


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
    # a finite sum proves every entry finite; only otherwise look closer
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


def as_transitions(model: Any, x: Any, u: Any, x_next: Any) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(x, u, x_next)`` as tensors of ``model``'s dtype and device, ``(N, n_x)``, ``(N, n_u)``,
    ``(N, n_x)``, with matching ``N`` (a 1-D input is one sample); ``model`` is an
    :class:`lcs_cvx.LCS` (its ``n_x``, ``n_u``, ``dtype``, ``device``)."""
    kw = {"dtype": model.dtype, "device": model.device}
    x = as_batch("x", x, model.n_x, **kw)
    u = as_batch("u", u, model.n_u, batch=x.shape[0], **kw)
    x_next = as_batch("x_next", x_next, model.n_x, batch=x.shape[0], **kw)
    return x, u, x_next


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


def check_number(name: str, value: Any, minimum: float | None = None) -> float:
    """``value`` as a float, or an :class:`lcs_cvx.LCSInputError` naming ``name``: a finite
    number (not a bool), ``>= minimum`` when given."""
    ok = not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)
    if not ok or (minimum is not None and value < minimum):
        bound = "" if minimum is None else f" >= {minimum:g}"
        raise LCSInputError(f"{name}: expected a finite number{bound}, received {value!r}")
    return float(value)


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


def as_held(name: str, value: Any, shape: tuple[int, ...]) -> torch.Tensor:
    """Values to hold (:meth:`lcs_cvx.LCS.hold`) as a CPU float64 tensor of exactly ``shape``:
    NaN where the entry is learned, finite elsewhere; or a clear error."""
    try:
        t = (value.detach().cpu() if isinstance(value, torch.Tensor)
             else torch.from_numpy(np.array(value, dtype=np.float64))).to(torch.float64)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise LCSInputError(f"{name}: expected an array of shape {tuple(shape)} (NaN where learned), "
                            f"received {type(value).__name__} {value!r}") from exc
    if tuple(t.shape) != tuple(shape):
        raise LCSInputError(f"{name}: expected an array of shape {tuple(shape)} (NaN where learned), "
                            f"received shape {tuple(t.shape)}")
    if bool(torch.isinf(t).any()):
        raise LCSInputError(f"{name}: expected finite values to hold (NaN where learned), received inf")
    return t


def as_pattern(name: str, value: Any, shape: tuple[int, ...]) -> torch.Tensor:
    """A mask pattern as a CPU bool tensor of exactly ``shape``, or a clear error."""
    if isinstance(value, torch.Tensor):
        t = value.detach().cpu()
    else:
        try:
            t = torch.from_numpy(np.array(value))
        except (TypeError, ValueError, RuntimeError) as exc:
            raise LCSInputError(
                f"{name}: expected a bool or 0/1 array of shape {tuple(shape)}, received "
                f"{type(value).__name__} {value!r}"
            ) from exc
    if tuple(t.shape) != tuple(shape):
        raise LCSInputError(
            f"{name}: expected a mask of shape {tuple(shape)}, received shape {tuple(t.shape)}"
        )
    if t.dtype == torch.bool:
        return t.clone()
    if t.is_complex() or not (t.is_floating_point() or t.dtype in (
            torch.uint8, torch.int8, torch.int16, torch.int32, torch.int64)):
        raise LCSInputError(f"{name}: expected a mask of bool or 0/1 values, received dtype {t.dtype}")
    bad = t[(t != 0) & (t != 1)]
    if bad.numel():
        shown = sorted({float(b) for b in bad.flatten()[:5].tolist()})
        raise LCSInputError(
            f"{name}: expected a mask of bool or 0/1 values, received {bad.numel()} other "
            f"values (e.g. {shown})"
        )
    return t != 0
