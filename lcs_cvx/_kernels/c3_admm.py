r"""C3's ADMM compiled (numba): one initial state at a time, the QP steps, the projections, the
dual update and the model's own rollout of the plan in one loop, for float64 NumPy arrays.

The same computation as the array kernels of :mod:`.c3` (which serve torch, other devices and
the QP paths this does not cover), written sample by sample: at C3's sizes (``n_y`` of a few
dozen, ``N`` of a few steps) a solve is a few hundred array operations of a few hundred numbers
each, and their per-operation overhead, not the arithmetic, is what an array library costs.

For one initial state ``x0`` and one projection, with ``delta^0`` given and ``w^0 = 0``, each
of the ``K`` iterations ``i`` does

$$
y = b_i + \mathrm{vec}(\delta - w)^\top Y_{t,i}, \qquad
\delta' = \Pi(z + w), \qquad w' = (w + z - \delta') / \rho_s
$$

(``y = (z_0, ..., z_{N-1}, x_N)``; ``b_i = p Y_{f,i} + y_{0,i}`` the fixed data's part of level
``i``'s affine map, :mod:`lcs_cvx.control.qp`), then the last step at level ``K`` with target
``delta``. With box bounds on coordinates ``S`` of ``y`` the step adds ``mu P_{S}^T`` with the
multipliers ``mu`` of the box QP :func:`.box_qp.box_qp` on ``y_S``. The projections:
``"lcp"`` (kind 0), ``lam_k = LCP(F_k, D_k x_k + E_k u_k + c_k)``, ``eta_k = D_k x_k + E_k u_k +
F_k lam_k + c_k``; ``"c3+"`` (kind 1), per unit the one of ``lam_i``, ``eta_i`` costlier to
keep in the ``U``-metric zeroed, the other clipped at 0.

Shapes: ``x0 (n_x,)``; the model's matrices stacked over the steps, ``A (N, n_x, n_x)``,
``B (N, n_x, n_u)``, ``C (N, n_x, n_lam)``, ``d (N, n_x)``, ``D (N, n_lam, n_x)``,
``E (N, n_lam, n_u)``, ``F (N, n_lam, n_lam)``, ``c (N, n_lam)``; the maps ``Yf (K + 1, n_p,
n_y)``, ``Yt (K + 1, N n_z, n_y)``, ``y0 (K + 1, n_y)``.
"""

from __future__ import annotations

import numba
import numpy as np

from .box_qp import box_qp
from .dense import JIT, lu_factor, lu_solve, move, progress

__all__ = ["FALLBACK", "admm_one", "model_lcp", "plan_cost", "rollout_model", "violation_of"]

#: The status of a solve the compiled path leaves to the array kernels (an LCP not solved by
#: pivoting, a singular system, a box QP that did not finish): they reach the same answer, or
#: raise, by their own fallbacks.
FALLBACK = 1


@numba.njit(inline="always", **JIT)
def _candidate(F, q, lo, lam, w, bad, free, idx, M, piv):  # pragma: no cover - compiled
    """One candidate of the LCP on the free set ``free``: ``F_II lam_I = -q_I`` (LU with
    partial pivoting in ``M[0]``), ``w = F lam + q``, the infeasible flags in ``bad`` (a free
    ``lam_i < lo`` or a bound ``w_i < lo``; every flag where ``F_II`` is singular); their count."""
    n = q.shape[0]
    m = 0
    for i in range(n):
        if free[i]:
            idx[m] = i
            m += 1
    for a in range(m):
        for b in range(m):
            M[0, a, b] = F[idx[a], idx[b]]
    ok = lu_factor(M, piv, 0, m)
    for i in range(n):
        lam[i] = 0.0
    if ok:
        for a in range(m):
            w[a] = -q[idx[a]]
        lu_solve(M, piv, 0, w, m)
        for a in range(m):
            lam[idx[a]] = w[a]
    count = 0
    for i in range(n):
        v = q[i]
        for j in range(n):
            v += F[i, j] * lam[j]
        w[i] = v
        f = free[i]
        b = (not ok) | (f & (lam[i] < lo)) | ((not f) & (v < lo))
        bad[i] = b
        count += b
    return count


@numba.njit(**JIT)
def model_lcp(F, q, lam, w, free, bad, M, piv, tol, max_iter, stall):  # pragma: no cover - compiled
    """``lam = LCP(F, q)`` (``0 <= lam _|_ F lam + q >= 0``, ``F (n, n)``, ``q (n,)``) into
    ``lam``, clamped at 0: block pivoting from the free set ``q < 0``, Murty's single pivot once
    ``stall`` sweeps pass without a new lowest infeasible count (:func:`.lcp.pivot_lcp`'s
    algorithm, as :func:`.compiled.lcp` runs it); ``F_II``'s LU factors in ``M[0]``, ``piv[0]``.
    Returns True where it converged within ``max_iter`` sweeps."""
    n = q.shape[0]
    big = 0.0
    for i in range(n):
        free[i] = q[i] < 0.0
        big = max(big, abs(q[i]))
    lo = -tol * (1.0 + big)
    idx = np.empty(n, dtype=np.int64)
    n_bad = _candidate(F, q, lo, lam, w, bad, free, idx, M, piv)
    sweeps, best, stalled = 0, n_bad, 0
    while sweeps < max_iter and n_bad > 0:
        move(bad, free, n, sweeps >= stall and stalled >= stall)
        n_bad = _candidate(F, q, lo, lam, w, bad, free, idx, M, piv)
        sweeps += 1
        best, stalled = progress(n_bad, best, stalled)
    for i in range(n):
        lam[i] = max(lam[i], 0.0)
    return n_bad == 0


