"""The projection step of C3 (lcs_cvx.control.projection): "c3+" against brute-force
enumeration of its 2^n_lam choices, "lcp" against enumerated LCP solutions, "miqp" against
the enumeration of the sign patterns (project_enumerate), "qp" feasible for the LCS's
constraints, and the named errors."""

from __future__ import annotations

import importlib.util
import itertools

import cvxpy as cp
import numpy as np
import pytest
import torch

import lcs_cvx
from lcs_cvx._kernels.arrays import array_ops
from lcs_cvx.control import project_enumerate
from lcs_cvx.control.costs import Horizon, Layout, weight_matrix
from lcs_cvx.control.projection import Projection
from lcs_cvx.lcp import solve_lcp_unchecked

XP = array_ops(torch.zeros(1))


def random_model(n_x=3, n_u=1, n_lam=2, seed=0):
    rng = np.random.default_rng(seed)
    M = rng.standard_normal((n_lam, n_lam))
    return lcs_cvx.LCS.from_matrices(
        A=np.eye(n_x) + 0.1 * rng.standard_normal((n_x, n_x)), B=rng.standard_normal((n_x, n_u)), C=rng.standard_normal((n_x, n_lam)),
        d=np.zeros(n_x), D=rng.standard_normal((n_lam, n_x)), E=rng.standard_normal((n_lam, n_u)),
        F=M @ M.T + np.eye(n_lam), c=rng.standard_normal(n_lam))


def c3plus_by_enumeration(c, lay, w_lam, w_eta):
    """Every choice of which of lam_i, eta_i is zero; the other clipped at 0; the cheapest."""
    best, best_cost = None, np.inf
    for keep_eta in itertools.product((False, True), repeat=lay.n_lam):
        k = np.array(keep_eta)
        d = c.copy()
        d[lay.lam] = np.where(k, 0.0, np.maximum(c[lay.lam], 0))
        d[lay.eta] = np.where(k, np.maximum(c[lay.eta], 0), 0.0)
        cost = (w_lam * (d[lay.lam] - c[lay.lam]) ** 2).sum() + (w_eta * (d[lay.eta] - c[lay.eta]) ** 2).sum()
        if cost < best_cost - 1e-14:
            best, best_cost = d, cost
    return best, best_cost


def lcp_of(F, q):
    """The LCP solution by enumeration (the test oracle of lcs_cvx.solve_lcp)."""
    return lcs_cvx.solve_lcp(torch.as_tensor(F), torch.as_tensor(q)[None], method="brute").lam[0].numpy()


@pytest.mark.parametrize("varying", [False, True])
def test_the_lcp_projection_keeps_x_and_u_and_sets_the_models_own_forces(varying):
    """"lcp": x_k and u_k as given, lam_k the LCP solution at (x_k, u_k) (checked against
    enumeration), eta_k = D x_k + E u_k + F lam_k + c: on the complementarity set. A time-varying
    horizon (a list of models) projects step by step, a fixed one all steps in one call."""
    N = 3
    models = [random_model(n_lam=3, seed=s) for s in range(N)] if varying else random_model(n_lam=3)
    hz = Horizon.of(models, N)
    lay = Layout(hz.n_x, hz.n_lam, hz.n_u, with_eta=True)
    proj = Projection(hz, lay, weight_matrix("U", np.ones(lay.n_z), lay.n_z, N), "lcp")
    assert proj.time_invariant is (not varying)

    def lcp(k, q):
        return solve_lcp_unchecked(torch.as_tensor(hz.F[k]), torch.as_tensor(np.ascontiguousarray(q))).lam.numpy()

    c = np.random.default_rng(2).standard_normal((7, N, lay.n_z))
    delta = proj.bind(XP, c, lcp)(c)
    np.testing.assert_array_equal(delta[..., lay.x], c[..., lay.x])
    np.testing.assert_array_equal(delta[..., lay.u], c[..., lay.u])
    for b in range(7):
        for k in range(N):
            x, u = c[b, k, lay.x], c[b, k, lay.u]
            q = hz.D[k] @ x + hz.E[k] @ u + hz.c[k]
            lam = delta[b, k, lay.lam]
            np.testing.assert_allclose(lam, lcp_of(hz.F[k], q), rtol=0, atol=1e-12)
            np.testing.assert_allclose(delta[b, k, lay.eta], q + hz.F[k] @ lam, rtol=0, atol=1e-12)
            assert lam.min() >= 0 and delta[b, k, lay.eta].min() >= -1e-12


