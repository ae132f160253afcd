"""Every LCP solver path on every problem of the zoo (``tests/zoo.py``): the fast pivoting in
NumPy arrays and in torch tensors, enumeration of the ``2^n`` free sets, and the Clarabel
reference on the declared problem (P). Assumption 1 makes the solution unique, so all must give
the known answer (or enumeration's): the exact solvers to round-off, the interior-point
reference within its a-posteriori bound, and to 1e-8 on samples with a complementarity margin.
"""

from __future__ import annotations

import warnings

import pytest
import torch
from helpers import rel_dev
from zoo import (
    BUILDERS,
    FAST,
    SOLVERS,
    answer,
    assert_lcp_conditions,
    check_against_reference,
    problem,
)

import lcs_cvx
from lcs_cvx._kernels.arrays import array_ops


# Clarabel itself flags some ill-conditioned solves OPTIMAL_INACCURATE (cvxpy warns); the
# a-posteriori bound is what decides whether its answer is acceptable.
@pytest.mark.filterwarnings("ignore:Solution may be inaccurate:UserWarning")
@pytest.mark.parametrize("name", list(BUILDERS))
@pytest.mark.parametrize("solver", list(SOLVERS))
def test_solver_solves_problem(solver, name):
    p, exact = problem(name), answer(name)
    if solver == "cvxpy":  # the reference: one CVXPY solve per sample, so a few samples
        k = p.n_reference
        ref = SOLVERS[solver](p.F, p.q[:k])
        assert check_against_reference(p.F, p.q[:k], exact[:k], ref.lam, p.smin, p.margin) >= p.min_sharp
        assert float((ref.lam - exact[:k]).abs().max()) <= p.reference_atol
        return
    with warnings.catch_warnings():
        warnings.simplefilter("error", lcs_cvx.FallbackWarning)  # no sample may fall back
        sol = SOLVERS[solver](p.F, p.q)
    err = (sol.lam - exact).abs().amax(-1)
    bound = p.atol + p.rtol * exact.abs().amax(-1)
    assert bool((err <= bound).all()), float((err - bound).max())
    assert_lcp_conditions(p.F, p.q, sol.lam, tol=p.kkt_tol)
    assert sol.n_fallback == 0 and sol.fallback_residual == 0.0
    if solver in FAST:
        assert float(sol.residual.max()) <= p.residual_tol
        assert torch.equal(sol.free, sol.lam > 0)
        assert float((sol.w - (sol.lam @ p.F.mT + p.q)).abs().max()) <= 1e-13 * (1 + float(sol.lam.abs().max()))


@pytest.mark.parametrize("name", list(BUILDERS))
def test_fast_arrays_agree(name):
    """NumPy arrays (CPU) and torch tensors (the CUDA back-end, here on CPU): the same answer to
    round-off of two BLAS libraries, the same free sets, the same number of sweeps (where no
    index is degenerate: there, which of lam_i = w_i = 0 comes out as 1e-17 is round-off)."""
    p = problem(name)
    a, b = (SOLVERS[s](p.F, p.q) for s in FAST)
    assert rel_dev(a.lam, b.lam) <= p.arrays_tol
    if not p.degenerate:
        assert a.iterations == b.iterations
        assert torch.equal(a.free, b.free)


def test_contact_free_needs_no_pivoting():
    """q >= 0: the first guess (free = {q < 0}, empty) is the solution, lam = 0 and w = q."""
    p = problem("contact-free")
    for solver in FAST:
        sol = SOLVERS[solver](p.F, p.q)
        assert sol.iterations == 0
        assert float(sol.lam.abs().max()) == 0.0
        assert torch.equal(sol.w, p.q)


@pytest.mark.parametrize("name", [k for k in BUILDERS if k.startswith(("random-P", "wide-q"))])
def test_random_batches_exercise_the_solver(name):
    """Not vacuous: the random P-matrix batches visit several modes and need pivoting."""
    p = problem(name)
    n = p.F.shape[0]
    sol = SOLVERS["fast-numpy"](p.F, p.q)
    assert torch.unique(sol.lam > 0, dim=0).shape[0] >= min(2**n, 4)
    if n >= 2:
        assert sol.iterations >= 1


def test_known_answers_are_not_trivial():
    """The known-answer problems have contact and no contact, free and bound indices."""
    for name in ("spring-wall", "decoupled-3", "strictly-complementary-3", "degenerate-5"):
        lam = answer(name)
        assert bool((lam > 0).any()) and bool((lam == 0).any()), name
    by_hand = answer("spring-wall")[:5, 0] > 0
    assert by_hand.tolist() == [False, True, True, False, True]


def test_ill_conditioned_problems_have_their_sigma_min():
    for name in BUILDERS:
        if name.startswith(("ill-conditioned", "wide-q")):
            p = problem(name)
            assert float(torch.linalg.eigvalsh(p.F + p.F.mT)[0]) == pytest.approx(p.smin, rel=1e-6)


def test_nearly_skew_F_needs_murty_and_a_shrinking_work_set():
    """Fig. 1(c)'s stiffest truth, F = s I + H - H^T with s = 1e-5 (G = 0): pivoting needs many
    sweeps on some samples (here ~70; up to ~220 on Fig. 1(c)'s 50,000 samples at n = 10, where
    a limit of 100 sent 2,441 of them to a Clarabel that failed): Murty's single pivots, and a
    work set that shrinks to the unconverged samples -- in the torch back-end too (3,000
    samples x 8^2 is above its threshold). The answers are checked by test_solver_solves_problem."""
    p = problem("nearly-skew-8")
    assert array_ops(p.q, "torch").subset_min_work <= p.q.shape[0] * 8 * 8
    for solver in FAST:
        assert SOLVERS[solver](p.F, p.q).iterations > 20
