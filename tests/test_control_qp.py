"""The QP step of C3 (lcs_cvx.control.qp): the fast affine path against the declared CVXPY
problem (Clarabel and OSQP), with and without a fixed lam_0 and eta, and the finite-horizon LQR
as its closed form when contact plays no part."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

import lcs_cvx
from lcs_cvx._kernels.arrays import array_ops
from lcs_cvx.control import C3, dare
from lcs_cvx.control.costs import Horizon, Layout, weight_matrix
from lcs_cvx.control.qp import Bounds, QPStep


def random_model(n_x=4, n_u=2, n_lam=3, seed=0, E_zero=False):
    rng = np.random.default_rng(seed)
    M = rng.standard_normal((n_lam, n_lam))
    return lcs_cvx.LCS.from_matrices(
        A=np.eye(n_x) + 0.1 * rng.standard_normal((n_x, n_x)), B=rng.standard_normal((n_x, n_u)),
        C=rng.standard_normal((n_x, n_lam)), d=0.1 * rng.standard_normal(n_x),
        D=rng.standard_normal((n_lam, n_x)), E=np.zeros((n_lam, n_u)) if E_zero else rng.standard_normal((n_lam, n_u)),
        F=M @ M.T + np.eye(n_lam), c=rng.standard_normal(n_lam))


def horizon_weights(model, N, with_eta, seed):
    """The horizon, layout and random stage weights ``Q``, ``R`` (and ``QN`` from the Riccati
    equation) of a QP-step test, and its generator for the rest."""
    hz = Horizon.of(model, N)
    lay = Layout(hz.n_x, hz.n_lam, hz.n_u, with_eta)
    rng = np.random.default_rng(seed)
    Q = weight_matrix("Q", rng.uniform(0.5, 2, hz.n_x), hz.n_x, N)
    R = weight_matrix("R", rng.uniform(0.5, 2, hz.n_u), hz.n_u, N)
    return hz, lay, Q, R, dare(hz.A[0], hz.B[0], Q[0], R[0]), rng


def qp_pair(model, N, with_eta, fix_lam0, seed=0):
    hz, lay, Q, R, QN, rng = horizon_weights(model, N, with_eta, seed)
    Gm = rng.standard_normal((lay.n_z, lay.n_z))
    G = weight_matrix("G", Gm @ Gm.T / lay.n_z + 0.1 * np.eye(lay.n_z), lay.n_z, N)
    rho = 2.0 ** np.arange(3)
    kw = dict(fix_lam0=fix_lam0, bounds=Bounds())
    fast = QPStep(hz, lay, Q, R, QN, G, rho, path="fast", solver="CLARABEL", **kw)
    return hz, lay, fast, {s: QPStep(hz, lay, Q, R, QN, G, rho, path="cvxpy", solver=s, **kw) for s in ("CLARABEL", "OSQP")}


@pytest.mark.parametrize("with_eta,fix_lam0", [(False, False), (True, False), (False, True), (True, True)])
def test_fast_path_equals_the_declared_problem(with_eta, fix_lam0):
    model = random_model(E_zero=fix_lam0)
    hz, lay, fast, slow = qp_pair(model, 4, with_eta, fix_lam0)
    rng = np.random.default_rng(1)
    B = 3
    x0 = rng.standard_normal((B, hz.n_x))
    lam0 = np.abs(rng.standard_normal((B, hz.n_lam))) if fix_lam0 else None
    xd = rng.standard_normal((B, hz.N + 1, hz.n_x))
    target = rng.standard_normal((B, hz.N, lay.n_z))
    xp = array_ops(torch.zeros(1))
    for level in (0, 2):
        z, xN, bad = fast.bind(xp, x0, lam0, xd)(level, target)
        assert bad == 0
        for solver, qp in slow.items():
            z2, xN2, bad2 = qp.bind(xp, x0, lam0, xd)(level, target)
            assert bad2 == 0
            scale = max(1.0, np.abs(z).max())
            assert np.abs(z - z2).max() <= 1e-8 * scale, solver
            assert np.abs(xN - xN2).max() <= 1e-8 * scale, solver
        # the solution satisfies the dynamics (and eta's definition, and the fixed lam_0) exactly
        x = np.concatenate([z[..., lay.x], xN[:, None]], axis=1)
        nxt = (np.einsum("kij,bkj->bki", hz.A, x[:, :-1]) + np.einsum("kij,bkj->bki", hz.B, z[..., lay.u])
               + np.einsum("kij,bkj->bki", hz.C, z[..., lay.lam]) + hz.d)
        assert np.abs(nxt - x[:, 1:]).max() < 1e-10
        assert np.abs(x[:, 0] - x0).max() < 1e-12
        if with_eta:
            eta = (np.einsum("kij,bkj->bki", hz.D, x[:, :-1]) + np.einsum("kij,bkj->bki", hz.E, z[..., lay.u])
                   + np.einsum("kij,bkj->bki", hz.F, z[..., lay.lam]) + hz.c)
            assert np.abs(eta - z[..., lay.eta]).max() < 1e-10
        if fix_lam0:
            assert np.abs(z[:, 0, lay.lam] - lam0).max() < 1e-12


def test_fast_path_runs_on_torch_arrays_like_numpy():
    model = random_model()
    hz, lay, fast, _ = qp_pair(model, 3, True, False)
    rng = np.random.default_rng(2)
    args = [rng.standard_normal((2, hz.n_x)), None, rng.standard_normal((2, 4, hz.n_x))]
    target = rng.standard_normal((2, 3, lay.n_z))
    z_np, _, _ = fast.bind(array_ops(torch.zeros(1)), *args)(1, target)
    t = [None if a is None else torch.tensor(a) for a in args]
    z_t, _, _ = fast.bind(array_ops(torch.zeros(1), "torch"), *t)(1, torch.tensor(target))
    assert torch.allclose(z_t, torch.tensor(z_np), rtol=0, atol=1e-12)


def lqr_plan(A, B, Q, R, QN, x0, N):
    """Finite-horizon LQR by the backward Riccati recursion, then the forward rollout."""
    P, gains = QN, []
    for _ in range(N):
        K = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
        P = Q + A.T @ P @ (A - B @ K)
        gains.append(K)
    gains = gains[::-1]
    xs, us = [x0], []
    for k in range(N):
        us.append(-gains[k] @ xs[-1])
        xs.append(A @ xs[-1] + B @ us[-1])
    return np.array(xs), np.array(us)


@pytest.mark.parametrize("projection,path", [("c3+", "fast"), ("c3+", "cvxpy"), ("qp", "fast"), ("miqp", "fast")])
def test_without_contact_c3_is_the_finite_horizon_lqr(projection, path):
    """lam does not enter the dynamics (C = 0) nor its own constraint through x or u (D = E = 0),
    c > 0 so lam = 0 is feasible and optimal; with G and U weighting only lam (and eta), the plan
    is the LQR plan whatever the ADMM does."""
    if projection == "miqp":
        pytest.importorskip("pyscipopt")
    rng = np.random.default_rng(3)
    n_x, n_u, n_lam, N = 4, 2, 2, 6
    A = np.eye(n_x) + 0.1 * rng.standard_normal((n_x, n_x))
    B = rng.standard_normal((n_x, n_u))
    model = lcs_cvx.LCS.from_matrices(A=A, B=B, C=np.zeros((n_x, n_lam)), d=np.zeros(n_x),
                                      D=np.zeros((n_lam, n_x)), E=np.zeros((n_lam, n_u)),
                                      F=np.eye(n_lam), c=np.ones(n_lam))
    Q, R = np.diag([3.0, 1.0, 2.0, 0.5]), np.diag([0.7, 1.3])
    n_z = n_x + n_lam + n_u + (n_lam if projection == "c3+" else 0)
    G = np.zeros(n_z)
    G[n_x:n_x + n_lam] = 1.0
    U = G.copy()
    if projection == "c3+":
        G[-n_lam:] = 1.0
        U[-n_lam:] = 100.0
    ctrl = C3(model, N, Q=Q, R=R, QN="dare", G=G, U=U, projection=projection, qp_path=path)
    x0 = rng.standard_normal(n_x)
    plan = ctrl.solve(x0)
    xs, us = lqr_plan(A, B, Q, R, dare(A, B, Q, R), x0, N)
    assert np.abs(plan.u.numpy() - us).max() < 1e-8
    assert np.abs(plan.x.numpy() - xs).max() < 1e-8


def test_dare_solves_the_riccati_equation():
    rng = np.random.default_rng(4)
    A, B = rng.standard_normal((3, 3)), rng.standard_normal((3, 1))
    Q, R = np.eye(3), np.eye(1)
    P = dare(A, B, Q, R)
    rhs = A.T @ P @ A - A.T @ P @ B @ np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A) + Q
    assert np.abs(P - rhs).max() < 1e-9 * np.abs(P).max()


def bounded_pair(model, N, with_eta, fix_lam0, bounds, seed=0):
    """The fast and the declared QP step with the same weights and box ``bounds``."""
    hz, lay, Q, R, QN, rng = horizon_weights(model, N, with_eta, seed)
    G = weight_matrix("G", rng.uniform(0.1, 1, lay.n_z), lay.n_z, N)
    rho = 2.0 ** np.arange(11)  # C3's default levels, up to 1024
    box = Bounds.of(lay, **bounds)
    kw = dict(fix_lam0=fix_lam0, bounds=box, solver="CLARABEL")
    return hz, lay, QPStep(hz, lay, Q, R, QN, G, rho, path="fast", **kw), QPStep(hz, lay, Q, R, QN, G, rho, path="cvxpy", **kw)


def fallback_rows(z, x0, lay):
    """The initial states whose plan is C3's fallback: ``x_k = x0``, ``lam = u = eta = 0``."""
    rest = np.delete(z, np.arange(lay.n_x), axis=2)
    return np.all(rest == 0, axis=(1, 2)) & np.all(z[:, :, lay.x] == x0[:, None, :], axis=(1, 2))


