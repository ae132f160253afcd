r"""Fast batched solver of the violation problem (V), eq. (9b).

It consumes the parameters of the declared problem (:func:`lcs_cvx.problems.violation_problem`)::

    min_{lam >= 0}  f(lam) = 1/2 ||L lam + b||^2 + 1/2 ||pos(K lam - h)||^2

``f`` is piecewise quadratic and strongly convex; block principal pivoting on its pieces is
finite and exact (the kernel :mod:`lcs_cvx._kernels.violation`, whose module docstring derives
the sweep). Every sweep solves one batched ``n x n`` system in ``L^T L``, ``L^T b``, ``K`` and
``h`` -- (V) before the factorisation, :meth:`lcs_cvx.problems.ViolationProblem.normal_equations`:
:func:`solve_violation_fast` forms them from the parameter values; the fast violation loss builds
them directly (no factorisation, no triangular solve per call) and calls :func:`finish` on the
kernel's answer. Samples that do not converge are solved exactly by enumeration of the ``4^n``
pieces (:func:`solve_violation_brute`, ``n <= BRUTE_MAX``), else by the Clarabel reference on the
same declaration -- whose answers can be far off where pivoting is slow (a KKT residual of ~1
against round-off: ``solve_violation_fast``'s ``max_iter``).
"""

from __future__ import annotations

import itertools
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import torch

from ._checks import FallbackWarning, LCSInputError, report_unconverged
from ._kernels import violation as kernel
from ._kernels.violation import PIVOT_TOL
from .problems import violation_problem

__all__ = ["ViolationSolution", "solve_violation_fast", "solve_violation_brute",
           "violation_kkt_residual", "finish"]

#: A fallback answer whose relative KKT residual exceeds this is reported
#: (:class:`lcs_cvx.FallbackWarning`).
REFERENCE_TOL = 1e-6

#: Up to this ``n`` an unconverged sample falls back to enumerating the ``4^n`` pieces of (V)
#: (4,096 at ``n = 6``, as many as the LCP's ``2^12`` free sets); above it, to Clarabel.
BRUTE_MAX = 6

#: Pieces solved at once by :func:`solve_violation_brute` (times the samples: its memory).
_CHUNK_ELEMENTS = 1 << 21


@dataclass(frozen=True)
class ViolationSolution:
    """Solution of a batch of (V) problems.

    Attributes:
        lam: ``(B, n)`` minimiser.
        active: ``(B, 2 n)`` bool ``[free, pos]``: the ``warm_start`` of a later solve.
        iterations: pivoting sweeps.
        n_fallback: samples solved by the reference instead.
        residual: ``(B,)`` relative KKT residual (:func:`violation_kkt_residual`), or None when
            not asked for (convergence of the pivoting is itself a KKT check to ``tol``).
        fallback_residual: the largest relative KKT residual among the samples the reference
            solved (0.0 if none).
    """

    lam: torch.Tensor
    active: torch.Tensor
    iterations: int
    n_fallback: int
    residual: torch.Tensor | None
    fallback_residual: float = 0.0

    @property
    def free(self) -> torch.Tensor:
        """``(B, n)`` bool, ``lam_i`` free (not at its bound)."""
        return self.active[:, : self.lam.shape[1]]

    @property
    def pos(self) -> torch.Tensor:
        """``(B, n)`` bool, ``(K lam - h)_i > 0`` (``phi_i = 0``)."""
        return self.active[:, self.lam.shape[1]:]


def _gradient(L: torch.Tensor, b: torch.Tensor, K: torch.Tensor, h: torch.Tensor, lam: torch.Tensor):
    t = lam @ K.mT - h
    return (lam @ L.mT + b) @ L + t.clamp(min=0.0) @ K, t


def violation_kkt_residual(values: dict[str, torch.Tensor], lam: torch.Tensor) -> torch.Tensor:
    """Relative KKT residual of (V) at ``lam``, per sample ``(B,)``.

    The natural residual in units of ``lam``: ``|min(lam, grad f(lam) / diag H)|_inf /
    (1 + |lam|_inf)``, with ``H = L^T L + K^T diag(s) K`` the Hessian of the current piece (a
    Jacobi scaling: one projected Newton-like step). Zero exactly at the minimiser.
    """
    L, b, K, h = values["L"], values["b"], values["K"], values["h"]
    g, t = _gradient(L, b, K, h, lam)
    hdiag = (L * L).sum(0) + (t > 0).to(lam.dtype) @ (K * K)
    return torch.minimum(lam, g / hdiag).abs().amax(-1) / (1.0 + lam.abs().amax(-1))


