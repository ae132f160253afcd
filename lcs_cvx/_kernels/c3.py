"""The array work of C3 (:mod:`lcs_cvx.control`): its ADMM loop, the fast QP step and the
closed-form ``"c3+"`` projection, on the arrays of an :class:`~.arrays.ArrayOps` back-end.

Shapes: ``x0 (B, n_x)``, ``delta``, ``w``, ``z (B, N, n_z)``; the QP step's affine map
``y = p_fixed Yf + t Yt + y0`` with ``p_fixed = (x0, lam0, x^d)`` and ``t`` the flattened
targets, ``y = (z_0, ..., z_{N-1}, x_N)``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from .._checks import SolverError
from .box_qp import box_qp

__all__ = ["active_set_maps", "admm", "affine_qp", "bounded_affine_qp", "model_rollout", "plan_cost",
           "project_active_sets", "project_c3plus", "project_lcp", "step_products", "step_values", "rollout", "violation"]


def affine_qp(base: Any, Yt: Any, target: Any) -> tuple[Any, Any]:
    """The equality-constrained QP step as its affine solution map, ``y = base + t Yt`` (``base =
    p_fixed Yf + y0``, the part of one solve's data that stays fixed): ``z (B, N, n_z)``,
    ``x_N (B, n_x)``."""
    B, N, nz = target.shape
    y = base + target.reshape(B, N * nz) @ Yt
    return y[:, : N * nz].reshape(B, N, nz), y[:, N * nz:]


def bounded_affine_qp(base: Any, Yt: Any, target: Any, S: Any, lo: Any, hi: Any, P_SS: Any, P_S_T: Any
                      ) -> tuple[Any, Any, Any]:
    """:func:`affine_qp` with the bounds ``lo <= y_S <= hi`` (NumPy): the unbounded solution
    ``y*``, then ``y = y* + mu P_S^T`` with ``mu`` the bound multipliers
    (:func:`lcs_cvx._kernels.box_qp.box_qp`; ``P_SS (m, m)``, ``P_S_T (m, n_y)``). Returns
    ``z``, ``x_N`` and ``failed (B,)``: the initial states for which no choice meets the bounds."""
    B, N, nz = target.shape
    y = base + target.reshape(B, N * nz) @ Yt
    mu, status = box_qp(P_SS, np.ascontiguousarray(y[:, S]), lo, hi, 20 * S.size + 100)
    if (status == -2).any():
        raise SolverError(f"C3's bounded QP step: the active-set method did not finish for "
                          f"{int((status == -2).sum())} initial state(s)")
    y = y + mu @ P_S_T
    return y[:, : N * nz].reshape(B, N, nz), y[:, N * nz:], status < 0


def rollout(x0: Any, u: Any, lam: Any, A: Any, B: Any, C: Any, d: Any) -> list[Any]:
    """``x_{k+1} = A_k x_k + B_k u_k + C_k lam_k + d_k`` from ``x0 (B, n_x)``: the ``N + 1``
    states ``(B, n_x)``; ``u (B, N, n_u)``, ``lam (B, N, n_lam)``, matrices stacked over ``k``."""
    xs = [x0]
    for k in range(A.shape[0]):
        xs.append(xs[-1] @ A[k].T + u[:, k] @ B[k].T + lam[:, k] @ C[k].T + d[k])
    return xs


def violation(xp: Any, xs: list[Any], u: Any, lam: Any, D: Any, E: Any, F: Any, c: Any) -> Any:
    """``max_k max_i |min(lam, D_k x_k + E_k u_k + F_k lam_k + c_k)_i|`` per plan, ``(B, 1)``:
    the steps as the batch of one product each (``(N, B, .)``)."""
    B, N = u.shape[0], u.shape[1]
    x = xp.concat([v.reshape(B, 1, -1) for v in xs[:N]]).reshape(B, N, -1)
    eta = step_values(x, u, D, E, c) + step_products(lam, F)
    return xp.amax_abs(xp.minimum(lam, eta).reshape(B, -1))


def project_c3plus(xp: Any, c: Any, lam: slice, eta: slice, sqrt_w_lam: Any, sqrt_w_eta: Any) -> Any:
    """Per coordinate, zero ``lam_i`` where ``sqrt(w_eta) eta_i > sqrt(w_lam) lam_i``, else
    ``eta_i``; clip both at 0. ``c (B, N, n_z)``; weights ``(N, n_lam)``."""
    cl, ce = c[..., lam], c[..., eta]
    keep_eta = ce * sqrt_w_eta > cl * sqrt_w_lam
    out = xp.copy(c)
    out[..., lam] = xp.where(keep_eta, 0.0, xp.clamp_min(cl, 0.0))
    out[..., eta] = xp.where(keep_eta, xp.clamp_min(ce, 0.0), 0.0)
    return out


def step_values(x: Any, u: Any, D: Any, E: Any, c: Any) -> Any:
    """``D_k x_k + E_k u_k + c_k`` ``(B, N, m)`` for ``x (B, N, n_x)``, ``u (B, N, n_u)`` and
    stacks ``D (N, m, n_x)``, ``E (N, m, n_u)``, ``c (N, m)``: the steps as the batch of one
    product each."""
    steps = lambda a: a.swapaxes(0, 1)  # noqa: E731  (B, N, m) <-> (N, B, m)
    return steps(steps(x) @ D.swapaxes(1, 2) + steps(u) @ E.swapaxes(1, 2) + c[:, None, :])


def step_products(lam: Any, F: Any) -> Any:
    """``F_k lam_k`` ``(B, N, m)`` for ``lam (B, N, n)`` and ``F (N, m, n)``."""
    return (lam.swapaxes(0, 1) @ F.swapaxes(1, 2)).swapaxes(0, 1)


def project_lcp(xp: Any, c: Any, layout: Any, D: Any, E: Any, F: Any, cc: Any, lcp: Callable[[int, Any], Any],
                time_invariant: bool) -> Any:
    """``x_k``, ``u_k`` of ``c (B, N, n_z)`` kept, ``lam_k = LCP(F_k, q_k)`` with
    ``q_k = D_k x_k + E_k u_k + c_k`` and ``eta_k = q_k + F_k lam_k``; ``lcp(k, q (M, n_lam))``
    solves step ``k``'s LCP (every step at once with ``k = 0`` when ``time_invariant``)."""
    B, N = c.shape[0], c.shape[1]
    q = step_values(c[..., layout.x], c[..., layout.u], D, E, cc)
    nl = q.shape[-1]
    if time_invariant:
        lam = lcp(0, xp.contiguous(q).reshape(B * N, nl)).reshape(B, N, nl)
    else:
        lam = xp.copy(q)
        for k in range(N):
            lam[:, k] = lcp(k, xp.contiguous(q[:, k]))
    out = xp.copy(c)
    out[..., layout.lam] = lam
    out[..., layout.eta] = q + step_products(lam, F)
    return out


def model_rollout(x0: Any, u: Any, mats: dict[str, Any], lcp: Callable[[int, Any], Any],
                  forces: list[Any] | None = None) -> list[Any]:
    """The model's own states under the inputs ``u (B, N, n_u)`` from ``x0 (B, n_x)``:
    ``lam_k = LCP(F_k, D_k x_k + E_k u_k + c_k)``, ``x_{k+1} = A_k x_k + B_k u_k + C_k lam_k +
    d_k`` (eq. (1)); the ``N + 1`` states ``(B, n_x)`` (and the ``N`` forces ``(B, n_lam)``
    appended to ``forces`` when given)."""
    A, Bm, C, d, D, E, c = (mats[k] for k in "ABCdDEc")
    xs = [x0]
    for k in range(A.shape[0]):
        x, uk = xs[-1], u[:, k]
        lam = lcp(k, x @ D[k].T + uk @ E[k].T + c[k])
        if forces is not None:
            forces.append(lam)
        xs.append(x @ A[k].T + uk @ Bm[k].T + lam @ C[k].T + d[k])
    return xs


def plan_cost(xs: list[Any], u: Any, x_des: Any, Q: Any, R: Any, QN: Any) -> Any:
    """``sum_k (x_k - x^d_k)^T Q_k (x_k - x^d_k) + u_k^T R_k u_k + (x_N - x^d_N)^T Q_N (x_N -
    x^d_N)`` per plan ``(B,)``: the horizon cost of :mod:`lcs_cvx.control.costs` on the states
    ``xs`` (``N + 1`` of ``(B, n_x)``), ``u (B, N, n_u)``, ``x_des (B, N + 1, n_x)``."""
    N = u.shape[1]
    total = 0.0
    for k in range(N + 1):
        e = xs[k] - x_des[:, k]
        total = total + ((e @ (Q[k] if k < N else QN)) * e).sum(-1)
        if k < N:
            total = total + ((u[:, k] @ R[k]) * u[:, k]).sum(-1)
    return total


def active_set_maps(metric: Any, rows: Any) -> list[tuple[Any, Any]]:
    """The ``3^n_lam`` active sets of the complementarity set ``0 <= lam _|_ eta >= 0``, each as the
    affine map of its equality-constrained projection (NumPy).

    ``metric (N, n, n)`` positive definite; ``rows (N, 2 n_lam, n)``: ``lam = rows[:, :n_lam] z``
    and ``eta = rows[:, n_lam:] z + offset``. Per coordinate ``i`` an active set holds ``lam_i = 0``,
    ``eta_i = 0`` or both; with ``A`` its rows, the nearest point of ``{A z + b = 0}`` is
    ``z = c - K (A c + b)``, ``K = M^-1 A^T (A M^-1 A^T)^+``. Returns ``(active, K (N, n, m))`` per set.
    """
    import itertools

    import numpy as np

    nl = rows.shape[1] // 2
    Minv = np.linalg.inv(metric)
    maps = []
    for choice in itertools.product((0, 1, 2), repeat=nl):
        active = np.array([i for i, a in enumerate(choice) if a != 1] + [nl + i for i, a in enumerate(choice) if a != 0])
        A = rows[:, active]
        MAt = Minv @ A.swapaxes(1, 2)
        maps.append((active, MAt @ np.linalg.pinv(A @ MAt, hermitian=True)))
    return maps


def project_active_sets(c: Any, metric: Any, rows: Any, offset: Any, maps: list[tuple[Any, Any]]) -> tuple[Any, Any]:
    """The exact projection of ``c (B, N, n)`` onto ``{0 <= lam _|_ eta >= 0}`` in the metric
    ``(N, n, n)`` (NumPy): the nearest point of each active set of :func:`active_set_maps`, kept
    where it is feasible (``lam, eta >= 0`` and the set's equalities, to 1e-9 relative), the
    cheapest one. The projection's minimiser is the nearest point of its own active set, so this is
    the exact projection; ``offset (N, 2 n_lam)`` (0 for ``lam``, the LCP's ``c`` for ``eta``).
    Returns the projection and ``found (B, N)``: whether some active set was feasible."""
    import numpy as np

    value = np.einsum("kmn,bkn->bkm", rows, c) + offset
    tol = 1e-9 * (1.0 + np.abs(value).max(axis=-1))
    best, out = np.full(c.shape[:2], np.inf), c.copy()
    for active, K in maps:
        d = c - np.einsum("knm,bkm->bkn", K, value[..., active])
        v = np.einsum("kmn,bkn->bkm", rows, d) + offset
        ok = (v.min(axis=-1) >= -tol) & (np.abs(v[..., active]).max(axis=-1, initial=0.0) <= tol)
        step = d - c
        cost = np.einsum("bkn,knm,bkm->bk", step, metric, step)
        better = ok & (cost < best)
        best = np.where(better, cost, best)
        out[better] = d[better]
    return out, np.isfinite(best)


def admm(xp: Any, qp_step: Callable[..., tuple[Any, Any, int]], project: Callable[[Any], Any], delta: Any,
         iterations: int, rho_scale: float, last_target_is_delta: bool) -> dict[str, Any]:
    """C3's iterations: ``z = QP(i, delta - w)``, ``delta' = project(z + w)``,
    ``w' = (w + z - delta') / rho_scale``; then ``z = QP(K, delta - w)`` (``delta`` if
    ``last_target_is_delta``). ``qp_step(level, target) -> (z, x_N, failures)``.

    Returns ``z``, ``x_N``, ``delta``, ``primal`` and ``dual`` (``(B, K)``: ``max |z - delta'|``
    and ``max |delta' - delta|`` of each iteration), ``failures`` and the seconds in ``"qp"`` and
    ``"projection"``.
    """
    w = delta * 0.0
    primal, dual, failures = [], [], 0
    t_qp = t_proj = 0.0
    for i in range(iterations):
        t0 = time.perf_counter()
        z, _, bad = qp_step(i, delta - w)
        t1 = time.perf_counter()
        new = project(z + w)
        t_proj += time.perf_counter() - t1
        t_qp += t1 - t0
        failures += bad
        w = (w + z - new) / rho_scale
        primal.append(z - new)
        dual.append(new - delta)
        delta = new
    t0 = time.perf_counter()
    z, xN, bad = qp_step(iterations, delta if last_target_is_delta else delta - w)
    t_qp += time.perf_counter() - t0
    B = delta.shape[0]
    # (B, K * m) -> one row per (plan, iteration) -> (B, K)
    primal = xp.amax_abs(xp.concat([d.reshape(B, -1) for d in primal]).reshape(B * iterations, -1)).reshape(B, -1)
    dual = xp.amax_abs(xp.concat([d.reshape(B, -1) for d in dual]).reshape(B * iterations, -1)).reshape(B, -1)
    return {"z": z, "x_N": xN, "delta": delta, "primal": primal, "dual": dual,
            "failures": failures + bad, "qp": t_qp, "projection": t_proj}
