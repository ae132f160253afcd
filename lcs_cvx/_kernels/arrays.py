"""The array back-end of the kernels: one set of operations on NumPy arrays or torch tensors.

A kernel call is a few hundred operations on arrays of a few hundred numbers, so what it costs
is the per-operation overhead of the array library, not arithmetic. For CPU tensors the kernels
therefore run on NumPy arrays that share the tensors' memory (``Tensor.numpy()`` /
``torch.from_numpy``: no copy), NumPy's per-call overhead being a fraction of a torch dispatch;
on any other device they run on the torch tensors themselves. :class:`ArrayOps` is the adapter
that lets one kernel source serve both.
"""

from __future__ import annotations

import contextlib
import functools
import os
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from .._checks import LCSInputError

__all__ = [
    "ARRAYS", "ArrayOps", "NUMPY_SOLVE_WORK", "SMALL_N", "TORCH", "array_ops", "spd_solve",
]


#: Up to this size a batch of linear solves is one LAPACK LU call (``linalg.solve_ex``), which
#: costs less than a Cholesky factorisation plus two triangular solves for tiny matrices (one
#: call instead of three); above it, Cholesky and two triangular solves (half the flops).
SMALL_N = 6


#: Up to this much work (``batch * n * n``) the NumPy back-end solves with NumPy's batched LU
#: rather than torch's LAPACK calls: NumPy's is cheaper to call, torch's faster per matrix, and
#: the two cross in this range for the kernels' sizes (n from 4 to 20, batches of a few hundred
#: samples); large batches (a whole data set) go to torch's.
NUMPY_SOLVE_WORK = 4096


