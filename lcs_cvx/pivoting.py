"""Batched block principal pivoting: the active-set engine behind both fast kernels.

Both per-sample problems of the paper reduce to a linear complementarity problem with a
P-matrix: the LCP of eq. (equ.lcp) itself, and the KKT system of the strongly convex
violation QP (eq. equ.contactnet.2), whose Hessian is positive definite (Lemma 3a).
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

import warnings
from collections.abc import Callable
from dataclasses import dataclass

import torch

from ._checks import LCSInputError, SolverError

__all__ = [
    "PivotResult", "block_pivoting", "unconverged", "initial_state", "spd_solve", "FallbackWarning",
    "SMALL_N",
]


class FallbackWarning(RuntimeWarning):
    """The fast solver did not converge on some samples; the reference solved them."""


#: Up to this size a batch of linear solves is one LAPACK LU call (``linalg.solve_ex``), which
#: is 2-3x faster than Cholesky plus ``cholesky_solve`` on CPU for tiny matrices; above it,
#: Cholesky and two triangular solves (half the flops).
SMALL_N = 6


def initial_state(guess: torch.Tensor, warm_start: torch.Tensor | None) -> torch.Tensor:
    """The pivoting's starting state: ``warm_start`` where given (checked to be a bool tensor of
    ``guess``'s shape), else the cold ``guess``."""
    if warm_start is None:
        return guess
    if not isinstance(warm_start, torch.Tensor) or warm_start.dtype != torch.bool \
            or warm_start.shape != guess.shape:
        got = (f"{warm_start.dtype} tensor of shape {tuple(warm_start.shape)}"
               if isinstance(warm_start, torch.Tensor) else type(warm_start).__name__)
        raise LCSInputError(
            f"warm_start: expected a bool tensor of shape {tuple(guess.shape)} (the active sets of "
            f"an earlier solve of these samples, LossInfo.active), received {got}"
        )
    return warm_start.to(guess.device)


def spd_solve(M: torch.Tensor, rhs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Solve the batch of symmetric positive definite systems ``M x = rhs``.

    Args:
        M: ``(B, n, n)``; rhs: ``(B, n)``.

    Returns:
        ``x`` ``(B, n)`` and a ``(B,)`` bool mask of the systems whose factorisation failed
        (not positive definite to working precision, or singular), or None if none did.
    """
    if M.shape[-1] <= SMALL_N:
        x, info = torch.linalg.solve_ex(M, rhs.unsqueeze(-1))
    else:
        chol, info = torch.linalg.cholesky_ex(M)
        y = torch.linalg.solve_triangular(chol, rhs.unsqueeze(-1), upper=False)
        x = torch.linalg.solve_triangular(chol.mT, y, upper=True)
    return x.squeeze(-1), (info != 0 if bool(info.any()) else None)

#: ``solve(free, idx) -> (solution, infeasible)``; ``idx`` selects samples (None: all).
SolveFn = Callable[[torch.Tensor, torch.Tensor | None], tuple[torch.Tensor, torch.Tensor]]


@dataclass(frozen=True)
class PivotResult:
    """Outcome of :func:`block_pivoting` for a batch of ``B`` problems.

    Attributes:
        solution: ``(B, ...)`` solution of the last linear solve of each sample.
        free: ``(B, k)`` bool, the final free set.
        converged: ``(B,)`` bool, True where no index is infeasible.
        iterations: number of pivoting sweeps made.
    """

    solution: torch.Tensor
    free: torch.Tensor
    converged: torch.Tensor
    iterations: int


def block_pivoting(
    solve: SolveFn,
    free0: torch.Tensor,
    *,
    max_iter: int = 100,
    stall: int = 3,
    subset_fraction: float = 0.25,
    subset_min_work: int = 65_536,
) -> PivotResult:
    """Run block principal pivoting with Murty's fallback on a batch.

    Args:
        solve: callback ``solve(free, idx)``; ``free`` is ``(b, k)`` bool for the samples
            ``idx`` (a LongTensor, or None for the whole batch). Returns the ``(b, ...)``
            solution and a ``(b, k)`` bool mask of infeasible indices.
        free0: ``(B, k)`` bool initial guess of the free set.
        max_iter: sweeps before giving up on the remaining samples (they come back with
            ``converged = False``; callers fall back to a reference solver).
        stall: sweeps without a new lowest infeasibility count before a sample switches
            to single (Murty) pivots.
        subset_fraction: once at most this fraction of the work set is unconverged, the work
            set shrinks to those samples (a converged sample re-solved with its unchanged free
            set gives the same answer, so shrinking is only a saving, not a correctness matter).

    Returns:
        :class:`PivotResult`.
    """
    free = free0.clone()
    B, k = free.shape
    device = free.device
    solution, bad = solve(free, None)
    active: torch.Tensor | None = None  # None: the whole batch is the work set
    n_bad = bad.sum(dim=1)
    best = n_bad.clone()
    stalled = torch.zeros_like(n_bad)
    weights = torch.arange(1, k + 1, device=device)
    sweeps = 0
    while sweeps < max_iter:
        todo = n_bad > 0
        n_todo = int(todo.sum())
        if n_todo == 0:
            break
        size = B if active is None else active.numel()
        if size * k * k >= subset_min_work and n_todo <= subset_fraction * size:
            keep = todo.nonzero().squeeze(1)
            active = keep if active is None else active[keep]
            bad, n_bad, best, stalled = bad[keep], n_bad[keep], best[keep], stalled[keep]
        flip = bad
        if sweeps >= stall:  # Murty's rule (largest infeasible index) for stalled samples
            last = torch.argmax(bad.long() * weights, dim=1, keepdim=True)
            single = torch.zeros_like(bad).scatter_(1, last, True) & bad
            flip = torch.where((stalled >= stall)[:, None], single, bad)
        if active is None:
            free ^= flip
            solution, bad = solve(free, None)
        else:
            free_act = free[active] ^ flip
            free[active] = free_act
            sol, bad = solve(free_act, active)
            solution[active] = sol
        sweeps += 1
        n_bad = bad.sum(dim=1)
        improved = n_bad < best
        best = torch.minimum(best, n_bad)
        stalled = torch.where(improved, 0, stalled + 1)
    converged = torch.ones(B, dtype=torch.bool, device=device)
    failed = n_bad > 0
    converged[failed if active is None else active[failed]] = False
    return PivotResult(solution=solution, free=free, converged=converged, iterations=sweeps)


def unconverged(res: PivotResult, what: str, max_iter: int, fallback: bool,
                reference: str = "the Clarabel reference") -> torch.Tensor | None:
    """Indices of the samples ``res`` did not converge on (None if all did), after saying so:
    a :class:`FallbackWarning` if ``fallback`` (the caller then solves them with ``reference``),
    else :class:`lcs_cvx.SolverError`."""
    if bool(res.converged.all()):
        return None
    idx = (~res.converged).nonzero().squeeze(1)
    msg = (f"{what} pivoting did not converge on {idx.numel()} of {res.converged.numel()} "
           f"samples in {max_iter} sweeps")
    if not fallback:
        raise SolverError(msg)
    warnings.warn(f"{msg}; solved them with {reference}", FallbackWarning, stacklevel=3)
    return idx
