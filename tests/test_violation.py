"""The fast solver of the violation problem (V), eq. (9b) (:mod:`lcs_cvx.violation`).

Its answer is certified exact against a high-precision refinement of the paper's (lam, phi) QP,
independent of the library's DPP form, in the paper's and in a stiff setting; the two array
back-ends (NumPy on CPU, torch as on CUDA) give the same answer, active sets and sweeps; the
Clarabel reference on the same declaration agrees to its accuracy; unconverged samples fall back
to enumeration of (V)'s pieces (exact) or, above ``BRUTE_MAX``, to that reference, said (a
warning, or an error) and measured (``fallback_residual``).
"""

from __future__ import annotations

import warnings

import pytest
import torch
from helpers import (
    CASES,
    N_LAMS,
    SETTINGS,
    certified_violation_solution,
    make_problem,
    rel_dev,
    violation_case,
    violation_values,
)

import lcs_cvx
from lcs_cvx.problems import violation_problem
from lcs_cvx.violation import solve_violation_brute, solve_violation_fast, violation_kkt_residual

F64 = torch.float64
KERNELS = ("numpy", "torch")

#: Agreement of the two back-ends, relative to ``1 + |lam|_inf``: round-off of two BLAS
#: libraries (NumPy's OpenBLAS, torch's MKL). Measured <= 1.0e-14 in both settings.
BACKEND_AGREEMENT = 1e-12


def _dev(a, b, lam):
    """Per-sample ``|a - b|_inf`` relative to ``1 + |lam|_inf``, worst sample."""
    return float(((a - b).abs().amax(-1) / (1.0 + lam.abs().amax(-1))).max())


@pytest.mark.parametrize("n_lam, setting", CASES)
def test_fast_violation_solution_is_certified_exact(n_lam, setting):
    """The fast kernel's (lam, phi) is the exact minimiser to round-off in every setting,
    the stiff one included. Measured: <= 1e-14 relative to 1 + |lam|_inf; KKT <= 8e-16."""
    model, data, gamma, eps, values, info = violation_case(n_lam, setting)
    lam_x, phi_x, certified = certified_violation_solution(model, data, info.lam, info.phi, gamma, eps)
    assert bool(certified.all())
    assert _dev(info.lam, lam_x, info.lam) <= 1e-12
    assert _dev(info.phi, phi_x, info.lam) <= 1e-12
    assert float(violation_kkt_residual(values, info.lam).max()) <= 1e-13
    assert info.n_fallback == 0


def test_certificate_rejects_a_wrong_point():
    """The certificate is not vacuous: a wrong support fails it, and a point off by ``delta``
    on the right support is refined back (the measured distance is ``delta``)."""
    model, data = make_problem(n=8)
    gamma, eps = 1e-2, 1e-3
    info = lcs_cvx.violation_loss_info(model, data.x, data.u, data.x_next, gamma=gamma, eps=eps)
    lam, phi, ok = certified_violation_solution(model, data, info.lam, info.phi, gamma, eps)
    assert bool(ok.all())
    k, i = (int(v) for v in (info.lam > 0).nonzero()[0])
    wrong = info.lam.clone()
    wrong[k, i] = 0.0  # drop an active lam from the support
    _, _, ok_wrong = certified_violation_solution(model, data, wrong, info.phi, gamma, eps)
    assert not bool(ok_wrong[k]) and bool(ok_wrong[torch.arange(8) != k].all())
    nudged = info.lam.clone()
    nudged[k, i] += 1e-6
    lam_n, _, ok_n = certified_violation_solution(model, data, nudged, info.phi, gamma, eps)
    assert bool(ok_n.all())
    assert float((lam_n - lam).abs().max()) <= 1e-13
    assert float((nudged - lam_n).abs().max()) == pytest.approx(1e-6, rel=1e-6)