def spd_solve(M: torch.Tensor, rhs: torch.Tensor, spd: bool = True) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Solve the batch of systems ``M x = rhs``.

    Args:
        M: ``(B, n, n)``; rhs: ``(B, n)``.
        spd: ``M`` is symmetric positive definite (Cholesky above :data:`SMALL_N`); if False, LU.

    Returns:
        ``x`` ``(B, n)`` and a ``(B,)`` bool mask of the systems whose factorisation failed
        (not positive definite to working precision, or singular), or None if none did.
    """
    if M.shape[-1] <= SMALL_N or not spd:
        # a symmetric M is its own transpose, whose view is the column-major layout LAPACK
        # takes without a copy
        x, info = torch.linalg.solve_ex(M.mT if spd else M, rhs.unsqueeze(-1))
    else:
        chol, info = torch.linalg.cholesky_ex(M)
        y = torch.linalg.solve_triangular(chol, rhs.unsqueeze(-1), upper=False)
        x = torch.linalg.solve_triangular(chol.mT, y, upper=True)
    return x.squeeze(-1), (info != 0 if bool(info.any()) else None)


class ArrayOps:
    """The array operations of the fast kernels, for one array library.

    :func:`lcs_cvx._kernels.pivoting.block_pivoting` and the kernels of :mod:`.lcp`,
    :mod:`.violation` and :mod:`.losses` are written once, against Python's operators
    (``@ + * < & | ^ ~``, indexing, ``.sum``, ``.any``, ``.all``, ``.reshape``, ``.swapaxes`` of a
    matrix) and the methods below, which NumPy arrays and torch tensors share through this
    adapter. Two instances:

    - ``"numpy"`` (CPU tensors, the default there): NumPy arrays on the tensors' memory; small
      batched factorisations are NumPy's, large ones torch's LAPACK calls on the same memory
      (:meth:`solve`).
    - ``"torch"`` (any device; used for CUDA tensors): the same kernel on torch tensors.

    Both give the same answer to round-off (tested on CPU, side by side).

    The elementwise ``where(cond, a, b)`` and ``minimum(a, b)`` and ``concat(parts)`` (join along
    the last axis) are the library's own functions, bound at construction: a kernel calls them
    ~10 times per sweep, and a Python method around each would cost as much as NumPy's work.
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self.np = name == "numpy"
        #: :func:`block_pivoting` shrinks its work set to the unconverged samples once at most
        #: this fraction of it is unconverged, and only above this much work (``samples * k *
        #: k``). An indexing pass is cheap in NumPy, so it shrinks at every sweep; in torch an
        #: indexing pass costs several dispatches and pays only on large work sets.
        self.subset_fraction = 1.0 if self.np else 0.25
        self.subset_min_work = 0 if self.np else 65_536
        lib: Any = np if self.np else torch
        self.where, self.minimum = lib.where, lib.minimum
        self.concat = functools.partial(np.concatenate if self.np else torch.cat, axis=-1)

    def __repr__(self) -> str:
        return f"ArrayOps({self.name!r})"

    def threads(self) -> contextlib.AbstractContextManager[None]:
        """Run the enclosed kernel with as many BLAS threads as torch may use
        (``torch.get_num_threads()``). NumPy's OpenBLAS would otherwise put every core on
        products of a few thousand numbers: no faster, and it oversubscribes a process pool
        whose workers run one torch thread each. The setting is restored on exit; a nested
        use is free (the outermost one sets and restores)."""
        return _BLAS_THREADS if self.np else contextlib.nullcontext()

    # -- boundary
    def wrap(self, t: torch.Tensor) -> Any:
        """The kernel's array for the tensor ``t`` (no copy on CPU; detached)."""
        return t.detach().numpy() if self.np else t.detach()  # NumPy: CPU tensors only

    def unwrap(self, a: Any) -> torch.Tensor:
        """The tensor of the kernel's array ``a`` (no copy of a contiguous NumPy array; a NumPy
        scalar becomes a 0-dim tensor)."""
        if not self.np:
            return a
        a = np.asarray(a)
        return torch.from_numpy(a if a.flags.c_contiguous else np.ascontiguousarray(a))

    def via_torch(self, fn: Callable[..., Any], *arrays: Any) -> Any:
        """``fn(*arrays)`` for a torch function ``fn`` (a factorisation, a triangular solve):
        on NumPy arrays through tensors on the same memory, its tensors (a tuple of them, or
        None) returned as arrays; on torch tensors, a plain call (autograd records it)."""
        if not self.np:
            return fn(*arrays)
        out = fn(*(torch.from_numpy(a) for a in arrays))
        if isinstance(out, tuple):
            return tuple(None if o is None else o.numpy() for o in out)
        return out.numpy()

    def scalar(self, t: torch.Tensor) -> Any:
        """The 0-dim tensor ``t`` as a factor of the kernel's arrays: a float for NumPy, the
        tensor itself for torch (no device synchronisation)."""
        return float(t) if self.np else t

    # -- construction
    def copy(self, a: Any) -> Any:
        return a.copy() if self.np else a.clone()

    def arange(self, k: int, like: Any) -> Any:
        """``[0, 1, ..., k - 1]`` (int64) beside ``like``."""
        return np.arange(k) if self.np else torch.arange(k, device=like.device)

    def eye(self, n: int, like: Any) -> Any:
        """The ``n x n`` identity of ``like``'s dtype (and device)."""
        if self.np:
            return np.eye(n, dtype=like.dtype)
        return torch.eye(n, dtype=like.dtype, device=like.device)

    def empty(self, shape: tuple[int, ...], like: Any) -> Any:
        """An uninitialised array of ``shape`` with ``like``'s dtype (and device)."""
        if self.np:
            return np.empty(shape, dtype=like.dtype)
        return torch.empty(shape, dtype=like.dtype, device=like.device)

    def zeros(self, shape: tuple[int, ...], like: Any) -> Any:
        """Zeros of ``shape`` with ``like``'s dtype (and device)."""
        if self.np:
            return np.zeros(shape, dtype=like.dtype)
        return torch.zeros(shape, dtype=like.dtype, device=like.device)

    def ones_bool(self, n: int, like: Any) -> Any:
        """``n`` True values beside ``like``."""
        return np.ones(n, dtype=bool) if self.np else torch.ones(n, dtype=torch.bool, device=like.device)

    def zeros_bool(self, n: int, like: Any) -> Any:
        """``n`` False values beside ``like``."""
        return np.zeros(n, dtype=bool) if self.np else torch.zeros(n, dtype=torch.bool, device=like.device)

    def repeat(self, a: Any, times: int) -> Any:
        """Each entry of the 1-D ``a`` ``times`` times in a row: ``[a0, a0, ..., a1, a1, ...]``."""
        return np.repeat(a, times) if self.np else a.repeat_interleave(times)

    def concat_index(self, spans: list[tuple[int, int]], like: Any) -> Any:
        """The int64 indices ``i:j`` of each ``(i, j)`` of ``spans``, one after the other (beside
        ``like``)."""
        if self.np:
            return np.concatenate([np.arange(i, j) for i, j in spans])
        return torch.cat([torch.arange(i, j, device=like.device) for i, j in spans])

    def searchsorted(self, a: Any, v: Any) -> Any:
        """Where each entry of ``v`` would go in the sorted 1-D ``a`` (to the left of equals)."""
        return np.searchsorted(a, v) if self.np else torch.searchsorted(a, v)

    def to_list(self, a: Any) -> list:
        """The 1-D ``a`` as a list of Python numbers."""
        return a.tolist()

    def free_block(self, M: Any, free: Any) -> Any:
        """The batch of matrices of a linear solve on the free sets: ``M`` (row-major
        ``(b, n * n)``, or ``(1, n * n)`` for one matrix) on the rows and columns of ``free``
        ``(b, n)``, the identity elsewhere; ``(b, n, n)``."""
        b, n = free.shape
        both = (free[:, :, None] & free[:, None, :]).reshape(b, n * n)
        eye = _eye_row(n, M.dtype) if self.np else self.eye(n, M).reshape(1, n * n)
        return self.where(both, M, eye).reshape(b, n, n)

    def to_float(self, a: Any, like: Any) -> Any:
        """``a`` (bool) as 0/1 of ``like``'s floating dtype."""
        return a.astype(like.dtype) if self.np else a.to(like.dtype)

    def contiguous(self, a: Any) -> Any:
        return np.ascontiguousarray(a) if self.np else a.contiguous()

    # -- elementwise and reductions
    def clamp_min(self, a: Any, lo: float) -> Any:
        return np.maximum(a, lo) if self.np else a.clamp(min=lo)

    def amax_abs(self, a: Any) -> Any:
        """``max_j |a_ij|`` as a ``(B, 1)`` column."""
        if self.np:  # NumPy reduces a short last axis slowly, its first axis fast
            return np.abs(np.ascontiguousarray(a.T)).max(axis=0)[:, None]
        return a.abs().amax(-1, keepdim=True)

    def argmax(self, a: Any) -> Any:
        """Index of the largest entry of each row, ``(B,)``."""
        return a.argmax(axis=1) if self.np else a.argmax(dim=1)

    def vdot(self, a: Any, b: Any) -> Any:
        """``sum(a * b)`` over every entry (a 0-dim array or tensor)."""
        return np.vdot(a, b) if self.np else torch.vdot(a.reshape(-1), b.reshape(-1))

    def inner(self, a: Any, b: Any) -> Any:
        """``sum(a * b)`` over a batch ``(B, m)`` (a 0-dim array or tensor), or per model over
        a stack ``(K, B, m)`` (``(K,)``; NumPy: each model's :meth:`vdot`, the number of its own
        batch)."""
        if a.ndim == 2:
            return self.vdot(a, b)
        if self.np:
            return np.array([np.vdot(a[k], b[k]) for k in range(a.shape[0])])
        return (a * b).reshape(a.shape[0], -1).sum(1)

    def count_rows(self, a: Any) -> Any:
        """The number of True entries of each row of the bool ``(B, k)`` ``a``, ``(B,)`` (as
        floating numbers for NumPy: a product with ones, which NumPy does faster than a row
        sum)."""
        if self.np:
            return a.astype(np.float64) @ _ones(a.shape[1], np.dtype(np.float64))
        return a.sum(1)

    def colsum(self, a: Any) -> Any:
        """``a.sum(-2)``: the column sums of ``(B, m)``, or of each model's ``(B, m)`` of a stack
        ``(K, B, m)`` (NumPy: a product with ones, faster than its column sum)."""
        return _ones(a.shape[-2], a.dtype) @ a if self.np else a.sum(-2)

    def count(self, a: Any) -> int:
        """The number of nonzero entries of ``a``."""
        return int(np.count_nonzero(a) if self.np else torch.count_nonzero(a))

    def flatnonzero(self, a: Any) -> Any:
        """Indices of the True entries of the 1-D ``a``."""
        return np.flatnonzero(a) if self.np else a.nonzero().squeeze(1)

    # -- linear algebra
    def solve(self, M: Any, rhs: Any, spd: bool = True, batch: int | None = None) -> tuple[Any, Any | None]:
        """:func:`spd_solve` on the kernel's arrays.

        NumPy: a batch of at most :data:`NUMPY_SOLVE_WORK` ``b * n * n`` goes to NumPy's
        batched LU (``numpy.linalg.solve``), cheaper to call than torch's -- and inside a kernel
        of NumPy operations a call into torch costs more than in a loop of its own. A larger
        batch, or one with an exactly singular matrix (NumPy raises for the whole batch), goes
        to :func:`spd_solve`, which says which one failed. ``batch`` (default: the rows of
        ``rhs``) is the ``b`` of that choice: a call that solves several models' systems at once
        passes one model's (:class:`lcs_cvx._kernels.stacks.Stacked`), so that each model's
        systems go to the library its own call would use.
        """
        if not self.np:
            return spd_solve(M, rhs, spd)
        b, n = rhs.shape
        if (b if batch is None else batch) * n * n <= NUMPY_SOLVE_WORK:
            try:
                return np.linalg.solve(M, rhs[..., None])[..., 0], None
            except np.linalg.LinAlgError:
                pass
        return self.via_torch(functools.partial(spd_solve, spd=spd), M, rhs)


