"""The two CVXPY declarations of :mod:`lcs_cvx.problems`: (P), eq. (5), and (V),
eq. (9b), in its DPP form: phi eliminated, the whole objective times ``eps``,
constants dropped.

(V) with ``C = 0`` and ``r = 0`` is Lemma 2's QP ``min_{lam, phi >= 0} lam^T phi +
|F lam + q - phi|^2 / (2 gamma)``, whose minimiser is the LCP solution for every
``0 < gamma < sigma_min(F + F^T)``.
"""

from __future__ import annotations

import cvxpy as cp
import numpy as np
import pytest
import torch
from conftest import random_p_matrix, random_q

import lcs_cvx
from lcs_cvx._kernels import violation as kernel_violation
from lcs_cvx._kernels.arrays import array_ops
from lcs_cvx.lcp import solve_lcp_fast
from lcs_cvx.problems import (
    ConvexLCPProblem,
    ViolationProblem,
    convex_lcp_problem,
    sym_min_eig,
    violation_problem,
)

F64 = torch.float64


def randn(*shape, seed=0):
    return torch.tensor(np.random.default_rng(seed).standard_normal(shape), dtype=F64)


# -- the declarations ---------------------------------------------------------------------


@pytest.mark.parametrize(
    "factory, cls, params, shapes",
    [
        (convex_lcp_problem, ConvexLCPProblem, ["R", "F", "q"], ["nn", "nn", "n"]),
        (violation_problem, ViolationProblem, ["L", "b", "K", "h"], ["nn", "n", "nn", "n"]),
    ],
)
@pytest.mark.parametrize("n", [1, 3, 8])
def test_declaration_is_dpp_cached_and_named(factory, cls, params, shapes, n):
    decl = factory(n)
    assert isinstance(decl, cls)
    assert decl.n_lam == n
    assert decl.problem.is_dpp()
    assert decl.problem.is_dcp()
    # cached: one declaration per dimension
    assert factory(n) is decl
    assert factory(n + 1) is not decl
    assert factory(n + 1).n_lam == n + 1
    # parameters and variables by their documented names, and they are the problem's own
    assert list(decl.parameters) == params
    assert decl.parameter_order == params
    for name, kind in zip(params, shapes, strict=True):
        p = decl.parameters[name]
        assert isinstance(p, cp.Parameter)
        assert p.name() == name
        assert p.shape == ((n, n) if kind == "nn" else (n,))
    assert {id(p) for p in decl.problem.parameters()} == {id(p) for p in decl.parameters.values()}
    assert list(decl.variables) == ["lam"]
    lam = decl.variables["lam"]
    assert lam.shape == (n,) and lam.name() == "lam"
    assert [id(v) for v in decl.problem.variables()] == [id(lam)]


def test_declaration_rejects_bad_dimension():
    with pytest.raises(lcs_cvx.LCSInputError, match=r"n_lam: expected an integer >= 1, received 0"):
        convex_lcp_problem(0)
    with pytest.raises(lcs_cvx.LCSInputError, match=r"n_lam: expected an integer >= 1, received 2\.5"):
        violation_problem(2.5)


# -- (P) ----------------------------------------------------------------------------------


def test_convex_lcp_parameter_values_and_solve():
    n = 4
    F = random_p_matrix(n, smin=0.5, seed=1)
    q = random_q(6, n, seed=2)
    decl = convex_lcp_problem(n)
    vals = decl.parameter_values(F, q)
    R = vals["R"]
    assert torch.allclose(R.mT @ R, F + F.mT, atol=1e-13)
    assert torch.equal(torch.triu(R), R)  # upper triangular
    assert vals["F"] is F and vals["q"] is q
    lam = decl.solve(F, q)
    assert lam.dtype == F64 and lam.shape == q.shape
    exact = solve_lcp_fast(F, q).lam
    assert float((lam - exact).abs().max()) <= 1e-7
    # the optimal value of (P) is 0 at the LCP solution (lam^T (F lam + q) = 0)
    decl.parameters["q"].value = q[-1].numpy()
    assert abs(decl.problem.value - 0.0) <= 1e-8


