"""Small dense linear algebra and the pivoting moves of the compiled kernels (numba).

The compiled kernels (:mod:`.compiled`) solve one sample at a time, on systems of a few to a
few dozen unknowns held in the leading ``m x m`` block of a preallocated array: at that size a
LAPACK call costs more than the arithmetic, so the factorisations are written out here, inlined
into the kernels (``inline="always"``). :func:`move` and :func:`progress` are the two phases of
:func:`.pivoting.block_pivoting`'s rule for one sample.
"""

from __future__ import annotations

import math

import numba

__all__ = ["JIT", "cholesky_solve", "lu_factor", "lu_solve", "lu_solve_transposed", "move", "progress"]

#: The options of every compiled function: cached on disk, the GIL released.
JIT = {"cache": True, "nogil": True}


@numba.njit(inline="always", **JIT)
def cholesky_solve(M, rhs, m):  # pragma: no cover - compiled
    """Solve ``M[:m, :m] z = rhs[:m]`` in place (lower triangle of ``M`` read and overwritten by
    its Cholesky factor, the diagonal by its reciprocal); False if ``M`` is not positive definite
    to working precision."""
    for j in range(m):
        s = M[j, j]
        for k in range(j):
            s -= M[j, k] * M[j, k]
        if not s > 0.0:
            return False
        r = 1.0 / math.sqrt(s)
        M[j, j] = r
        for i in range(j + 1, m):
            t = M[i, j]
            for k in range(j):
                t -= M[i, k] * M[j, k]
            M[i, j] = t * r
    for i in range(m):
        t = rhs[i]
        for k in range(i):
            t -= M[i, k] * rhs[k]
        rhs[i] = t * M[i, i]
    for i in range(m - 1, -1, -1):
        t = rhs[i]
        for k in range(i + 1, m):
            t -= M[k, i] * rhs[k]
        rhs[i] = t * M[i, i]
    return True


@numba.njit(inline="always", **JIT)
def lu_factor(M, piv, m):  # pragma: no cover - compiled
    """LU with partial pivoting of ``M[:m, :m]`` in place (``piv``: the row swaps); False on an
    exactly zero pivot (a singular matrix, as LAPACK's ``getrf`` reports it)."""
    for k in range(m):
        p, big = k, abs(M[k, k])
        for i in range(k + 1, m):
            if abs(M[i, k]) > big:
                p, big = i, abs(M[i, k])
        piv[k] = p
        if big == 0.0:
            return False
        if p != k:
            for j in range(m):
                M[k, j], M[p, j] = M[p, j], M[k, j]
        for i in range(k + 1, m):
            f = M[i, k] / M[k, k]
            M[i, k] = f
            for j in range(k + 1, m):
                M[i, j] -= f * M[k, j]
    return True


@numba.njit(inline="always", **JIT)
def lu_solve(M, piv, b, m):  # pragma: no cover - compiled
    """``M z = b`` in place with :func:`lu_factor`'s factors."""
    for k in range(m):
        p = piv[k]
        if p != k:
            b[k], b[p] = b[p], b[k]
    for i in range(m):
        for k in range(i):
            b[i] -= M[i, k] * b[k]
    for i in range(m - 1, -1, -1):
        t = b[i]
        for k in range(i + 1, m):
            t -= M[i, k] * b[k]
        b[i] = t / M[i, i]


@numba.njit(inline="always", **JIT)
def lu_solve_transposed(M, piv, b, m):  # pragma: no cover - compiled
    """``M^T z = b`` in place with :func:`lu_factor`'s factors (``P M = L U``)."""
    for i in range(m):
        t = b[i]
        for k in range(i):
            t -= M[k, i] * b[k]
        b[i] = t / M[i, i]
    for i in range(m - 1, -1, -1):
        for k in range(i + 1, m):
            b[i] -= M[k, i] * b[k]
    for k in range(m - 1, -1, -1):
        p = piv[k]
        if p != k:
            b[k], b[p] = b[p], b[k]


@numba.njit(inline="always", **JIT)
def move(bad, state, k, murty):  # pragma: no cover - compiled
    """One pivoting move (:func:`.pivoting.block_pivoting`'s rule): flip every infeasible flag
    of ``state`` (``k`` flags), or only the largest one (Murty's rule)."""
    for i in range(k - 1, -1, -1) if murty else range(k):
        if bad[i]:
            state[i] = not state[i]
            if murty:
                return


@numba.njit(inline="always", **JIT)
def progress(n_bad, best, stalled):  # pragma: no cover - compiled
    """The lowest infeasible count so far and the sweeps since it fell."""
    return (n_bad, 0) if n_bad < best else (best, stalled + 1)
