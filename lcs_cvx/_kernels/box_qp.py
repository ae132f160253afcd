r"""Box bounds on coordinates of an equality-constrained QP, compiled (numba): the bounded QP
step of C3's fast path (:mod:`lcs_cvx.control.qp`).

The QP ``min 1/2 y^T H y + f^T y`` s.t. ``A y = b`` has the solution ``y*`` (the fast path's
affine map). Let ``P`` be the ``(n_y, n_y)`` block of the inverse of its KKT matrix
(``P = Z (Z^T H Z)^{-1} Z^T``, ``Z`` a basis of the null space of ``A``) and ``s = y_S`` the
bounded coordinates. With bound constraints ``lo <= s <= hi`` the KKT conditions give
``y = y* + P_{:,S} mu`` (``mu_j`` the bound multipliers of coordinate ``j``, positive at ``lo``,
negative at ``hi``), so that the whole problem lives in ``S``:

$$
s = s^* + P_{SS}\, \mu, \qquad lo \le s \le hi, \qquad
\mu_j \ge 0 \text{ where } s_j = lo_j, \quad \mu_j \le 0 \text{ where } s_j = hi_j,
\quad \mu_j = 0 \text{ elsewhere}.
$$

:func:`box_qp` solves it per sample by Goldfarb and Idnani's dual active-set method (Math.
Programming 27, 1983) with ``P_SS`` in the place of the inverse Hessian: from ``s*`` (the
unconstrained minimum) a violated bound joins the active set, a partial step drops an active
bound whose multiplier would change sign, and the iterate stays optimal for its active set.
Exact in finitely many steps; ``P_SS`` may be singular (more bounded coordinates than the QP
has freedom, e.g. bounds on every state), and a bound set no choice of the QP meets is reported
as infeasible.

Shapes: ``P (m, m)`` (``P_SS``), ``s_star (B, m)``, ``lo, hi (m,)`` (``+-inf`` for none); returns
``mu (B, m)`` and a status per sample (the iterations; ``-1`` infeasible, ``-2`` not converged,
or an answer that misses a bound by more than 1e-8 relative, beyond the round-off of ``s*``'s
size: the active bounds nearly dependent).
"""

from __future__ import annotations

import numba
import numpy as np

from .dense import JIT

__all__ = ["box_qp"]


@numba.njit(**JIT)
def _directions(P, coord, sign, q, jp, sp):  # pragma: no cover - compiled
    """For the active bounds ``0..q-1`` (coordinates ``coord``, normals ``sign * e``) and the
    candidate ``(jp, sp)``: the primal step ``z = P n_p - P N r`` (``(m,)``) and the dual step
    ``r = (N^T P N)^{-1} N^T P n_p`` (``(q,)``)."""
    m = P.shape[0]
    r = np.zeros(q)
    if q:
        M = np.empty((q, q))
        v = np.empty(q)
        for a in range(q):
            v[a] = sign[a] * sp * P[coord[a], jp]
            for b in range(q):
                M[a, b] = sign[a] * sign[b] * P[coord[a], coord[b]]
        r = np.linalg.solve(M, v)
    z = np.empty(m)
    for k in range(m):
        acc = sp * P[k, jp]
        for a in range(q):
            acc -= sign[a] * P[k, coord[a]] * r[a]
        z[k] = acc
    return z, r


@numba.njit(**JIT)
def box_qp(P, s_star, lo, hi, max_iter):  # pragma: no cover - compiled
    """``mu (B, m)`` and the status ``(B,)`` of the bounded problem of the module docstring per
    row of ``s_star``."""
    n, m = s_star.shape
    out = np.zeros((n, m))
    status = np.zeros(n, dtype=np.int64)
    scale = 1.0
    for i in range(m):
        scale = max(scale, abs(P[i, i]))
    for b in range(n):
        s = s_star[b].copy()
        coord = np.empty(m, dtype=np.int64)  # the active bounds: coordinate, normal sign, multiplier
        sign = np.empty(m)
        u = np.empty(m)
        q = 0
        tol = 1e-11 * (1.0 + np.abs(s).max())
        it = 0
        state = -2
        while it < max_iter:
            # the most violated bound
            jp, sp, worst = -1, 0.0, -tol
            for j in range(m):
                if s[j] - lo[j] < worst:
                    jp, sp, worst = j, 1.0, s[j] - lo[j]
                if hi[j] - s[j] < worst:
                    jp, sp, worst = j, -1.0, hi[j] - s[j]
            if jp < 0:
                state = it
                break
            up = 0.0  # the candidate's multiplier
            while it < max_iter:
                it += 1
                z, r = _directions(P, coord, sign, q, jp, sp)
                zn = sp * z[jp]
                slack = s[jp] - lo[jp] if sp > 0 else hi[jp] - s[jp]
                # the bound's freedom left by the active ones (a Schur complement of P); below a
                # 1e-9 share of its own, it counts as fixed by them (dependent in P's metric)
                t2 = -slack / zn if zn > 1e-9 * P[jp, jp] and zn > 1e-14 * scale else np.inf
                t1, drop = np.inf, -1
                for a in range(q):
                    if r[a] > 0.0 and u[a] / r[a] < t1:
                        t1, drop = u[a] / r[a], a
                t = min(t1, t2)
                if t == np.inf:
                    state = -1  # no choice of the QP meets this bound with the active ones
                    break
                if t2 < np.inf:
                    for k in range(m):
                        s[k] += t * z[k]
                for a in range(q):
                    u[a] -= t * r[a]
                up += t
                if t == t2:  # the bound is met: it joins the active set
                    coord[q], sign[q], u[q] = jp, sp, up
                    q += 1
                    if sp > 0:
                        s[jp] = lo[jp]
                    else:
                        s[jp] = hi[jp]
                    break
                for a in range(drop, q - 1):  # a partial step: the blocking bound leaves
                    coord[a], sign[a], u[a] = coord[a + 1], sign[a + 1], u[a + 1]
                q -= 1
            if state == -1:
                break
        for a in range(q):
            out[b, coord[a]] += sign[a] * u[a]
        if state >= 0:  # the bounds met by the answer itself, not only by the iterate
            size = 1.0 + np.abs(s_star[b]).max()  # s = s* + P mu cancels: round-off of s*'s size
            for j in range(m):
                acc = s_star[b, j]
                for k in range(m):
                    acc += P[j, k] * out[b, k]
                miss = 1e-8 * (abs(acc) + 1.0) + 1e-12 * size
                if acc < lo[j] - miss or acc > hi[j] + miss:
                    state = -2
        status[b] = state
    return out, status