@numba.njit(inline="always", **JIT)
def affine_row(off, P, p, Q, q, k, i):  # pragma: no cover - compiled
    """``off[k, i] + P[k, i] . p[k] + Q[k, i] . q[k]``, summed in that order (row ``i`` of step
    ``k``'s ``D x + E u + c`` or of its dynamics)."""
    v = off[k, i]
    for j in range(p.shape[1]):
        v += P[k, i, j] * p[k, j]
    for j in range(q.shape[1]):
        v += Q[k, i, j] * q[k, j]
    return v


@numba.njit(inline="always", **JIT)
def affine_row3(off, P, p, Q, q, R, r, k, i):  # pragma: no cover - compiled
    """:func:`affine_row` ``+ R[k, i] . r[k]`` (``A x + B u + C lam + d``, ``D x + E u + F lam + c``)."""
    v = affine_row(off, P, p, Q, q, k, i)
    for j in range(r.shape[1]):
        v += R[k, i, j] * r[k, j]
    return v


@numba.njit(**JIT)
def rollout_model(x0, u, A, B, C, d, D, E, c, F, xs, lams, scratch, piv, tol, max_iter, stall):  # pragma: no cover
    """The model's own rollout of the inputs ``u (N, n_u)`` from ``x0``: ``lam_k =
    LCP(F_k, D_k x_k + E_k u_k + c_k)``, ``x_{k+1} = A_k x_k + B_k u_k + C_k lam_k + d_k`` into
    ``xs (N + 1, n_x)`` and ``lams (N, n_lam)``; False if an LCP did not converge."""
    N, nx = A.shape[0], A.shape[1]
    nl = C.shape[2]
    q, w = np.empty(nl), np.empty(nl)
    free, bad = np.empty(nl, dtype=np.bool_), np.empty(nl, dtype=np.bool_)
    xs[0] = x0
    for k in range(N):
        for i in range(nl):
            q[i] = affine_row(c, D, xs, E, u, k, i)
        if not model_lcp(F[k], q, lams[k], w, free, bad, scratch, piv, tol, max_iter, stall):
            return False
        for i in range(nx):
            xs[k + 1, i] = affine_row3(d, A, xs, B, u, C, lams, k, i)
    return True


@numba.njit(inline="always", **JIT)
def _quadratic(v, M):  # pragma: no cover - compiled
    """``v^T M v``, summed column by column (``sum_j (sum_i v_i M_ij) v_j``)."""
    s = 0.0
    for j in range(v.shape[0]):
        acc = 0.0
        for i in range(v.shape[0]):
            acc += v[i] * M[i, j]
        s += acc * v[j]
    return s


@numba.njit(**JIT)
def plan_cost(xs, u, u_ref, xd, Q, R, QN):  # pragma: no cover - compiled
    """``sum_k (x_k - x^d_k)^T Q_k (x_k - x^d_k) + (u_k - u^ref_k)^T R_k (u_k - u^ref_k)`` plus
    the terminal ``(x_N - x^d_N)^T Q_N (x_N - x^d_N)``; ``xs (N + 1, n_x)``, ``u (N, n_u)``."""
    N, nx, nu = u.shape[0], xs.shape[1], u.shape[1]
    total = 0.0
    e = np.empty(nx)
    du = np.empty(nu)
    for k in range(N + 1):
        for i in range(nx):
            e[i] = xs[k, i] - xd[k, i]
        total += _quadratic(e, Q[k] if k < N else QN)
        if k < N:
            for i in range(nu):
                du[i] = u[k, i] - u_ref[k, i]
            total += _quadratic(du, R[k])
    return total


@numba.njit(**JIT)
def violation_of(xs, u, lam, D, E, F, c):  # pragma: no cover - compiled
    """``max_k max_i |min(lam_k, D_k x_k + E_k u_k + F_k lam_k + c_k)_i|``."""
    N, nl = u.shape[0], lam.shape[1]
    out = 0.0
    for k in range(N):
        for i in range(nl):
            out = max(out, abs(min(lam[k, i], affine_row3(c, D, xs, E, u, F, lam, k, i))))
    return out


