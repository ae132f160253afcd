"""Batched block principal pivoting: the active-set engine behind both fast kernels.

Both per-sample problems of the paper reduce to a linear complementarity problem with a
P-matrix: the LCP of eq. (equ.lcp) itself, and the KKT system of the strongly convex
violation QP (eq. equ.contactnet.2), whose Hessian is positive definite (Lemma 3a).
For a P-matrix LCP ``0 <= z  _|_  M z + p >= 0`` every guess of the *free set* I
(``z_I`` free, ``z_J = 0``) gives one linear solve, and the guess is right iff the
result is feasible. Block principal pivoting (Judice & Pires, 1994) flips every
infeasible index at once; when that stops reducing the number of infeasibilities it
falls back to Murty's single pivot on the largest infeasible index, which terminates
for every P-matrix (Murty, 1974). The result is the exact active-set solution, to
round-off, not an approximate one.

The driver is problem-agnostic: a ``solve(free, idx)`` callback returns the solution of
the linear system for the given free sets and a mask of infeasible indices; it works
on a whole batch at once and only re-solves the samples that have not converged.

The kernels are framework-free: they are written against :class:`ArrayOps`, which runs them on
NumPy arrays for CPU tensors (a NumPy call costs a fraction of a torch dispatch, and a kernel
call is a few hundred operations on small arrays) and on torch tensors for other devices.
"""

from __future__ import annotations

import contextlib
import functools
import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ._checks import LCSInputError, SolverError

__all__ = [
    "PivotResult", "block_pivoting", "unconverged", "initial_state", "spd_solve", "FallbackWarning",
    "SMALL_N", "ArrayOps", "array_ops", "ops_of", "BACKENDS",
]


class FallbackWarning(RuntimeWarning):
    """The fast solver did not converge on some samples; the reference solved them."""


#: Up to this size a batch of linear solves is one LAPACK LU call (``linalg.solve_ex``), which
#: is 2-3x faster than Cholesky plus ``cholesky_solve`` on CPU for tiny matrices; above it,
#: Cholesky and two triangular solves (half the flops).
SMALL_N = 6


#: Up to this much work (``batch * n * n``) the NumPy back-end solves with NumPy's batched LU
#: rather than torch's LAPACK calls: NumPy's is cheaper to call, torch's faster per matrix.
#: Measured (one thread): alone, the two cross between 1,000 and 10,000 for n from 4 to 20;
#: inside the fast violation loss at n_lam = 4, batch 200 (3,200), NumPy's made the call
#: 1.05-1.16x faster; at batch 50,000 torch's LCP kernel was 1.3x faster.
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
        # takes without a copy (~15 % of the call for 200 matrices of 4 x 4)
        x, info = torch.linalg.solve_ex(M.mT if spd else M, rhs.unsqueeze(-1))
    else:
        chol, info = torch.linalg.cholesky_ex(M)
        y = torch.linalg.solve_triangular(chol, rhs.unsqueeze(-1), upper=False)
        x = torch.linalg.solve_triangular(chol.mT, y, upper=True)
    return x.squeeze(-1), (info != 0 if bool(info.any()) else None)


