"""Small dense linear algebra and the pivoting moves of the compiled kernels (numba).

The compiled kernels (:mod:`.compiled`) solve one sample at a time, on systems of a few to a
few dozen unknowns held in the leading ``m x m`` block of one slot of a preallocated stack: at
that size a LAPACK call costs more than the arithmetic, so the factorisations are written out
here, inlined into the kernels (``inline="always"``), and index the stack in place (a view of a
slot costs reference counting, more than a small solve). :func:`move` and :func:`progress` are
the two phases of :func:`.pivoting.block_pivoting`'s rule for one sample.

A kernel's matrix on a pivoting state (a free set, or (V)'s free and pos sets) is the same for
every sample of a call: its factorisation is kept in the call's :func:`factor_table`, and a
sample that meets a state seen before (:func:`lookup`) skips building and factoring it -- the
same numbers as a new factorisation. Small problems share few states among many samples (on a
Fig. 1 model at ``n = 4``, 14 states in the 262 candidate solves of a batch of 200), so the
table is kept for ``n <= TABLE_N`` only.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba.core import cgutils
from numba.extending import intrinsic
from numba.np.arrayobj import make_array, populate_array

__all__ = ["JIT", "TABLE_N", "borrow", "cholesky_factor", "cholesky_substitute", "factor_table", "lookup",
           "lu_factor", "lu_solve", "lu_solve_transposed", "move", "progress", "release"]

#: The options of every compiled function: cached on disk, the GIL released.
JIT = {"cache": True, "nogil": True}

#: Index arrays are unsigned: an index read from one then needs no wrap-around test for a
#: negative value (numba's Python semantics), which costs a third of a small solve.
_INDEX = np.uint64

#: The largest ``n`` whose factorisations a call keeps (:func:`factor_table`), and the most
#: states it keeps (``2**_TABLE_BITS`` slots, filled to three quarters).
TABLE_N = 12
_TABLE_BITS = 9

#: Fibonacci hashing's multiplier (``2**64`` over the golden ratio).
_GOLDEN = np.uint64(11400714819323198485)


@intrinsic
def borrow(typingctx, array):  # pragma: no cover - compiled
    """A view of ``array`` outside reference counting (no owner): numba counts references to an
    array at every binding, and an inlined function's arguments are new bindings, so each
    candidate solve would pay a dozen atomic increments and decrements -- a fifth of a small
    solve's time. The owner must stay alive while the view is used (a kernel holds the owners in
    a tuple until :func:`release`), and a view is never returned: its memory is the owner's."""
    def codegen(context, builder, sig, args):
        src = make_array(sig.args[0])(context, builder, args[0])
        view = make_array(sig.return_type)(context, builder)
        populate_array(view, data=src.data, shape=src.shape, strides=src.strides, itemsize=src.itemsize,
                       meminfo=cgutils.get_null_value(src.meminfo.type))
        return view._getvalue()

    return array(array), codegen


@numba.njit(**JIT)
def release(owners):  # pragma: no cover - compiled
    """The last use of ``owners`` (a tuple of arrays), whose :func:`borrow`ed views are used up to
    here: numba frees an array after its last use."""
    return len(owners)


@numba.njit(**JIT)
def factor_table(n, k, rows):  # pragma: no cover - compiled
    """An empty table of ``n x n`` factorisations keyed by states of ``k`` flags, for one call:
    ``(meta, index, piv, M)``. Per slot: ``meta[slot] = [key, m, m2, ok]`` (the state's key, -1
    while empty; its matrix's order, one more integer of the kernel's and whether the
    factorisation succeeded), ``rows`` integers of ``index`` (the state's index sets), the row
    swaps ``piv`` and the factor ``M``. ``meta[-1] = [slots filled, log2 slots, the slot of the
    last state looked up, slots]``. Slot ``S`` after the ``S`` kept ones is scratch: a state built
    there is not kept; it is the only one where ``n > TABLE_N``."""
    bits = min(k, _TABLE_BITS) if n <= TABLE_N else 0
    S = 1 << bits if bits else 0
    meta = np.full((S + 2, 4), -1, dtype=np.int64)
    meta[S + 1, 0], meta[S + 1, 1], meta[S + 1, 2], meta[S + 1, 3] = 0, bits, 0, S
    return meta, np.empty((S + 1, rows), dtype=_INDEX), np.empty((S + 1, n), dtype=_INDEX), np.empty((S + 1, n, n))


