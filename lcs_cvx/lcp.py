r"""Exact batched solution of the LCP of eq. (equ.lcp): ``0 <= lam _|_ F lam + q >= 0``.

Three solvers, one answer (Assumption 1, ``F + F^T > 0``, makes it unique):

- ``"fast"``: batched block principal pivoting (:mod:`lcs_cvx.pivoting`) on the free set
  ``I = {i : lam_i > 0}``; each sweep solves ``F_II lam_I = -q_I`` for the whole batch with
  one batched LU. The converged free set gives the exact active-set solution. A sample that
  does not converge is re-solved with the reference and reported (warning + counter).
- ``"cvxpy"``: the declared problem (P) (:func:`lcs_cvx.problems.convex_lcp_problem`)
  solved with Clarabel, one sample at a time -- the reference.
- ``"brute"``: enumeration of all ``2^n`` active sets -- for tests, ``n <= 12``.

The fast solve also provides :func:`active_set_solve`: given the free set, ``lam`` as a
differentiable function of ``(F, q)`` -- the implicit-function-theorem map of Lemma 1.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ._checks import LCSInputError, as_batch, as_matrix
from .pivoting import (
    ArrayOps,
    FallbackWarning,
    PivotResult,
    array_ops,
    block_pivoting,
    initial_state,
    unconverged,
)
from .problems import convex_lcp_problem

__all__ = [
    "LCPSolution",
    "solve_lcp",
    "solve_lcp_fast",
    "solve_lcp_brute",
    "active_set_solve",
    "free_set_matrix",
    "lcp_residual",
    "FallbackWarning",
]

#: Up to this ``n`` an unconverged sample falls back to enumerating its ``2^n`` free sets.
BRUTE_MAX = 12

#: Relative tolerance for feasibility of a pivoting candidate (scaled by ``1 + |q|_inf``).
PIVOT_TOL = 1e-11


@dataclass(frozen=True)
class LCPSolution:
    """Solution of a batch of LCPs.

    Attributes:
        lam: ``(B, n)`` the solution.
        w: ``(B, n)`` ``F lam + q``.
        free: ``(B, n)`` bool, the free set (``lam_i`` determined by ``w_i = 0``).
        iterations: pivoting sweeps (0 for the reference solvers).
        n_fallback: samples the fast solver handed to the reference.
        residual: ``(B,)`` relative LCP residual (:func:`lcp_residual`).
    """

    lam: torch.Tensor
    w: torch.Tensor
    free: torch.Tensor
    iterations: int
    n_fallback: int
    residual: torch.Tensor


def lcp_residual(F: torch.Tensor, q: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """Relative violation of the LCP conditions, per sample ``(B,)``.

    The natural residual ``|min(lam, w)|_inf / (1 + |q|_inf)`` with ``w = F lam + q``: zero
    exactly at the solution, and it bounds the violation of ``lam >= 0``, ``w >= 0`` and of
    complementarity (``min(lam_i, w_i) = 0``).
    """
    w = lam @ F.mT + q
    return torch.minimum(lam, w).abs().amax(-1) / (1.0 + q.abs().amax(-1))


def free_set_matrix(F: torch.Tensor, free: torch.Tensor) -> torch.Tensor:
    """``(B, n, n)``: ``F`` (``(n, n)`` or ``(B, n, n)``) on the rows and columns of the free sets
    ``free`` ``(B, n)``, the identity elsewhere -- the matrix of ``lam_I = -F_II^{-1} q_I`` with
    ``lam_J = 0``. Differentiable in ``F``; the kernels' :meth:`ArrayOps.free_block`."""
    n = F.shape[-1]
    return array_ops(F, "torch").free_block(F.reshape(-1, n * n), free)


def active_set_solve(F: torch.Tensor, q: torch.Tensor, free: torch.Tensor) -> torch.Tensor:
    """``lam`` with ``lam_J = 0`` and ``(F lam + q)_I = 0`` for the free sets ``free`` ``(B, n)``.

    Differentiable in ``F`` ``(n, n)`` or ``(B, n, n)`` and ``q`` ``(B, n)``: for the correct
    free set this is the implicit function of Lemma 1 (a non-strictly-complementary index is
    treated as not free, i.e. ``lam_i`` held at 0 -- a one-sided derivative).
    """
    rhs = torch.where(free, -q, 0.0).unsqueeze(-1)
    return torch.linalg.solve(free_set_matrix(F, free), rhs).squeeze(-1)


