r"""C3's polish and a whole C3 solve compiled (numba), initial state by initial state: the
compiled counterpart of :mod:`.polish` and of :class:`lcs_cvx.control.C3`'s solve on the array
kernels, for float64 NumPy arrays.

The polish (:mod:`.polish` states it in full): in the contact mode ``a_k = {i : lam_{k,i} > 0}``
the model visits under the inputs ``u``, the LCS is affine,

$$
[\tilde A_k\ \tilde B_k\ \tilde d_k] = [A_k\ B_k\ d_k] - C_{k,a} F_{k,aa}^{-1} [D_{k,a}\ E_{k,a}\ c_{k,a}],
$$

and the horizon cost a quadratic ``1/2 U^T H U + f^T U`` in the stacked inputs ``U (N n_u,)``,
minimised by ``H U = -f`` (LU with partial pivoting), or within the input bounds by the active
set method of :mod:`.box_qp` with ``P = H^{-1}``. The model's rollout of the new inputs is kept
where it costs less (and meets the state and force bounds), and the step repeats in the modes it
visits, at most ``iterations`` times, until the modes repeat.

:func:`solve_states` runs, per initial state, the ADMM with each projection
(:func:`.c3_admm.admm_one`), the model's rollout and cost of each plan, the cheapest plan (the
first unless another costs less by more than ``1e-9 (1 + |cost|)``) and its polish.
"""

from __future__ import annotations

import numba
import numpy as np

from .box_qp import box_qp
from .c3_admm import FALLBACK, admm_one, model_lcp, plan_cost, rollout_model, violation_of
from .dense import JIT, lu_factor, lu_solve

__all__ = ["polish_one", "solve_states"]


@numba.njit(**JIT)
def _mode_dynamics(A, B, C, d, D, E, F, c, active, At, Bt, dt, M, piv):  # pragma: no cover - compiled
    """``At (N, n_x, n_x)``, ``Bt (N, n_x, n_u)``, ``dt (N, n_x)`` of the modes ``active
    (N, n_lam)``; False where some ``F_aa`` is singular."""
    N, nx, nu, nl = A.shape[0], A.shape[1], B.shape[2], C.shape[2]
    idx = np.empty(nl, dtype=np.int64)
    col = np.empty(nl)
    sol = np.empty((nl, nx + nu + 1))
    for k in range(N):
        m = 0
        for i in range(nl):
            if active[k, i]:
                idx[m] = i
                m += 1
        for a in range(m):
            for b in range(m):
                M[0, a, b] = F[k, idx[a], idx[b]]
        if not lu_factor(M, piv, 0, m):
            return False
        for j in range(nx + nu + 1):
            for a in range(m):
                i = idx[a]
                col[a] = D[k, i, j] if j < nx else (E[k, i, j - nx] if j < nx + nu else c[k, i])
            lu_solve(M, piv, 0, col, m)
            for a in range(m):
                sol[a, j] = col[a]
        for r in range(nx):
            for j in range(nx + nu + 1):
                v = 0.0
                for a in range(m):
                    v += C[k, r, idx[a]] * sol[a, j]
                if j < nx:
                    At[k, r, j] = A[k, r, j] - v
                elif j < nx + nu:
                    Bt[k, r, j - nx] = B[k, r, j - nx] - v
                else:
                    dt[k, r] = d[k, r] - v
    return True


