r"""The two fast losses compiled (numba): solution, loss and gradient of a batch in one call.

A call of the array kernels (:mod:`.violation`, :mod:`.lcp`, :mod:`.losses`) is a few hundred
NumPy operations on arrays of a few hundred numbers: at the paper's sizes (``n <= 20``, batches
of 200) its cost is the per-operation overhead, not arithmetic. Here the same computation is
one compiled function per loss, which loops over the samples and pivots each one on its own
(``n x n`` factorisations written out: Cholesky for (V)'s positive definite systems, LU with
partial pivoting for the LCP's ``F_II``), then forms the batch's loss and its closed-form
gradients with a few matrix products:

- :func:`violation` -- (V), eq. (9b), in the normal-equation form of :mod:`.violation`
  (``LtL = eps C^T C + F + F^T - gamma I``, ``Ltb = eps C^T r + q``, ``K = (gamma I - F) /
  sqrt(gamma)``, ``h = q / sqrt(gamma)``), then Lemma 3's envelope gradients
  (:func:`.losses.envelope_backward`);
- :func:`prediction` -- the LCP of eq. (2), then Lemma 1's implicit gradient
  (:func:`.losses.implicit_backward`), whose adjoint solve ``F_II^T mu_I = (C^T g_e)_I`` reuses
  the LU factors of the last pivoting sweep;
- :func:`lcp` -- the LCP alone (``solve_lcp``'s fast path).

The ``n x n`` factorisations, the call's table of them (a state met again reuses its factor)
and the pivoting moves are in :mod:`.dense`.

Both follow :func:`.pivoting.block_pivoting` sample by sample: the same cold guess (for (V),
:func:`.violation.cold_guess`), the same feasibility tests and tolerances, every infeasible index flipped, Murty's single pivot (largest
infeasible index) once a sample has gone ``stall`` sweeps without a new lowest count. A sample
that has not converged after ``max_iter`` sweeps, or whose factorisation failed, is reported
(``n_unconverged``) and the caller hands the batch to the array kernels, which end it with the
reference solvers. Inputs are C-contiguous float64 arrays: parameters ``A (n_x, n_x)``,
``B (n_x, n_u)``, ``C (n_x, n)``, ``d (n_x,)``, ``D (n, n_x)``, ``E (n, n_u)``, ``c (n,)``,
``G (n, n)``, ``H (n, n)`` and the stiffness ``s`` (``F = G G^T + H - H^T + s I``); data
``x (N, n_x)``, ``u (N, n_u)``, ``x_next (N, n_x)``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .dense import JIT as _JIT
from .dense import (
    borrow,
    cholesky_factor,
    cholesky_substitute,
    factor_table,
    lookup,
    lu_factor,
    lu_solve,
    lu_solve_transposed,
    move,
    progress,
    release,
)
from .products import batch_inputs, parameter_gradients, stiffness_matrix

__all__ = ["COLD", "lcp", "prediction", "violation"]

#: The cold start (an empty warm start) of every kernel here.
COLD = np.zeros((0, 0), dtype=np.bool_)


@numba.njit(inline="always", **_JIT)
def _violation_solve(state, LtL, K, KT, Ltb_all, h_all, s, tol, lam, t, g, bad, meta, idx, M, KIP):  # pragma: no cover
    """One candidate of (V) on the pieces ``state = [free, pos]`` of one sample: ``lam`` (zero
    off the free set) from ``(LtL + K_P^T K_P)_II lam_I = (-Ltb + K_P^T h_P)_I`` (``P`` the pos
    set; the matrix's factor from the call's :func:`.dense.factor_table` ``(meta, idx, _, M)``,
    built there the first time the state is met; ``idx``: the free set, then from ``n`` the pos
    set), ``t = K lam - h``, the gradient ``g = LtL lam + Ltb + K_P^T t_P``, and the ``2 n``
    infeasible flags of :func:`.violation.pivot_violation` in ``bad`` (``tol``: ``[gradient,
    lam, t]`` scales; ``tol[1]`` is set from the first candidate's ``|lam|``); returns their
    count."""
    n = lam.shape[0]
    at, found = lookup(meta, state, 2 * n)
    if not found:
        m, mp = 0, n
        for i in range(n):
            if state[i]:
                idx[at, m] = i
                m += 1
            if state[n + i]:
                idx[at, mp] = i
                mp += 1
        for a in range(m):  # KIP = (K_PI)^T, compact: M = LtL_II + KIP KIP^T
            for c in range(mp - n):
                KIP[a, c] = KT[idx[at, a], idx[at, n + c]]
        for a in range(m):
            ia = idx[at, a]
            for b in range(a + 1):
                v = LtL[ia, idx[at, b]]
                for c in range(mp - n):
                    v += KIP[a, c] * KIP[b, c]
                M[at, a, b] = v
        meta[at, 1], meta[at, 2], meta[at, 3] = m, mp, cholesky_factor(M, at, m)
    m, mp, ok = meta[at, 1], meta[at, 2], meta[at, 3] != 0
    for a in range(m):  # rhs = -Ltb_I + (K_PI)^T h_P
        ia = idx[at, a]
        v = -Ltb_all[s, ia]
        for c in range(n, mp):
            k = idx[at, c]
            v += KT[ia, k] * h_all[s, k]
        g[a] = v
    lam[:] = 0.0
    if ok:
        cholesky_substitute(M, at, g, m)
        for a in range(m):
            lam[idx[at, a]] = g[a]
    for i in range(n):
        t[i] = -h_all[s, i]
        g[i] = Ltb_all[s, i]
    for a in range(m):  # t = K lam - h and LtL lam: over the free columns only
        j = idx[at, a]
        la = lam[j]
        for i in range(n):
            t[i] += KT[j, i] * la
            g[i] += LtL[j, i] * la
    for c in range(n, mp):  # + K_P^T t_P
        k = idx[at, c]
        tk = t[k]
        for i in range(n):
            g[i] += K[k, i] * tk
    if tol[1] > 0.0:  # the first candidate: the lower bound of a free lam, -tol (1 + |lam|_inf)
        big = 0.0
        for i in range(n):
            big = max(big, abs(lam[i]))
        tol[1] = -tol[1] * (1.0 + big)
    lo, glo, tlo = tol[1], -tol[0], tol[2]
    count = 0
    for i in range(n):  # (branch-free: & and | of the flags)
        f, p = state[i], state[n + i]
        b1 = (not ok) | (f & (lam[i] < lo)) | ((not f) & (g[i] < glo))
        b2 = (not ok) | (p & (t[i] < -tlo)) | ((not p) & (t[i] > tlo))
        bad[i], bad[n + i] = b1, b2
        count += b1 + b2
    return count


@numba.njit(**_JIT)
def violation(A, B, C, d, D, E, c, G, H, stiffness, x, u, x_next, gamma, eps, tol, max_iter,
              stall, warm):  # pragma: no cover - compiled
    """(V) for every sample, its batch-mean value and Lemma 3's gradients.

    ``warm``: ``(N, 2 n)`` bool first guess of ``[free, pos]`` (an empty ``(0, 0)`` array: the
    cold guess of :func:`.violation.cold_guess`). Returns ``(value, (dA, dB, dC, dd, dD, dE, dG,
    dH, dc), lam, phi, active, n_unconverged, sweeps)``; ``active = [lam > 0, K lam - h > 0]``
    ``(N, 2 n)``, the gradients those of the mean value; ``n_unconverged = -1`` (and nothing else
    computed) if the data are not finite."""
    N, n_x = x.shape
    n_u, n = u.shape[1], C.shape[1]
    F = stiffness_matrix(G, H, stiffness)
    X, QR, finite = batch_inputs(A, B, C, d, D, E, c, x, u, x_next)
    scale = 1.0 / math.sqrt(gamma)
    LtL = eps * (C.T @ C) + F + F.T
    K = -F * scale
    for i in range(n):
        LtL[i, i] -= gamma
        K[i, i] += gamma * scale
    # per sample: Ltb = eps C^T r + q, h = q / sqrt(gamma), and K^T h for the tolerances
    Q, R = np.ascontiguousarray(QR[:, :n]), np.ascontiguousarray(QR[:, n:])
    Ltb_all = eps * (R @ C) + Q
    h_all = Q * scale
    KTh_all = h_all @ K
    lam_all = np.empty((N, n))
    state = np.zeros(2 * n, dtype=np.bool_)
    lam, t, g, tols = np.empty(n), np.empty(n), np.empty(n), np.empty(3)
    KT, bad, KIP = np.ascontiguousarray(K.T), np.zeros(2 * n, dtype=np.bool_), np.empty((n, n))
    m_K = -np.diag(K).copy()
    meta, index, _, factors = factor_table(n, 2 * n, 2 * n)
    # the sample loop's arrays as borrowed views (.dense.borrow), their owners held to the end
    held = (state, LtL, K, KT, Ltb_all, h_all, tols, lam, t, g, bad, meta, index, factors, KIP)
    state, LtL, K, KT, Ltb_all, h_all, tols = (borrow(state), borrow(LtL), borrow(K), borrow(KT),
                                               borrow(Ltb_all), borrow(h_all), borrow(tols))
    lam, t, g, bad, meta, index, factors, KIP = (borrow(lam), borrow(t), borrow(g), borrow(bad), borrow(meta),
                                                 borrow(index), borrow(factors), borrow(KIP))
    use_warm = warm.shape[0] == N
    n_unconverged, sweeps_max = 0 if finite else -1, 0
    for s in range(N if finite else 0):
        b1, b2, b3 = 0.0, 0.0, 0.0
        for i in range(n):  # the tolerances of pivot_violation
            hi = h_all[s, i]
            b1, b2, b3 = max(b1, abs(Ltb_all[s, i])), max(b2, abs(KTh_all[s, i])), max(b3, abs(hi))
            if use_warm:
                state[i], state[n + i] = warm[s, i], warm[s, n + i]
            else:  # .violation.cold_guess: lam0 = max(0, -h / m), m = -diag(K)
                lam[i] = max(-hi / m_K[i], 0.0) if m_K[i] > 0.0 else 0.0
        for i in range(n if not use_warm else 0):  # w = h - K lam0; guess m lam0 - w > 0
            v = 0.0
            for j in range(n):
                v += K[i, j] * lam[j]
            hi = h_all[s, i]
            guess = m_K[i] * lam[i] - (hi - v) > 0.0 if m_K[i] > 0.0 else hi < 0.0
            state[i], state[n + i] = guess, guess
        tols[0], tols[1], tols[2] = tol * (1.0 + b1 + b2), tol, tol * (1.0 + b3)
        n_bad = _violation_solve(state, LtL, K, KT, Ltb_all, h_all, s, tols, lam, t, g, bad, meta, index, factors, KIP)
        sweeps = 0
        best, stalled = n_bad, 0
        while sweeps < max_iter and n_bad > 0:  # block pivoting, Murty's rule once stalled
            move(bad, state, 2 * n, sweeps >= stall and stalled >= stall)
            n_bad = _violation_solve(state, LtL, K, KT, Ltb_all, h_all, s, tols, lam, t, g, bad, meta, index, factors, KIP)
            sweeps += 1
            best, stalled = progress(n_bad, best, stalled)
        sweeps_max = max(sweeps_max, sweeps)
        n_unconverged += n_bad > 0
        for i in range(n):
            lam_all[s, i] = max(lam[i], 0.0)
    # phi = max(0, F lam + q - gamma lam), e = C lam + r, w = F lam + q - phi; the value; the
    # pieces K lam - h = (gamma lam - (F lam + q)) / sqrt(gamma) > 0
    Flq = lam_all @ F.T + Q
    Y = np.empty((N, n_x + n))
    Y[:, :n_x] = R + lam_all @ C.T
    phi = np.empty((N, n))
    active = np.empty((N, 2 * n), dtype=np.bool_)
    total = 0.0
    for s in range(N if finite else 0):
        for i in range(n):
            la, v = lam_all[s, i], Flq[s, i]
            active[s, i] = la > 0.0
            active[s, n + i] = gamma * la - v > 0.0
            ph = max(v - gamma * la, 0.0)
            phi[s, i] = ph
            w = v - ph
            total += (la * ph + 0.5 / gamma * w * w) / eps
            Y[s, n_x + i] = w / (gamma * eps * N)
        for k in range(n_x):
            v = Y[s, k]
            total += 0.5 * v * v
            Y[s, k] = v / N
    grads = parameter_gradients(X, lam_all, Y, G, n_x, n_u)
    release(held)
    return total / N, grads, lam_all, phi, active, n_unconverged, sweeps_max


@numba.njit(inline="always", **_JIT)
def _lcp_solve(F, Q, s, lo, lam, w, bad, free, meta, idx, piv, M):  # pragma: no cover - compiled
    """One candidate of the LCP ``0 <= lam _|_ F lam + q >= 0`` (``q = Q[s]``) on the free set
    ``free``: ``F_II lam_I = -q_I`` (``F_II``'s LU factors from the call's
    :func:`.dense.factor_table` ``(meta, idx, piv, M)``, built there the first time the free set
    is met), ``w = F lam + q``, and the infeasible flags of :func:`.lcp.pivot_lcp` in ``bad``
    (``lo``: ``-tol (1 + |q|_inf)``); returns their count."""
    n = lam.shape[0]
    at, found = lookup(meta, free, n)
    if not found:
        m = 0
        for i in range(n):
            if free[i]:
                idx[at, m] = i
                m += 1
        for a in range(m):
            for b in range(m):
                M[at, a, b] = F[idx[at, a], idx[at, b]]
        meta[at, 1], meta[at, 3] = m, lu_factor(M, piv, at, m)
    m, ok = meta[at, 1], meta[at, 3] != 0
    lam[:] = 0.0
    if ok:
        for a in range(m):
            w[a] = -Q[s, idx[at, a]]
        lu_solve(M, piv, at, w, m)
        for a in range(m):
            lam[idx[at, a]] = w[a]
    count = 0
    for i in range(n):
        v = Q[s, i]
        for j in range(n):
            v += F[i, j] * lam[j]
        w[i] = v
        f = free[i]
        b = (not ok) | (f & (lam[i] < lo)) | ((not f) & (v < lo))
        bad[i] = b
        count += b
    return count


@numba.njit(inline="always", **_JIT)
def _lcp_pivot(F, Q, s, lo, lam, w, bad, free, meta, idx, piv, M, max_iter, stall):  # pragma: no cover
    """Block pivoting on the LCP of ``Q[s]`` from the free set ``free`` (:func:`_lcp_solve`'s
    arguments): (infeasible count at the end, sweeps), the last candidate in ``lam``, ``w`` and
    the table (its slot ``meta[-1, 2]``)."""
    n_bad = _lcp_solve(F, Q, s, lo, lam, w, bad, free, meta, idx, piv, M)
    sweeps = 0
    best, stalled = n_bad, 0
    while sweeps < max_iter and n_bad > 0:  # Murty's rule once stalled
        move(bad, free, free.shape[0], sweeps >= stall and stalled >= stall)
        n_bad = _lcp_solve(F, Q, s, lo, lam, w, bad, free, meta, idx, piv, M)
        sweeps += 1
        best, stalled = progress(n_bad, best, stalled)
    return n_bad, sweeps


@numba.njit(**_JIT)
def lcp(F, q_all, tol, max_iter, stall, warm):  # pragma: no cover - compiled
    """The LCP ``0 <= lam _|_ F lam + q >= 0`` for every row of ``q_all`` ``(N, n)``
    (:func:`.lcp.pivot_lcp`'s algorithm, sample by sample). ``warm``: ``(N, n)`` bool first guess
    of the free sets (empty ``(0, 0)``: the cold guess ``q < 0``). Returns ``(lam, w, free,
    unconverged, sweeps)``: ``lam`` clamped at 0, ``w = F lam + q``, ``free`` the final free sets
    where ``lam > 0``, ``unconverged`` the indices of the samples still infeasible."""
    N, n = q_all.shape
    lam_all, free_all = np.empty((N, n)), np.zeros((N, n), dtype=np.bool_)
    free, bad = np.zeros(n, dtype=np.bool_), np.empty(n, dtype=np.bool_)
    lam, w = np.empty(n), np.empty(n)
    meta, idx, piv, M = factor_table(n, n, n)
    # the sample loop's arrays as borrowed views (.dense.borrow), their owners held to the end
    held = (F, q_all, lam, w, bad, free, meta, idx, piv, M)
    F, q_all, lam, w, bad, free = borrow(F), borrow(q_all), borrow(lam), borrow(w), borrow(bad), borrow(free)
    meta, idx, piv, M = borrow(meta), borrow(idx), borrow(piv), borrow(M)
    use_warm = warm.shape[0] == N
    failed = np.zeros(N, dtype=np.bool_)
    sweeps_max = 0
    for s in range(N):
        big = 0.0
        for i in range(n):
            qi = q_all[s, i]
            free[i] = warm[s, i] if use_warm else qi < 0.0
            big = max(big, abs(qi))
        lo = -tol * (1.0 + big)
        n_bad, sweeps = _lcp_pivot(F, q_all, s, lo, lam, w, bad, free, meta, idx, piv, M, max_iter, stall)
        sweeps_max = max(sweeps_max, sweeps)
        failed[s] = n_bad > 0
        for i in range(n):
            free_all[s, i] = free[i] and lam[i] > 0.0
            lam_all[s, i] = max(lam[i], 0.0)
    w_all = lam_all @ F.T + q_all
    release(held)
    return lam_all, w_all, free_all, np.flatnonzero(failed), sweeps_max


@numba.njit(**_JIT)
def prediction(A, B, C, d, D, E, c, G, H, stiffness, x, u, x_next, tol, max_iter, stall,
               degenerate_tol, warm):  # pragma: no cover - compiled
    """The LCP of every sample, the batch mean of ``1/2 ||C lam + r||^2`` and Lemma 1's gradients.

    ``warm``: ``(N, n)`` bool first guess of the free sets (empty ``(0, 0)``: the cold guess
    ``q < 0``). Returns ``(value, grads, lam, w, free, n_unconverged, sweeps, n_degenerate)``,
    ``free`` the final free sets (``lam > 0``), ``w = F lam + q``, ``n_degenerate`` the samples
    with some ``lam_i = w_i = 0`` (both below ``degenerate_tol (1 + |q|_inf)``);
    ``n_unconverged = -1`` if the data are not finite."""
    N, n_x = x.shape
    n_u, n = u.shape[1], C.shape[1]
    F = stiffness_matrix(G, H, stiffness)
    X, QR, finite = batch_inputs(A, B, C, d, D, E, c, x, u, x_next)
    Y = np.empty((N, n_x + n))
    lam_all, w_all = np.empty((N, n)), np.empty((N, n))
    free_all = np.zeros((N, n), dtype=np.bool_)
    free = np.zeros(n, dtype=np.bool_)
    lam, w, mu = np.empty(n), np.empty(n), np.empty(n)
    meta, idx, piv, M = factor_table(n, n, n)
    bad = np.empty(n, dtype=np.bool_)
    # the sample loop's arrays as borrowed views (.dense.borrow), their owners held to the end
    held = (F, QR, lam, w, mu, bad, free, meta, idx, piv, M)
    F, QR, lam, w, mu, bad, free = borrow(F), borrow(QR), borrow(lam), borrow(w), borrow(mu), borrow(bad), borrow(free)
    meta, idx, piv, M = borrow(meta), borrow(idx), borrow(piv), borrow(M)
    use_warm = warm.shape[0] == N
    n_unconverged, sweeps_max, n_deg, total = 0 if finite else -1, 0, 0, 0.0
    for s in range(N if finite else 0):
        big = 0.0
        for i in range(n):
            qi = QR[s, i]
            free[i] = warm[s, i] if use_warm else qi < 0.0
            big = max(big, abs(qi))
        lo = -tol * (1.0 + big)
        n_bad, sweeps = _lcp_pivot(F, QR, s, lo, lam, w, bad, free, meta, idx, piv, M, max_iter, stall)
        sweeps_max = max(sweeps_max, sweeps)
        n_unconverged += n_bad > 0
        # the final free set: free and lam > 0 (an index at zero is held there: one-sided)
        refactor = False
        for i in range(n):
            refactor = refactor or (free[i] and not lam[i] > 0.0)
            free[i] = free[i] and lam[i] > 0.0
            free_all[s, i] = free[i]
            lam[i] = max(lam[i], 0.0)
            lam_all[s, i] = lam[i]
        if refactor:
            _lcp_solve(F, QR, s, lo, lam, w, bad, free, meta, idx, piv, M)  # F_II on the final free set
            for i in range(n):
                lam[i] = lam_all[s, i]
        final = meta[-1, 2]  # the slot of F_II's factors on the final free set
        m = meta[final, 1]
        # e = C lam + r; the adjoint F_II^T mu_I = (C^T e / N)_I, mu_J = 0; g_q = -mu
        for k in range(n_x):
            v = QR[s, n + k]
            for j in range(n):
                v += C[k, j] * lam[j]
            total += 0.5 * v * v
            Y[s, k] = v / N
        for a in range(m):
            v = 0.0
            for k in range(n_x):
                v += C[k, idx[final, a]] * Y[s, k]
            mu[a] = v
        lu_solve_transposed(M, piv, final, mu, m)
        for i in range(n):
            Y[s, n_x + i] = 0.0
        for a in range(m):
            Y[s, n_x + idx[final, a]] = -mu[a]
        deg = False
        atd = degenerate_tol * (1.0 + big)
        for i in range(n):  # w = F lam + q: the last sweep's, unless lam was clamped there
            v = w[i]
            if refactor:
                v = QR[s, i]
                for j in range(n):
                    v += F[i, j] * lam[j]
            w_all[s, i] = v
            deg = deg or (lam[i] <= atd and abs(v) <= atd)
        n_deg += deg
    grads = parameter_gradients(X, lam_all, Y, G, n_x, n_u)
    release(held)
    return total / N, grads, lam_all, w_all, free_all, n_unconverged, sweeps_max, n_deg
