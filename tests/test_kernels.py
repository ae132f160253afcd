"""The private kernels of :mod:`lcs_cvx._kernels`: the array back-end, the pivoting engine and
the fast losses' array arithmetic.

The kernels are written once against :class:`lcs_cvx._kernels.arrays.ArrayOps` and run on NumPy
arrays for CPU tensors and on torch tensors elsewhere (CUDA). Here: the choice of back-end and
its errors, the zero-copy boundary, the engine on its own, the BLAS threads, and the fast losses'
formulas against their torch counterparts. That both back-ends solve every problem alike is
``test_zoo.py`` (LCP) and ``test_violation.py`` ((V)).
"""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from lcs_cvx import LCSInputError
from lcs_cvx._kernels import losses as kernel_losses
from lcs_cvx._kernels.arrays import ARRAYS, TORCH, ArrayOps, array_ops
from lcs_cvx._kernels.pivoting import block_pivoting, unconverged
from lcs_cvx.lcp import solve_lcp_fast
from lcs_cvx.parameters import F_adjoint, F_matrix

F64 = torch.float64
KERNELS = ("numpy", "torch")


def test_array_ops_choice_and_errors():
    t = torch.zeros(3, 2, dtype=F64)
    assert array_ops(t).name == "numpy"  # CPU tensors run in NumPy by default
    assert array_ops(t, "torch").name == "torch"
    assert set(ARRAYS) == {"auto", "numpy", "torch", "compiled"}
    assert array_ops(t, "compiled").name == "numpy"  # what the compiled kernels leave to arrays
    with pytest.raises(LCSInputError, match=r"arrays: expected one of .*received 'jax'"):
        array_ops(t, "jax")
    with pytest.raises(LCSInputError, match="arrays"):
        solve_lcp_fast(torch.eye(2, dtype=F64), t, arrays="cupy")


@pytest.mark.parametrize("kernel", KERNELS)
def test_array_ops_share_memory_and_round_trip(kernel):
    xp = array_ops(torch.zeros(1), kernel)
    t = torch.arange(6, dtype=F64).reshape(2, 3)
    a = xp.wrap(t)
    assert isinstance(a, np.ndarray if kernel == "numpy" else torch.Tensor)
    if kernel == "numpy":  # no copy: the array is the tensor's memory
        assert np.shares_memory(a, t.numpy())
    back = xp.unwrap(a)
    assert torch.equal(back, t) and back.dtype == F64
    # the free-set matrix: M on the free rows and columns, the identity elsewhere
    M = xp.wrap(torch.arange(1.0, 10.0, dtype=F64).reshape(1, 9))
    free = xp.wrap(torch.tensor([[True, False, True]]))
    got = xp.unwrap(xp.free_block(M, free))
    expected = torch.tensor([[[1.0, 0.0, 3.0], [0.0, 1.0, 0.0], [7.0, 0.0, 9.0]]], dtype=F64)
    assert torch.equal(got, expected)


def test_block_pivoting_counts_sweeps_and_reports_unconverged():
    """The engine on its own, with a callback that is never satisfied on sample 1: sample 0
    converges at once, sample 1 is reported unconverged after ``max_iter`` sweeps."""
    xp: ArrayOps = array_ops(torch.zeros(1))
    calls = []

    def solve(free, idx):
        calls.append(None if idx is None else idx.tolist())
        n = free.shape[0]
        bad = np.zeros((n, 2), dtype=bool)
        rows = np.arange(n) if idx is None else idx
        bad[rows == 1, 0] = True
        return np.zeros((n, 2)), bad

    res = block_pivoting(xp, solve, np.zeros((2, 2), dtype=bool), max_iter=5)
    assert res.iterations == 5
    assert res.converged.tolist() == [True, False]
    assert len(calls) == 6 and calls[0] is None
    idx = unconverged(xp, res.converged)
    assert isinstance(idx, torch.Tensor) and idx.tolist() == [1]
    assert unconverged(xp, np.ones(3, dtype=bool)) is None