@numba.njit(**JIT)
def _condensed(x0, At, Bt, dt, xd, u_ref, Q, R, QN, H, f):  # pragma: no cover - compiled
    """``H (M, M)``, ``f (M,)`` of the horizon cost on the modes' dynamics: ``x_k = xbar_k +
    Gamma_k U``, ``H = sum_k Gamma_k^T Q_k Gamma_k + blkdiag(R_k)``, ``f = sum_k Gamma_k^T Q_k
    (xbar_k - x^d_k) - (R_k u^ref_k)_k`` (``M = N n_u``)."""
    N, nx, nu = Bt.shape[0], Bt.shape[1], Bt.shape[2]
    M = N * nu
    H[:, :] = 0.0
    f[:] = 0.0
    xbar, nxt = x0.copy(), np.empty(nx)
    Gam, Gn = np.zeros((nx, M)), np.empty((nx, M))
    GW = np.empty((M, nx))
    for k in range(N + 1):
        if k > 0:
            for a in range(M):
                for j in range(nx):
                    v = 0.0
                    for i in range(nx):
                        v += Gam[i, a] * (Q[k, i, j] if k < N else QN[i, j])
                    GW[a, j] = v
            for a in range(M):
                for b in range(M):
                    v = 0.0
                    for j in range(nx):
                        v += GW[a, j] * Gam[j, b]
                    H[a, b] += v
                v = 0.0
                for j in range(nx):
                    v += GW[a, j] * (xbar[j] - xd[k, j])
                f[a] += v
        if k == N:
            break
        s = k * nu
        for a in range(nu):
            for b in range(nu):
                H[s + a, s + b] += R[k, a, b]
            v = 0.0
            for i in range(nu):
                v += u_ref[k, i] * R[k, i, a]
            f[s + a] -= v
        for i in range(nx):
            v = dt[k, i]
            for j in range(nx):
                v += At[k, i, j] * xbar[j]
            nxt[i] = v
            for b in range(M):
                v = 0.0
                for j in range(nx):
                    v += At[k, i, j] * Gam[j, b]
                Gn[i, b] = v
        xbar[:] = nxt
        for i in range(nx):
            for b in range(M):
                Gam[i, b] = Gn[i, b]
            for a in range(nu):
                Gam[i, s + a] += Bt[k, i, a]


@numba.njit(**JIT)
def _within(xs, lams, x_lo, x_hi, l_lo, l_hi):  # pragma: no cover - compiled
    """Whether ``x_1 .. x_N`` and the forces meet their bounds, to ``1e-9 (1 + |v|)``."""
    for k in range(1, xs.shape[0]):
        for i in range(xs.shape[1]):
            v = xs[k, i]
            t = 1e-9 * (1.0 + abs(v))
            if not (v >= x_lo[i] - t and v <= x_hi[i] + t):
                return False
    for k in range(lams.shape[0]):
        for i in range(lams.shape[1]):
            v = lams[k, i]
            t = 1e-9 * (1.0 + abs(v))
            if not (v >= l_lo[i] - t and v <= l_hi[i] + t):
                return False
    return True


@numba.njit(**JIT)
def polish_one(x0, xd, u_ref, A, B, C, d, D, E, F, c, Q, R, QN, u_lo, u_hi, x_lo, x_hi, l_lo, l_hi,
               iterations, u, xs, lams, cost, tol, max_iter, stall):  # pragma: no cover - compiled
    """The polish of the plan ``u (N, n_u)`` (its model rollout ``xs (N + 1, n_x)``, ``lams
    (N, n_lam)`` and ``cost``), in place: the cheapest plan found. ``u_lo, u_hi``: bounds of the
    stacked inputs ``(N n_u,)`` (empty: none). Returns ``(polished, cost, status)``; a status of
    :data:`.c3_admm.FALLBACK` (an LCP not solved by pivoting, a singular ``F_aa`` or ``H``)
    leaves the solve to the array kernels."""
    N, nx, nu, nl = A.shape[0], A.shape[1], B.shape[2], C.shape[2]
    M = N * nu
    At, Bt, dt = np.empty((N, nx, nx)), np.empty((N, nx, nu)), np.empty((N, nx))
    scratch, piv = np.empty((1, max(nl, M), max(nl, M))), np.empty((1, max(nl, M)), dtype=np.uint64)
    H, f = np.empty((M, M)), np.empty(M)
    U = np.empty(M)
    Un = np.empty((N, nu))
    xn, ln = np.empty((N + 1, nx)), np.empty((N, nl))
    active = np.empty((N, nl), dtype=np.bool_)
    for k in range(N):
        for i in range(nl):
            active[k, i] = lams[k, i] > 0.0
    polished = False
    for _ in range(iterations):
        if not _mode_dynamics(A, B, C, d, D, E, F, c, active, At, Bt, dt, scratch, piv):
            return polished, cost, FALLBACK
        _condensed(x0, At, Bt, dt, xd, u_ref, Q, R, QN, H, f)
        for a in range(M):
            for b in range(M):
                scratch[0, a, b] = H[a, b]
            U[a] = -f[a]
        if not lu_factor(scratch, piv, 0, M):
            return polished, cost, FALLBACK
        lu_solve(scratch, piv, 0, U, M)
        failed = False
        if u_lo.shape[0]:
            P = np.empty((M, M))
            e = np.empty(M)
            for j in range(M):
                for a in range(M):
                    e[a] = 1.0 if a == j else 0.0
                lu_solve(scratch, piv, 0, e, M)
                for a in range(M):
                    P[a, j] = e[a]
            mu, status = box_qp(P, U.reshape(1, M).copy(), u_lo, u_hi, 20 * M + 100)
            if status[0] < 0:
                failed = True
            else:
                for a in range(M):
                    v = 0.0
                    for j in range(M):
                        v += P[a, j] * mu[0, j]
                    U[a] += v
        for k in range(N):
            for i in range(nu):
                Un[k, i] = U[k * nu + i]
        if not rollout_model(x0, Un, A, B, C, d, D, E, c, F, xn, ln, scratch, piv, tol, max_iter, stall):
            return polished, cost, FALLBACK
        cn = plan_cost(xn, Un, u_ref, xd, Q, R, QN)
        if not failed and cn < cost - 1e-12 * (1.0 + abs(cost)) and _within(xn, ln, x_lo, x_hi, l_lo, l_hi):
            u[:, :] = Un
            xs[:, :] = xn
            lams[:, :] = ln
            cost = cn
            polished = True
        same = True
        for k in range(N):
            for i in range(nl):
                a = ln[k, i] > 0.0
                same = same and a == active[k, i]
                active[k, i] = a
        if same:
            break
    return polished, cost, 0


