"""Batched block principal pivoting: the active-set engine behind both fast kernels.

Both per-sample problems of the paper reduce to a linear complementarity problem with a
P-matrix: the LCP of eq. (2) itself, and the KKT system of the strongly convex
violation QP (eq. (9b)), whose Hessian is positive definite (Lemma 3a).
For a P-matrix LCP ``0 <= z  _|_  M z + p >= 0`` every guess of the *free set* I
(``z_I`` free, ``z_J = 0``) gives one linear solve, and the guess is right iff the
result is feasible. Block principal pivoting (Judice & Pires, 1994) flips every
infeasible index at once; when that stops reducing the number of infeasibilities it
falls back to Murty's single pivot on the largest infeasible index, which terminates
for every P-matrix (Murty, 1974). The result is the exact active-set solution, to
round-off, not an approximate one.

The driver is problem-agnostic: a ``solve(free, idx)`` callback returns the solution of
the linear system for the given free sets and a mask of infeasible indices; it works
on a whole batch at once and only re-solves the samples that have not converged.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from .._checks import LCSInputError
from .arrays import ArrayOps

__all__ = ["STALL", "PivotResult", "SolveFn", "block_pivoting", "check_warm_start", "initial_state",
           "unconverged"]


#: Sweeps without a new lowest infeasibility count before a sample switches to Murty's single
#: pivot (:func:`block_pivoting`'s ``stall``; also the compiled kernels', :mod:`.compiled`).
STALL = 3


def check_warm_start(warm_start: Any, shape: tuple[int, ...]) -> None:
    """A clear error unless ``warm_start`` is a bool tensor of ``shape`` (the active sets of an
    earlier solve of the same samples, ``LossInfo.active``)."""
    if not isinstance(warm_start, torch.Tensor) or warm_start.dtype != torch.bool \
            or tuple(warm_start.shape) != tuple(shape):
        got = (f"{warm_start.dtype} tensor of shape {tuple(warm_start.shape)}"
               if isinstance(warm_start, torch.Tensor) else type(warm_start).__name__)
        raise LCSInputError(
            f"warm_start: expected a bool tensor of shape {tuple(shape)} (the active sets of "
            f"an earlier solve of these samples, LossInfo.active), received {got}"
        )


def initial_state(xp: ArrayOps, cold: Callable[[], Any], shape: tuple[int, ...],
                  warm_start: torch.Tensor | None, device: torch.device) -> Any:
    """The pivoting's starting state (a kernel array for ``device``, ``shape``): ``warm_start``
    where given (checked to be a bool tensor of ``shape``), else the cold guess ``cold()``."""
    if warm_start is None:
        return cold()
    check_warm_start(warm_start, shape)
    return xp.wrap(warm_start.to(device))


#: ``solve(free, idx) -> (solution, infeasible)``; ``idx`` selects samples (None: all).
SolveFn = Callable[[Any, Any], tuple[Any, Any]]


@dataclass(frozen=True)
class PivotResult:
    """Outcome of :func:`block_pivoting` for a batch of ``B`` problems (kernel arrays).

    Attributes:
        solution: ``(B, ...)`` solution of the last linear solve of each sample.
        free: ``(B, k)`` bool, the final free set.
        converged: ``(B,)`` bool, True where no index is infeasible.
        iterations: number of pivoting sweeps made.
    """

    solution: Any
    free: Any
    converged: Any
    iterations: int


def block_pivoting(
    xp: ArrayOps,
    solve: SolveFn,
    free0: Any,
    *,
    max_iter: int = 100,
    stall: int = STALL,
    subset_fraction: float | None = None,
    subset_min_work: int | None = None,
) -> PivotResult:
    """Run block principal pivoting with Murty's fallback on a batch.

    Args:
        xp: the array operations (:func:`lcs_cvx._kernels.arrays.array_ops`) of ``free0`` and
            of ``solve``'s arrays.
        solve: callback ``solve(free, idx)``; ``free`` is ``(b, k)`` bool for the samples
            ``idx`` (an int64 index array, or None for the whole batch). Returns the
            ``(b, ...)`` solution and a ``(b, k)`` bool mask of infeasible indices.
        free0: ``(B, k)`` bool initial guess of the free set.
        max_iter: sweeps before giving up on the remaining samples (they come back with
            ``converged = False``; callers fall back to a reference solver).
        stall: sweeps without a new lowest infeasibility count before a sample switches
            to single (Murty) pivots.
        subset_fraction: once at most this fraction of the work set is unconverged, the work
            set shrinks to those samples (a converged sample re-solved with its unchanged free
            set gives the same answer, so shrinking is only a saving, not a correctness matter;
            default: the back-end's :attr:`ArrayOps.subset_fraction`).
        subset_min_work: ... and only when the work set is this large (``size * k * k``): on
            small batches one more indexing pass can cost more than the solves it saves
            (default: the back-end's :attr:`ArrayOps.subset_min_work`).

    Returns:
        :class:`PivotResult`.
    """
    if subset_fraction is None:
        subset_fraction = xp.subset_fraction
    if subset_min_work is None:
        subset_min_work = xp.subset_min_work
    free = xp.copy(free0)
    B, k = free.shape
    solution, bad = solve(free, None)
    active = None  # None: the whole batch is the work set
    n_bad = xp.count_rows(bad)
    best = xp.copy(n_bad)
    stalled = n_bad * 0
    columns = xp.arange(k, free)
    sweeps = 0
    while sweeps < max_iter:
        n_todo = xp.count(n_bad)
        if n_todo == 0:
            break
        size = B if active is None else active.shape[0]
        if size * k * k >= subset_min_work and n_todo <= subset_fraction * size:
            keep = xp.flatnonzero(n_bad > 0)
            active = keep if active is None else active[keep]
            bad, n_bad, best, stalled = bad[keep], n_bad[keep], best[keep], stalled[keep]
        flip = bad
        if sweeps >= stall:  # Murty's rule (largest infeasible index) for stalled samples
            last = xp.argmax(xp.where(bad, columns, -1))
            single = (columns == last[:, None]) & bad
            flip = xp.where((stalled >= stall)[:, None], single, bad)
        if active is None:
            free ^= flip
            solution, bad = solve(free, None)
        else:
            free_act = free[active] ^ flip
            free[active] = free_act
            sol, bad = solve(free_act, active)
            solution[active] = sol
        sweeps += 1
        n_bad = xp.count_rows(bad)
        improved = n_bad < best
        best = xp.minimum(best, n_bad)
        stalled = xp.where(improved, 0, stalled + 1)
    converged = n_bad == 0
    if active is not None:  # the samples outside the work set had converged
        converged_all = xp.ones_bool(B, free)
        converged_all[active] = converged
        converged = converged_all
    return PivotResult(solution=solution, free=free, converged=converged, iterations=sweeps)


def unconverged(xp: ArrayOps, converged: Any) -> torch.Tensor | None:
    """Indices (an int64 tensor) of the samples that did not converge (``converged``, the
    ``(B,)`` bool kernel array of :class:`PivotResult`, is False), or None if all did -- checked
    in the kernel's arrays, so that the common case costs no tensor operation."""
    if bool(converged.all()):
        return None
    return xp.unwrap(xp.flatnonzero(~converged))
