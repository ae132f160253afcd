r"""Exact batched solution of the LCP of eq. (2): ``0 <= lam _|_ F lam + q >= 0``.

Three solvers, one answer (Assumption 1, ``F + F^T > 0``, makes it unique):

- ``"fast"``: batched block principal pivoting (the kernel :mod:`lcs_cvx._kernels.lcp`) on the
  free set ``I = {i : lam_i > 0}``; each sweep solves ``F_II lam_I = -q_I`` for the whole batch
  with one batched LU. The converged free set gives the exact active-set solution. A sample that
  does not converge is re-solved with a reference and reported (warning + counter).
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

from ._checks import LCSInputError, as_batch, as_matrix, report_unconverged
from ._kernels import lcp as kernel
from ._kernels.arrays import TORCH
from ._kernels.lcp import PIVOT_TOL
from .problems import convex_lcp_problem, sym_min_eig

__all__ = [
    "LCPSolution",
    "solve_lcp",
    "solve_lcp_unchecked",
    "check_assumption_1",
    "solve_lcp_fast",
    "solve_lcp_brute",
    "active_set_solve",
    "free_set_matrix",
    "lcp_residual",
]

#: Up to this ``n`` an unconverged sample falls back to enumerating its ``2^n`` free sets.
BRUTE_MAX = 12


@dataclass(frozen=True)
class LCPSolution:
    """Solution of a batch of LCPs.

    Attributes:
        lam: ``(B, n)`` the solution.
        w: ``(B, n)`` ``F lam + q``.
        free: ``(B, n)`` bool, the free set (``lam_i`` determined by ``w_i = 0``).
        iterations: pivoting sweeps (0 for the reference solvers).
        n_fallback: samples the fast solver handed to a reference.
        residual: ``(B,)`` relative LCP residual (:func:`lcp_residual`), or None when not asked
            for (a converged pivoting is exact to its tolerance by construction).
        fallback_residual: the largest relative LCP residual among the samples a reference
            solved (0.0 if none).
    """

    lam: torch.Tensor
    w: torch.Tensor
    free: torch.Tensor
    iterations: int
    n_fallback: int
    residual: torch.Tensor | None
    fallback_residual: float = 0.0


def lcp_residual(F: torch.Tensor, q: torch.Tensor, lam: torch.Tensor,
                 w: torch.Tensor | None = None) -> torch.Tensor:
    """Relative violation of the LCP conditions, per sample ``(B,)``.

    The natural residual ``|min(lam, w)|_inf / (1 + |q|_inf)`` with ``w = F lam + q`` (computed
    unless given): zero exactly at the solution, and it bounds the violation of ``lam >= 0``,
    ``w >= 0`` and of complementarity (``min(lam_i, w_i) = 0``).
    """
    if w is None:
        w = lam @ F.mT + q
    return torch.minimum(lam, w).abs().amax(-1) / (1.0 + q.abs().amax(-1))


def free_set_matrix(F: torch.Tensor, free: torch.Tensor) -> torch.Tensor:
    """``(B, n, n)``: ``F`` (``(n, n)`` or ``(B, n, n)``) on the rows and columns of the free sets
    ``free`` ``(B, n)``, the identity elsewhere -- the matrix of ``lam_I = -F_II^{-1} q_I`` with
    ``lam_J = 0``. Differentiable in ``F``; the kernels' ``ArrayOps.free_block``."""
    n = F.shape[-1]
    return TORCH.free_block(F.reshape(-1, n * n), free)


def active_set_solve(F: torch.Tensor, q: torch.Tensor, free: torch.Tensor) -> torch.Tensor:
    """``lam`` with ``lam_J = 0`` and ``(F lam + q)_I = 0`` for the free sets ``free`` ``(B, n)``.

    Differentiable in ``F`` ``(n, n)`` or ``(B, n, n)`` and ``q`` ``(B, n)``: for the correct
    free set this is the implicit function of Lemma 1 (a non-strictly-complementary index is
    treated as not free, i.e. ``lam_i`` held at 0 -- a one-sided derivative).
    """
    rhs = torch.where(free, -q, 0.0).unsqueeze(-1)
    return torch.linalg.solve(free_set_matrix(F, free), rhs).squeeze(-1)