def solve_violation_brute(values: dict[str, torch.Tensor]) -> ViolationSolution:
    """Solve (V) exactly for a batch by enumerating its ``4^n`` pieces (tests and fallback;
    ``n <= 8``).

    A piece is a free set ``I`` of ``lam`` (``lam_J = 0``) and a set ``s`` where ``K lam - h > 0``
    (``phi = 0`` there); on it ``f`` is quadratic and its minimiser over ``lam_I`` solves
    ``(L^T L + K^T diag(s) K)_II lam_I = -(L^T b - K^T (s * h))_I`` -- a positive definite
    matrix (``L^T L`` is), one per piece for the whole batch. (V) is strongly convex: its one
    minimiser is the solution of its own piece, the only candidate whose KKT residual
    (:func:`violation_kkt_residual`) is zero; each sample keeps its candidate of smallest residual, as
    :func:`lcs_cvx.lcp.solve_lcp_brute` does for the LCP. ``values`` as in
    :func:`solve_violation_fast`; returns the solution with its residual, ``iterations`` 0.
    """
    b = values["b"]
    B, n = b.shape
    if n > 8:
        raise LCSInputError(f"n_lam: enumeration of (V)'s 4^n pieces, expected n <= 8, received {n}")
    with torch.no_grad():
        L, K, h = values["L"].detach(), values["K"].detach(), values["h"].detach()
        b = b.detach()
        LtL, Ltb = L.mT @ L, b @ L
        kw = {"dtype": b.dtype, "device": b.device}
        eye = torch.eye(n, **kw)
        K_outer = K[:, :, None] * K[:, None, :]  # (n, n, n): K_k^T K_k, the row k's outer product
        best_res = torch.full((B,), float("inf"), **kw)
        best_lam = torch.zeros_like(b)
        pieces = torch.tensor(list(itertools.product([False, True], repeat=2 * n)), device=b.device)
        chunk = max(1, _CHUNK_ELEMENTS // max(1, B * n * n))
        for start in range(0, pieces.shape[0], chunk):
            part = pieces[start:start + chunk]
            free, pos = part[:, :n], part[:, n:].to(b.dtype)  # (S, n)
            M = LtL + torch.einsum("sk,kij->sij", pos, K_outer)  # (S, n, n)
            both = free[:, :, None] & free[:, None, :]
            M = torch.where(both, M, eye)  # the identity on the bound rows and columns
            rhs = -(Ltb[None] - (pos[:, None, :] * h[None]) @ K)  # (S, B, n)
            rhs = torch.where(free[:, None, :], rhs, 0.0)
            lam = torch.linalg.solve(M, rhs.mT).mT  # (S, B, n): one factorisation per piece
            res = violation_kkt_residual({"L": L, "b": b, "K": K, "h": h}, lam)  # (S, B)
            low, arg = res.min(0)
            better = low < best_res
            best_res = torch.where(better, low, best_res)
            pick = lam.gather(0, arg[None, :, None].expand(1, B, n)).squeeze(0)
            best_lam = torch.where(better[:, None], pick, best_lam)
        lam = best_lam.clamp(min=0.0)
        active = torch.cat([lam > 0, (lam @ K.mT - h) > 0], dim=1)
        return ViolationSolution(lam, active, 0, 0, violation_kkt_residual(values, lam), 0.0)


def solve_violation_fast(
    values: dict[str, torch.Tensor],
    *,
    max_iter: int = 1000,
    tol: float = PIVOT_TOL,
    fallback: bool = True,
    residual: bool = True,
    warm_start: torch.Tensor | None = None,
    arrays: str = "auto",
) -> ViolationSolution:
    """Solve (V) for a batch, from the declaration's parameter values.

    Args:
        values: ``{"L": (n, n), "b": (B, n), "K": (n, n), "h": (B, n)}`` as built by
            :meth:`lcs_cvx.problems.ViolationProblem.parameter_values`.
        max_iter: pivoting sweeps before unconverged samples fall back: to enumeration of the
            ``4^n`` pieces (exact) for ``n <= BRUTE_MAX``, else to Clarabel. Murty's single
            pivots end on every sample, but nearly skew-symmetric ``F`` with a tiny ``gamma``
            needs hundreds of sweeps (``G = 0``, ``s = gamma = 1e-6``, ``n = 10``: 387), where
            Clarabel's answer is far off (KKT residual ~1 against 1e-15).
        tol: relative feasibility tolerance of a candidate.
        fallback: if False, raise :class:`lcs_cvx.SolverError` on non-convergence instead.
        residual: also compute the per-sample KKT residual (a few more batched products).
        warm_start: ``(B, 2 n)`` bool first guess ``[free, pos]`` of the pivoting, e.g.
            :attr:`ViolationSolution.active` of an earlier solve of the same samples (default:
            one projected Jacobi step from ``lam = 0``, :func:`lcs_cvx._kernels.violation.cold_guess`).
            The solution does not depend on it (the problem is
            strongly convex); the number of sweeps does: from the exact active sets, none.
        arrays: the kernel's array library: ``"auto"`` (NumPy for CPU tensors, torch
            otherwise), ``"numpy"`` or ``"torch"``.

    Returns:
        :class:`ViolationSolution` (no autograd graph), on the device of ``values``.
    """
    with torch.no_grad():
        values = {k: v.detach() for k, v in values.items()}
        L, b = values["L"], values["b"]
        normal = {"LtL": L.mT @ L, "Ltb": b @ L, "K": values["K"], "h": values["h"]}
        sol = kernel.solve(normal, tol=tol, max_iter=max_iter, warm_start=warm_start, arrays=arrays)
        return finish(sol, lambda: values, max_iter=max_iter, fallback=fallback, residual=residual)


def finish(sol: kernel.Pivoted, values: Callable[[], dict[str, torch.Tensor]], *, max_iter: int,
           fallback: bool = True, residual: bool = True) -> ViolationSolution:
    """The :class:`ViolationSolution` of the kernel's answer ``sol``: its unconverged samples
    reported (:func:`lcs_cvx._checks.report_unconverged`) and solved by enumeration of the
    ``4^n`` pieces (:func:`solve_violation_brute`, exact) for ``n <= BRUTE_MAX``, else by the
    Clarabel reference, and the KKT residual if asked for. ``values()`` returns (V)'s parameter values
    ``{"L", "b", "K", "h"}`` (tensors); it is called only for a fallback or the residual.
    Package-internal: :func:`solve_violation_fast` and the fast violation loss end here."""
    lam, active, bad_idx = sol.lam, sol.active, sol.unconverged
    n = lam.shape[1]
    n_fb, worst, vals = 0, 0.0, None
    if bad_idx is not None:
        n_fb = int(bad_idx.numel())
        brute = n <= BRUTE_MAX
        report_unconverged(n_fb, lam.shape[0], "violation QP", max_iter, fallback,
                           f"enumeration of the 4^{n} pieces" if brute else "the Clarabel reference")
        vals = values()
        L, K = vals["L"], vals["K"]
        sub = {"L": L, "K": K, "b": vals["b"][bad_idx], "h": vals["h"][bad_idx]}
        lam_ref = solve_violation_brute(sub).lam if brute else violation_problem(n).solve(sub)
        lam[bad_idx] = lam_ref
        active[bad_idx] = torch.cat([lam_ref > 0, (lam_ref @ K.mT - sub["h"]) > 0], dim=1)
        worst = float(violation_kkt_residual(sub, lam_ref).max())
        if worst > REFERENCE_TOL:  # said, not hidden (Clarabel is an interior point)
            warnings.warn(
                f"violation QP: the {'enumeration' if brute else 'Clarabel reference'}'s answers "
                f"are inaccurate (worst relative "
                f"KKT residual {worst:.2e} > {REFERENCE_TOL:g}); raise max_iter (now "
                f"{max_iter}) so that pivoting, which is exact, ends on these samples",
                FallbackWarning, stacklevel=3,
            )
    resid = None
    if residual:
        resid = violation_kkt_residual(values() if vals is None else vals, lam)
    return ViolationSolution(lam, active, sol.iterations, n_fb, resid, worst)