@pytest.mark.filterwarnings("ignore:Solution may be inaccurate:UserWarning")
def test_reference_solve_does_not_depend_on_earlier_solves():
    """Regression: under CVXPY's default warm start the cached Clarabel solver was updated in
    place and kept the equilibration of the first problem it had seen, so the reference answer
    on an ill-conditioned (P) depended on what had been solved before (measured: |lam - lam*|
    from 2e-6 to 3e-4 depending on the earlier problem, and one sample failing outright after
    the demo's problem). Each reference solve now starts a fresh solver."""
    n = 2
    F_ill = random_p_matrix(n, smin=1e-5, seed=5, skew=1e-3, min_dir=np.ones(n))
    q_ill = random_q(15, n, seed=2)
    exact = solve_lcp_fast(F_ill, q_ill).lam
    assert float(exact.max()) > 1e3
    cached = convex_lcp_problem(n)
    other = lcs_cvx.random_lcs(4, 2, n, stiffness=0.5, seed=1)
    ds = lcs_cvx.make_dataset(other, 5, seed=1)
    cached.solve(other.F, other.lcp_offset(ds.x, ds.u))  # something else first
    after_other = cached.solve(F_ill, q_ill)
    fresh = convex_lcp_problem.__wrapped__(n).solve(F_ill, q_ill)  # a brand-new declaration
    assert torch.equal(after_other, fresh)
    assert float((fresh - exact).abs().max()) <= 1e-8 * (1 + float(exact.max()))


def test_convex_lcp_parameter_values_reject_non_p_matrix():
    F = torch.tensor([[1.0, 0.0], [0.0, -0.5]], dtype=F64)
    with pytest.raises(lcs_cvx.LCSInputError, match=r"F \+ F\^T: expected a positive definite"):
        convex_lcp_problem(2).parameter_values(F, torch.zeros(1, 2, dtype=F64))


# -- (V): Lemma 2 -------------------------------------------------------------------------


@pytest.mark.parametrize("n", [1, 3, 6])
@pytest.mark.parametrize("eps", [1.0, 1e-4])
def test_violation_problem_with_c_zero_solves_the_lcp(n, eps):
    """Lemma 2: with C = 0 and r = 0, (V) is the LCP's QP for every 0 < gamma < sigma_min."""
    F = random_p_matrix(n, smin=0.4, seed=10 + n)
    smin = float(sym_min_eig(F))
    assert smin == pytest.approx(0.4)
    q = random_q(8, n, seed=n, scale=2.0)
    exact = solve_lcp_fast(F, q).lam
    assert bool((exact > 0).any()) and bool((exact == 0).any())
    decl = violation_problem(n)
    C = torch.zeros(3, n, dtype=F64)
    r = torch.zeros(8, 3, dtype=F64)
    for frac in (1e-3, 0.3, 0.9):
        vals = decl.parameter_values(C, F, q, r, frac * smin, eps)
        lam = torch.as_tensor(decl.solve(vals))
        err = (lam - exact).abs().amax(-1) / (1.0 + exact.abs().amax(-1))
        assert float(err.max()) <= 1e-6, (frac, float(err.max()))
        assert bool((lam >= 0).all())


@pytest.mark.parametrize("factor", [1.0 + 1e-9, 1.5, 10.0])
def test_violation_parameter_values_reject_gamma_above_sigma_min(factor):
    F = random_p_matrix(3, smin=0.2, seed=0)
    q = random_q(2, 3)
    C, r = randn(2, 3), randn(2, 2)
    with pytest.raises(lcs_cvx.LCSInputError, match=r"gamma: expected 0 < gamma < sigma_min\(F \+ F\^T\) = 0\.2"):
        violation_problem(3).parameter_values(C, F, q, r, factor * 0.2, 1e-2)


@pytest.mark.parametrize("gamma", [0.0, -0.1, float("nan")])
def test_violation_parameter_values_reject_nonpositive_gamma(gamma):
    F = random_p_matrix(3, smin=1.0, seed=0)
    with pytest.raises(lcs_cvx.LCSInputError, match=r"gamma: expected a finite number > 0"):
        violation_problem(3).parameter_values(randn(2, 3), F, random_q(2, 3), randn(2, 2), gamma, 1e-2)


def test_violation_parameter_values_complete_the_square():
    """L^T L = eps C^T C + F + F^T - gamma I, L^T b = eps C^T r + q, K = (gamma I - F)/sqrt(gamma),
    h = q/sqrt(gamma): the module docstring's completed square of eps * (V)."""
    n, n_x, B, gamma, eps = 4, 3, 5, 0.1, 1e-2
    F = random_p_matrix(n, smin=0.5, seed=3)
    C, q, r = randn(n_x, n, seed=1), randn(B, n, seed=2), randn(B, n_x, seed=3)
    v = violation_problem(n).parameter_values(C, F, q, r, gamma, eps)
    I = torch.eye(n, dtype=F64)
    L = v["L"]
    assert torch.equal(torch.triu(L), L)
    assert torch.allclose(L.mT @ L, eps * C.mT @ C + F + F.mT - gamma * I, rtol=1e-12, atol=1e-12)
    assert torch.allclose(v["b"] @ L, eps * r @ C + q, rtol=1e-12, atol=1e-12)
    s = gamma**-0.5
    assert torch.allclose(v["K"], (gamma * I - F) * s, rtol=1e-14, atol=0)
    assert torch.allclose(v["h"], q * s, rtol=1e-14, atol=0)
    # differentiable in every input
    leaves = [t.clone().requires_grad_(True) for t in (C, F, q, r)]
    out = violation_problem(n).parameter_values(*leaves, gamma, eps)
    sum(t.sum() for t in out.values()).backward()
    assert all(t.grad is not None and bool(torch.isfinite(t.grad).all()) for t in leaves)
    assert all(float(t.grad.abs().max()) > 0 for t in leaves)