def test_c3plus_is_the_exact_projection_of_its_set():
    model = random_model(n_lam=4)
    N = 3
    hz = Horizon.of(model, N)
    lay = Layout(hz.n_x, hz.n_lam, hz.n_u, with_eta=True)
    rng = np.random.default_rng(1)
    U = np.zeros(lay.n_z)
    U[lay.lam] = rng.uniform(0.5, 2, hz.n_lam)
    U[lay.eta] = rng.uniform(0.5, 2, hz.n_lam)
    proj = Projection(hz, lay, weight_matrix("U", U, lay.n_z, N), "c3+")
    c = rng.standard_normal((20, N, lay.n_z))
    delta = proj.bind(XP, c)(c)
    for b in range(20):
        for k in range(N):
            want, want_cost = c3plus_by_enumeration(c[b, k], lay, U[lay.lam], U[lay.eta])
            d = delta[b, k]
            cost = (U[lay.lam] * (d[lay.lam] - c[b, k, lay.lam]) ** 2).sum() + (U[lay.eta] * (d[lay.eta] - c[b, k, lay.eta]) ** 2).sum()
            assert cost == pytest.approx(want_cost, rel=1e-12, abs=1e-14)
            assert np.abs(d - want).max() < 1e-12
            assert np.all(d[lay.lam] >= 0) and np.all(d[lay.eta] >= 0)
            assert np.all(d[lay.lam] * d[lay.eta] == 0)
            np.testing.assert_array_equal(d[lay.x], c[b, k, lay.x])  # x and u pass through
    tc = torch.tensor(c)
    torch_delta = proj.bind(array_ops(tc, "torch"), tc)(tc)
    assert torch.equal(torch_delta, torch.tensor(delta))


@pytest.mark.parametrize("n_lam", [2, 3])
def test_miqp_equals_the_enumeration_of_sign_patterns(n_lam):
    pytest.importorskip("pyscipopt")
    model = random_model(n_lam=n_lam, seed=n_lam)
    N = 2
    hz = Horizon.of(model, N)
    lay = Layout(hz.n_x, hz.n_lam, hz.n_u, with_eta=False)
    rng = np.random.default_rng(5)
    U = np.concatenate([rng.uniform(1, 3, hz.n_x), rng.uniform(0.5, 2, hz.n_lam), rng.uniform(0.5, 1, hz.n_u)])
    proj = Projection(hz, lay, weight_matrix("U", U, lay.n_z, N), "miqp")
    c = rng.standard_normal((2, N, lay.n_z))
    delta = proj.bind(XP, c)(c)
    m = model.to_matrices()
    for b in range(2):
        for k in range(N):
            want = project_enumerate(c[b, k], np.diag(U), m["D"], m["E"], m["F"], m["c"], hz.n_x, hz.n_u)
            def cost(d, point=c[b, k]):
                return float(np.sum(U * (d - point) ** 2))
            assert cost(delta[b, k]) == pytest.approx(cost(want), rel=1e-6, abs=1e-8)
            assert np.abs(delta[b, k] - want).max() < 1e-7
            lam = delta[b, k, lay.lam]
            eta = m["D"] @ delta[b, k, lay.x] + m["E"] @ delta[b, k, lay.u] + m["F"] @ lam + m["c"]
            assert np.abs(np.minimum(lam, eta)).max() < 1e-6


