"""The LCP solvers of :mod:`lcs_cvx.lcp`: ``0 <= lam _|_ F lam + q >= 0`` (eq. (2)).

Three solvers must give the one solution Assumption 1 guarantees: batched block pivoting
(``fast``), enumeration of the 2^n active sets (``brute``) and the declared problem (P) solved
by Clarabel (``cvxpy``, the reference; ~10^3 samples/s, so its batches stay small). Every
solver on every problem of the zoo is ``test_zoo.py``; here: random problems drawn by
hypothesis, the solution's fields, Clarabel's accuracy on ill-conditioned ``F``, the residual,
the fallback to a reference, and the active-set map of Lemma 1 with its derivatives.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import random_p_matrix, random_q, strictly_complementary_lcp
from hypothesis import given, settings
from hypothesis import strategies as st
from zoo import ATOL, assert_lcp_conditions, check_against_reference, degenerate_lcp, max_abs

import lcs_cvx
from lcs_cvx.lcp import (
    active_set_solve,
    check_assumption_1,
    lcp_residual,
    solve_lcp,
    solve_lcp_brute,
    solve_lcp_fast,
)

F64 = torch.float64


# -- agreement of the three solvers ------------------------------------------------------


@settings(max_examples=20, deadline=None, derandomize=True)
@given(
    n=st.integers(1, 8),
    seed=st.integers(0, 2**20),
    smin=st.sampled_from([2.0, 0.5, 1e-1, 1e-2]),
    scale=st.sampled_from([0.1, 1.0, 10.0]),
)
def test_solvers_agree_property(n, seed, smin, scale):
    F = random_p_matrix(n, smin=smin, seed=seed)
    q = random_q(12, n, seed=seed + 1, scale=scale)
    fast = solve_lcp(F, q, method="fast")
    brute = solve_lcp(F, q, method="brute")
    ref = solve_lcp(F, q, method="cvxpy")
    assert max_abs(fast.lam, brute.lam) <= ATOL * max(1.0, scale)  # lam scales with q
    # Clarabel: 1e-8 absolute on samples that are not near-degenerate (margin >= 1e-2 at
    # |q| ~ 1), the a-posteriori bound on all (measured: 1.3e-6 at margin 1e-5, 2e-8 at
    # smin = 1e-2, |q| ~ 0.1 and margin 0.1, where Clarabel's absolute gap tolerance dominates)
    if scale >= 1.0 and smin >= 0.1:
        check_against_reference(F, q, fast.lam, ref.lam, smin)
    else:
        check_against_reference(F, q, fast.lam, ref.lam, smin, margin=float("inf"))
    assert_lcp_conditions(F, q, fast.lam)
    assert float(fast.residual.max()) <= 1e-12


def test_solution_fields_are_consistent():
    F = random_p_matrix(5, smin=1.0, seed=3)
    q = random_q(200, 5, seed=4)
    sol = solve_lcp_fast(F, q)
    assert sol.lam.shape == sol.w.shape == sol.free.shape == (200, 5)
    assert sol.residual.shape == (200,)
    assert sol.free.dtype == torch.bool
    assert max_abs(sol.w, sol.lam @ F.mT + q) <= 1e-13
    # free set = {lam_i > 0}, and the free set reproduces lam through the active-set solve
    assert torch.equal(sol.free, sol.lam > 0)
    assert max_abs(active_set_solve(F, q, sol.free), sol.lam) <= 1e-12
    assert torch.allclose(sol.residual, lcp_residual(F, q, sol.lam), rtol=0, atol=1e-15)
    # on the free set w = 0, off it lam = 0
    assert float(sol.w[sol.free].abs().max()) <= 1e-12
    assert float(sol.lam[~sol.free].abs().max()) == 0.0


# -- degenerate LCPs: lam_i = w_i = 0 ------------------------------------------------------


@settings(max_examples=25, deadline=None, derandomize=True)
@given(n=st.integers(1, 8), seed=st.integers(0, 2**20))
def test_degenerate_property(n, seed):
    F = random_p_matrix(n, smin=0.3, seed=seed)
    q, lam_star = degenerate_lcp(F, 30, seed=seed + 7)
    assert max_abs(solve_lcp_fast(F, q).lam, lam_star) <= 1e-11
    assert max_abs(solve_lcp_brute(F, q).lam, lam_star) <= 1e-11


# -- ill-conditioned F: sigma_min(F + F^T) down to 1e-5 -----------------------------------


@pytest.mark.parametrize("n", [2, 4, 8])
def test_ill_conditioned_against_clarabel_well_scaled(n):
    """sigma_min(F + F^T) = 1e-5 but F well-conditioned (skew part O(1)): |lam| = O(1) and
    Clarabel reaches the full 1e-8 absolute agreement."""
    F = random_p_matrix(n, smin=1e-5, seed=40 + n, skew=1.0)
    q = random_q(15, n, seed=n)
    fast = solve_lcp_fast(F, q)
    ref = solve_lcp(F, q, method="cvxpy")
    assert float(fast.lam.abs().max()) < 100
    assert check_against_reference(F, q, fast.lam, ref.lam, smin=1e-5) >= 10


# Clarabel itself flags some of these solves OPTIMAL_INACCURATE (cvxpy warns); the check below
# is what decides whether its answer is acceptable.
@pytest.mark.filterwarnings("ignore:Solution may be inaccurate:UserWarning")
@pytest.mark.parametrize("n", [2, 4, 8])
def test_ill_conditioned_against_clarabel_large_lam(n):
    """sigma_min(F + F^T) = 1e-5 and F ill-conditioned (cond ~1e5, its weak direction in the
    positive orthant): lam reaches 2e4..3e5. Clarabel's residual (~1e-11..1e-10) then moves
    lam by up to ~1e-5 in absolute terms (measured 1.2e-8 / 1.7e-6 / 1.3e-5 at n = 8 / 4 / 2)
    -- 1e-8 absolute is out of its reach -- so the agreement is checked relative to |lam|
    (measured <= 1.6e-10) and by the a-posteriori bound; the pivoting answer, exact on its
    active set, has the smaller residual."""
    F = random_p_matrix(n, smin=1e-5, seed=30 + n, skew=1e-3, min_dir=np.ones(n))
    q = random_q(15, n, seed=n)
    fast = solve_lcp_fast(F, q)
    ref = solve_lcp(F, q, method="cvxpy")
    assert float(fast.lam.max()) > 1e3
    check_against_reference(F, q, fast.lam, ref.lam, smin=1e-5, margin=float("inf"))
    scale = 1.0 + fast.lam.abs().amax(-1)
    err = (fast.lam - ref.lam).abs().amax(-1)
    assert bool((err <= ATOL * scale).all()), float((err / scale).max())
    # well-scaled samples still agree absolutely
    small = fast.lam.abs().amax(-1) <= 10
    assert bool(small.any())
    assert float(err[small].max()) <= ATOL
    # the round-off floor of w = F lam + q is ~eps |F| |lam|, i.e. ~1e-11 at |lam| ~ 1e5
    assert bool((fast.residual <= 1e-15 * scale).all())
    assert float(fast.residual.max()) <= float(ref.residual.max())


# -- the residual ------------------------------------------------------------------------


def test_lcp_residual_zero_at_solution_positive_elsewhere():
    F = random_p_matrix(6, smin=1.0, seed=5)
    q = random_q(100, 6, seed=6)
    lam = solve_lcp_fast(F, q).lam
    assert float(lcp_residual(F, q, lam).max()) <= 1e-14
    for delta in (1e-2, 0.1, 1.0):
        for sign in (1.0, -1.0):
            bumped = lam.clone()
            bumped[:, 2] += sign * delta
            res = lcp_residual(F, q, bumped)
            # lam_2 + delta leaves min(lam_2, w_2) >= delta * min(1, F_22) > 0 ...
            # lam_2 - delta makes lam_2 < 0 or w_2 < 0 on the free ones
            assert bool((res > 1e-3 * delta).all()), float(res.min())
    # the natural residual also flags a wrong but feasible-looking point: lam = 0 when q has
    # a negative entry
    neg = q.min(-1).values < 0
    assert bool((lcp_residual(F, q, torch.zeros_like(q))[neg] > 0).all())


# -- fallback to the reference ------------------------------------------------------------


@pytest.mark.parametrize("reference, brute_max, resid_tol", [
    ("enumeration of the 2\\^6 free sets", 12, 1e-12),
    ("the Clarabel reference", 0, 1e-8),
])
def test_fallback_warns_and_is_correct(monkeypatch, reference, brute_max, resid_tol):
    """Unconverged samples go to enumeration (n <= BRUTE_MAX, exact) or to Clarabel, polished."""
    monkeypatch.setattr(lcs_cvx.lcp, "BRUTE_MAX", brute_max)
    F = random_p_matrix(6, smin=0.5, seed=3)
    q = random_q(20, 6, seed=0)
    brute = solve_lcp_brute(F, q)
    # the initial guess of the pivoting is free = {q < 0}; samples where it is wrong must pivot
    needs_pivot = (brute.lam > 0) != (q < 0)
    n_need = int(needs_pivot.any(-1).sum())
    assert n_need > 0
    with pytest.warns(lcs_cvx.FallbackWarning, match=f"did not converge.*solved them with {reference}"):
        sol = solve_lcp_fast(F, q, max_iter=0)
    assert sol.n_fallback == n_need
    assert sol.iterations == 0
    assert max_abs(sol.lam, brute.lam) <= ATOL
    assert torch.equal(sol.free, brute.lam > 0)
    assert float(sol.residual.max()) <= resid_tol
    check_against_reference(F, q, brute.lam, sol.lam, smin=0.5)
    assert max_abs(sol.w, sol.lam @ F.mT + q) <= 1e-13  # w follows the reference's lam
    # the worst residual of the samples the reference solved, also without the full residual
    assert sol.fallback_residual == pytest.approx(float(sol.residual[needs_pivot.any(-1)].max()), rel=1e-12)
    with pytest.warns(lcs_cvx.FallbackWarning):
        lean = solve_lcp_fast(F, q, max_iter=0, residual=False)
    assert lean.residual is None and lean.fallback_residual == sol.fallback_residual


def test_fallback_disabled_raises():
    F = random_p_matrix(6, smin=0.5, seed=3)
    q = random_q(20, 6, seed=0)
    with pytest.raises(lcs_cvx.SolverError, match=r"did not converge on \d+ of 20 samples"):
        solve_lcp_fast(F, q, max_iter=0, fallback=False)
    # with enough sweeps the same batch needs neither
    sol = solve_lcp_fast(F, q, fallback=False)
    assert sol.n_fallback == 0


# -- the active-set map (Lemma 1) and its gradient ----------------------------------------


@pytest.mark.parametrize("n", [1, 3, 6])
def test_active_set_solve_gradcheck(n):
    F = random_p_matrix(n, smin=1.0, seed=60 + n)
    q, lam_star = strictly_complementary_lcp(F, 6, seed=n)
    sol = solve_lcp_fast(F, q)
    assert max_abs(sol.lam, lam_star) <= 1e-12
    free = sol.free
    assert torch.equal(free, lam_star > 0)
    Fg = F.clone().requires_grad_(True)
    qg = q.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda F_, q_: active_set_solve(F_, q_, free), (Fg, qg))
    # batched F (B, n, n) as well
    Fb = F.expand(q.shape[0], n, n).clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda F_, q_: active_set_solve(F_, q_, free), (Fb, qg))


@pytest.mark.parametrize("n", [2, 5])
def test_lcp_solution_map_gradient_matches_finite_differences(n):
    """Differentiating the active-set map at the solver's free set gives the derivative of the
    true solution map: the numerical Jacobian re-solves the LCP at every perturbed point."""
    F = random_p_matrix(n, smin=1.0, seed=70 + n)
    q, _ = strictly_complementary_lcp(F, 4, seed=n)

    def lam_of(F_, q_):
        free = solve_lcp_fast(F_, q_).free  # no grad: recomputed at each perturbed point
        return active_set_solve(F_, q_, free)

    Fg = F.clone().requires_grad_(True)
    qg = q.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lam_of, (Fg, qg), eps=1e-6, atol=1e-6)


def test_active_set_solve_closed_form_jacobian():
    """d lam_I / d q_I = -F_II^{-1}, d lam_J / d q = 0."""
    n = 4
    F = random_p_matrix(n, smin=1.0, seed=9)
    q, lam_star = strictly_complementary_lcp(F, 1, seed=2)
    free = lam_star > 0
    idx = free[0].nonzero().squeeze(1)
    assert 0 < idx.numel() < n or n == 1
    J = torch.autograd.functional.jacobian(lambda q_: active_set_solve(F, q_, free), q)[0, :, 0, :]
    expected = torch.zeros(n, n, dtype=F64)
    expected[idx[:, None], idx[None, :]] = -torch.linalg.inv(F[idx][:, idx])
    assert torch.allclose(J, expected, atol=1e-12)


# -- Assumption 1 at the boundary -------------------------------------------------------------


NOT_ASSUMPTION_1 = [
    (np.array([[1.0, 0.0], [0.0, -0.5]]), "-1"),
    (np.array([[0.0, 1.0], [-1.0, 0.0]]), "0"),  # skew: F + F^T = 0
    (np.array([[1.0, 3.0], [0.0, 1.0]]), "-1"),  # a P-matrix (positive minors), F + F^T indefinite
    (np.array([[1.0, 0.0], [0.0, 0.0]]), "0"),
]


@pytest.mark.parametrize("method", ["fast", "brute", "cvxpy"])
@pytest.mark.parametrize("F, smin", NOT_ASSUMPTION_1)
def test_solve_lcp_refuses_F_without_assumption_1(F, smin, method):
    """A user's ``F`` whose symmetric part is not positive definite is refused before any solve
    (pivoting could cycle to its sweep limit and a fallback return the best candidate of an LCP
    without a solution), naming ``F``, Assumption 1 and the smallest eigenvalue received."""
    q = np.array([[-1.0, -1.0], [1.0, -2.0]])
    with pytest.raises(lcs_cvx.LCSInputError, match=(
            r"^F: expected F \+ F\^T positive definite \(Assumption 1\), received smallest "
            rf"eigenvalue sigma_min\(F \+ F\^T\) = {smin}$")):
        solve_lcp(F, q, method=method)
    with pytest.raises(lcs_cvx.LCSInputError, match=r"^F: expected F \+ F\^T positive definite"):
        solve_lcp(torch.as_tensor(F, dtype=torch.float32), q, method=method)  # any dtype


def test_solve_lcp_without_a_solution_is_refused_not_answered():
    """``F = [[-1, 0], [0, 1]]``, ``q = (-1, 1)``: ``w_1 = -lam_1 - 1 < 0`` for every ``lam_1 >= 0``,
    so the LCP has no solution; the check stops it instead of a fallback's best candidate."""
    F = torch.tensor([[-1.0, 0.0], [0.0, 1.0]], dtype=F64)
    q = torch.tensor([[-1.0, 1.0]], dtype=F64)
    with pytest.raises(lcs_cvx.LCSInputError, match=r"received smallest eigenvalue sigma_min\(F \+ F\^T\) = -2$"):
        solve_lcp(F, q)