def solve_lcp_fast(
    F: torch.Tensor,
    q: torch.Tensor,
    *,
    max_iter: int = 1000,
    tol: float = PIVOT_TOL,
    fallback: bool = True,
    residual: bool = True,
    warm_start: torch.Tensor | None = None,
    arrays: str = "auto",
) -> LCPSolution:
    """Solve ``0 <= lam _|_ F lam + q >= 0`` for a batch by block principal pivoting.

    Args:
        F: ``(n, n)`` with ``F + F^T > 0`` (not checked here; :class:`lcs_cvx.LCS` ensures it).
        q: ``(B, n)``.
        max_iter: pivoting sweeps before the remaining samples fall back. Murty's rule ends
            on every P-matrix, but it can take hundreds of sweeps on nearly skew-symmetric
            ``F`` (Fig. 1(c)'s ``G = 0``, ``s = 1e-5``), hence a generous default.
        tol: relative feasibility tolerance of a candidate free set.
        fallback: re-solve unconverged samples (and warn) -- by enumeration of the ``2^n``
            free sets for ``n <= BRUTE_MAX`` (exact), else with the Clarabel reference; if
            False, raise :class:`lcs_cvx.SolverError` instead.
        residual: also compute the per-sample residual (:func:`lcp_residual`).
        warm_start: ``(B, n)`` bool first guess of the free sets, e.g. ``free`` of an earlier
            solve of the same samples (default: ``q < 0``, the guess of ``lam = 0``). The
            solution is unique (Assumption 1) and does not depend on it; the sweeps do.
        arrays: ``"auto"`` (a float64 CPU ``F``: the compiled kernel, each sample pivoted on its
            own; else the array kernel in NumPy for CPU tensors, torch otherwise), ``"compiled"``,
            or the array kernel's library, ``"numpy"`` or ``"torch"``.

    Returns:
        :class:`LCPSolution` (no autograd graph; see :func:`active_set_solve`).
    """
    with torch.no_grad():
        F = F.detach()
        q = q.detach()
        sol = kernel.solve(F, q, tol=tol, max_iter=max_iter, warm_start=warm_start, arrays=arrays)
        return finish(F, q, sol, max_iter=max_iter, fallback=fallback, residual=residual)


def finish(F: torch.Tensor, q: torch.Tensor, sol: kernel.Pivoted, *, max_iter: int,
           fallback: bool = True, residual: bool = True) -> LCPSolution:
    """The :class:`LCPSolution` of the kernel's answer ``sol`` for ``(F, q)`` (detached): its
    unconverged samples reported (:func:`lcs_cvx._checks.report_unconverged`) and solved by a
    reference (in place in ``sol``'s tensors), and the residual if asked for. Package-internal:
    :func:`solve_lcp_fast` and the stacked prediction loss (:mod:`lcs_cvx.stacked`, per model)
    end here."""
    n = q.shape[1]
    lam, w, free, bad_idx = sol.lam, sol.w, sol.free, sol.unconverged
    n_fb, worst = 0, 0.0
    if bad_idx is not None:
        brute = n <= BRUTE_MAX
        n_fb = int(bad_idx.numel())
        report_unconverged(n_fb, q.shape[0], "LCP", max_iter, fallback,
                           f"enumeration of the 2^{n} free sets" if brute else "the Clarabel reference")
        lam[bad_idx], free[bad_idx] = _reference(F, q[bad_idx], brute)
        w[bad_idx] = lam[bad_idx] @ F.mT + q[bad_idx]
        worst = float(lcp_residual(F, q[bad_idx], lam[bad_idx]).max())
    resid = lcp_residual(F, q, lam, w) if residual else None
    return LCPSolution(lam, w, free, sol.iterations, n_fb, resid, worst)