@pytest.mark.parametrize("with_eta, fix_lam0", [(True, False), (False, False), (True, True)])
@pytest.mark.parametrize("bounds", [
    {"u": (-0.3, 0.3)},
    {"u": (-0.3, 0.3), "x": ([-0.5, -np.inf, -np.inf, -1.0], [0.5, np.inf, np.inf, 1.0])},
    {"u": (-0.3, np.inf), "lam": (0.0, 0.5)},
    {"x": (-0.6, 0.6)},  # every state bounded: more bounds than the QP has freedom
], ids=["u", "u+x", "u+lam", "all-x"])
def test_the_bounded_fast_step_solves_the_declared_problem(with_eta, fix_lam0, bounds):
    """The fast path's bounded step (the unbounded map, then Goldfarb-Idnani on the bounded
    coordinates) against the declared CVXPY problem with Clarabel at tight tolerances, at every
    consensus level, where Clarabel solves it: 1e-6; both find the same infeasible states."""
    model = random_model(n_lam=2, seed=3)
    hz, lay, fast, slow = bounded_pair(model, 4, with_eta, fix_lam0, bounds)
    rng = np.random.default_rng(1)
    B = 6
    x0 = 0.3 * rng.normal(size=(B, 4))
    lam0 = 0.3 * np.abs(rng.normal(size=(B, 2))) if fix_lam0 else None
    xd = 0.2 * rng.normal(size=(B, 5, 4))
    target = rng.normal(size=(B, 4, lay.n_z))
    xp = array_ops(torch.zeros(0), "numpy")
    step_f, step_s = fast.bind(xp, x0, lam0, xd), slow.bind(xp, x0, lam0, xd)
    compared = 0
    for level in range(11):
        z_f, xN_f, bad_f = step_f(level, target)
        with warnings.catch_warnings():  # CVXPY's "may be inaccurate": counted as a failure below
            warnings.simplefilter("ignore", UserWarning)
            z_s, xN_s, bad_s = step_s(level, target)
        y_f = np.concatenate([z_f.reshape(B, -1), xN_f], 1)
        y_s = np.concatenate([z_s.reshape(B, -1), xN_s], 1)
        # a failed state's plan is C3's fallback (x_k = x0, the rest 0): compare the others
        fell_s, fell_f = fallback_rows(z_s, x0, lay), fallback_rows(z_f, x0, lay)
        assert int(fell_s.sum()) == bad_s and int(fell_f.sum()) == bad_f
        assert not (fell_f & ~fell_s).any()  # the fast path fails only where Clarabel does
        both = ~fell_s
        if both.any():
            assert np.abs(y_f[both] - y_s[both]).max() <= 1e-6 * (1 + np.abs(y_s[both]).max())
        compared += int(both.sum())
        # the bounds hold on the fast path
        for key, sl, steps in (("u", lay.u, range(4)), ("lam", lay.lam, range(1 if fix_lam0 else 0, 4))):
            if key in bounds:
                lo, hi = bounds[key]
                v = z_f[:, list(steps), sl]
                assert (v >= np.asarray(lo) - 1e-9).all() and (v <= np.asarray(hi) + 1e-9).all()
    assert compared >= 30


