r"""The LCP kernel: block pivoting on ``0 <= lam _|_ w = F lam + q >= 0`` (eq. (2)).

Each sweep solves ``F_II lam_I = -q_I`` (``lam_J = 0``) on the current free sets ``I`` for the
whole batch with one batched LU, and marks infeasible a free ``lam_i < 0`` or a bound
``w_i < 0`` (to a relative tolerance). :func:`solve` is the entry point on tensors; the
fallback of unconverged samples to a reference is the caller's (:mod:`lcs_cvx.lcp`).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch

from .arrays import ArrayOps, array_ops
from .pivoting import (
    STALL,
    PivotResult,
    block_pivoting,
    check_warm_start,
    initial_state,
    unconverged,
)
from .stacks import matrices

__all__ = ["PIVOT_TOL", "Pivoted", "pivot_lcp", "solve"]

#: Relative tolerance for feasibility of a pivoting candidate (scaled by ``1 + |q|_inf``).
PIVOT_TOL = 1e-11


class Pivoted(NamedTuple):
    """The kernel's answer for a batch of ``B`` LCPs of size ``n`` (tensors).

    Attributes:
        lam: ``(B, n)`` the solution of the last sweep, clamped at 0.
        w: ``(B, n)`` ``F lam + q``.
        free: ``(B, n)`` bool, the free set with ``lam_i > 0``.
        unconverged: int64 indices of the samples still infeasible after ``max_iter`` sweeps
            (their ``lam`` is not a solution), or None if every sample converged.
        iterations: pivoting sweeps made.
    """

    lam: torch.Tensor
    w: torch.Tensor
    free: torch.Tensor
    unconverged: torch.Tensor | None
    iterations: int


def pivot_lcp(xp: ArrayOps, F: Any, q: Any, tol: float, max_iter: int,
          warm_start: torch.Tensor | None, device: torch.device) -> PivotResult:
    """Block pivoting on the LCP in the kernel's arrays: ``F`` ``(n, n)`` (or a stack
    ``(K, n, n)``, :mod:`.stacks`), ``q`` ``(B, n)``; the initial free set is ``q < 0`` (the guess
    of ``lam = 0``) or ``warm_start``."""
    n = q.shape[1]
    mats = matrices(xp, F, q.shape[0])
    F_flat, FT = F.reshape(-1, n * n), xp.contiguous(F.swapaxes(-1, -2))
    data = xp.concat([q, -tol * (1.0 + xp.amax_abs(q))])  # one gather when the work set shrinks

    def solve(free: Any, idx: Any):
        d = data if idx is None else data[idx]
        on = mats.select(idx)
        qq, at = d[:, :n], d[:, n:]
        # F on the free rows and columns, the identity elsewhere: lam_I = -F_II^{-1} q_I
        lam, failed = on.solve(xp.free_block(on.rows(F_flat), free), xp.where(free, -qq, 0.0), spd=False)
        w = qq + on.rmul(lam, FT)
        bad = xp.where(free, lam < at, w < at)
        if failed is not None:
            bad |= failed[:, None]  # a singular F_II (not a P-matrix) is never trusted
        return lam, bad

    state0 = initial_state(xp, lambda: q < 0, tuple(q.shape), warm_start, device)
    return block_pivoting(xp, solve, state0, max_iter=max_iter)


def solve(F: torch.Tensor, q: torch.Tensor, *, tol: float = PIVOT_TOL, max_iter: int = 1000,
          warm_start: torch.Tensor | None = None, arrays: str = "auto") -> Pivoted:
    """Pivot the LCPs ``(F, q_t)`` for the rows of ``q`` ``(B, n)`` (``F`` ``(n, n)``, or a stack
    ``(K, n, n)`` whose models own ``B / K`` rows each, model-major; detached tensors) in the
    ``arrays`` back-end (:func:`lcs_cvx._kernels.arrays.array_ops`; one float64 CPU ``F`` runs
    the compiled kernel, :func:`lcs_cvx._kernels.compiled.lcp`, unless ``arrays`` names an array
    library)."""
    if arrays in ("auto", "compiled") and F.dim() == 2 and q.dtype == torch.float64 and q.is_cpu:
        from . import compiled

        warm = compiled.COLD
        if warm_start is not None:
            check_warm_start(warm_start, tuple(q.shape))
            warm = np.ascontiguousarray(warm_start.numpy())
        lam, w, free, bad, sweeps = compiled.lcp(np.ascontiguousarray(F.numpy()),
                                                 np.ascontiguousarray(q.numpy()), tol, max_iter,
                                                 STALL, warm)
        idx = torch.from_numpy(bad.astype(np.int64)) if len(bad) else None
        return Pivoted(torch.from_numpy(lam), torch.from_numpy(w), torch.from_numpy(free), idx, sweeps)
    xp = array_ops(q, arrays)
    with xp.threads():
        Fa, qa = xp.wrap(F), xp.wrap(q)
        res = pivot_lcp(xp, Fa, qa, tol, max_iter, warm_start, q.device)
        lam = xp.clamp_min(res.solution, 0.0)
        free = res.free & (res.solution > 0)
        w = matrices(xp, Fa, qa.shape[0]).select(None).rmul(lam, Fa.swapaxes(-1, -2)) + qa
        idx = unconverged(xp, res.converged)
    return Pivoted(xp.unwrap(lam), xp.unwrap(w), xp.unwrap(free), idx, res.iterations)