def test_assumption_1_check_is_batched_and_names_the_matrix():
    good = random_p_matrix(3, smin=1e-6, seed=1)
    check_assumption_1(good)  # small but positive: accepted
    check_assumption_1(torch.stack([good, good.mT]))
    bad = good - 1e-3 * torch.eye(3, dtype=F64)  # sigma_min(F + F^T) = 1e-6 - 2e-3
    with pytest.raises(lcs_cvx.LCSInputError, match=r"= -0\.001999 \(matrix 1 of the batch\)$"):
        check_assumption_1(torch.stack([good, bad, good]))
    with pytest.raises(lcs_cvx.LCSInputError, match=r"^F: expected F \+ F\^T positive definite"):
        check_assumption_1(torch.full((2, 2), float("nan"), dtype=F64))


def test_model_solve_lcp_skips_the_eigenvalue_check(monkeypatch):
    """An :class:`lcs_cvx.LCS` builds ``F = G G^T + H - H^T + s I`` (Assumption 1 by construction):
    its ``solve_lcp`` (and so ``step`` and the losses) computes no eigenvalues; the public
    ``solve_lcp`` on the same ``F`` does."""
    model = lcs_cvx.random_lcs(3, 1, 3, seed=2)
    x, u = torch.randn(5, 3, dtype=F64), torch.randn(5, 1, dtype=F64)
    expected = model.solve_lcp(x, u).lam

    def forbidden(F):
        raise AssertionError("eigenvalues computed")

    monkeypatch.setattr(lcs_cvx.lcp, "sym_min_eig", forbidden)
    assert torch.equal(model.solve_lcp(x, u).lam, expected)
    model.step(x, u)
    with pytest.raises(AssertionError, match="eigenvalues computed"):
        solve_lcp(model.F.detach(), model.lcp_offset(x, u).detach())