def _initial_free(q: Any) -> Any:
    return q < 0


def _pivot(xp: ArrayOps, F: Any, q: Any, tol: float, max_iter: int,
           warm_start: torch.Tensor | None, device: torch.device) -> PivotResult:
    """Block pivoting on the LCP in the kernel's arrays."""
    n = q.shape[1]
    F_flat, FT = F.reshape(1, n * n), xp.contiguous(F.T)
    data = xp.concat([q, -tol * (1.0 + xp.amax_abs(q))])  # one gather when the work set shrinks

    def solve(free: Any, idx: Any):
        d = data if idx is None else data[idx]
        qq, at = d[:, :n], d[:, n:]
        # F on the free rows and columns, the identity elsewhere: lam_I = -F_II^{-1} q_I
        lam, failed = xp.solve(xp.free_block(F_flat, free), xp.where(free, -qq, 0.0), spd=False)
        w = qq + lam @ FT
        bad = xp.where(free, lam < at, w < at)
        if failed is not None:
            bad |= failed[:, None]  # a singular F_II (not a P-matrix) is never trusted
        return lam, bad

    state0 = initial_state(xp, _initial_free(q), warm_start, device)
    return block_pivoting(xp, solve, state0, max_iter=max_iter)


def solve_lcp_fast(
    F: torch.Tensor,
    q: torch.Tensor,
    *,
    max_iter: int = 1000,
    tol: float = PIVOT_TOL,
    fallback: bool = True,
    warm_start: torch.Tensor | None = None,
    backend: str = "auto",
) -> LCPSolution:
    """Solve ``0 <= lam _|_ F lam + q >= 0`` for a batch by block principal pivoting.

    Args:
        F: ``(n, n)`` with ``F + F^T > 0`` (not checked here; :class:`lcs_cvx.LCS` ensures it).
        q: ``(B, n)``.
        max_iter: pivoting sweeps before the remaining samples fall back. Murty's rule ends
            on every P-matrix, but it can take hundreds of sweeps on nearly skew-symmetric
            ``F`` (Fig. 1(c)'s ``G = 0``, ``s = 1e-5``: 224 for the slowest of 50,000 samples).
        tol: relative feasibility tolerance of a candidate free set.
        fallback: re-solve unconverged samples (and warn) -- by enumeration of the ``2^n``
            free sets for ``n <= BRUTE_MAX`` (exact), else with the Clarabel reference; if
            False, raise :class:`SolverError` instead.
        warm_start: ``(B, n)`` bool first guess of the free sets, e.g. ``free`` of an earlier
            solve of the same samples (default: ``q < 0``, the guess of ``lam = 0``). The
            solution is unique (Assumption 1) and does not depend on it; the sweeps do.
        backend: the kernel's arrays (:func:`lcs_cvx.pivoting.array_ops`): ``"auto"`` (NumPy
            for CPU tensors, torch otherwise), ``"numpy"`` or ``"torch"``.

    Returns:
        :class:`LCPSolution` (no autograd graph; see :func:`active_set_solve`).
    """
    with torch.no_grad():
        F = F.detach()
        q = q.detach()
        n = q.shape[1]
        xp = array_ops(q, backend)
        with xp.threads():
            res = _pivot(xp, xp.wrap(F), xp.wrap(q), tol, max_iter, warm_start, q.device)
        solution = xp.unwrap(res.solution)
        lam = solution.clamp(min=0.0)
        free = xp.unwrap(res.free) & (solution > 0)
        brute = n <= BRUTE_MAX
        bad_idx = unconverged(xp, res.converged, "LCP", max_iter, fallback,
                              f"enumeration of the 2^{n} free sets" if brute else "the Clarabel reference")
        n_fb = 0 if bad_idx is None else int(bad_idx.numel())
        if bad_idx is not None and brute:
            ref = solve_lcp_brute(F, q[bad_idx])
            lam[bad_idx], free[bad_idx] = ref.lam, ref.free & (ref.lam > 0)
        elif bad_idx is not None:
            ref = convex_lcp_problem(n).solve(F.cpu(), q[bad_idx].cpu().numpy())
            lam_ref = torch.as_tensor(ref, dtype=q.dtype, device=q.device).clamp(min=0.0)
            # polish: re-solve exactly on the reference's active set, keep it if it is better
            free_ref = lam_ref > lam_ref @ F.mT + q[bad_idx]
            lam_pol = active_set_solve(F, q[bad_idx], free_ref)
            better = lcp_residual(F, q[bad_idx], lam_pol) < lcp_residual(F, q[bad_idx], lam_ref)
            lam[bad_idx] = torch.where(better[:, None], lam_pol.clamp(min=0.0), lam_ref)
            free[bad_idx] = free_ref
        w = lam @ F.mT + q
        return LCPSolution(lam, w, free, res.iterations, n_fb, lcp_residual(F, q, lam))