def test_violation_normal_equations_are_the_kernels_and_what_parameter_values_factor():
    """The kernel's form ``{LtL, Ltb, K, h}`` is what the parameter values factor: ``L^T L =
    LtL`` and ``L^T b = Ltb`` for ``factor(normal_equations(...))``, and ``parameter_values`` is
    that factorisation. The formula is the kernel's (``lcs_cvx._kernels.violation``): the
    declaration evaluates it on tensors, the fast loss in NumPy arrays -- the same numbers."""
    n, n_x, B, gamma, eps = 4, 3, 5, 0.1, 1e-2
    F = random_p_matrix(n, smin=0.5, seed=3)
    C, q, r = randn(n_x, n, seed=1), randn(B, n, seed=2), randn(B, n_x, seed=3)
    decl = violation_problem(n)
    normal = decl.normal_equations(C, F, q, r, gamma, eps)
    I = torch.eye(n, dtype=F64)
    assert torch.allclose(normal["LtL"], eps * C.mT @ C + F + F.mT - gamma * I, rtol=1e-14, atol=1e-14)
    assert torch.allclose(normal["Ltb"], eps * r @ C + q, rtol=1e-14, atol=1e-14)
    v = decl.factor(normal)
    assert torch.allclose(v["L"].mT @ v["L"], normal["LtL"], rtol=1e-12, atol=1e-12)
    assert torch.allclose(v["b"] @ v["L"], normal["Ltb"], rtol=1e-12, atol=1e-12)
    values = decl.parameter_values(C, F, q, r, gamma, eps)
    for k in ("L", "b", "K", "h"):
        assert torch.equal(values[k], v[k]), k
    # the fast loss's arrays: the kernel's formula in NumPy, factored, gives the same values
    xp = array_ops(F, "numpy")
    normal_np = kernel_violation.normal_equations(xp, *(t.numpy() for t in (C, F, q, r)), gamma, eps)
    for k in ("LtL", "Ltb", "K", "h"):
        assert isinstance(normal_np[k], np.ndarray)
        assert np.allclose(normal_np[k], normal[k].numpy(), rtol=1e-14, atol=1e-14), k
    v_np = decl.factor({k: torch.from_numpy(a) for k, a in normal_np.items()})
    for k in ("L", "b", "K", "h"):
        assert torch.allclose(v_np[k], v[k], rtol=1e-13, atol=1e-13), k
    with pytest.raises(lcs_cvx.LCSInputError, match=r"gamma: expected 0 < gamma < sigma_min"):
        decl.normal_equations(C, F, q, r, 10.0, eps)


# -- (V): the (lam, phi) objective against the declared problem ----------------------------


def _cvxpy_objective(decl, vals, i, lam_i):
    """Value of the declared (V) for sample ``i`` at ``lam = lam_i``."""
    decl.parameters["L"].value = vals["L"].detach().numpy()
    decl.parameters["K"].value = vals["K"].detach().numpy()
    decl.parameters["b"].value = vals["b"][i].detach().numpy()
    decl.parameters["h"].value = vals["h"][i].detach().numpy()
    decl.variables["lam"].value = lam_i.numpy()
    return float(decl.problem.objective.value)