def test_numpy_kernel_runs_with_torchs_thread_count():
    """NumPy's OpenBLAS would put every core on the kernel's small products (measured here:
    2 cores busy, no faster); inside the kernel it uses ``torch.get_num_threads()`` threads and
    the caller's setting is restored afterwards -- by the outermost of nested uses. (Only NumPy's
    own BLAS, from its wheel, is set: SciPy's and SCS's are not what the kernels call.)"""
    import threadpoolctl  # a declared dependency

    xp = array_ops(torch.zeros(1), "numpy")
    limit = torch.get_num_threads() + 1  # the caller's setting differs from the kernel's
    blas = threadpoolctl.ThreadpoolController().select(user_api="blas")
    home = os.path.dirname(os.path.abspath(np.__file__))

    def numpys() -> list[int]:
        info = blas.info()
        own = [lib for lib in info if os.path.abspath(lib["filepath"]).startswith(home)]
        return [lib["num_threads"] for lib in own or info]

    with blas.limit(limits=limit):
        outside = numpys()
        with xp.threads():
            inside = numpys()
            with xp.threads():
                nested = numpys()
            after_nested = numpys()
        after = numpys()
    # the libraries that take the caller's limit (one whose threading layer is OpenMP reports
    # OMP_NUM_THREADS's count instead, where that is set: not a fact of this package)
    settable = [i for i, n in enumerate(outside) if n == limit]
    assert settable
    assert all(inside[i] == torch.get_num_threads() for i in settable)
    assert nested == inside and after_nested == inside
    assert after == outside


@pytest.mark.parametrize("kernel", KERNELS)
def test_F_matrix_and_its_adjoint_on_both_back_ends(kernel):
    """The kernels' ``F = G G^T + H - H^T + s I`` and its chain rule are the model's (the tensor
    functions of :mod:`lcs_cvx.system` call them), and the adjoint is autograd's."""
    g = torch.Generator().manual_seed(0)
    G, H, T = (torch.randn(4, 4, generator=g, dtype=F64) for _ in range(3))
    xp = array_ops(G, kernel)
    F = xp.unwrap(kernel_losses.F_matrix(xp, xp.wrap(G), xp.wrap(H), 0.3))
    assert torch.allclose(F, G @ G.mT + H - H.mT + 0.3 * torch.eye(4, dtype=F64), rtol=0, atol=1e-15)
    assert torch.equal(F_matrix(G, H, 0.3), kernel_losses.F_matrix(TORCH, G, H, 0.3))
    dG, dH = (xp.unwrap(a) for a in kernel_losses.F_adjoint(xp.wrap(T), xp.wrap(G)))
    Gg, Hg = G.clone().requires_grad_(True), H.clone().requires_grad_(True)
    (F_matrix(Gg, Hg, 0.3) * T).sum().backward()
    assert torch.allclose(dG, Gg.grad, rtol=1e-14, atol=1e-14)
    assert torch.allclose(dH, Hg.grad, rtol=1e-14, atol=1e-14)
    # batched T_F (..., n, n), as the Hessian's Jacobians use it
    Tb = torch.randn(3, 2, 4, 4, generator=g, dtype=F64)
    dGb, dHb = F_adjoint(Tb, G)
    assert torch.allclose(dGb[1, 0], F_adjoint(Tb[1, 0], G)[0], rtol=0, atol=1e-14)
    assert torch.equal(dHb, Tb - Tb.mT)


@pytest.mark.parametrize("kernel", KERNELS)
def test_degenerate_count(kernel):
    """A sample counts when some index has both ``lam_i`` and ``w_i`` below ``tol (1 + |q|_inf)``."""
    lam = torch.tensor([[0.0, 1.0], [0.0, 0.0], [1e-12, 2.0], [0.0, 3.0]], dtype=F64)
    w = torch.tensor([[1.0, 0.0], [0.0, 0.5], [1e-12, 0.0], [1e-6, 0.0]], dtype=F64)
    q = torch.tensor([[1.0, -1.0], [0.0, 0.5], [1e3, 1.0], [1.0, 1.0]], dtype=F64)
    xp = array_ops(lam, kernel)
    n = kernel_losses.degenerate_count(xp, *(xp.wrap(t) for t in (lam, w, q)), 1e-9)
    assert n == 2  # samples 1 (lam_0 = w_0 = 0) and 2 (both 1e-12 <= 1e-9 (1 + 1e3))