@pytest.mark.parametrize("n_lam, setting", CASES)
def test_clarabel_reference_agrees_with_fast(n_lam, setting):
    """The independent Clarabel reference (cvxpy, QP form, tolerances 1e-10) on the same
    declaration. Measured relative: paper <= 1.3e-9; stiff <= 2.3e-7 (n = 10)."""
    model, data, gamma, eps, values, info = violation_case(n_lam, setting)
    lam_ref = violation_problem(n_lam).solve(values)
    assert lam_ref.dtype == F64 and lam_ref.shape == info.lam.shape
    dev = _dev(lam_ref, info.lam, info.lam)
    assert dev <= (1e-8 if setting == "paper" else 1e-6), dev
    kkt_fast = float(violation_kkt_residual(values, info.lam).max())
    assert kkt_fast <= float(violation_kkt_residual(values, lam_ref).max()) + 1e-15


@pytest.mark.parametrize("setting", list(SETTINGS))
@pytest.mark.parametrize("n_lam", N_LAMS)
def test_violation_kernel_backends_agree(n_lam, setting):
    """Same (V) solution to round-off, same active sets, same sweeps; both KKT-exact."""
    values = violation_values(n_lam, setting)
    sol = {k: solve_violation_fast(values, arrays=k) for k in KERNELS}
    a, b = sol["numpy"], sol["torch"]
    assert a.iterations == b.iterations
    assert a.n_fallback == b.n_fallback == 0
    assert rel_dev(a.lam, b.lam) <= BACKEND_AGREEMENT
    assert torch.equal(a.free, b.free) and torch.equal(a.pos, b.pos)
    assert torch.equal(a.active, torch.cat([a.free, a.pos], dim=1))
    for s in (a, b):
        assert s.lam.dtype == F64 and s.lam.device.type == "cpu"
        assert float(s.residual.max()) <= 1e-13
        assert s.fallback_residual == 0.0
    # not vacuous: the batch pivots, and both kinds of index are present
    assert a.iterations >= (1 if n_lam > 1 else 0)
    assert bool(a.free.any()) and bool((~a.free).any())


@pytest.mark.parametrize("kernel", KERNELS)
def test_fallback_and_warm_start_on_each_backend(kernel):
    values = violation_values(4, "paper", batch=60)
    cold = solve_violation_fast(values, arrays=kernel)
    assert cold.iterations >= 1
    warm = solve_violation_fast(values, arrays=kernel, warm_start=cold.active)
    assert warm.iterations == 0 and torch.equal(warm.lam, cold.lam)
    with pytest.warns(lcs_cvx.FallbackWarning, match="violation QP pivoting did not converge"):
        fb = solve_violation_fast(values, arrays=kernel, max_iter=0)
    assert fb.n_fallback >= 1
    assert rel_dev(fb.lam, cold.lam) <= 1e-12  # n = 4: enumeration of the pieces, exact
    assert torch.equal(fb.free, fb.lam > 0)
    # the reference's worst KKT residual is reported, with or without the full residual
    assert 0.0 < fb.fallback_residual <= float(fb.residual.max())
    with pytest.warns(lcs_cvx.FallbackWarning):
        lean = solve_violation_fast(values, arrays=kernel, max_iter=0, residual=False)
    assert lean.residual is None and lean.fallback_residual == fb.fallback_residual
    with pytest.raises(lcs_cvx.SolverError, match=r"did not converge on \d+ of 60 samples"):
        solve_violation_fast(values, arrays=kernel, max_iter=0, fallback=False)


def _nearly_skew_values(n: int, batch: int) -> dict[str, torch.Tensor]:
    """(V)'s parameter values for a perturbed ``random_lcs(n, 4, n, stiffness=1e-6)`` with
    ``G = 0`` (``F`` nearly skew-symmetric), ``gamma = 1e-6``, ``eps = 1e-4``."""
    truth = lcs_cvx.random_lcs(n, 4, n, stiffness=1e-6, seed=10)
    data = lcs_cvx.make_dataset(truth, batch, noise=1e-2, seed=17)
    gen = torch.Generator().manual_seed(10)
    with torch.no_grad():
        for p in truth.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=gen, dtype=F64))
        truth.G.zero_()
        q = truth.lcp_offset(data.x, data.u)
        r = data.x @ truth.A.mT + data.u @ truth.B.mT + truth.d - data.x_next
        return violation_problem(n).parameter_values(truth.C, truth.F, q, r, 1e-6, 1e-4)