def _reference(F: torch.Tensor, q: torch.Tensor, brute: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """``(lam, free)`` of the LCPs ``(F, q)`` by enumeration (``brute``), else by the Clarabel
    reference polished on its active set (kept where that lowers the residual)."""
    if brute:
        ref = solve_lcp_brute(F, q)
        return ref.lam, ref.free & (ref.lam > 0)
    lam_ref = convex_lcp_problem(q.shape[1]).solve(F, q).clamp(min=0.0)
    # polish: re-solve exactly on the reference's active set, keep it if it is better
    free_ref = lam_ref > lam_ref @ F.mT + q
    lam_pol = active_set_solve(F, q, free_ref)
    better = lcp_residual(F, q, lam_pol) < lcp_residual(F, q, lam_ref)
    return torch.where(better[:, None], lam_pol.clamp(min=0.0), lam_ref), free_ref


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
        return LCPSolution(lam, lam @ F.mT + q, best_free, 0, 0, lcp_residual(F, q, lam), 0.0)


def check_assumption_1(F: torch.Tensor) -> None:
    """:class:`LCSInputError` unless ``F + F^T`` is positive definite (Assumption 1: then the LCP
    has exactly one solution for every ``q``, and pivoting ends on it). ``F`` is ``(n, n)`` or a
    batch ``(B, n, n)``; one batched ``eigvalsh`` of ``F + F^T``. Without it, pivoting on an ``F``
    that is not a P-matrix can cycle to its sweep limit and a fallback would return the best
    candidate of an LCP that may have no solution at all."""
    low = sym_min_eig(F.detach())
    worst = int(low.argmin()) if low.dim() else None
    value = float(low.min())
    if not value > 0.0:  # also catches NaN
        which = "" if worst is None else f" (matrix {worst} of the batch)"
        raise LCSInputError(
            f"F: expected F + F^T positive definite (Assumption 1), received smallest eigenvalue "
            f"sigma_min(F + F^T) = {value:.6g}{which}"
        )


def solve_lcp(F: Any, q: Any, method: str = "fast") -> LCPSolution:
    r"""Solve the LCP (eq. (2)) for a batch ``q`` ``(B, n)`` (or ``(n,)``):

    $$
    0 \le \lambda \perp F \lambda + q \ge 0.
    $$

    ``F`` is ``(n, n)`` with ``F + F^T`` positive definite (Assumption 1, checked:
    :class:`lcs_cvx.LCSInputError` otherwise). ``method`` is ``"fast"`` (batched pivoting,
    default), ``"cvxpy"`` (declared problem (P), Clarabel) or ``"brute"`` (enumeration).
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
    check_assumption_1(F)
    return solve_lcp_unchecked(F, q, method)


def solve_lcp_unchecked(F: torch.Tensor, q: torch.Tensor, method: str = "fast") -> LCPSolution:
    """:func:`solve_lcp` without its input checks, for an ``F`` ``(n, n)`` that satisfies
    Assumption 1 by construction (an :class:`lcs_cvx.LCS`'s ``G G^T + H - H^T + s I``) and a
    checked ``q`` ``(B, n)`` of its dtype and device. Package-internal: :meth:`LCS.solve_lcp`."""
    if method == "fast":
        return solve_lcp_fast(F, q)
    if method == "brute":
        return solve_lcp_brute(F, q)
    if method == "cvxpy":
        with torch.no_grad():
            F, q = F.detach(), q.detach()
            lam = convex_lcp_problem(q.shape[-1]).solve(F, q).clamp(min=0.0)
            w = lam @ F.mT + q
            return LCPSolution(lam, w, lam > w, 0, 0, lcp_residual(F, q, lam), 0.0)
    raise LCSInputError(f"method: expected one of 'fast', 'cvxpy', 'brute', received {method!r}")