@functools.cache
def _eye_row(n: int, dtype: np.dtype) -> np.ndarray:
    """The ``n x n`` identity as one row-major ``(1, n * n)`` row (read-only, made once)."""
    eye = np.eye(n, dtype=dtype).reshape(1, n * n)
    eye.flags.writeable = False
    return eye


@functools.cache
def _ones(k: int, dtype: np.dtype) -> np.ndarray:
    """``k`` ones (read-only, made once)."""
    ones = np.ones(k, dtype=dtype)
    ones.flags.writeable = False
    return ones


@functools.cache
def _numpy_blas() -> list[Any]:
    """threadpoolctl's controllers of NumPy's BLAS (found once): the one shipped in NumPy's
    wheel (``numpy.libs``), else every BLAS loaded (a NumPy linked to a shared one)."""
    from threadpoolctl import ThreadpoolController

    libs = ThreadpoolController().select(user_api="blas").lib_controllers
    home = os.path.dirname(os.path.abspath(np.__file__))
    own = [lib for lib in libs if os.path.abspath(lib.filepath).startswith(home)]
    return own or list(libs)


class _BlasThreads:
    """:meth:`ArrayOps.threads` for NumPy. A plain context manager rather than a generator-based
    one, as it is entered at every kernel call and every fast-loss backward; re-entrant: only
    the outermost use sets and restores the limit (NumPy's BLAS setting is process-wide)."""

    def __init__(self) -> None:
        self.depth = 0
        self.changed: list[tuple[Any, int]] = []

    def __enter__(self) -> None:
        self.depth += 1
        if self.depth > 1:
            return
        want = torch.get_num_threads()
        self.changed = []
        for lib in _numpy_blas():
            before = lib.get_num_threads()
            if before != want:
                lib.set_num_threads(want)
                self.changed.append((lib, before))

    def __exit__(self, *exc: object) -> None:
        self.depth -= 1
        if self.depth > 0:
            return
        for lib, before in self.changed:
            lib.set_num_threads(before)
        self.changed = []


