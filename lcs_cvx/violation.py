r"""Fast batched solver of the violation problem (V), eq. (equ.contactnet.2).

It consumes the parameters of the declared problem (:func:`lcs_cvx.problems.violation_problem`)::

    min_{lam >= 0}  f(lam) = 1/2 ||L lam + b||^2 + 1/2 ||pos(K lam - h)||^2

``f`` is piecewise quadratic and strongly convex. Its pieces are indexed by the set
``s = {i : (K lam - h)_i > 0}`` -- exactly the indices where ``phi_i = 0`` in the paper's
(lam, phi) form -- and the KKT system of the (lam, phi) problem is a 2 n-dimensional LCP with a
positive definite matrix. Block principal pivoting on the joint set (free ``lam`` indices, ``s``)
is therefore finite (:mod:`lcs_cvx.pivoting`), and every sweep costs one batched ``n x n``
Cholesky solve of

    (L^T L + K^T diag(s) K)_II lam_I = -(L^T b - K^T (s * h))_I.

The kernel therefore consumes ``L^T L``, ``L^T b``, ``K`` and ``h``
(:meth:`lcs_cvx.problems.ViolationProblem.normal_equations`): :func:`solve_violation_fast` forms
them from the parameter values, the fast violation loss builds them directly (no factorisation
and no triangular solve per call). Samples that do not converge are solved by the Clarabel
reference on the same declaration.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import torch

from .pivoting import (
    ArrayOps,
    FallbackWarning,
    PivotResult,
    array_ops,
    block_pivoting,
    initial_state,
    unconverged,
)
from .problems import violation_problem

__all__ = ["ViolationSolution", "solve_violation_fast", "solve_arrays", "violation_kkt_residual"]

#: Relative feasibility tolerance of a pivoting candidate: ``lam`` against ``1 + |lam|_inf``,
#: the gradient against ``1 + |L^T b|_inf + |K^T h|_inf`` (which is ~1/gamma large), and
#: ``K lam - h`` against ``1 + |h|_inf``.
PIVOT_TOL = 1e-11

#: A fallback answer of the Clarabel reference whose relative KKT residual exceeds this is
#: reported (:class:`lcs_cvx.FallbackWarning`).
REFERENCE_TOL = 1e-6


@dataclass(frozen=True)
class ViolationSolution:
    """Solution of a batch of (V) problems.

    Attributes:
        lam: ``(B, n)`` minimiser.
        free: ``(B, n)`` bool, ``lam_i`` free (not at its bound).
        pos: ``(B, n)`` bool, ``(K lam - h)_i > 0`` (``phi_i = 0``).
        iterations: pivoting sweeps.
        n_fallback: samples solved by the reference instead.
        residual: ``(B,)`` relative KKT residual (:func:`violation_kkt_residual`), or None when
            not asked for (convergence of the pivoting is itself a KKT check to ``tol``).
    """

    lam: torch.Tensor
    free: torch.Tensor
    pos: torch.Tensor
    iterations: int
    n_fallback: int
    residual: torch.Tensor | None

    @property
    def active(self) -> torch.Tensor:
        """``(B, 2 n)`` bool ``[free, pos]``: the ``warm_start`` of a later solve."""
        return torch.cat([self.free, self.pos], dim=1)


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


def _pivot(xp: ArrayOps, LtL: Any, Ltb: Any, K: Any, h: Any, tol: float, max_iter: int,
           warm_start: torch.Tensor | None, device: torch.device) -> tuple[Any, Any, Any, PivotResult]:
    """Block pivoting on (V) in the kernel's arrays (:meth:`ViolationProblem.normal_equations`):
    ``(lam, free, pos, result)``."""
    n = Ltb.shape[1]
    # K^T diag(s) K = sum_k s_k K_k^T K_k: one (B, n) x (n, n*n) product per sweep.
    K_outer = (K[:, :, None] * K[:, None, :]).reshape(n, n * n)
    scale_g = tol * (1.0 + xp.amax_abs(Ltb) + xp.amax_abs(h @ K))
    scale_t = tol * (1.0 + xp.amax_abs(h))
    neg_l: list[Any] = []  # -(lam's scale), from the first candidate
    LtL_flat = LtL.reshape(1, n * n)
    KT_LtL = xp.concat([K.T, LtL])  # (n, 2 n): lam @ KT_LtL is [K lam, L^T L lam] in one product
    # the per-sample data side by side: one gather when the work set shrinks
    data = xp.concat([Ltb, -Ltb, h, -h, -scale_g, scale_t, -scale_t])
    cut = [0, n, 2 * n, 3 * n, 4 * n, 4 * n + 1, 4 * n + 2, 4 * n + 3]
    parts = [slice(i, j) for i, j in zip(cut[:-1], cut[1:], strict=True)]

    def solve(state: Any, idx: Any):
        free, pos = state[:, :n], state[:, n:]
        d = data if idx is None else data[idx]
        bb, nbb, hh, nhh, ng, st, nt = (d[:, part] for part in parts)
        sf = xp.to_float(pos, Ltb)
        # (L^T L + K^T diag(s) K) on the free rows and columns, the identity elsewhere
        M = xp.free_block(LtL_flat + sf @ K_outer, free)
        rhs = xp.where(free, nbb + (sf * hh) @ K, 0.0)
        lam, failed = xp.solve(M, rhs)
        prod = lam @ KT_LtL
        t = prod[:, :n] + nhh
        g = prod[:, n:] + bb + (sf * t) @ K
        if not neg_l:
            neg_l.append(-tol * (1.0 + xp.amax_abs(lam)))
        nl = neg_l[0] if idx is None else neg_l[0][idx]
        # infeasible: a free lam below 0, a bound lam with a negative gradient; a piece's
        # t = K lam - h on the wrong side of 0 (to the tolerances above)
        bad = xp.concat([xp.where(free, lam < nl, g < ng), xp.where(pos, t < nt, t > st)])
        if failed is not None:
            bad |= failed[:, None]  # a failed factorisation is never trusted
        return lam, bad

    state0 = initial_state(xp, xp.concat([h < 0, h < 0]), warm_start, device)
    res = block_pivoting(xp, solve, state0, max_iter=max_iter)
    lam = xp.clamp_min(res.solution, 0.0)
    return lam, lam > 0, (lam @ K.T - h) > 0, res


def solve_violation_fast(
    values: dict[str, torch.Tensor],
    *,
    max_iter: int = 1000,
    tol: float = PIVOT_TOL,
    fallback: bool = True,
    residual: bool = True,
    warm_start: torch.Tensor | None = None,
    backend: str = "auto",
) -> ViolationSolution:
    """Solve (V) for a batch, from the declaration's parameter values.

    Args:
        values: ``{"L": (n, n), "b": (B, n), "K": (n, n), "h": (B, n)}`` as built by
            :meth:`lcs_cvx.problems.ViolationProblem.parameter_values`.
        max_iter: pivoting sweeps before unconverged samples fall back to Clarabel. Murty's
            single pivots end on every sample, but nearly skew-symmetric ``F`` with a tiny
            ``gamma`` needs hundreds of sweeps (``G = 0``, ``s = gamma = 1e-6``, ``n = 10``:
            387), where Clarabel's answer is far off (KKT residual ~1 against 1e-15).
        tol: relative feasibility tolerance of a candidate.
        fallback: if False, raise :class:`lcs_cvx.SolverError` on non-convergence instead.
        residual: also compute the per-sample KKT residual (a few more batched products).
        warm_start: ``(B, 2 n)`` bool first guess ``[free, pos]`` of the pivoting, e.g.
            :attr:`ViolationSolution.active` of an earlier solve of the same samples (default:
            the guess of ``lam = 0``). The solution does not depend on it (the problem is
            strongly convex); the number of sweeps does: from the exact active sets, none.
        backend: the kernel's arrays (:func:`lcs_cvx.pivoting.array_ops`): ``"auto"`` (NumPy
            for CPU tensors, torch otherwise), ``"numpy"`` or ``"torch"``.

    Returns:
        :class:`ViolationSolution` (no autograd graph), on the device of ``values``.
    """
    with torch.no_grad():
        device = values["b"].device
        xp = array_ops(values["b"], backend)
        with xp.threads():
            L, b, K, h = (xp.wrap(values[k]) for k in ("L", "b", "K", "h"))
            normal = {"LtL": L.T @ L, "Ltb": b @ L, "K": K, "h": h}
            return solve_arrays(xp, normal, max_iter=max_iter, tol=tol, fallback=fallback,
                                residual=residual, warm_start=warm_start, device=device,
                                values={"L": L, "b": b, "K": K, "h": h})


def solve_arrays(xp: ArrayOps, normal: dict[str, Any], *, device: torch.device,
                 max_iter: int = 1000, tol: float = PIVOT_TOL, fallback: bool = True,
                 residual: bool = True, warm_start: torch.Tensor | None = None,
                 values: dict[str, Any] | None = None) -> ViolationSolution:
    """:func:`solve_violation_fast` on the kernel's arrays of (V) in the form the kernel consumes,
    ``normal = {"LtL", "Ltb", "K", "h"}`` (:meth:`ViolationProblem.normal_equations`; the fast
    violation loss builds it there, without factorising). The parameter values ``{"L", "b",
    "K", "h"}`` are needed only for a fallback or the residual: ``values``, or factored from
    ``normal`` then. The caller holds :meth:`ArrayOps.threads`."""
    *sets, res = _pivot(xp, normal["LtL"], normal["Ltb"], normal["K"], normal["h"], tol, max_iter,
                        warm_start, device)
    lam, free, pos = (xp.unwrap(a) for a in sets)
    n = lam.shape[1]
    bad_idx = unconverged(xp, res.converged, "violation QP", max_iter, fallback)
    n_fb = 0 if bad_idx is None else int(bad_idx.numel())
    if bad_idx is not None or residual:
        values = violation_problem(n).factor(normal) if values is None else values
        L, b, K, h = (xp.unwrap(values[k]) for k in ("L", "b", "K", "h"))
    if bad_idx is not None:
        sub = {"L": L, "K": K, "b": b[bad_idx], "h": h[bad_idx]}
        ref = violation_problem(n).solve(sub)
        lam[bad_idx] = torch.as_tensor(ref, dtype=b.dtype, device=b.device)
        free[bad_idx] = lam[bad_idx] > 0
        pos[bad_idx] = (lam[bad_idx] @ K.mT - h[bad_idx]) > 0
        worst = float(violation_kkt_residual(sub, lam[bad_idx]).max())
        if worst > REFERENCE_TOL:  # said, not hidden: the reference is an interior point
            warnings.warn(
                f"violation QP: the Clarabel reference's answers are inaccurate (worst relative "
                f"KKT residual {worst:.2e} > {REFERENCE_TOL:g}); raise max_iter (now "
                f"{max_iter}) so that pivoting, which is exact, ends on these samples",
                FallbackWarning, stacklevel=3,
            )
    resid = violation_kkt_residual({"L": L, "b": b, "K": K, "h": h}, lam) if residual else None
    return ViolationSolution(lam, free, pos, res.iterations, n_fb, resid)
