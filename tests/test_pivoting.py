"""The pivoting engine of :mod:`lcs_cvx.pivoting` and its two array back-ends.

The fast kernels are written once against :class:`lcs_cvx.pivoting.ArrayOps` and run on NumPy
arrays for CPU tensors and on torch tensors elsewhere (CUDA). The losses' tests certify the
default (NumPy, on this CPU) answers; here the torch back-end, the one CUDA runs, must give the
same answer, the same active sets and the same number of sweeps on every problem class:
the violation QP (V) in the paper's and the stiff setting, P-matrix LCPs including nearly
skew-symmetric ones (Murty's rule and the shrinking work set), fallbacks and warm starts.
"""

from __future__ import annotations

import os
import warnings

import numpy as np
import pytest
import torch
from conftest import random_p_matrix, random_q

import lcs_cvx
from lcs_cvx._checks import LCSInputError
from lcs_cvx.lcp import solve_lcp_brute, solve_lcp_fast
from lcs_cvx.pivoting import BACKENDS, ArrayOps, array_ops, block_pivoting
from lcs_cvx.problems import violation_problem
from lcs_cvx.violation import solve_violation_fast

F64 = torch.float64
KERNELS = ("numpy", "torch")

#: (gamma, eps, stiffness) as in the losses' tests: the paper's setting and the stiff one
#: (1 / (eps gamma) = 1e10).
SETTINGS = {"paper": (1e-2, 1e-4, 0.5), "stiff": (1e-6, 1e-4, 1e-6)}


def violation_values(n_lam: int, setting: str, batch: int = 200, perturb: float = 0.05):
    """(V)'s parameter values for a random truth (the losses' tests' settings) moved by
    ``perturb * N(0, 1)`` in every parameter: a mid-training model, whose active sets are
    neither trivial nor the truth's."""
    gamma, eps, stiffness = SETTINGS[setting]
    truth = lcs_cvx.random_lcs(10, 4, n_lam, stiffness=stiffness, seed=n_lam)
    data = lcs_cvx.make_dataset(truth, batch, noise=1e-2, seed=7 + n_lam)
    gen = torch.Generator().manual_seed(n_lam)
    with torch.no_grad():
        for p in truth.parameters():
            p.add_(perturb * torch.randn(p.shape, generator=gen, dtype=F64))
        assert gamma < truth.sigma_min
        q = truth.lcp_offset(data.x, data.u)
        r = data.x @ truth.A.mT + data.u @ truth.B.mT + truth.d - data.x_next
        return violation_problem(n_lam).parameter_values(truth.C, truth.F, q, r, gamma, eps)


def rel_dev(a: torch.Tensor, b: torch.Tensor) -> float:
    """Worst per-sample ``|a - b|_inf / (1 + |b|_inf)``."""
    return float(((a - b).abs().amax(-1) / (1.0 + b.abs().amax(-1))).max())


#: Agreement of the two back-ends, relative to ``1 + |lam|_inf``: round-off of two BLAS
#: libraries (NumPy's OpenBLAS, torch's MKL). Measured <= 1.0e-14 in both settings.
BACKEND_AGREEMENT = 1e-12


@pytest.mark.parametrize("setting", list(SETTINGS))
@pytest.mark.parametrize("n_lam", [1, 4, 10, 20])
def test_violation_kernel_backends_agree(n_lam, setting):
    """Same (V) solution to round-off, same active sets, same sweeps; both KKT-exact."""
    values = violation_values(n_lam, setting)
    sol = {k: solve_violation_fast(values, backend=k) for k in KERNELS}
    a, b = sol["numpy"], sol["torch"]
    assert a.iterations == b.iterations
    assert a.n_fallback == b.n_fallback == 0
    assert rel_dev(a.lam, b.lam) <= BACKEND_AGREEMENT
    assert torch.equal(a.free, b.free) and torch.equal(a.pos, b.pos)
    for s in (a, b):
        assert s.lam.dtype == F64 and s.lam.device.type == "cpu"
        assert float(s.residual.max()) <= 1e-13
    # not vacuous: the batch pivots, and both kinds of index are present
    assert a.iterations >= (1 if n_lam > 1 else 0)
    assert bool(a.free.any()) and bool((~a.free).any())


@pytest.mark.parametrize("n, smin, skew", [(3, 0.5, 1.0), (6, 0.1, 1.0), (8, 1e-5, 1.0)])
def test_lcp_kernel_backends_agree_with_enumeration(n, smin, skew):
    F = random_p_matrix(n, smin=smin, skew=skew, seed=n)
    q = random_q(500, n, seed=n, scale=10.0)
    brute = solve_lcp_brute(F, q)
    sols = {k: solve_lcp_fast(F, q, backend=k) for k in KERNELS}
    assert sols["numpy"].iterations == sols["torch"].iterations >= 1
    for s in sols.values():
        assert s.n_fallback == 0
        assert rel_dev(s.lam, brute.lam) <= 1e-9
        assert torch.equal(s.free, brute.lam > 0)
    assert rel_dev(sols["numpy"].lam, sols["torch"].lam) <= 1e-12