def test_violation_pivoting_outlasts_clarabel_on_nearly_skew_F():
    """Nearly skew-symmetric ``F`` (``G = 0``, ``s = gamma = 1e-6``, 1 / (eps gamma) = 1e10):
    pivoting needs hundreds of sweeps (Murty's rule) and ends exact, where a 100-sweep limit
    hands 88 of 200 samples to Clarabel, whose answers have a KKT residual of ~1."""
    values = _nearly_skew_values(10, 200)
    with warnings.catch_warnings():
        warnings.simplefilter("error", lcs_cvx.FallbackWarning)
        sol = solve_violation_fast(values)
    assert sol.iterations > 100 and sol.n_fallback == 0
    assert float(sol.residual.max()) <= 1e-13
    with pytest.warns(lcs_cvx.FallbackWarning):
        capped = solve_violation_fast(values, max_iter=100)
    assert capped.n_fallback > 0  # a 100-sweep limit is too short for these samples
    assert capped.fallback_residual > 1e-6  # ... and the reference's answers are far off


def test_inaccurate_reference_answers_are_reported(monkeypatch):
    """A fallback answer that is not a minimiser (here the reference is replaced by one that
    answers lam = 0) is used, but said: a second FallbackWarning names its KKT residual."""
    values = violation_values(4, "paper", batch=30)
    monkeypatch.setattr(lcs_cvx.violation, "BRUTE_MAX", 0)  # n = 4 falls back to Clarabel
    decl = violation_problem(4)
    monkeypatch.setattr(type(decl), "solve", lambda self, v: torch.zeros(tuple(v["b"].shape), dtype=F64))
    with pytest.warns(lcs_cvx.FallbackWarning) as record:
        sol = solve_violation_fast(values, max_iter=0)
    messages = [str(w.message) for w in record]
    assert any("did not converge" in m for m in messages)
    assert any("answers are inaccurate (worst relative KKT residual" in m for m in messages)
    assert sol.n_fallback >= 1 and float(sol.residual.max()) > 1e-6
    assert sol.fallback_residual == pytest.approx(float(sol.residual.max()), rel=1e-12)


# -- the exact fallback: enumeration of (V)'s pieces -----------------------------------------


@pytest.mark.parametrize("setting", list(SETTINGS))
@pytest.mark.parametrize("n_lam", [1, 2, 4, 6])
def test_enumeration_of_the_pieces_is_the_fast_kernels_answer(n_lam, setting):
    """``solve_violation_brute``: one quadratic per piece (free set, ``K lam - h > 0`` set), the
    candidate of smallest KKT residual kept -- the minimiser, as the pivoting's, to round-off.
    Measured: <= 1e-14 relative to 1 + |lam|_inf; KKT <= 7e-16."""
    values = violation_values(n_lam, setting)
    fast = solve_violation_fast(values)
    brute = solve_violation_brute(values)
    assert fast.n_fallback == 0 and brute.iterations == 0
    assert _dev(brute.lam, fast.lam, fast.lam) <= 1e-12
    assert torch.equal(brute.active, fast.active)
    assert float(brute.residual.max()) <= 1e-13
    assert float(violation_kkt_residual(values, brute.lam).max()) <= 1e-13


