"""The per-batch products of the compiled kernels (:mod:`.compiled`), in numba: the data's
``q`` and ``r`` from one product, ``F``, and the nine parameter gradients from two products
(:func:`.losses.parameter_gradients`'s formulas). Inputs are C-contiguous float64 arrays, as
:mod:`.compiled` takes them.
"""

from __future__ import annotations

import numba
import numpy as np

from .dense import JIT

__all__ = ["batch_inputs", "parameter_gradients", "stiffness_matrix"]


@numba.njit(**JIT)
def batch_inputs(A, B, C, d, D, E, c, x, u, x_next):  # pragma: no cover - compiled
    """``X = [x, u, 1]`` ``(N, n_x + n_u + 1)``, ``QR = [q, r]`` ``(N, n + n_x)``, ``q = D x + E u +
    c``, ``r = A x + B u + d - x'`` (one product ``X [[D, E, c], [A, B, d]]^T``), and whether the
    data are finite (the sum of their entries is)."""
    N, n_x = x.shape
    n_u, n = u.shape[1], C.shape[1]
    p = n_x + n_u + 1
    X = np.empty((N, p))
    total = 0.0
    for s in range(N):
        for j in range(n_x):
            X[s, j] = x[s, j]
            total += x[s, j] + x_next[s, j]
        for j in range(n_u):
            X[s, n_x + j] = u[s, j]
            total += u[s, j]
        X[s, n_x + n_u] = 1.0
    W = np.empty((p, n + n_x))  # [[D, E, c], [A, B, d]]^T
    for i in range(n):
        for j in range(n_x):
            W[j, i] = D[i, j]
        for j in range(n_u):
            W[n_x + j, i] = E[i, j]
        W[p - 1, i] = c[i]
    for i in range(n_x):
        for j in range(n_x):
            W[j, n + i] = A[i, j]
        for j in range(n_u):
            W[n_x + j, n + i] = B[i, j]
        W[p - 1, n + i] = d[i]
    QR = X @ W
    for s in range(N):
        for i in range(n_x):
            QR[s, n + i] -= x_next[s, i]
    return X, QR, np.isfinite(total)


@numba.njit(**JIT)
def parameter_gradients(X, lam, Y, G, n_x, n_u):  # pragma: no cover - compiled
    """The nine parameter gradients from ``Y^T [X, lam]`` (``Y = [g_r, g_q]`` ``(N, n_x + n)``,
    the loss's sensitivities to ``r`` and ``q``; ``X = [x, u, 1]``): ``dA = g_r^T x``, ``dB =
    g_r^T u``, ``dd = sum g_r``, ``dC = g_r^T lam``, the same with ``g_q`` for ``D, E, c, F``, and
    ``dG = (dF + dF^T) G``, ``dH = dF - dF^T`` (:func:`.losses.parameter_gradients`)."""
    P = Y.T @ X
    L = Y.T @ lam
    p = n_x + n_u + 1
    dF = np.ascontiguousarray(L[n_x:])
    return (np.ascontiguousarray(P[:n_x, :n_x]), np.ascontiguousarray(P[:n_x, n_x:n_x + n_u]),
            np.ascontiguousarray(L[:n_x]), P[:n_x, p - 1].copy(),
            np.ascontiguousarray(P[n_x:, :n_x]), np.ascontiguousarray(P[n_x:, n_x:n_x + n_u]),
            (dF + dF.T) @ G, dF - dF.T, P[n_x:, p - 1].copy())


@numba.njit(**JIT)
def stiffness_matrix(G, H, stiffness):  # pragma: no cover - compiled
    """``F = G G^T + H - H^T + s I``."""
    F = G @ G.T + H - H.T
    for i in range(F.shape[0]):
        F[i, i] += stiffness
    return F