class ArrayOps:
    """The array operations of the fast kernels, for one array library (the kernels' core).

    :func:`block_pivoting` and the per-sweep solves of :mod:`lcs_cvx.violation` and
    :mod:`lcs_cvx.lcp` are written once, against Python's operators (``@ + * < & | ^ ~``,
    indexing, ``.sum``, ``.any``, ``.all``, ``.reshape``, ``.T`` of a matrix) and the methods
    below, which NumPy arrays and torch tensors share through this adapter. Two instances:

    - ``"numpy"`` (CPU tensors, the default there): the kernels are a few hundred operations
      on arrays of a few hundred numbers per call, so they cost the per-call overhead of the
      array library: ~0.5 us for a NumPy elementwise operation against ~1.5-5 us for a torch
      dispatch (products and reductions are closer). The arrays share memory with the tensors
      (``Tensor.numpy()`` / ``torch.from_numpy``: no copy); small batched factorisations are
      NumPy's, large ones torch's LAPACK calls on the same memory (:meth:`solve`).
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
        #: k``). An indexing pass is cheap in NumPy: it shrinks at every sweep (5-15 % faster
        #: kernels than at 0.25, n_lam 4 to 20, batch 200, measured); in torch it is not.
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
        products of a few thousand numbers: no faster here, and it oversubscribes a process
        pool whose workers run one torch thread each. The setting is restored on exit."""
        return _BlasThreads() if self.np else contextlib.nullcontext()

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

    def ones_bool(self, n: int, like: Any) -> Any:
        """``n`` True values beside ``like``."""
        return np.ones(n, dtype=bool) if self.np else torch.ones(n, dtype=torch.bool, device=like.device)

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
        if self.np:  # NumPy reduces a short last axis slowly (~9 us for 200 x 4); its first, fast
            return np.abs(np.ascontiguousarray(a.T)).max(axis=0)[:, None]
        return a.abs().amax(-1, keepdim=True)

    def argmax(self, a: Any) -> Any:
        """Index of the largest entry of each row, ``(B,)``."""
        return a.argmax(axis=1) if self.np else a.argmax(dim=1)

    def vdot(self, a: Any, b: Any) -> Any:
        """``sum(a * b)`` over every entry (a 0-dim array or tensor)."""
        return np.vdot(a, b) if self.np else torch.vdot(a.reshape(-1), b.reshape(-1))

    def count_rows(self, a: Any) -> Any:
        """The number of True entries of each row of the bool ``(B, k)`` ``a``, ``(B,)`` (as
        floating numbers for NumPy: a product with ones, 2-3x faster than NumPy's row sum)."""
        if self.np:
            return a.astype(np.float64) @ _ones(a.shape[1], np.dtype(np.float64))
        return a.sum(1)

    def colsum(self, a: Any) -> Any:
        """``a.sum(0)`` (NumPy: a product with ones, ~3x faster than its column sum)."""
        return _ones(a.shape[0], a.dtype) @ a if self.np else a.sum(0)

    def count(self, a: Any) -> int:
        """The number of nonzero entries of ``a``."""
        return int(np.count_nonzero(a) if self.np else torch.count_nonzero(a))

    def flatnonzero(self, a: Any) -> Any:
        """Indices of the True entries of the 1-D ``a``."""
        return np.flatnonzero(a) if self.np else a.nonzero().squeeze(1)

    # -- linear algebra
    def solve(self, M: Any, rhs: Any, spd: bool = True) -> tuple[Any, Any | None]:
        """:func:`spd_solve` on the kernel's arrays.

        NumPy: a batch of at most :data:`NUMPY_SOLVE_WORK` ``b * n * n`` goes to NumPy's
        batched LU (``numpy.linalg.solve``): ~5 us for one small matrix against ~17 us for
        torch's call, and inside a kernel of NumPy operations a call into torch costs more than
        in a loop of its own. A larger batch, or one with an exactly singular matrix (NumPy
        raises for the whole batch), goes to :func:`spd_solve`, which says which one failed.
        """
        if not self.np:
            return spd_solve(M, rhs, spd)
        b, n = rhs.shape
        if b * n * n <= NUMPY_SOLVE_WORK:
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
    """:meth:`ArrayOps.threads` for NumPy: a plain context manager, as it runs at every kernel
    call and every fast-loss backward (a generator-based one cost 5-7 us there)."""

    def __enter__(self) -> None:
        want = torch.get_num_threads()
        self.changed = []
        for lib in _numpy_blas():
            before = lib.get_num_threads()
            if before != want:
                lib.set_num_threads(want)
                self.changed.append((lib, before))

    def __exit__(self, *exc: object) -> None:
        for lib, before in self.changed:
            lib.set_num_threads(before)


#: The kernel back-ends: ``"auto"`` picks NumPy for CPU tensors and torch otherwise.
BACKENDS = ("auto", "numpy", "torch")
_OPS = {"numpy": ArrayOps("numpy"), "torch": ArrayOps("torch")}


def array_ops(t: torch.Tensor, backend: str = "auto") -> ArrayOps:
    """The :class:`ArrayOps` that runs the kernels on ``t``'s device.

    ``backend``: ``"auto"`` (NumPy for CPU tensors, torch otherwise), ``"numpy"`` (CPU tensors
    only) or ``"torch"``.
    """
    if backend not in BACKENDS:
        raise LCSInputError(f"backend: expected one of {BACKENDS}, received {backend!r}")
    cpu = t.device.type == "cpu"
    if backend == "numpy" and not cpu:
        raise LCSInputError(f"backend: 'numpy' runs on CPU tensors only, received a tensor on {t.device}")
    return _OPS["numpy" if (backend == "auto" and cpu) or backend == "numpy" else "torch"]


def ops_of(a: Any) -> ArrayOps:
    """The :class:`ArrayOps` of an array: NumPy for an ``ndarray``, torch for a tensor."""
    return _OPS["numpy" if isinstance(a, np.ndarray) else "torch"]


def initial_state(xp: ArrayOps, guess: Any, warm_start: torch.Tensor | None, device: torch.device) -> Any:
    """The pivoting's starting state (a kernel array for ``device``): ``warm_start`` where given
    (checked to be a bool tensor of ``guess``'s shape), else the cold ``guess``."""
    if warm_start is None:
        return guess
    if not isinstance(warm_start, torch.Tensor) or warm_start.dtype != torch.bool \
            or tuple(warm_start.shape) != tuple(guess.shape):
        got = (f"{warm_start.dtype} tensor of shape {tuple(warm_start.shape)}"
               if isinstance(warm_start, torch.Tensor) else type(warm_start).__name__)
        raise LCSInputError(
            f"warm_start: expected a bool tensor of shape {tuple(guess.shape)} (the active sets of "
            f"an earlier solve of these samples, LossInfo.active), received {got}"
        )
    return xp.wrap(warm_start.to(device))