@pytest.mark.parametrize("n_lam", [2, 3])
def test_miqp_by_active_sets_equals_the_enumeration_of_sign_patterns(n_lam):
    """projection_solver="enumerate" (3^n_lam active sets, closed form) is the exact projection:
    equal to the sign-pattern oracle on random points and on points already in the set with
    lam_i = eta_i = 0 (degenerate), and to SCIP's big-M projection where SCIP is installed."""
    model = random_model(n_lam=n_lam, seed=n_lam)
    N = 2
    hz = Horizon.of(model, N)
    lay = Layout(hz.n_x, hz.n_lam, hz.n_u, with_eta=False)
    rng = np.random.default_rng(11)
    U = np.concatenate([rng.uniform(1, 3, hz.n_x), rng.uniform(0.5, 2, hz.n_lam), rng.uniform(0.5, 1, hz.n_u)])
    Um = weight_matrix("U", U, lay.n_z, N)
    proj = Projection(hz, lay, Um, "miqp", solver="enumerate")
    m = model.to_matrices()
    c = rng.standard_normal((3, N, lay.n_z))
    # a degenerate point of the set: lam = 0, eta_0 = 0 (x moved onto D_0 x + E_0 u + c_0 = 0), eta >= 0
    for _ in range(200):
        p = rng.standard_normal(lay.n_z)
        p[lay.lam] = 0.0
        p[lay.x] -= (m["D"][0] @ p[lay.x] + m["E"][0] @ p[lay.u] + m["c"][0]) * m["D"][0] / (m["D"][0] @ m["D"][0])
        if (m["D"] @ p[lay.x] + m["E"] @ p[lay.u] + m["c"]).min() >= -1e-12:
            break
    else:
        raise AssertionError("no degenerate point found")
    c[2, 0] = p
    delta = proj.bind(XP, c)(c)
    for b in range(3):
        for k in range(N):
            want = project_enumerate(c[b, k], np.diag(U), m["D"], m["E"], m["F"], m["c"], hz.n_x, hz.n_u)
            # the oracle's interior-point QPs end ~1e-6 from a boundary where lam_i = eta_i = 0;
            # the closed form is on it, and costs no more
            assert np.abs(delta[b, k] - want).max() < 1e-5
            cost = np.sum(U * (delta[b, k] - c[b, k]) ** 2)
            assert cost <= np.sum(U * (want - c[b, k]) ** 2) + 1e-12
            lam = delta[b, k, lay.lam]
            eta = m["D"] @ delta[b, k, lay.x] + m["E"] @ delta[b, k, lay.u] + m["F"] @ lam + m["c"]
            assert lam.min() >= -1e-12 and eta.min() >= -1e-9 and np.abs(lam * eta).max() < 1e-9
    np.testing.assert_allclose(delta[2, 0], c[2, 0], atol=1e-12)  # already in the set: kept
    if importlib.util.find_spec("pyscipopt"):
        scip = Projection(hz, lay, Um, "miqp").bind(XP, c)(c)
        assert np.abs(scip - delta).max() < 1e-5


def test_miqp_by_active_sets_names_its_limits():
    hz = Horizon.of(random_model(n_lam=7, seed=1), 2)
    lay = Layout(hz.n_x, hz.n_lam, hz.n_u, with_eta=False)
    with pytest.raises(lcs_cvx.LCSInputError, match="n_lam <= 6, received 7"):
        Projection(hz, lay, weight_matrix("U", np.ones(lay.n_z), lay.n_z, 2), "miqp", solver="enumerate")
    hz = Horizon.of(random_model(n_lam=2, seed=1), 2)
    lay = Layout(hz.n_x, hz.n_lam, hz.n_u, with_eta=False)
    U = np.ones((lay.n_z, lay.n_z))  # PSD, rank one, no zero diagonal: no tie-break helps
    with pytest.raises(lcs_cvx.LCSInputError, match="singular U"):
        Projection(hz, lay, weight_matrix("U", U, lay.n_z, 2), "miqp", solver="enumerate")


def test_qp_projection_satisfies_the_constraints_of_its_relaxation():
    model = random_model(n_lam=3, seed=7)
    N = 2
    hz = Horizon.of(model, N)
    lay = Layout(hz.n_x, hz.n_lam, hz.n_u, with_eta=False)
    U = np.concatenate([np.full(hz.n_x, 1000.0), np.ones(hz.n_lam), np.zeros(hz.n_u)])
    proj = Projection(hz, lay, weight_matrix("U", U, lay.n_z, N), "qp")
    c = np.random.default_rng(8).standard_normal((3, N, lay.n_z))
    delta = proj.bind(XP, c)(c)
    m = model.to_matrices()
    lam = delta[..., lay.lam]
    eta = (np.einsum("ij,bkj->bki", m["D"], delta[..., lay.x]) + np.einsum("ij,bkj->bki", m["E"], delta[..., lay.u])
           + np.einsum("ij,bkj->bki", m["F"], lam) + m["c"])
    assert lam.min() >= -1e-7 and eta.min() >= -1e-6
    # with x held by its weight, the relaxation stays close to the point on x
    assert np.abs(delta[..., lay.x] - c[..., lay.x]).max() < 0.1


def test_projection_options_reach_the_solver(monkeypatch):
    model = random_model(n_lam=2, seed=7)
    ctrl = lcs_cvx.control.C3(model, 2, Q=np.ones(3), R=np.ones(1), projection="qp",
                              projection_options={"tol_gap_abs": 1e-9}, gap_tol=None)
    seen = []
    real = cp.Problem.solve

    def spy(self, *args, **kwargs):
        seen.append(kwargs)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(cp.Problem, "solve", spy)
    ctrl.solve(np.array([0.1, -0.2, 0.3]))
    assert seen and all(kw.get("tol_gap_abs") == 1e-9 and kw.get("solver") == "CLARABEL" for kw in seen)