@pytest.mark.parametrize("kernel", KERNELS)
def test_fallback_is_exact_up_to_brute_max(kernel, monkeypatch):
    """With no sweeps allowed, every sample whose first guess is wrong falls back: for
    ``n <= BRUTE_MAX`` to the enumeration (said in the warning), whose answers are the pivoting's
    to round-off; above it (``BRUTE_MAX`` lowered) to Clarabel, accurate only to ~1e-9."""
    values = violation_values(6, "paper", batch=60)
    exact = solve_violation_fast(values, arrays=kernel)
    with pytest.warns(lcs_cvx.FallbackWarning, match=r"solved them with enumeration of the 4\^6 pieces"):
        fb = solve_violation_fast(values, arrays=kernel, max_iter=0)
    assert fb.n_fallback >= 1 and fb.iterations == 0
    assert _dev(fb.lam, exact.lam, exact.lam) <= 1e-10
    assert fb.fallback_residual <= 1e-10 and float(fb.residual.max()) <= 1e-10
    assert torch.equal(fb.active, exact.active)
    monkeypatch.setattr(lcs_cvx.violation, "BRUTE_MAX", 5)
    with pytest.warns(lcs_cvx.FallbackWarning, match="solved them with the Clarabel reference"):
        ref = solve_violation_fast(values, arrays=kernel, max_iter=0)
    assert ref.n_fallback == fb.n_fallback
    assert ref.fallback_residual > fb.fallback_residual  # an interior point, not round-off exact


def test_exact_fallback_where_clarabel_is_far_off():
    """Nearly skew-symmetric ``F`` (``G = 0``, ``s = gamma = 1e-6``) at ``n = 6``: capped
    pivoting hands samples to the enumeration, whose answers are KKT-exact (measured 5e-16)
    where Clarabel's are not (measured KKT residual ~1e2)."""
    n = 6
    values = _nearly_skew_values(n, 60)
    with warnings.catch_warnings():
        warnings.simplefilter("error", lcs_cvx.FallbackWarning)
        full = solve_violation_fast(values)
    assert full.iterations > 20 and float(full.residual.max()) <= 1e-13
    with pytest.warns(lcs_cvx.FallbackWarning, match="enumeration") as record:
        capped = solve_violation_fast(values, max_iter=20)
    assert capped.n_fallback > 0
    assert not any("inaccurate" in str(w.message) for w in record)
    assert capped.fallback_residual <= 1e-13 and float(capped.residual.max()) <= 1e-13
    clarabel = violation_problem(n).solve(values)
    assert float(violation_kkt_residual(values, clarabel).max()) > 1e-3  # the reference's


def test_enumeration_refuses_large_n():
    values = violation_values(10, "paper", batch=2)
    with pytest.raises(lcs_cvx.LCSInputError, match=r"^n_lam: enumeration of \(V\)'s 4\^n pieces, expected n <= 8, received 10$"):
        solve_violation_brute(values)


@pytest.mark.parametrize("arrays", ["numpy", "torch"])
def test_cold_guess_is_one_projected_jacobi_step(arrays):
    """Without a warm start, pivoting starts from one projected Jacobi step on ``-K lam + h``:
    worked by hand on ``-K = [[2, 1], [-3, 1]]``, and ``h < 0`` (the guess of ``lam = 0``) where
    ``-K_ii <= 0``."""
    from lcs_cvx._kernels.arrays import array_ops
    from lcs_cvx._kernels.violation import cold_guess

    K = -torch.tensor([[2.0, 1.0], [-3.0, 1.0]], dtype=torch.float64)
    h = torch.tensor([[-2.0, 1.0], [1.0, -1.0]], dtype=torch.float64)
    # row 0: lam0 = [1, 0], w = h - K lam0 = [0, -2], guess = [2 - 0 > 0, 0 + 2 > 0]
    # row 1: lam0 = [0, 1], w = [2, 0], guess = [0 - 2 > 0, 1 - 0 > 0]
    xp = array_ops(h, arrays)
    guess = xp.unwrap(cold_guess(xp, xp.wrap(K), xp.wrap(h)))
    assert guess.tolist() == [[True, True, True, True], [False, True, False, True]]
    K[1, 1] = 1.0  # -K_11 < 0: lam0_1 = 0 and guess_1 = h_1 < 0
    guess = xp.unwrap(cold_guess(xp, xp.wrap(K), xp.wrap(h)))
    assert guess.tolist() == [[True, False, True, False], [False, True, False, True]]