def test_murty_rule_and_shrinking_work_set_on_both_backends():
    """Nearly skew-symmetric F (Fig. 1(c)'s stiffest truth): tens of sweeps, Murty's single
    pivots, and a work set that shrinks to the unconverged samples (in the torch back-end too:
    3,000 samples x 8^2 is above its threshold) -- the same answer as enumeration."""
    gen = torch.Generator().manual_seed(5)
    H = torch.rand(8, 8, generator=gen, dtype=F64) * 2 - 1
    F = 1e-5 * torch.eye(8, dtype=F64) + H - H.mT
    q = 10 * (torch.rand(3000, 8, generator=gen, dtype=F64) * 2 - 1)
    brute = solve_lcp_brute(F, q)
    with warnings.catch_warnings():
        warnings.simplefilter("error", lcs_cvx.FallbackWarning)
        sols = {k: solve_lcp_fast(F, q, backend=k) for k in KERNELS}
    assert array_ops(q, "torch").subset_min_work <= 3000 * 8 * 8
    for s in sols.values():
        assert s.iterations > 20
        assert float((s.lam - brute.lam).abs().max() / (1 + brute.lam.abs().max())) <= 1e-8


@pytest.mark.parametrize("kernel", KERNELS)
def test_fallback_and_warm_start_on_each_backend(kernel):
    values = violation_values(4, "paper", batch=60)
    cold = solve_violation_fast(values, backend=kernel)
    assert cold.iterations >= 1
    warm = solve_violation_fast(values, backend=kernel, warm_start=cold.active)
    assert warm.iterations == 0 and torch.equal(warm.lam, cold.lam)
    with pytest.warns(lcs_cvx.FallbackWarning, match="violation QP pivoting did not converge"):
        fb = solve_violation_fast(values, backend=kernel, max_iter=0)
    assert fb.n_fallback >= 1
    assert rel_dev(fb.lam, cold.lam) <= 1e-7  # the Clarabel reference's accuracy
    assert torch.equal(fb.free, fb.lam > 0)
    with pytest.raises(lcs_cvx.SolverError, match=r"did not converge on \d+ of 60 samples"):
        solve_violation_fast(values, backend=kernel, max_iter=0, fallback=False)


def test_array_ops_choice_and_errors():
    t = torch.zeros(3, 2, dtype=F64)
    assert array_ops(t).name == "numpy"  # CPU tensors run in NumPy by default
    assert array_ops(t, "torch").name == "torch"
    assert set(BACKENDS) == {"auto", "numpy", "torch"}
    with pytest.raises(LCSInputError, match=r"backend: expected one of .*received 'jax'"):
        array_ops(t, "jax")
    with pytest.raises(LCSInputError, match="backend"):
        solve_lcp_fast(torch.eye(2, dtype=F64), t, backend="cupy")


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


def test_numpy_kernel_runs_with_torchs_thread_count():
    """NumPy's OpenBLAS would put every core on the kernel's small products (measured here:
    2 cores busy, no faster); inside the kernel it uses ``torch.get_num_threads()`` threads and
    the caller's setting is restored afterwards. (Only NumPy's own BLAS, from its wheel, is
    set: SciPy's and SCS's are not what the kernels call.)"""
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
        after = numpys()
    assert outside and all(n == limit for n in outside)
    assert inside and all(n == torch.get_num_threads() for n in inside)
    assert after == outside


def test_violation_pivoting_outlasts_clarabel_on_nearly_skew_F():
    """Nearly skew-symmetric ``F`` (``G = 0``, ``s = gamma = 1e-6``, 1 / (eps gamma) = 1e10):
    pivoting needs hundreds of sweeps (Murty's rule) and ends exact, where the former 100-sweep
    limit handed 88 of 200 samples to Clarabel, whose answers had a KKT residual of ~1."""
    gamma, eps = 1e-6, 1e-4
    truth = lcs_cvx.random_lcs(10, 4, 10, stiffness=1e-6, seed=10)
    data = lcs_cvx.make_dataset(truth, 200, noise=1e-2, seed=17)
    gen = torch.Generator().manual_seed(10)
    with torch.no_grad():
        for p in truth.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=gen, dtype=F64))
        truth.G.zero_()
        q = truth.lcp_offset(data.x, data.u)
        r = data.x @ truth.A.mT + data.u @ truth.B.mT + truth.d - data.x_next
        values = violation_problem(10).parameter_values(truth.C, truth.F, q, r, gamma, eps)
    with warnings.catch_warnings():
        warnings.simplefilter("error", lcs_cvx.FallbackWarning)
        sol = solve_violation_fast(values)
    assert sol.iterations > 100 and sol.n_fallback == 0
    assert float(sol.residual.max()) <= 1e-13
    with pytest.warns(lcs_cvx.FallbackWarning):
        capped = solve_violation_fast(values, max_iter=100)
    assert capped.n_fallback > 0  # the former limit was too short for these samples


def test_inaccurate_reference_answers_are_reported(monkeypatch):
    """A fallback answer that is not a minimiser (here the reference is replaced by one that
    answers lam = 0) is used, but said: a second FallbackWarning names its KKT residual."""
    values = violation_values(4, "paper", batch=30)
    decl = violation_problem(4)
    monkeypatch.setattr(type(decl), "solve", lambda self, v: np.zeros(tuple(v["b"].shape)))
    with pytest.warns(lcs_cvx.FallbackWarning) as record:
        sol = solve_violation_fast(values, max_iter=0)
    messages = [str(w.message) for w in record]
    assert any("did not converge" in m for m in messages)
    assert any("answers are inaccurate (worst relative KKT residual" in m for m in messages)
    assert sol.n_fallback >= 1 and float(sol.residual.max()) > 1e-6