def test_project_enumerate_agrees_with_a_direct_mixed_integer_solve():
    pytest.importorskip("pyscipopt")
    model = random_model(n_lam=2, seed=11)
    m = model.to_matrices()
    c = np.array([0.3, -0.2, 0.5, 0.4, -0.1, 0.2])
    U = np.diag([1.0, 2.0, 1.0, 3.0, 1.0, 0.5])
    got = project_enumerate(c, U, m["D"], m["E"], m["F"], m["c"], 3, 1)
    d, b = cp.Variable(6), cp.Variable(2, boolean=True)
    lam = d[3:5]
    eta = m["D"] @ d[:3] + m["E"] @ d[5:] + m["F"] @ lam + m["c"]
    cp.Problem(cp.Minimize(cp.quad_form(d - c, U)),
               [lam >= 0, lam <= 100 * (1 - b), eta >= 0, eta <= 100 * b]).solve(solver="SCIP")
    # SCIP's default feasibility tolerance (1e-6) leaves its answer ~1e-4 from the exact one
    assert np.abs(got - d.value).max() < 1e-3
    assert float(np.sum(np.diag(U) * (got - c) ** 2)) <= float(np.sum(np.diag(U) * (d.value - c) ** 2)) + 1e-7


def test_bad_projection_inputs_are_named(monkeypatch):
    model = random_model()
    with pytest.raises(lcs_cvx.LCSInputError, match="projection: expected one of"):
        lcs_cvx.control.C3(model, 2, Q=np.ones(3), R=np.ones(1), projection="admm")
    with pytest.raises(lcs_cvx.LCSInputError, match="projection_solver: expected 'enumerate' or a mixed-integer QP solver"):
        lcs_cvx.control.C3(model, 2, Q=np.ones(3), R=np.ones(1), projection="miqp", projection_solver="OSQP")
    # a mixed-integer solver that is not installed: the error names the extra
    monkeypatch.setattr(cp, "installed_solvers", lambda: ["CLARABEL", "OSQP"])
    with pytest.raises(ModuleNotFoundError, match=r"lcs_cvx\[control\]"):
        lcs_cvx.control.C3(model, 2, Q=np.ones(3), R=np.ones(1), projection="miqp", projection_solver="GUROBI")
    U = np.eye(3 + 2 + 1 + 2)
    U[3, 6] = U[6, 3] = 0.5  # couples lam_0 and eta_0
    with pytest.raises(lcs_cvx.LCSInputError, match="U: the 'c3\\+' projection is closed-form for a U diagonal"):
        lcs_cvx.control.C3(model, 2, Q=np.ones(3), R=np.ones(1), U=U)


def test_qp_projection_set_up_once_in_clarabel_equals_the_declared_problem():
    """The "qp" projection's direct Clarabel QP (set up once, only its linear term updated) and
    the declared CVXPY problem solve the same relaxation."""
    model = random_model(n_lam=3, seed=9)
    N = 3
    hz = Horizon.of(model, N)
    lay = Layout(hz.n_x, hz.n_lam, hz.n_u, with_eta=False)
    U = weight_matrix("U", np.concatenate([np.full(hz.n_x, 1000.0), np.ones(hz.n_lam), np.full(hz.n_u, 0.5)]), lay.n_z, N)
    direct = Projection(hz, lay, U, "qp")
    declared = Projection(hz, lay, U, "qp", solver="CLARABEL",
                          options={"tol_gap_abs": 1e-11, "tol_gap_rel": 1e-11, "tol_feas": 1e-11})
    assert direct.direct and not declared.direct
    c = np.random.default_rng(10).standard_normal((4, N, lay.n_z))
    a, b = direct.bind(XP, c)(c), declared.bind(XP, c)(c)
    assert np.abs(a - b).max() < 1e-6 * max(1.0, np.abs(a).max())


def test_qp_projection_keeps_unweighted_coordinates_at_the_point():
    """C3's published U leaves u unweighted; where u does not enter the constraints (E = 0) any
    value is optimal, and the direct QP keeps the point's."""
    P = lcs_cvx.control.c3_cartpole()
    hz = Horizon.of(P.model, 2)
    lay = Layout(hz.n_x, hz.n_lam, hz.n_u, with_eta=False)
    _, U = P.weights["qp"]
    proj = Projection(hz, lay, weight_matrix("U", U, lay.n_z, 2), "qp")
    c = np.random.default_rng(11).standard_normal((2, 2, lay.n_z))
    delta = proj.bind(XP, c)(c)
    assert np.abs(delta[..., lay.u] - c[..., lay.u]).max() < 1e-6
