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

from collections.abc import Callable
from dataclasses import dataclass

import torch

__all__ = ["PivotResult", "block_pivoting"]

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

    Returns:
        :class:`PivotResult`. Converged samples are not re-solved after they converge.
    """
    free = free0.clone()
    B, k = free.shape
    device = free.device
    solution, bad = solve(free, None)
    solution = solution.clone()
    n_bad = bad.sum(dim=1)
    best = n_bad.clone()
    stalled = torch.zeros(B, dtype=torch.long, device=device)
    weights = torch.arange(1, k + 1, device=device)
    active = torch.arange(B, device=device)
    sweeps = 0
    while sweeps < max_iter:
        todo = n_bad > 0
        if not bool(todo.any()):
            break
        if not bool(todo.all()):  # drop converged samples from the work set
            keep = todo.nonzero().squeeze(1)
            active, bad, n_bad = active[keep], bad[keep], n_bad[keep]
            best, stalled = best[keep], stalled[keep]
        # Murty's rule (largest infeasible index) for stalled samples, block flips otherwise.
        last = torch.argmax(bad.long() * weights, dim=1)
        single = torch.nn.functional.one_hot(last, k).bool()
        flip = torch.where((stalled >= stall)[:, None], single & bad, bad)
        free_act = free[active] ^ flip
        free[active] = free_act
        full = active.numel() == B
        sol, bad = solve(free_act, None if full else active)
        if full:
            solution = sol
        else:
            solution[active] = sol
        sweeps += 1
        n_bad = bad.sum(dim=1)
        improved = n_bad < best
        best = torch.minimum(best, n_bad)
        stalled = torch.where(improved, torch.zeros_like(stalled), stalled + 1)
    converged = torch.ones(B, dtype=torch.bool, device=device)
    converged[active[n_bad > 0]] = False
    return PivotResult(solution=solution, free=free, converged=converged, iterations=sweeps)
