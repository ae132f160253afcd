"""Private array kernels of lcs_cvx: the array back-end and all array-level work.

The public modules (:mod:`lcs_cvx.lcp`, :mod:`lcs_cvx.violation`, :mod:`lcs_cvx.losses`,
:mod:`lcs_cvx.problems`, :mod:`lcs_cvx.system`) take and return torch tensors; the arithmetic
they share runs here, written once against :class:`~lcs_cvx._kernels.arrays.ArrayOps`, which
executes it on NumPy arrays for CPU tensors (no copy) and on torch tensors elsewhere:

- :mod:`.arrays` -- the back-end (:class:`ArrayOps`, :func:`array_ops`) and its BLAS threads;
- :mod:`.pivoting` -- batched block principal pivoting, the engine of both solvers;
- :mod:`.lcp` -- the LCP kernel, ``0 <= lam _|_ F lam + q >= 0``;
- :mod:`.violation` -- the kernel of the violation problem (V) and its normal equations;
- :mod:`.losses` -- the forward and backward arithmetic of the two fast losses;
- :mod:`.compiled` -- the two fast losses and the LCP compiled (numba), solve, loss and gradient
  in one call, for one model's float64 CPU tensors (the default there); :mod:`.dense`, their
  small dense algebra; :mod:`.calls`, tensors in and out of them;
- :mod:`.stacks`, :mod:`.c3` -- a kernel call's matrices (one model or a stack), C3's array work;
  :mod:`.c3_admm`, :mod:`.c3_polish` -- C3's ADMM, polish and whole solve compiled (numba), one
  initial state at a time (:mod:`lcs_cvx.control.compiled_path` calls them).

Nothing here is public API; no name here is exported by :mod:`lcs_cvx`.
"""