def test_box_bounds_hold_on_both_paths_and_the_fast_one_is_the_default():
    model = random_model(n_lam=2)
    ctrl = C3(model, 3, Q=np.ones(4), R=np.ones(2), u_bounds=(-0.1, 0.1), gap_tol=None)
    assert ctrl.qp.path == "fast"
    declared = C3(model, 3, Q=np.ones(4), R=np.ones(2), u_bounds=(-0.1, 0.1), qp_path="cvxpy", gap_tol=None)
    free = C3(model, 3, Q=np.ones(4), R=np.ones(2), gap_tol=None)
    x0 = np.array([1.0, -2.0, 0.5, 1.0])
    assert float(free.solve(x0).u.abs().max()) > 0.1  # the bound is active
    assert float(ctrl.solve(x0).u.abs().max()) <= 0.1 + 1e-9
    assert float(declared.solve(x0).u.abs().max()) <= 0.1 + 1e-7


@pytest.mark.parametrize("path", ["fast", "cvxpy"])
def test_infeasible_bounds_are_named_and_an_infeasible_qp_falls_back_visibly(path):
    model = random_model(n_lam=2)
    with pytest.raises(lcs_cvx.LCSInputError, match=r"x_bounds: infeasible bounds, lo\[1\]"):
        C3(model, 3, Q=np.ones(4), R=np.ones(2), x_bounds=([-1, 2, -1, -1], [1, 1, 1, 1]))
    # x_1 cannot reach a box 100 away in one step with |u| <= 1: every QP step fails
    ctrl = C3(model, 3, Q=np.ones(4), R=np.ones(2), x_bounds=(100.0, 101.0), u_bounds=(-1, 1), qp_path=path,
              projection="c3+", gap_tol=None)
    with pytest.warns(lcs_cvx.FallbackWarning, match="QP step"):
        plan = ctrl.solve(np.zeros(4))
    assert plan.qp_failures == ctrl.admm_iterations + 1
    assert float(plan.u.abs().max()) == 0.0