@pytest.mark.parametrize("n", [1, 3, 5])
def test_violation_objective_matches_declared_problem(n):
    n_x, B, gamma, eps = 4, 6, 0.05, 1e-2
    F = random_p_matrix(n, smin=0.3, seed=20 + n)
    C, q, r = randn(n_x, n, seed=n), randn(B, n, seed=n + 1), randn(B, n_x, seed=n + 2)
    decl = violation_problem(n)
    vals = decl.parameter_values(C, F, q, r, gamma, eps)
    g = np.random.default_rng(n)
    # points on both sides of the kink of pos(.): lam = 0, lam large, random
    lams = [
        torch.zeros(B, n, dtype=F64),
        torch.tensor(g.random((B, n)), dtype=F64),
        torch.tensor(5 * g.random((B, n)), dtype=F64),
        solve_lcp_fast(F, q).lam,
    ]
    torch_vals, cvx_vals = [], []
    for lam in lams:
        phi = ViolationProblem.phi(lam, F, q, gamma)
        torch_vals.append(ViolationProblem.objective(lam, phi, C, F, q, r, gamma, eps))
        cvx_vals.append(
            torch.tensor([_cvxpy_objective(decl, vals, i, lam[i]) for i in range(B)], dtype=F64)
        )
    # the declared problem is eps * (V) with the constant eps/2 |r|^2 - 1/2 |b|^2 dropped
    const = 0.5 * eps * (r * r).sum(-1) - 0.5 * (vals["b"] * vals["b"]).sum(-1)
    for t, c in zip(torch_vals, cvx_vals, strict=True):
        assert torch.allclose(eps * t - c, const, rtol=1e-9, atol=1e-9 * float(c.abs().max()))
    # so differences between two lam points agree (after the eps scaling)
    for a in range(len(lams)):
        for b in range(a + 1, len(lams)):
            d_torch = eps * (torch_vals[a] - torch_vals[b])
            d_cvx = cvx_vals[a] - cvx_vals[b]
            scale = 1.0 + cvx_vals[a].abs() + cvx_vals[b].abs()
            assert bool(((d_torch - d_cvx).abs() <= 1e-10 * scale).all())
            assert float(d_cvx.abs().max()) > 1e-3  # the points really differ


def test_violation_solution_minimises_the_lam_phi_objective():
    """The declared (V)'s minimiser, with phi*(lam), beats every nearby feasible (lam, phi)."""
    n, n_x, B, gamma, eps = 3, 4, 5, 0.1, 1e-1
    F = random_p_matrix(n, smin=0.5, seed=4)
    C, q, r = randn(n_x, n, seed=5), randn(B, n, seed=6), randn(B, n_x, seed=7)
    decl = violation_problem(n)
    lam = torch.as_tensor(decl.solve(decl.parameter_values(C, F, q, r, gamma, eps)))
    phi = ViolationProblem.phi(lam, F, q, gamma)
    best = ViolationProblem.objective(lam, phi, C, F, q, r, gamma, eps)
    g = np.random.default_rng(0)
    for _ in range(200):
        dl = torch.tensor(g.standard_normal((B, n)) * 1e-2, dtype=F64)
        dp = torch.tensor(g.standard_normal((B, n)) * 1e-2, dtype=F64)
        other = ViolationProblem.objective(
            (lam + dl).clamp(min=0), (phi + dp).clamp(min=0), C, F, q, r, gamma, eps
        )
        assert bool((other >= best - 1e-7 * (1 + best.abs())).all())


# -- phi*(lam) -----------------------------------------------------------------------------


def test_phi_is_the_exact_minimiser_over_phi():
    n, B, gamma, eps = 4, 50, 0.1, 1e-2
    F = random_p_matrix(n, smin=0.5, seed=8)
    q = random_q(B, n, seed=9, scale=2.0)
    C, r = randn(3, n, seed=10), randn(B, 3, seed=11)
    lam = torch.tensor(np.random.default_rng(1).random((B, n)), dtype=F64)
    phi = ViolationProblem.phi(lam, F, q, gamma)
    w = lam @ F.mT + q
    assert torch.equal(phi, torch.clamp(w - gamma * lam, min=0.0))
    assert bool((phi >= 0).all())
    assert bool((phi > 0).any()) and bool((phi == 0).any())  # both branches exercised

    def obj(p):
        return ViolationProblem.objective(lam, p, C, F, q, r, gamma, eps)

    best = obj(phi)
    g = np.random.default_rng(2)
    for scale in (1e-4, 1e-2, 1.0):
        for _ in range(100):
            # random phi >= 0 near phi* and far from it
            other = (phi + scale * torch.tensor(g.standard_normal((B, n)), dtype=F64)).clamp(min=0)
            assert bool((obj(other) >= best - 1e-12 * best.abs()).all())
    far = torch.tensor(10 * g.random((B, n)), dtype=F64)
    assert bool((obj(far) > best).all())
    # KKT of min_{phi >= 0}: gradient = 0 where phi > 0 and >= 0 where phi = 0
    p = phi.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(obj(p).sum(), p)
    assert float(grad[phi > 0].abs().max()) <= 1e-8 * float(grad.abs().max())
    assert bool((grad[phi == 0] >= -1e-10).all())