@numba.njit(**JIT)
def solve_states(X0, XD, UREF, DELTA0, kinds, Yf, Yt, y0, S, lo, hi, P_SS, P_ST, iterations, rho_scale,
                 sw_lam, sw_eta, A, B, C, d, D, E, F, c, Da, Ea, ca, Q, R, QN, fix_lam0, lam_scale, polish,
                 u_lo, u_hi, x_lo, x_hi, l_lo, l_hi, tol, max_iter, stall,
                 x, u, lam, delta, primal, dual, compl, x_model, lam_model, cost, polished, chosen, gap
                 ):  # pragma: no cover - compiled
    """C3's solve from each row of ``X0 (B, n_x)`` (targets ``XD (B, N + 1, n_x)``, input
    references ``UREF (B, N, n_u)``, first ``DELTA0 (B, N, n_z)``) with the projections
    ``kinds`` (0 ``"lcp"``, 1 ``"c3+"``), the QP maps ``Yf, Yt, y0`` and the bounded step's
    ``S, lo, hi, P_SS (K + 1, m, m), P_ST (K + 1, m, n_y)``. ``Da, Ea, ca``: the ADMM's system
    (the model's, or with ``lam`` rescaled by ``lam_scale``); ``fix_lam0``: ``lam_0 =
    LCP(F_0, D_0 x0 + c_0)``; ``polish``: the polish's iterations, within the bounds ``u_lo,
    u_hi`` (stacked, empty: none) and, for its rollouts, ``x_lo, x_hi, l_lo, l_hi``. Fills in,
    row by row, ``x``, ``u``, ``lam``, ``delta``, the residuals ``primal, dual (B, K)``,
    ``compl``, ``x_model``, ``lam_model``, ``cost``, ``polished``, ``chosen`` (the index in
    ``kinds`` of the plan applied) and ``gap`` (``max |x_model - x|``). Returns ``(failures,
    status)``; a status of :data:`.c3_admm.FALLBACK` leaves the whole solve to the array
    kernels."""
    n_b, nx = X0.shape
    N, nz = DELTA0.shape[1], DELTA0.shape[2]
    nu, nl = B.shape[2], C.shape[2]
    n_pf, n_y = Yf.shape[1], Yf.shape[2]
    levels = Yf.shape[0]
    base = np.empty((levels, n_y))
    p = np.empty(n_pf)
    q, w = np.empty(nl), np.empty(nl)
    free, bad = np.empty(nl, dtype=np.bool_), np.empty(nl, dtype=np.bool_)
    scratch, piv = np.empty((1, nl, nl)), np.empty((1, nl), dtype=np.uint64)
    lam0 = np.zeros(nl)
    z, xN = np.empty((N, nz)), np.empty(nx)
    dl, pr, du = np.empty((N, nz)), np.empty(iterations), np.empty(iterations)
    up, lp = np.empty((N, nu)), np.empty((N, nl))
    xs, xm, lm = np.empty((N + 1, nx)), np.empty((N + 1, nx)), np.empty((N, nl))
    failures = 0
    for b in range(n_b):
        x0 = X0[b]
        # the fixed data p = (x0, lam0, x^d, u^ref) and its part of each level's map
        at = 0
        for j in range(nx):
            p[at] = x0[j]
            at += 1
        if fix_lam0:
            neg = False
            for i in range(nl):
                v = c[0, i]
                for j in range(nx):
                    v += D[0, i, j] * x0[j]
                q[i] = v
                neg = neg or v < 0.0
            if neg:
                if not model_lcp(F[0], q, lam0, w, free, bad, scratch, piv, tol, max_iter, stall):
                    return failures, FALLBACK
            else:
                lam0[:] = 0.0
            for i in range(nl):
                p[at] = lam0[i] / lam_scale
                at += 1
        for k in range(N + 1):
            for j in range(nx):
                p[at] = XD[b, k, j]
                at += 1
        for k in range(N):
            for j in range(nu):
                p[at] = UREF[b, k, j]
                at += 1
        for lv in range(levels):
            for j in range(n_y):
                base[lv, j] = 0.0
            for a in range(n_pf):
                v = p[a]
                if v != 0.0:
                    for j in range(n_y):
                        base[lv, j] += v * Yf[lv, a, j]
            for j in range(n_y):
                base[lv, j] += y0[lv, j]
        for pi in range(kinds.shape[0]):
            fails, status = admm_one(kinds[pi], x0, DELTA0[b], base, Yt, S, lo, hi, P_SS, P_ST, iterations,
                                     rho_scale, sw_lam, sw_eta, Da, Ea, F, ca, nx, nl, nu, dl, pr, du, z, xN,
                                     tol, max_iter, stall)
            if status != 0:
                return failures, status
            failures += fails
            for k in range(N):
                for j in range(nu):
                    up[k, j] = z[k, nx + nl + j]
                for j in range(nl):
                    lp[k, j] = z[k, nx + j] * lam_scale
            # the plan's states (its inputs and forces through the dynamics) and the model's
            xs[0] = x0
            for k in range(N):
                for i in range(nx):
                    v = 0.0
                    for j in range(nx):
                        v += A[k, i, j] * xs[k, j]
                    for j in range(nu):
                        v += B[k, i, j] * up[k, j]
                    for j in range(nl):
                        v += C[k, i, j] * lp[k, j]
                    xs[k + 1, i] = v + d[k, i]
            if not rollout_model(x0, up, A, B, C, d, D, E, c, F, xm, lm, scratch, piv, tol, max_iter, stall):
                return failures, FALLBACK
            cp = plan_cost(xm, up, UREF[b], XD[b], Q, R, QN)
            if pi > 0 and not cp < cost[b] - 1e-9 * (1.0 + abs(cost[b])):
                continue
            chosen[b] = pi
            cost[b] = cp
            x[b] = xs
            u[b] = up
            lam[b] = lp
            delta[b] = dl
            primal[b] = pr
            dual[b] = du
            x_model[b] = xm
            lam_model[b] = lm
            compl[b] = violation_of(xs, up, lp, D, E, F, c)
        polished[b] = False
        if polish > 0:
            done, cb, status = polish_one(x0, XD[b], UREF[b], A, B, C, d, D, E, F, c, Q, R, QN, u_lo, u_hi,
                                          x_lo, x_hi, l_lo, l_hi, polish, u[b], x_model[b], lam_model[b],
                                          cost[b], tol, max_iter, stall)
            if status != 0:
                return failures, status
            if done:
                cost[b] = cb
                polished[b] = True
                x[b] = x_model[b]
                lam[b] = lam_model[b]
                compl[b] = violation_of(x[b], u[b], lam[b], D, E, F, c)
        g = 0.0
        for k in range(N + 1):
            for j in range(nx):
                g = max(g, abs(x_model[b, k, j] - x[b, k, j]))
        gap[b] = g
    return failures, 0
