"""C3 (lcs_cvx.control.c3): C3's own cart-pole end-to-end check for every projection, the
fast and the declared paths planning alike, a batch planning as its members one by one, the
ADMM's fixed point complementarity-feasible, and the conversions to and from C3's naming."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import learned_like

import lcs_cvx
from lcs_cvx.control import C3, c3_cartpole, closed_loop


@pytest.fixture(scope="module")
def cartpole():
    return c3_cartpole()


def controller(P, projection, **kw):
    """C3 with C3's published weights for ``projection``. Without the plan-gap check: from ``x0``
    the published projections plan with wall forces the model does not produce (a gap of 0.84
    at the first solve for ``"c3+"``), and these tests are of C3 itself; the check has its own.
    Without the polish too (C3's ADMM as published; the polish has its own tests)."""
    G, U = P.weights["c3+" if projection in ("lcp", "auto") else projection]
    kw.setdefault("gap_tol", None)
    kw.setdefault("polish", 0)
    return C3(P.model, P.horizon, Q=P.Q, R=P.R, QN="dare", G=G, U=U, projection=projection, **kw)


@pytest.mark.parametrize("projection, options", [("c3+", {}), ("qp", {}), ("miqp", {"projection_solver": "enumerate"}),
                                                 ("lcp", {}), ("auto", {})])
def test_c3_cartpole_end_to_end(cartpole, projection, options):
    """C3's end-to-end test: from x0 = (0.1, -0.5, 0.5, -0.4), closing the loop on the exact LCS
    brings every coordinate within 0.1 of zero and keeps it there for 30 steps. (The "miqp"
    projection runs here by its active sets; through SCIP, at about a second per solve, it runs
    in the control study, settling at the same step 187.)"""
    ctrl = controller(cartpole, projection, **options)
    res = closed_loop(ctrl, cartpole.model, cartpole.x0, 400, stop_when_settled=True)
    assert 0 < int(res.settled[0]) < 400
    assert float(res.x[0, -1].abs().max()) <= 0.1
    # the walls were hit on the way (the problem is not the LQR's)
    lam = cartpole.model.solve_lcp(res.x[0, :-1], res.u[0]).lam.detach()
    assert float(lam.max()) > 0
    if projection == "miqp":
        assert int(res.settled[0]) == 187  # as SCIP's big-M projection does


@pytest.mark.parametrize("projection", ["c3+", "qp"])
def test_fast_and_declared_paths_plan_alike(cartpole, projection):
    fast = controller(cartpole, projection, qp_path="fast")
    slow = controller(cartpole, projection, qp_path="cvxpy")
    for x0 in (cartpole.x0, np.array([0.3, 0.2, -0.4, 0.6])):
        a, b = fast.solve(x0), slow.solve(x0)
        for name in ("x", "u", "lam"):
            assert torch.allclose(getattr(a, name), getattr(b, name), rtol=0, atol=1e-7), name


def test_a_batch_plans_as_its_members_one_by_one(cartpole):
    ctrl = controller(cartpole, "c3+")
    X0 = torch.tensor(np.random.default_rng(0).uniform(-0.4, 0.4, (6, 4)))
    batch = ctrl.solve(X0)
    assert batch.x.shape == (6, 6, 4) and batch.u.shape == (6, 5, 1) and batch.lam.shape == (6, 5, 2)
    assert batch.primal_residual.shape == (6, 10) and batch.complementarity.shape == (6,)
    for b in range(6):
        one = ctrl.solve(X0[b])
        assert one.x.shape == (6, 4)
        assert torch.allclose(one.u, batch.u[b], rtol=0, atol=1e-12)
        assert torch.allclose(one.x, batch.x[b], rtol=0, atol=1e-12)


def test_the_admm_fixed_point_is_complementarity_feasible(cartpole):
    """delta is in the complementarity set at every iteration, so where z = delta (a fixed point)
    the plan is complementarity-feasible: its violation is bounded by the primal residual, which
    the growing rho drives down. The plan follows the dynamics with its forces, and its first
    force is the LCP's at x0 (E = 0: lam_0 fixed)."""
    ctrl = controller(cartpole, "c3+", admm_iterations=30)
    x0 = np.array([0.3, -0.2, 0.8, -0.5])  # heading into the right wall
    plan = ctrl.solve(x0)
    lay = ctrl.layout
    lam, eta = plan.delta[:, lay.lam], plan.delta[:, lay.eta]
    assert float(lam.min()) >= 0 and float(eta.min()) >= 0 and float((lam * eta).abs().max()) == 0
    assert float(plan.primal_residual[-1]) < 0.01 * float(plan.primal_residual[0])
    assert float(plan.complementarity) <= float(plan.primal_residual[-1]) + 1e-9
    lam0 = cartpole.model.solve_lcp(x0, np.zeros(1)).lam[0].detach()
    assert torch.allclose(plan.lam[0], lam0, atol=1e-10)
    m = cartpole.model.to_matrices()
    x, u, lam = plan.x.numpy(), plan.u.numpy(), plan.lam.numpy()
    np.testing.assert_allclose(x[1:], x[:-1] @ m["A"].T + u @ m["B"].T + lam @ m["C"].T + m["d"], atol=1e-10)


def test_miqp_projections_are_complementarity_feasible(cartpole):
    """The exact projection's delta satisfies the LCS's complementarity at every step."""
    pytest.importorskip("pyscipopt")
    ctrl = controller(cartpole, "miqp", admm_iterations=3)
    plan = ctrl.solve(np.array([0.3, -0.2, 0.8, -0.5]))
    m, lay = cartpole.model.to_matrices(), ctrl.layout
    d = plan.delta.numpy()
    eta = d[:, lay.x] @ m["D"].T + d[:, lay.u] @ m["E"].T + d[:, lay.lam] @ m["F"].T + m["c"]
    assert np.abs(np.minimum(d[:, lay.lam], eta)).max() < 1e-8


def test_warm_start_shifts_the_previous_plan(cartpole):
    ctrl = controller(cartpole, "c3+")
    u0 = ctrl(cartpole.x0)
    first = ctrl.last_plan
    assert torch.equal(u0, first.u[0])
    shifted = ctrl._shift(first, 1)
    assert torch.equal(shifted[0, :-1], first.delta[1:]) and torch.equal(shifted[0, -1], first.delta[-1])
    x1 = cartpole.model.step(cartpole.x0, u0.detach().numpy()).detach()
    warm = ctrl.solve(x1, warm_start=first)
    cold = ctrl.solve(x1)
    assert not torch.equal(warm.u, cold.u)  # the start matters to a finite ADMM
    ctrl.reset()
    assert ctrl.last_plan is None


def test_input_in_the_complementarity_leaves_lam0_free():
    rng = np.random.default_rng(2)
    model = lcs_cvx.LCS.from_matrices(A=np.eye(3) + 0.05 * rng.standard_normal((3, 3)), B=rng.standard_normal((3, 1)),
                                      C=0.1 * rng.standard_normal((3, 2)), d=np.zeros(3), D=rng.standard_normal((2, 3)),
                                      E=rng.standard_normal((2, 1)), F=np.eye(2), c=np.ones(2))
    ctrl = C3(model, 4, Q=np.ones(3), R=np.ones(1), projection="c3+", admm_iterations=30)
    assert not ctrl.fix_lam0
    plan = ctrl.solve(np.array([0.5, -0.5, 0.2]))
    assert float(plan.complementarity) < 1e-5


def test_fix_lam0_for_a_learned_model_whose_E_is_merely_small(cartpole):
    """A learned model's E is small, not zero: C3 leaves lam_0 free unless told; told, it fixes
    lam_0 to the LCP solution at x0 (u = 0), as for the exact E = 0."""
    m = cartpole.model.to_c3()
    m["H"] = np.full((2, 1), 1e-9)
    nearly = lcs_cvx.LCS.from_c3(m)
    G, U = cartpole.weights["c3+"]
    kw = dict(Q=cartpole.Q, R=cartpole.R, G=G, U=U)
    assert not C3(nearly, 5, **kw).fix_lam0
    fixed = C3(nearly, 5, fix_lam0=True, **kw)
    exact = C3(cartpole.model, 5, **kw)
    x0 = np.array([0.3, -0.2, 0.8, -0.5])
    assert fixed.fix_lam0 and exact.fix_lam0
    assert torch.allclose(fixed.solve(x0).u, exact.solve(x0).u, atol=1e-6)


def test_a_time_varying_horizon(cartpole):
    """A list of N models: the same model N times plans as the one model."""
    P = cartpole
    G, U = P.weights["c3+"]
    one = C3(P.model, P.horizon, Q=P.Q, R=P.R, G=G, U=U)
    many = C3([P.model] * P.horizon, P.horizon, Q=P.Q, R=P.R, G=G, U=U)
    assert torch.allclose(one.solve(P.x0).u, many.solve(P.x0).u, rtol=0, atol=1e-12)


def test_from_c3_inverts_to_c3(cartpole):
    m = cartpole.model
    back = lcs_cvx.LCS.from_c3(m.to_c3())
    for key, value in m.to_matrices().items():
        np.testing.assert_allclose(back.to_matrices()[key], value, atol=1e-12)
    bad = m.to_c3()
    bad["F"] = -np.eye(2)
    with pytest.raises(lcs_cvx.LCSInputError, match="F: expected F \\+ F\\^T positive definite"):
        lcs_cvx.LCS.from_c3(bad)
    with pytest.raises(lcs_cvx.LCSInputError, match="missing \\['H'\\]"):
        lcs_cvx.LCS.from_c3({k: v for k, v in m.to_c3().items() if k != "H"})


def test_x_des_moves_the_target(cartpole):
    P = cartpole
    ctrl = controller(P, "c3+", x_des=np.array([0.1, 0, 0, 0]))
    res = closed_loop(ctrl, P.model, np.zeros(4), 300, x_des=np.array([0.1, 0, 0, 0]), tol=0.02, hold=20)
    assert int(res.settled[0]) > 0
    with pytest.raises(lcs_cvx.LCSInputError, match="x_des: expected finite"):
        controller(P, "c3+", x_des=np.zeros(3))
    # a target per call: the same first input as solve(x0, x_des=...) from the same warm start
    moving = controller(P, "c3+")
    x0, target = np.array([0.05, 0.1, 0.0, 0.0]), np.array([0.1, 0, 0, 0])
    u = moving(x0, x_des=target)
    want = controller(P, "c3+").solve(x0, x_des=target)
    assert torch.equal(u, want.u[0]) and torch.equal(moving.last_plan.u, want.u)


def test_the_torch_back_end_plans_as_numpy(cartpole):
    """The fast c3+ solve written once for both array libraries: torch on the CPU (as on a GPU)
    plans what NumPy plans, to round-off."""
    P = cartpole
    X0 = torch.tensor(np.random.default_rng(3).uniform(-0.4, 0.4, (5, 4)))
    a = controller(P, "c3+").solve(X0)
    b = controller(P, "c3+", arrays="torch").solve(X0)
    for name in ("x", "u", "lam", "delta", "primal_residual", "complementarity"):
        assert torch.allclose(getattr(a, name), getattr(b, name), rtol=0, atol=1e-10), name
    a, b = controller(P, "auto").solve(X0), controller(P, "auto", arrays="torch").solve(X0)
    assert a.projection == b.projection
    for name in ("x", "x_model", "u", "lam", "gap", "cost"):
        assert torch.allclose(getattr(a, name), getattr(b, name), rtol=1e-9, atol=1e-9), name
    with pytest.raises(lcs_cvx.LCSInputError, match="arrays: expected one of"):
        controller(P, "c3+", arrays="jax")


def test_dare_uses_the_mode_active_at_the_target():
    """QN = "dare" linearises the model in the contact mode active at x_des: there the LCS step
    is that affine map (checked against the step itself), and a unit active at the target
    changes QN from the free mode's."""
    from lcs_cvx.control import Horizon, dare
    from lcs_cvx.control.costs import mode_dynamics

    rng = np.random.default_rng(5)
    n_x, n_u, n_lam = 3, 1, 2
    m = dict(A=np.eye(n_x) + 0.1 * rng.standard_normal((n_x, n_x)), B=rng.standard_normal((n_x, n_u)),
             C=rng.standard_normal((n_x, n_lam)), d=np.zeros(n_x), D=rng.standard_normal((n_lam, n_x)),
             E=rng.standard_normal((n_lam, n_u)), F=np.array([[2.0, 0.5], [-0.5, 1.0]]), c=np.array([-1.0, 1.0]))
    model = lcs_cvx.LCS.from_matrices(**m)  # unit 0 active at the origin (c_0 < 0), unit 1 not
    A_S, B_S, S = mode_dynamics(Horizon.of(model, 1), np.zeros(n_x), np.zeros(n_u))
    assert S == [0]
    dx, du = 1e-4 * rng.standard_normal((4, n_x)), 1e-4 * rng.standard_normal((4, n_u))
    base = model.step(np.zeros((1, n_x)), np.zeros((1, n_u))).detach().numpy()
    moved = model.step(dx, du).detach().numpy()
    np.testing.assert_allclose(moved - base, dx @ A_S.T + du @ B_S.T, atol=1e-12)
    ctrl = C3(model, 4, Q=np.ones(n_x), R=np.ones(n_u))
    assert ctrl.target_mode == [0]
    np.testing.assert_allclose(ctrl.QN, dare(A_S, B_S, np.eye(n_x), np.eye(n_u)), rtol=1e-10)
    assert not np.allclose(ctrl.QN, dare(m["A"], m["B"], np.eye(n_x), np.eye(n_u)), rtol=1e-3)


def test_default_projection_metric_weighs_u_where_it_enters_the_complementarity(cartpole):
    rng = np.random.default_rng(6)
    with_E = lcs_cvx.LCS.from_matrices(A=np.eye(3) + 0.05 * rng.standard_normal((3, 3)), B=rng.standard_normal((3, 1)),
                                       C=rng.standard_normal((3, 2)), d=np.zeros(3), D=rng.standard_normal((2, 3)),
                                       E=rng.standard_normal((2, 1)), F=np.eye(2), c=np.ones(2))
    U_free = np.diagonal(C3(cartpole.model, 3, Q=np.ones(4), R=np.ones(1), projection="qp").U[0])
    U_with = np.diagonal(C3(with_E, 3, Q=np.ones(3), R=np.ones(1), projection="qp").U[0])
    assert U_free[-1] == 0.0 and U_with[-1] == 1000.0


def test_warm_start_from_a_given_delta(cartpole):
    ctrl = controller(cartpole, "c3+")
    plan = ctrl.solve(cartpole.x0)
    again = ctrl.solve(cartpole.x0, warm_start=plan.delta)  # the converged delta, unshifted
    assert float(again.primal_residual[0]) < float(plan.primal_residual[0])
    with pytest.raises(lcs_cvx.LCSInputError, match=r"warm_start: expected a Plan or a finite delta of shape \(5, 9\)"):
        ctrl.solve(cartpole.x0, warm_start=np.zeros((4, 9)))


def test_a_plan_carries_the_models_own_rollout_its_gap_and_cost(cartpole):
    """x_model is eq. (1) stepped with the LCP's forces under the plan's inputs (LCS.step), gap
    its largest distance to the planned states, cost the horizon cost of that rollout."""
    P = cartpole
    ctrl = controller(P, "c3+")
    plan = ctrl.solve(P.x0)
    x = torch.as_tensor(P.x0)[None]
    states = [x[0]]
    for k in range(P.horizon):
        x = P.model.step(x, plan.u[k][None]).detach()
        states.append(x[0])
    rollout = torch.stack(states)
    assert torch.allclose(plan.x_model, rollout, rtol=0, atol=1e-12)
    assert float(plan.gap) == pytest.approx(float((rollout - plan.x).abs().max()), rel=1e-12)
    Q, R, QN = np.diag(P.Q), np.diag(P.R), ctrl.QN
    xs, us = rollout.numpy(), plan.u.numpy()
    cost = sum(xs[k] @ Q @ xs[k] + us[k] @ R @ us[k] for k in range(P.horizon)) + xs[-1] @ QN @ xs[-1]
    assert float(plan.cost) == pytest.approx(cost, rel=1e-12)
    assert plan.projection == "c3+"


def test_auto_applies_the_plan_whose_model_rollout_costs_less():
    """Per initial state, "auto" returns the "c3+" or the "lcp" plan, whichever the model's own
    rollout says costs less (the same ADMM as each projection alone)."""
    model = learned_like(seed=1)
    X0 = torch.tensor(np.random.default_rng(0).uniform(-1, 1, (8, 4)))
    kw = dict(Q=np.ones(4), R=np.ones(1), gap_tol=None, polish=0)
    auto = C3(model, 6, projection="auto", **kw).solve(X0)
    each = {p: C3(model, 6, projection=p, **kw).solve(X0) for p in ("c3+", "lcp")}
    assert set(auto.projection) == {"c3+", "lcp"}  # both win somewhere on this model
    for b in range(8):
        best = min(each, key=lambda p: float(each[p].cost[b]))
        assert auto.projection[b] == best
        for name in ("u", "x", "x_model", "lam", "delta"):
            assert torch.allclose(getattr(auto, name)[b], getattr(each[best], name)[b], rtol=0, atol=1e-12), name


def test_the_lcp_projection_plans_forces_the_model_produces():
    """On a model with a learned model's traits, the per-unit "c3+" projection plans states the
    model does not reach (a PlanGapWarning, counted); "lcp" plans ones it does (no warning)."""
    model = learned_like(seed=1)
    x0 = np.array([1.0, -1.0, 0.5, 0.5])
    kw = dict(Q=np.ones(4), R=0.1 * np.ones(1), gap_tol=0.1, polish=0)  # the gap is 0.2 of the states' scale
    per_unit = C3(model, 8, projection="c3+", **kw)
    with pytest.warns(lcs_cvx.PlanGapWarning, match="disagree with the model"):
        plan = per_unit.solve(x0)
    assert per_unit.gap_warnings == 1
    own = C3(model, 8, projection="lcp", **kw).solve(x0)  # the suite turns a warning into an error
    assert float(own.gap) < 0.2 * float(plan.gap)
    assert float(own.complementarity) < float(plan.complementarity)


def test_gap_tol_is_checked():
    model = learned_like()
    with pytest.raises(lcs_cvx.LCSInputError, match="gap_tol: expected a finite number > 0"):
        C3(model, 3, Q=np.ones(4), R=np.ones(1), gap_tol=-1.0)
    with pytest.raises(lcs_cvx.LCSInputError, match="projection: expected one of"):
        C3(model, 3, Q=np.ones(4), R=np.ones(1), projection="lcp+")


@pytest.mark.parametrize("projection", ["c3+", "auto"])
def test_bounded_inputs_on_the_fast_path_plan_as_the_declared_problem(cartpole, projection):
    """C3's cart-pole with |u| bounded at 60 % of its unbounded peak: the fast path (no CVXPY)
    plans what the declared CVXPY problem plans, to 1e-6, and meets the bound."""
    P = cartpole
    peak = float(controller(P, "c3+").solve(P.x0).u.abs().max())
    bound = (-0.6 * peak, 0.6 * peak)
    fast = controller(P, projection, u_bounds=bound)
    slow = controller(P, projection, u_bounds=bound, qp_path="cvxpy")
    assert fast.qp.path == "fast"
    for x0 in (P.x0, np.array([0.3, 0.2, -0.4, 0.6])):
        a, b = fast.solve(x0), slow.solve(x0)
        assert float(a.u.abs().max()) <= 0.6 * peak + 1e-9
        for name in ("x", "u", "lam"):
            assert torch.allclose(getattr(a, name), getattr(b, name), rtol=0, atol=1e-6), name


def test_penalize_input_change_measures_the_inputs_from_the_previous_plan(cartpole):
    """With penalize_input_change the input cost is (u_k - u_ref_k)^T R (u_k - u_ref_k): a large R
    pins the plan to the reference (the previous plan shifted by one step, as ctrl(x) uses it);
    without the option a reference is ignored."""
    P = cartpole
    x0 = np.array([0.1, -0.2, 0.2, -0.1])
    ref = np.linspace(-1.0, 1.0, P.horizon)[:, None]
    G, U = P.weights["c3+"]
    pinned = C3(P.model, P.horizon, Q=P.Q, R=[1e6], QN=np.diag(P.Q), G=G, U=U, penalize_input_change=True,
                gap_tol=None)
    assert torch.allclose(pinned.solve(x0, u_ref=ref).u, torch.as_tensor(ref), atol=1e-3)
    plain = controller(P, "auto")
    assert torch.equal(plain.solve(x0, u_ref=ref).u, plain.solve(x0).u)
    ctrl = controller(P, "auto", penalize_input_change=True)
    ctrl(x0)
    first = ctrl.last_plan
    shifted = torch.cat([first.u[1:], first.u[-1:]])
    x1 = P.model.step(x0, first.u[0].numpy()).detach()
    assert torch.equal(ctrl.solve(x1, warm_start=first, u_ref=shifted.numpy()).u,
                       ctrl.solve(x1, warm_start=first, u_ref=first).u)
    with pytest.raises(lcs_cvx.LCSInputError, match=r"u_ref: expected a Plan or finite inputs of shape \(5, 1\)"):
        ctrl.solve(x0, u_ref=np.zeros(3))


@pytest.mark.parametrize("projection", ["lcp", "c3+"])
@pytest.mark.parametrize("lam_bounds", [None, (0.0, 3.0)])
def test_scale_lcs_is_the_admm_on_the_rescaled_system(cartpole, projection, lam_bounds):
    """scale_lcs (DAIRLab/c3's): the ADMM on the system with lam = s lam_s, s = ||A_0|| / ||C_0||:
    the plans of C3 on that LCS written out by hand (C s; D, E, c divided by s; lam bounds
    divided by s), with lam returned in the model's units; off, s = 1."""
    P = cartpole
    M = P.model.to_matrices()
    X0 = torch.tensor(np.random.default_rng(3).uniform(-0.4, 0.4, (8, 4)))
    kw = {"Q": P.Q, "R": P.R, "projection": projection, "gap_tol": None}
    scaled = C3(P.model, P.horizon, scale_lcs=True, lam_bounds=lam_bounds, **kw)
    s = scaled.lam_scale
    assert s == pytest.approx(np.linalg.norm(M["A"]) / np.linalg.norm(M["C"]), rel=1e-15)
    assert C3(P.model, P.horizon, **kw).lam_scale == 1.0
    by_hand = lcs_cvx.LCS.from_matrices(**{**M, "C": M["C"] * s, "D": M["D"] / s, "E": M["E"] / s, "c": M["c"] / s})
    hand = C3(by_hand, P.horizon, lam_bounds=None if lam_bounds is None else (0.0, 3.0 / s), **kw)
    a, b = scaled.solve(X0), hand.solve(X0)
    assert torch.allclose(a.u, b.u, rtol=0, atol=1e-12)
    assert torch.allclose(a.lam, s * b.lam, rtol=1e-12, atol=1e-12)
    assert torch.allclose(a.x, b.x, rtol=0, atol=1e-12) and torch.allclose(a.x_model, b.x_model, rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------- the polish

def polish_pair(model, horizon=6, **kw):
    """The same C3 without and with the polish (the default's 3 mode-fixed QPs)."""
    kw = dict(dict(Q=np.ones(model.n_x), R=np.ones(model.n_u), gap_tol=None), **kw)
    return C3(model, horizon, polish=0, **kw), C3(model, horizon, **kw)


@pytest.mark.parametrize("u_bounds", [None, (-0.5, 0.5)])
def test_the_polish_never_raises_the_cost_of_the_plan_applied(u_bounds):
    """Per initial state the polished plan's model rollout costs at most the ADMM's (and less
    where it was polished); with bounds its inputs meet them."""
    model = learned_like(seed=1)
    X0 = torch.tensor(np.random.default_rng(0).uniform(-1, 1, (16, 4)))
    plain, polished = polish_pair(model, u_bounds=u_bounds)
    a, b = plain.solve(X0), polished.solve(X0)
    assert bool(b.polished.any())
    assert bool((b.cost <= a.cost + 1e-12 * (1 + a.cost.abs())).all())
    assert bool((b.cost[b.polished] < a.cost[b.polished]).all())
    assert torch.equal(b.u[~b.polished], a.u[~b.polished])
    if u_bounds is not None:
        assert float(b.u.abs().max()) <= 0.5 + 1e-9


def test_a_polished_plan_is_the_models_own_rollout():
    """Where polished, the plan's states are the model's rollout of its inputs (gap 0) and its
    forces the model's LCP solutions (complementary)."""
    model = learned_like(seed=2)
    X0 = torch.tensor(np.random.default_rng(1).uniform(-1, 1, (8, 4)))
    plan = polish_pair(model)[1].solve(X0)
    done = plan.polished
    assert bool(done.any())
    assert torch.allclose(plan.x[done], plan.x_model[done], rtol=0, atol=1e-12)
    assert float(plan.gap[done].max()) <= 1e-12
    assert float(plan.complementarity[done].max()) <= 1e-9
    for b in torch.flatten(done.nonzero()).tolist():
        lam = model.solve_lcp(plan.x[b, :-1], plan.u[b]).lam.detach()
        assert torch.allclose(plan.lam[b], lam, rtol=0, atol=1e-10)


@pytest.mark.parametrize("bounded", [False, True])
def test_the_mode_fixed_qp_is_the_declared_problem(bounded):
    """The polish's QP in the modes of a rollout (the kernel: condensed, solved exactly, by
    active sets within the bounds) against the same problem declared in CVXPY with lam as
    variables, the active units' eta = 0 and the others' lam = 0 (Clarabel): 1e-6."""
    import cvxpy as cp

    from lcs_cvx._kernels.arrays import array_ops
    from lcs_cvx._kernels.c3 import model_rollout
    from lcs_cvx._kernels.polish import _condensed, _minimise, mode_dynamics

    model = learned_like(seed=3)
    m = {k: np.asarray(v) for k, v in model.to_matrices().items()}
    N, n_x, n_u, n_lam = 5, 4, 1, 3
    mats = {k: np.repeat(m[k][None], N, 0) for k in "ABCdDEFc"}
    rng = np.random.default_rng(4)
    x0, u0 = rng.uniform(-1, 1, (2, n_x)), rng.uniform(-1, 1, (2, N, n_u))
    xd, u_ref = rng.uniform(-0.5, 0.5, (2, N + 1, n_x)), np.zeros((2, N, n_u))
    Q, R = np.repeat(np.diag([1.0, 2.0, 0.5, 1.0])[None], N, 0), np.repeat(np.eye(1)[None], N, 0)
    QN = 3 * Q[0]
    xp = array_ops(torch.zeros(1))

    def lcp(k, q):
        return lcs_cvx.solve_lcp(mats["F"][k], q).lam.numpy()

    lams = []
    model_rollout(x0, u0, mats, lcp, lams)
    active = np.stack(lams, 1) > 0
    assert active.any() and not active.all()
    At, Bt, dt, singular = mode_dynamics(xp, mats, active)
    H, f = _condensed(xp, x0, At, Bt, dt, xd, u_ref, Q, R, QN)
    lo, hi = (np.full(N * n_u, -0.3), np.full(N * n_u, 0.3)) if bounded else (None, None)
    U, failed = _minimise(xp, H, f, lo, hi)
    assert not singular.any() and not failed.any()
    for b in range(2):
        x, u, lam = cp.Variable((N + 1, n_x)), cp.Variable((N, n_u)), cp.Variable((N, n_lam))
        cons, cost = [x[0] == x0[b]], 0
        for k in range(N):
            a = active[b, k]
            eta = m["D"] @ x[k] + m["E"] @ u[k] + m["F"] @ lam[k] + m["c"]
            cons += [x[k + 1] == m["A"] @ x[k] + m["B"] @ u[k] + m["C"] @ lam[k] + m["d"]]
            cons += [eta[i] == 0 if a[i] else lam[k, i] == 0 for i in range(n_lam)]
            if bounded:
                cons += [cp.abs(u[k]) <= 0.3]
            cost += cp.quad_form(x[k] - xd[b, k], Q[k]) + cp.quad_form(u[k], R[k])
        cost += cp.quad_form(x[N] - xd[b, N], QN)
        cp.Problem(cp.Minimize(cost), cons).solve(solver=cp.CLARABEL)
        assert np.allclose(U[b], u.value.ravel(), rtol=0, atol=1e-6)
    if bounded:
        assert np.isclose(np.abs(U).max(), 0.3)  # a bound is active


def test_the_polish_plans_alike_on_both_back_ends_and_batched():
    """NumPy and torch back-ends, and a batch against its members one by one, to round-off."""
    model = learned_like(seed=1)
    X0 = torch.tensor(np.random.default_rng(2).uniform(-1, 1, (6, 4)))
    ctrl = polish_pair(model)[1]
    on_torch = polish_pair(model, arrays="torch")[1]
    a, b = ctrl.solve(X0), on_torch.solve(X0)
    assert torch.equal(a.polished, b.polished)
    assert torch.allclose(a.u, b.u, rtol=0, atol=1e-10)
    for i in range(6):
        one = ctrl.solve(X0[i])
        assert bool(one.polished) == bool(a.polished[i])
        assert torch.allclose(one.u, a.u[i], rtol=0, atol=1e-10)


def test_a_polished_plan_keeps_the_model_within_the_state_bounds():
    """With x_bounds, a polished plan is applied only where the model's rollout meets them."""
    model = learned_like(seed=1)
    X0 = torch.tensor(np.random.default_rng(0).uniform(-1, 1, (16, 4)))
    free = polish_pair(model)[1].solve(X0)
    hi = np.full(4, np.inf)
    hi[0] = float(np.median(free.x_model[free.polished][:, 1:, 0].amax(1).numpy()))
    bounded = polish_pair(model, x_bounds=(-np.inf, hi))[1].solve(X0)
    assert 0 < int(bounded.polished.sum()) < int(free.polished.sum())
    assert float(bounded.x_model[bounded.polished][:, 1:, 0].max()) <= hi[0] + 1e-9


@pytest.mark.parametrize("value", [-1, 1.5, True, "3"])
def test_polish_is_checked(value):
    with pytest.raises(lcs_cvx.LCSInputError, match="polish: expected a number of mode-fixed QPs"):
        C3(learned_like(), 3, Q=np.ones(4), R=np.ones(1), polish=value)


def test_the_polish_does_not_read_uninitialised_memory():
    """A solve after memory full of NaN was freed plans as before (the condensed QP's arrays
    start from zeros, not from whatever memory NumPy hands out)."""
    model = learned_like(seed=1)
    X0 = torch.tensor(np.random.default_rng(0).uniform(-1, 1, (4, 4)))
    ctrl = polish_pair(model, horizon=6)[1]
    first = ctrl.solve(X0)
    for size in (6 * 6, 4 * 6 * 6, 4 * 4 * 6, 4 * 6):  # the sizes of the kernel's arrays
        junk = [np.full(size, np.nan) for _ in range(64)]
        del junk
        again = ctrl.solve(X0)
        assert torch.equal(again.polished, first.polished)
        assert torch.equal(again.u, first.u)