def test_weights_of_the_wrong_shape_are_named():
    model = random_model()
    with pytest.raises(lcs_cvx.LCSInputError, match="Q: expected 4 diagonal entries"):
        C3(model, 3, Q=np.ones(3), R=np.ones(2))
    with pytest.raises(lcs_cvx.LCSInputError, match="G: expected 12 diagonal"):
        C3(model, 3, Q=np.ones(4), R=np.ones(2), G=np.ones(9))
    with pytest.raises(lcs_cvx.LCSInputError, match="R: expected a positive semidefinite"):
        C3(model, 3, Q=np.ones(4), R=-np.ones(2))
    with pytest.raises(lcs_cvx.LCSInputError, match="horizon = 3"):
        C3([model, model], 3, Q=np.ones(4), R=np.ones(2))
    with pytest.raises(lcs_cvx.LCSInputError, match="G, R: the QP step has no unique solution"):
        C3(model, 3, Q=np.ones(4), R=np.zeros(2), G=np.zeros(12))


@pytest.mark.parametrize("bounds", [{}, {"u": (-0.3, 0.3)}], ids=["free", "bounded"])
def test_an_input_reference_enters_both_paths_alike(bounds):
    """The input cost (u - u_ref)^T R (u - u_ref) (penalize_input_change): the fast step, with and
    without bounds, against the declared problem, at every level; u_ref = 0 is the plain cost."""
    model = random_model(n_lam=2, seed=5)
    hz, lay, fast, slow = bounded_pair(model, 4, True, False, bounds)
    rng = np.random.default_rng(4)
    B = 4
    x0, xd = 0.3 * rng.normal(size=(B, 4)), 0.2 * rng.normal(size=(B, 5, 4))
    target, u_ref = rng.normal(size=(B, 4, lay.n_z)), rng.normal(size=(B, 4, 2))
    xp = array_ops(torch.zeros(0), "numpy")
    step_f, step_s = fast.bind(xp, x0, None, xd, u_ref), slow.bind(xp, x0, None, xd, u_ref)
    plain = fast.bind(xp, x0, None, xd)
    zero = fast.bind(xp, x0, None, xd, np.zeros((B, 4, 2)))
    moved = 0.0
    for level in range(11):
        z_f, xN_f, bad_f = step_f(level, target)
        z_s, xN_s, bad_s = step_s(level, target)
        assert bad_f == bad_s == 0
        assert np.abs(z_f - z_s).max() <= 1e-6 * (1 + np.abs(z_s).max())
        assert np.array_equal(plain(level, target)[0], zero(level, target)[0])  # the same operations
        moved = max(moved, float(np.abs(z_f - plain(level, target)[0]).max()))
    assert moved > 1e-3  # the reference changes the plan