@numba.njit(inline="always", **JIT)
def lookup(meta, state, k):  # pragma: no cover - compiled
    """The slot of ``state`` (``k`` flags) in :func:`factor_table`'s ``meta`` and whether its
    factor is there (also kept as the last slot looked up); a new state gets an empty slot
    (linear probing) while a quarter are empty, else the scratch slot."""
    info = meta.shape[0] - 1
    S = meta[info, 3]
    at, found = S, False
    if S > 0:
        key = 0
        for i in range(k):
            key = 2 * key + state[i]
        bits = meta[info, 1]
        at = key if k <= bits else np.int64((np.uint64(key) * _GOLDEN) >> np.uint64(64 - bits))
        while meta[at, 0] >= 0 and meta[at, 0] != key:
            at = (at + 1) & (S - 1)
        found = meta[at, 0] == key
        if not found:
            if 4 * meta[info, 0] < 3 * S:
                meta[at, 0] = key
                meta[info, 0] += 1
            else:
                at = S
    meta[info, 2] = at
    return at, found


@numba.njit(inline="always", **JIT)
def cholesky_factor(L, at, m):  # pragma: no cover - compiled
    """The Cholesky factor of ``M = L[at, :m, :m]`` in place (its lower triangle read and
    overwritten, the diagonal by its reciprocal); False if ``M`` is not positive definite to
    working precision. (Slot ``at`` of a stack of matrices, as :func:`factor_table` holds them:
    indexed in place, since a view of it costs more than a small solve.)"""
    for j in range(m):
        s = L[at, j, j]
        for k in range(j):
            s -= L[at, j, k] * L[at, j, k]
        if not s > 0.0:
            return False
        r = 1.0 / math.sqrt(s)
        L[at, j, j] = r
        for i in range(j + 1, m):
            t = L[at, i, j]
            for k in range(j):
                t -= L[at, i, k] * L[at, j, k]
            L[at, i, j] = t * r
    return True


@numba.njit(inline="always", **JIT)
def cholesky_substitute(L, at, rhs, m):  # pragma: no cover - compiled
    """Solve ``M z = rhs[:m]`` in place with :func:`cholesky_factor`'s factor of ``M`` in
    ``L[at]``."""
    for i in range(m):
        t = rhs[i]
        for k in range(i):
            t -= L[at, i, k] * rhs[k]
        rhs[i] = t * L[at, i, i]
    for i in range(m - 1, -1, -1):
        t = rhs[i]
        for k in range(i + 1, m):
            t -= L[at, k, i] * rhs[k]
        rhs[i] = t * L[at, i, i]


@numba.njit(inline="always", **JIT)
def lu_factor(M, piv, at, m):  # pragma: no cover - compiled
    """LU with partial pivoting of ``M[at, :m, :m]`` in place (``piv[at]``: the row swaps);
    False on an exactly zero pivot (a singular matrix, as LAPACK's ``getrf`` reports it)."""
    for k in range(m):
        p, big = k, abs(M[at, k, k])
        for i in range(k + 1, m):
            if abs(M[at, i, k]) > big:
                p, big = i, abs(M[at, i, k])
        piv[at, k] = p
        if big == 0.0:
            return False
        if p != k:
            for j in range(m):
                M[at, k, j], M[at, p, j] = M[at, p, j], M[at, k, j]
        for i in range(k + 1, m):
            f = M[at, i, k] / M[at, k, k]
            M[at, i, k] = f
            for j in range(k + 1, m):
                M[at, i, j] -= f * M[at, k, j]
    return True


@numba.njit(inline="always", **JIT)
def lu_solve(M, piv, at, b, m):  # pragma: no cover - compiled
    """``M[at] z = b`` in place with :func:`lu_factor`'s factors."""
    for k in range(m):
        p = piv[at, k]
        if p != k:
            b[k], b[p] = b[p], b[k]
    for i in range(m):
        for k in range(i):
            b[i] -= M[at, i, k] * b[k]
    for i in range(m - 1, -1, -1):
        t = b[i]
        for k in range(i + 1, m):
            t -= M[at, i, k] * b[k]
        b[i] = t / M[at, i, i]


@numba.njit(inline="always", **JIT)
def lu_solve_transposed(M, piv, at, b, m):  # pragma: no cover - compiled
    """``M[at]^T z = b`` in place with :func:`lu_factor`'s factors (``P M = L U``)."""
    for i in range(m):
        t = b[i]
        for k in range(i):
            t -= M[at, k, i] * b[k]
        b[i] = t / M[at, i, i]
    for i in range(m - 1, -1, -1):
        for k in range(i + 1, m):
            b[i] -= M[at, k, i] * b[k]
    for k in range(m - 1, -1, -1):
        p = piv[at, k]
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
