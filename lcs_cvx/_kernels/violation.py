r"""The kernel of the violation problem (V), eq. (9b), in the form it consumes.

(V) is declared once, in :func:`lcs_cvx.problems.violation_problem`; with ``phi`` eliminated and
the objective times ``eps`` it reads::

    min_{lam >= 0}  f(lam) = 1/2 ||L lam + b||^2 + 1/2 ||pos(K lam - h)||^2

``f`` is piecewise quadratic and strongly convex. Its pieces are indexed by the set
``s = {i : (K lam - h)_i > 0}`` -- exactly the indices where ``phi_i = 0`` in the paper's
(lam, phi) form -- and the KKT system of the (lam, phi) problem is a 2 n-dimensional LCP with a
positive definite matrix. Block principal pivoting on the joint set (free ``lam`` indices, ``s``)
is therefore finite (:mod:`.pivoting`), and every sweep costs one batched ``n x n`` solve of

    (L^T L + K^T diag(s) K)_II lam_I = -(L^T b - K^T (s * h))_I.

The kernel therefore consumes the *normal equations* ``{LtL, Ltb, K, h}`` -- ``L^T L``, the rows
of ``L^T b``, ``K`` and ``h`` -- which :func:`normal_equations` forms from the model's matrices
(the one formula for them: :meth:`lcs_cvx.problems.ViolationProblem.parameter_values` factors
its tensor result into the declaration's parameter values, and the fast violation loss builds
them here in its arrays, without factorising).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import torch

from .arrays import ArrayOps, array_ops
from .pivoting import PivotResult, block_pivoting, initial_state, unconverged
from .stacks import matrices

__all__ = ["PIVOT_TOL", "Pivoted", "cold_guess", "normal_equations", "phi", "pivot_violation", "solve",
           "solve_arrays"]

#: Relative feasibility tolerance of a pivoting candidate: ``lam`` against ``1 + |lam|_inf``,
#: the gradient against ``1 + |L^T b|_inf + |K^T h|_inf`` (which is ~1/gamma large), and
#: ``K lam - h`` against ``1 + |h|_inf``.
PIVOT_TOL = 1e-11


def normal_equations(xp: ArrayOps, C: Any, F: Any, q: Any, r: Any, gamma: float, eps: float) -> dict[str, Any]:
    """(V)'s data before the factorisation, in ``xp``'s arrays (differentiable on torch)::

        LtL = eps C^T C + F + F^T - gamma I        (= L^T L)
        Ltb = eps r C + q                          (rows of L^T b = eps C^T r + q)
        K   = (gamma I - F) / sqrt(gamma),   h = q / sqrt(gamma)

    ``C`` ``(n_x, n)``, ``F`` ``(n, n)``, ``q`` ``(B, n)``, ``r`` ``(B, n_x)``; or stacks of
    models, ``(K, n_x, n)``, ``(K, n, n)``, ``(K, B, n)``, ``(K, B, n_x)``. ``gamma`` is not
    checked here (:func:`lcs_cvx.problems.check_gamma`).
    """
    eye = xp.eye(F.shape[-1], F)
    scale = 1.0 / math.sqrt(gamma)
    return {
        "LtL": eps * (C.swapaxes(-1, -2) @ C) + F + F.swapaxes(-1, -2) - gamma * eye,
        "Ltb": eps * (r @ C) + q,
        "K": (gamma * eye - F) * scale,
        "h": q * scale,
    }


def phi(xp: ArrayOps, lam: Any, F: Any, q: Any, gamma: float) -> Any:
    """The exact minimiser of (V) over ``phi`` for fixed ``lam``: ``max(0, F lam + q - gamma lam)``
    (``lam``, ``q`` ``(B, n)`` and ``F`` ``(n, n)``, or stacks ``(K, B, n)``, ``(K, n, n)``)."""
    return xp.clamp_min(lam @ F.swapaxes(-1, -2) + q - gamma * lam, 0.0)


class Pivoted(NamedTuple):
    """The kernel's answer for a batch of ``B`` (V) problems of size ``n`` (tensors).

    Attributes:
        lam: ``(B, n)`` minimiser (of the last sweep, clamped at 0).
        active: ``(B, 2 n)`` bool ``[free, pos]``: ``lam_i > 0`` and ``(K lam - h)_i > 0``
            (``phi_i = 0``).
        unconverged: int64 indices of the samples still infeasible after ``max_iter`` sweeps, or
            None if every sample converged.
        iterations: pivoting sweeps made.
    """

    lam: torch.Tensor
    active: torch.Tensor
    unconverged: torch.Tensor | None
    iterations: int


def cold_guess(xp: ArrayOps, K: Any, h: Any) -> Any:
    """The pivoting's first guess ``[free, pos]`` ``(B, 2 n)`` without a warm start: one projected
    Jacobi step from ``lam = 0`` on the LCP ``0 <= lam _|_ -K lam + h >= 0`` (that of
    ``F - gamma I``, scaled by ``1 / sqrt(gamma)``; at (V)'s solution the free and pos sets mostly
    coincide with its free set)::

        lam0_i = max(0, -h_i / m_i),   w = h - K lam0,   guess_i = m_i lam0_i - w_i > 0

    with ``m_i = -K_ii``, and ``guess_i = h_i < 0`` (that of ``lam = 0``) where ``m_i <= 0``.
    On the Fig. 1 models (n_λ >= 4, 2,000 samples each) it leaves 4-21 % of the flags wrong
    against 19-29 % for ``h < 0``, and pivoting makes 12-29 % fewer candidate solves.
    ``K`` ``(n, n)`` (or a stack, :mod:`.stacks`), ``h`` ``(B, n)``."""
    n = h.shape[1]
    everyone = matrices(xp, K, h.shape[0]).select(None)
    m = -everyone.rows(xp.contiguous(K.diagonal(0, -2, -1)).reshape(-1, n))
    pos = m > 0
    lam0 = xp.where(pos, xp.clamp_min(-h / xp.where(pos, m, 1.0), 0.0), 0.0)
    w = h - everyone.rmul(lam0, xp.contiguous(K.swapaxes(-1, -2)))
    guess = xp.where(pos, m * lam0 - w > 0, h < 0)
    return xp.concat([guess, guess])


def pivot_violation(xp: ArrayOps, LtL: Any, Ltb: Any, K: Any, h: Any, tol: float, max_iter: int,
          warm_start: torch.Tensor | None, device: torch.device) -> tuple[Any, Any, PivotResult]:
    """Block pivoting on (V) in the kernel's arrays (:func:`normal_equations`; ``LtL`` and ``K``
    ``(n, n)``, or stacks ``(K, n, n)`` of models owning ``B / K`` rows each, :mod:`.stacks`):
    ``(lam, active, result)`` with ``active = [lam > 0, K lam - h > 0]`` ``(B, 2 n)``."""
    n = Ltb.shape[1]
    mats = matrices(xp, K, Ltb.shape[0])
    everyone = mats.select(None)
    # K^T diag(s) K = sum_k s_k K_k^T K_k: one (B, n) x (n, n*n) product per sweep; with a model
    # per sample (lcs_cvx.per_sample) the (B, n, n*n) table would cost B n^3 to build and hold
    # (400 MB at B = 200, n = 64), so each sample's K^T diag(s) K is one batched product instead
    per_sample = K.ndim == 3 and K.shape[0] == Ltb.shape[0] and Ltb.shape[0] > 1
    K_outer = None if per_sample else (K[..., :, None] * K[..., None, :]).reshape(K.shape[:-2] + (n, n * n))
    scale_g = tol * (1.0 + xp.amax_abs(Ltb) + xp.amax_abs(everyone.rmul(h, K)))
    scale_t = tol * (1.0 + xp.amax_abs(h))
    neg_l: list[Any] = []  # -(lam's scale), from the first candidate
    LtL_flat = LtL.reshape(-1, n * n)
    KT = K.swapaxes(-1, -2)
    KT_LtL = xp.concat([KT, LtL])  # (n, 2 n): lam @ KT_LtL is [K lam, L^T L lam] in one product
    # the per-sample data side by side: one gather when the work set shrinks
    data = xp.concat([Ltb, -Ltb, h, -h, -scale_g, scale_t, -scale_t])
    cut = [0, n, 2 * n, 3 * n, 4 * n, 4 * n + 1, 4 * n + 2, 4 * n + 3]
    parts = [slice(i, j) for i, j in zip(cut[:-1], cut[1:], strict=True)]

    def solve(state: Any, idx: Any):
        free, pos = state[:, :n], state[:, n:]
        d = data if idx is None else data[idx]
        on = mats.select(idx)
        bb, nbb, hh, nhh, ng, st, nt = (d[:, part] for part in parts)
        sf = xp.to_float(pos, Ltb)
        # (L^T L + K^T diag(s) K) on the free rows and columns, the identity elsewhere
        if per_sample:
            Ks = K if idx is None else K[idx]
            KtSK = ((Ks.swapaxes(-1, -2) * sf[:, None, :]) @ Ks).reshape(-1, n * n)
        else:
            KtSK = on.rmul(sf, K_outer)
        M = xp.free_block(on.rows(LtL_flat) + KtSK, free)
        rhs = xp.where(free, nbb + on.rmul(sf * hh, K), 0.0)
        lam, failed = on.solve(M, rhs, True)
        prod = on.rmul(lam, KT_LtL)
        t = prod[:, :n] + nhh
        g = prod[:, n:] + bb + on.rmul(sf * t, K)
        if not neg_l:
            neg_l.append(-tol * (1.0 + xp.amax_abs(lam)))
        nl = neg_l[0] if idx is None else neg_l[0][idx]
        # infeasible: a free lam below 0, a bound lam with a negative gradient; a piece's
        # t = K lam - h on the wrong side of 0 (to the tolerances above)
        bad = xp.concat([xp.where(free, lam < nl, g < ng), xp.where(pos, t < nt, t > st)])
        if failed is not None:
            bad |= failed[:, None]  # a failed factorisation is never trusted
        return lam, bad

    state0 = initial_state(xp, lambda: cold_guess(xp, K, h), (h.shape[0], 2 * n), warm_start, device)
    res = block_pivoting(xp, solve, state0, max_iter=max_iter)
    lam = xp.clamp_min(res.solution, 0.0)
    return lam, xp.concat([lam > 0, (everyone.rmul(lam, KT) - h) > 0]), res


def solve_arrays(xp: ArrayOps, normal: dict[str, Any], *, device: torch.device, tol: float = PIVOT_TOL,
                 max_iter: int = 1000, warm_start: torch.Tensor | None = None) -> Pivoted:
    """Pivot (V) given its normal equations in ``xp``'s arrays (:func:`normal_equations`); the
    caller holds :meth:`ArrayOps.threads`. ``warm_start``: ``(B, 2 n)`` bool ``[free, pos]``."""
    lam, active, res = pivot_violation(xp, normal["LtL"], normal["Ltb"], normal["K"], normal["h"], tol,
                             max_iter, warm_start, device)
    return Pivoted(xp.unwrap(lam), xp.unwrap(active), unconverged(xp, res.converged), res.iterations)


def solve(normal: dict[str, torch.Tensor], *, tol: float = PIVOT_TOL, max_iter: int = 1000,
          warm_start: torch.Tensor | None = None, arrays: str = "auto") -> Pivoted:
    """:func:`solve_arrays` on detached tensors ``{"LtL": (n, n), "Ltb": (B, n), "K": (n, n),
    "h": (B, n)}`` (or stacks ``(K, n, n)`` of ``LtL`` and ``K``, the rows model-major), in the
    ``arrays`` back-end (:func:`lcs_cvx._kernels.arrays.array_ops`)."""
    xp = array_ops(normal["Ltb"], arrays)
    with xp.threads():
        wrapped = {k: xp.wrap(v) for k, v in normal.items()}
        return solve_arrays(xp, wrapped, device=normal["Ltb"].device, tol=tol, max_iter=max_iter,
                            warm_start=warm_start)