@numba.njit(**JIT)
def _qp_step(level, target, base, Yt, S, lo, hi, P_SS, P_ST, y):  # pragma: no cover - compiled
    """The QP step at ``level``: ``y = base[level] + target Yt[level]`` (``target (N n_z,)``),
    then within the bounds ``lo <= y_S <= hi`` where ``S`` is not empty. Returns the box QP's
    status (``>= 0`` solved, ``-1`` infeasible, ``-2`` not finished)."""
    n_t, n_y = Yt.shape[1], Yt.shape[2]
    for j in range(n_y):
        y[j] = base[level, j]
    for t in range(n_t):
        v = target[t]
        if v != 0.0:
            for j in range(n_y):
                y[j] += v * Yt[level, t, j]
    m = S.shape[0]
    if m == 0:
        return 0
    s = np.empty((1, m))
    for a in range(m):
        s[0, a] = y[S[a]]
    mu, status = box_qp(P_SS[level], s, lo, hi, 20 * m + 100)
    for a in range(m):
        v = mu[0, a]
        if v != 0.0:
            for j in range(n_y):
                y[j] += v * P_ST[level, a, j]
    return status[0]


@numba.njit(**JIT)
def admm_one(kind, x0, delta0, base, Yt, S, lo, hi, P_SS, P_ST, iterations, rho_scale, sw_lam, sw_eta,
             Da, Ea, Fa, ca, n_x, n_lam, n_u, delta, primal, dual, z, xN, tol, max_iter, stall):  # pragma: no cover
    """C3's ADMM from ``delta0 (N, n_z)`` with the projection ``kind`` (0 ``"lcp"`` on the ADMM's
    system ``Da, Ea, Fa, ca``; 1 ``"c3+"`` with the weights ``sw_lam, sw_eta (N, n_lam)``, the
    square roots of ``U``'s diagonal), then the last QP step: ``z (N, n_z)``, ``xN (n_x,)``, the
    last projection ``delta`` and the residuals ``primal``, ``dual (K,)`` filled in. Returns
    ``(failures, status)``: the QP steps whose bounds no input meets (C3's fallback plan
    ``x_k = x0``, ``lam = u = 0``), and 0, or :data:`FALLBACK`."""
    N, nz = delta0.shape
    n_t = N * nz
    lam0, u0, eta0 = n_x, n_x + n_lam, n_x + n_lam + n_u
    y = np.empty(base.shape[1])
    target = np.empty(n_t)
    w = np.zeros((N, nz))
    new = np.empty((N, nz))
    q, lw = np.empty(n_lam), np.empty(n_lam)
    free, bad = np.empty(n_lam, dtype=np.bool_), np.empty(n_lam, dtype=np.bool_)
    scratch, piv = np.empty((1, n_lam, n_lam)), np.empty((1, n_lam), dtype=np.uint64)
    lam = np.empty(n_lam)
    for k in range(N):
        for j in range(nz):
            delta[k, j] = delta0[k, j]
    failures = 0
    for i in range(iterations + 1):
        for k in range(N):
            for j in range(nz):
                target[k * nz + j] = delta[k, j] - w[k, j] if i < iterations else delta[k, j]
        status = _qp_step(i, target, base, Yt, S, lo, hi, P_SS, P_ST, y)
        if status == -2:
            return failures, FALLBACK
        if status == -1:  # no input meets the bounds: C3's fallback plan
            failures += 1
            for j in range(y.shape[0]):
                y[j] = 0.0
            for k in range(N + 1):
                for j in range(n_x):
                    y[k * nz + j] = x0[j]
        for k in range(N):
            for j in range(nz):
                z[k, j] = y[k * nz + j]
        for j in range(n_x):
            xN[j] = y[N * nz + j]
        if i == iterations:
            break
        for k in range(N):
            for j in range(nz):
                new[k, j] = z[k, j] + w[k, j]
            if kind == 1:
                for a in range(n_lam):
                    cl, ce = new[k, lam0 + a], new[k, eta0 + a]
                    if ce * sw_eta[k, a] > cl * sw_lam[k, a]:
                        new[k, lam0 + a], new[k, eta0 + a] = 0.0, max(ce, 0.0)
                    else:
                        new[k, lam0 + a], new[k, eta0 + a] = max(cl, 0.0), 0.0
            else:
                for a in range(n_lam):
                    v = ca[k, a]
                    for j in range(n_x):
                        v += Da[k, a, j] * new[k, j]
                    for j in range(n_u):
                        v += Ea[k, a, j] * new[k, u0 + j]
                    q[a] = v
                if not model_lcp(Fa[k], q, lam, lw, free, bad, scratch, piv, tol, max_iter, stall):
                    return failures, FALLBACK
                for a in range(n_lam):
                    v = q[a]
                    for j in range(n_lam):
                        v += Fa[k, a, j] * lam[j]
                    new[k, lam0 + a] = lam[a]
                    new[k, eta0 + a] = v
        p = dd = 0.0
        for k in range(N):
            for j in range(nz):
                p = max(p, abs(z[k, j] - new[k, j]))
                dd = max(dd, abs(new[k, j] - delta[k, j]))
                w[k, j] = (w[k, j] + z[k, j] - new[k, j]) / rho_scale
                delta[k, j] = new[k, j]
        primal[i], dual[i] = p, dd
    return failures, 0