#: ``solve(free, idx) -> (solution, infeasible)``; ``idx`` selects samples (None: all).
SolveFn = Callable[[Any, Any], tuple[Any, Any]]


@dataclass(frozen=True)
class PivotResult:
    """Outcome of :func:`block_pivoting` for a batch of ``B`` problems (kernel arrays).

    Attributes:
        solution: ``(B, ...)`` solution of the last linear solve of each sample.
        free: ``(B, k)`` bool, the final free set.
        converged: ``(B,)`` bool, True where no index is infeasible.
        iterations: number of pivoting sweeps made.
    """

    solution: Any
    free: Any
    converged: Any
    iterations: int


def block_pivoting(
    xp: ArrayOps,
    solve: SolveFn,
    free0: Any,
    *,
    max_iter: int = 100,
    stall: int = 3,
    subset_fraction: float | None = None,
    subset_min_work: int | None = None,
) -> PivotResult:
    """Run block principal pivoting with Murty's fallback on a batch.

    Args:
        xp: the array operations (:func:`array_ops`) of ``free0`` and of ``solve``'s arrays.
        solve: callback ``solve(free, idx)``; ``free`` is ``(b, k)`` bool for the samples
            ``idx`` (an int64 index array, or None for the whole batch). Returns the
            ``(b, ...)`` solution and a ``(b, k)`` bool mask of infeasible indices.
        free0: ``(B, k)`` bool initial guess of the free set.
        max_iter: sweeps before giving up on the remaining samples (they come back with
            ``converged = False``; callers fall back to a reference solver).
        stall: sweeps without a new lowest infeasibility count before a sample switches
            to single (Murty) pivots.
        subset_fraction: once at most this fraction of the work set is unconverged, the work
            set shrinks to those samples (a converged sample re-solved with its unchanged free
            set gives the same answer, so shrinking is only a saving, not a correctness matter;
            default: the back-end's :attr:`ArrayOps.subset_fraction`).
        subset_min_work: ... and only when the work set is this large (``size * k * k``): on
            small batches one more indexing pass can cost more than the solves it saves
            (default: the back-end's :attr:`ArrayOps.subset_min_work`).

    Returns:
        :class:`PivotResult`.
    """
    if subset_fraction is None:
        subset_fraction = xp.subset_fraction
    if subset_min_work is None:
        subset_min_work = xp.subset_min_work
    free = xp.copy(free0)
    B, k = free.shape
    solution, bad = solve(free, None)
    active = None  # None: the whole batch is the work set
    n_bad = xp.count_rows(bad)
    best = xp.copy(n_bad)
    stalled = n_bad * 0
    columns = xp.arange(k, free)
    sweeps = 0
    while sweeps < max_iter:
        n_todo = xp.count(n_bad)
        if n_todo == 0:
            break
        size = B if active is None else active.shape[0]
        if size * k * k >= subset_min_work and n_todo <= subset_fraction * size:
            keep = xp.flatnonzero(n_bad > 0)
            active = keep if active is None else active[keep]
            bad, n_bad, best, stalled = bad[keep], n_bad[keep], best[keep], stalled[keep]
        flip = bad
        if sweeps >= stall:  # Murty's rule (largest infeasible index) for stalled samples
            last = xp.argmax(xp.where(bad, columns, -1))
            single = (columns == last[:, None]) & bad
            flip = xp.where((stalled >= stall)[:, None], single, bad)
        if active is None:
            free ^= flip
            solution, bad = solve(free, None)
        else:
            free_act = free[active] ^ flip
            free[active] = free_act
            sol, bad = solve(free_act, active)
            solution[active] = sol
        sweeps += 1
        n_bad = xp.count_rows(bad)
        improved = n_bad < best
        best = xp.minimum(best, n_bad)
        stalled = xp.where(improved, 0, stalled + 1)
    converged = n_bad == 0
    if active is not None:  # the samples outside the work set had converged
        converged_all = xp.ones_bool(B, free)
        converged_all[active] = converged
        converged = converged_all
    return PivotResult(solution=solution, free=free, converged=converged, iterations=sweeps)


def unconverged(xp: ArrayOps, converged: Any, what: str, max_iter: int, fallback: bool,
                reference: str = "the Clarabel reference") -> torch.Tensor | None:
    """Indices (a tensor) of the samples that did not converge (``converged``, the ``(B,)`` bool
    kernel array of :class:`PivotResult`, is False; None if all did, checked in the kernel's
    arrays), after saying so: a :class:`FallbackWarning` if ``fallback`` (the caller then solves
    them with ``reference``), else :class:`lcs_cvx.SolverError`."""
    if bool(converged.all()):
        return None
    idx = xp.unwrap(xp.flatnonzero(~converged))
    msg = (f"{what} pivoting did not converge on {idx.numel()} of {converged.shape[0]} "
           f"samples in {max_iter} sweeps")
    if not fallback:
        raise SolverError(msg)
    warnings.warn(f"{msg}; solved them with {reference}", FallbackWarning, stacklevel=3)
    return idx
