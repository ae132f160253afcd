"""A minibatch's rows of the training data, compiled (numba, the GIL released): gathered part by
part in the threads of a compiled call (:func:`.calls.compiled_call`'s ``rows``), the samples'
active sets written back into the trainer's tables, and the weighted sum that combines a call's
parts.

A step on a large minibatch then reads its rows where they lie: no copy of the whole minibatch
before the call, and each part's rows are gathered by the thread that solves them, into memory
it reuses while they are in its caches. Rows drawn at random from a large table are a cache miss
each: the gathers ask for the rows :data:`AHEAD` places on (a prefetch), so that many misses are
in flight at once, and read the four tables of a sample in one pass. The arrays are the same
numbers as NumPy's ``take``, so the kernels see what they saw before.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

from .dense import JIT

__all__ = ["AHEAD", "all_seen", "put_rows", "take_batch", "weighted_rows"]

#: How many rows ahead a gather prefetches (measured on a million random rows of ``(10, 4, 10)``
#: floats and 8 flags: 8 to 16 rows ahead took 0.7 of the time without prefetching).
AHEAD = 8


def _prefetcher(write: int) -> object:
    """An intrinsic ``prefetch(table, row)``: a hint that ``table[row]`` (its first and last
    entries: a row may span two cache lines) is read soon (``write=1``: written); no effect on
    any value."""

    @intrinsic
    def prefetch(typingctx, table, row):  # pragma: no cover - compiled
        sig = types.void(table, row)

        def codegen(context, builder, signature, args):
            aryty = signature.args[0]
            ary = context.make_array(aryty)(context, builder, args[0])
            i8p, i32 = ir.IntType(8).as_pointer(), ir.IntType(32)
            fn = cgutils.get_or_insert_function(
                builder.module, ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]), "llvm.prefetch.p0i8")
            last = builder.sub(cgutils.unpack_tuple(builder, ary.shape, 2)[1], context.get_constant(types.intp, 1))
            for col in (context.get_constant(types.intp, 0), last):
                ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [args[1], col], wraparound=False)
                builder.call(fn, [builder.bitcast(ptr, i8p), ir.Constant(i32, write), ir.Constant(i32, 3),
                                  ir.Constant(i32, 1)])
            return context.get_dummy_value()

        return sig, codegen

    return prefetch


_prefetch, _prefetch_write = _prefetcher(0), _prefetcher(1)


@numba.njit(inline="always", **JIT)
def _take(table, r, out, i):  # pragma: no cover - compiled
    for j in range(table.shape[1]):
        out[i, j] = table[r, j]


@numba.njit(**JIT)
def take_batch(x, u, x_next, warm, rows):  # pragma: no cover - compiled
    """``(x[rows], u[rows], x_next[rows], warm[rows])`` of 2-D C-contiguous tables (``warm`` may
    be empty, ``(0, 0)``: then returned as it is)."""
    B = rows.shape[0]
    with_warm = warm.shape[0] > 0
    ox, ou, on = np.empty((B, x.shape[1])), np.empty((B, u.shape[1])), np.empty((B, x_next.shape[1]))
    ow = np.empty((B, warm.shape[1]), dtype=np.bool_) if with_warm else warm
    for i in range(B + AHEAD):
        if i < B:
            r = rows[i]
            _take(x, r, ox, i)
            _take(u, r, ou, i)
            _take(x_next, r, on, i)
            if with_warm:
                _take(warm, r, ow, i)
        k = i + AHEAD
        if k < B:
            q = rows[k]
            _prefetch(x, q)
            _prefetch(x_next, q)
            if u.shape[1] > 0:
                _prefetch(u, q)
            if with_warm:
                _prefetch(warm, q)
    return ox, ou, on, ow


@numba.njit(**JIT)
def all_seen(seen, rows):  # pragma: no cover - compiled
    """Whether ``seen[rows]`` are all True."""
    for i in range(rows.shape[0]):
        if not seen[rows[i]]:
            return False
    return True


@numba.njit(**JIT)
def put_rows(table, seen, rows, values):  # pragma: no cover - compiled
    """``table[rows] = values`` and ``seen[rows] = True``, in place."""
    B = rows.shape[0]
    for i in range(B):
        k = i + AHEAD
        if k < B:
            _prefetch_write(table, rows[k])
        r = rows[i]
        for j in range(table.shape[1]):
            table[r, j] = values[i, j]
        seen[r] = True


@numba.njit(**JIT)
def weighted_rows(w, rows):  # pragma: no cover - compiled
    """``sum_k w[k] rows[k]`` ``(m,)`` of ``rows (P, m)``, summed in the order of ``k`` from 0.0
    (the arithmetic of Python's ``sum(w_k * row_k)``, element by element)."""
    P, m = rows.shape
    out = np.zeros(m)
    for k in range(P):
        wk = w[k]
        for j in range(m):
            out[j] = out[j] + wk * rows[k, j]
    return out