def solve_lcp_brute(F: torch.Tensor, q: torch.Tensor) -> LCPSolution:
    """Enumerate all ``2^n`` free sets and keep the feasible one (tests only; ``n <= 12``)."""
    B, n = q.shape
    if n > 12:
        raise LCSInputError(
            f"n_lam: brute force enumerates 2^n sets, expected n <= 12, received {n}"
        )
    with torch.no_grad():
        best_lam = torch.zeros_like(q)
        best_res = torch.full((B,), float("inf"), dtype=q.dtype, device=q.device)
        best_free = torch.zeros_like(q, dtype=torch.bool)
        for bits in itertools.product([False, True], repeat=n):
            free = torch.tensor(bits, device=q.device).expand(B, n)
            lam = active_set_solve(F, q, free)
            res = lcp_residual(F, q, lam)
            better = res < best_res
            best_res = torch.where(better, res, best_res)
            best_lam = torch.where(better[:, None], lam, best_lam)
            best_free = torch.where(better[:, None], free, best_free)
        lam = best_lam.clamp(min=0.0)
        return LCPSolution(lam, lam @ F.mT + q, best_free, 0, 0, lcp_residual(F, q, lam))


def solve_lcp(F: Any, q: Any, method: str = "fast") -> LCPSolution:
    """Solve the LCP ``0 <= lam _|_ F lam + q >= 0`` for a batch ``q`` ``(B, n)`` (or ``(n,)``).

    ``F`` is ``(n, n)`` with ``F + F^T`` positive definite (Assumption 1). ``method`` is
    ``"fast"`` (batched pivoting, default), ``"cvxpy"`` (declared problem (P), Clarabel) or
    ``"brute"`` (enumeration).
    """
    if not isinstance(F, torch.Tensor):
        F = torch.as_tensor(np.asarray(F, dtype=np.float64))
    if F.dim() != 2 or F.shape[0] != F.shape[1]:
        raise LCSInputError(f"F: expected a square (n, n) matrix, received shape {tuple(F.shape)}")
    F = as_matrix(
        "F",
        F,
        tuple(F.shape),
        dtype=F.dtype if F.is_floating_point() else torch.float64,
        device=F.device,
    )
    q = as_batch("q", q, F.shape[0], dtype=F.dtype, device=F.device)
    if method == "fast":
        return solve_lcp_fast(F, q)
    if method == "brute":
        return solve_lcp_brute(F, q)
    if method == "cvxpy":
        with torch.no_grad():
            n = q.shape[-1]
            ref = convex_lcp_problem(n).solve(F.detach().cpu(), q.detach().cpu().numpy())
            lam = torch.as_tensor(ref, dtype=q.dtype, device=q.device).clamp(min=0.0)
            w = lam @ F.detach().mT + q.detach()
            return LCPSolution(lam, w, lam > w, 0, 0, lcp_residual(F.detach(), q.detach(), lam))
    raise LCSInputError(f"method: expected one of 'fast', 'cvxpy', 'brute', received {method!r}")