_BLAS_THREADS = _BlasThreads()

#: The kernels' array libraries: ``"auto"`` picks NumPy for CPU tensors and torch otherwise;
#: ``"compiled"`` asks for the compiled kernels (:mod:`.compiled`: the fast losses, the LCP) and
#: is ``"auto"`` for the array kernels (what the compiled ones do not cover).
ARRAYS = ("auto", "numpy", "torch", "compiled")
_OPS = {"numpy": ArrayOps("numpy"), "torch": ArrayOps("torch")}
#: The torch instance, for kernels called on tensors with autograd (e.g. the normal equations
#: of :meth:`lcs_cvx.problems.ViolationProblem.normal_equations`).
TORCH = _OPS["torch"]


def array_ops(t: torch.Tensor, arrays: str = "auto") -> ArrayOps:
    """The :class:`ArrayOps` that runs the kernels on ``t``'s device.

    ``arrays``: ``"auto"`` or ``"compiled"`` (NumPy for CPU tensors, torch otherwise),
    ``"numpy"`` (CPU tensors only) or ``"torch"``.
    """
    if arrays not in ARRAYS:
        raise LCSInputError(f"arrays: expected one of {ARRAYS}, received {arrays!r}")
    cpu = t.device.type == "cpu"
    if arrays == "numpy" and not cpu:
        raise LCSInputError(f"arrays: 'numpy' runs on CPU tensors only, received a tensor on {t.device}")
    return _OPS["numpy" if (arrays in ("auto", "compiled") and cpu) or arrays == "numpy" else "torch"]
