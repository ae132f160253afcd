"""C3's compiled path (lcs_cvx.control.compiled_path): the whole solve of float64 CPU states in
one compiled call plans what the array kernels plan (arrays="numpy"), to 1e-10, on models with a
learned model's traits (dense F, E not zero), bounded and unbounded, with and without the polish,
one state and a batch; it is taken where it applies, and left to the array kernels elsewhere."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from helpers import learned_like as _learned_like

import lcs_cvx
import lcs_cvx.control.c3 as c3_module
from lcs_cvx.control import C3, c3_cartpole


def learned_like(seed=0):
    """:func:`helpers.learned_like` with two inputs and a skew-symmetric part in ``F``."""
    return _learned_like(seed, n_u=2, skew=0.3)


FIELDS = ("x", "u", "lam", "delta", "x_model", "lam_model", "primal_residual", "dual_residual",
          "complementarity", "gap")


def pair(model, horizon, **kw):
    """The same controller on the compiled path and on the array kernels."""
    one = model[0] if isinstance(model, list) else model
    kw = dict(dict(Q=np.ones(one.n_x), R=np.ones(one.n_u), gap_tol=None), **kw)
    fast, arrays = C3(model, horizon, **kw), C3(model, horizon, arrays="numpy", **kw)
    assert fast._compiled is not None and arrays._compiled is None
    return fast, arrays


def assert_same(a, b, tol=1e-10):
    for name in FIELDS:
        va, vb = getattr(a, name), getattr(b, name)
        assert va.shape == vb.shape, name
        assert torch.allclose(va, vb, rtol=0, atol=tol * (1 + float(vb.abs().max()))), name
    assert torch.allclose(a.cost, b.cost, rtol=tol, atol=tol), "cost"
    assert torch.equal(a.polished, b.polished)
    assert a.projection == b.projection
    assert a.qp_failures == b.qp_failures


CASES = {
    "defaults": {},
    "no polish": {"polish": 0},
    "u bounded": {"u_bounds": (-0.4, 0.4)},
    "u bounded, no polish": {"u_bounds": (-0.4, 0.4), "polish": 0},
    "x and lam bounded": {"x_bounds": (-1.5, 1.5), "lam_bounds": (0.0, 2.0), "u_bounds": (-1.0, 1.0)},
    "c3+": {"projection": "c3+"},
    "lcp, polish 5": {"projection": "lcp", "polish": 5},
    "fix_lam0, scale_lcs": {"fix_lam0": True, "scale_lcs": True},
    "x_des, rho_scale": {"x_des": np.array([0.3, -0.2, 0.0, 0.1]), "rho_scale": 1.5, "admm_iterations": 7},
}


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("seed", [1, 4])
def test_the_compiled_path_plans_as_the_array_kernels(case, seed):
    model = learned_like(seed)
    fast, arrays = pair(model, 6, **CASES[case])
    X0 = np.random.default_rng(seed).uniform(-1, 1, (12, 4))
    batch_fast, batch_arrays = fast.solve(torch.tensor(X0)), arrays.solve(torch.tensor(X0))
    assert_same(batch_fast, batch_arrays)
    for x0 in X0[:6]:
        one = fast.solve(x0)
        assert one.u.shape == (6, 2) and one.cost.shape == () and isinstance(one.projection, str)
        assert_same(one, arrays.solve(x0))


def test_the_compiled_path_plans_c3s_cartpole_as_the_array_kernels():
    """C3's cart-pole (E = 0: lam_0 fixed) with its defaults, unbounded and bounded."""
    P = c3_cartpole()
    G, U = P.weights["c3+"]
    X0 = np.concatenate([P.x0[None], np.random.default_rng(0).uniform(-0.6, 0.6, (10, 4))])
    for kw in ({}, {"u_bounds": (-2.0, 2.0)}):
        fast, arrays = (C3(P.model, P.horizon, Q=P.Q, R=P.R, G=G, U=U, gap_tol=None, arrays=a, **kw)
                        for a in ("auto", "numpy"))
        assert fast.fix_lam0
        assert_same(fast.solve(torch.tensor(X0)), arrays.solve(torch.tensor(X0)))
        for x0 in X0:
            assert_same(fast.solve(x0), arrays.solve(x0))


def test_warm_starts_input_references_and_a_time_varying_horizon_plan_alike():
    """ctrl(x) (warm-started from the previous plan, its inputs the reference of the input cost)
    in a closed loop, on a list of per-step models."""
    models = [learned_like(seed) for seed in (2, 3, 2, 5, 2)]
    fast, arrays = pair(models, 5, penalize_input_change=True)
    x_fast = x_arrays = np.array([0.5, -0.5, 0.3, 0.0])
    for _ in range(6):
        u_fast, u_arrays = fast(x_fast), arrays(x_arrays)
        assert torch.allclose(u_fast, u_arrays, rtol=0, atol=1e-10)
        assert_same(fast.last_plan, arrays.last_plan)
        x_fast = models[0].step(x_fast, u_fast.numpy()).detach().numpy()
        x_arrays = models[0].step(x_arrays, u_arrays.numpy()).detach().numpy()
    given = np.random.default_rng(0).uniform(-0.2, 0.2, (5, fast.layout.n_z))
    assert_same(fast.solve(x_fast, warm_start=given, u_ref=np.ones((5, 2))),
                arrays.solve(x_fast, warm_start=given, u_ref=np.ones((5, 2))))


def test_the_compiled_path_is_taken_where_it_applies(monkeypatch):
    """With the array kernels' ADMM and polish made to fail, float64 CPU states (a NumPy array, a
    tensor, a batch) still plan: the compiled path ran them."""
    model = learned_like(1)
    ctrls = [C3(model, 5, Q=np.ones(4), R=np.ones(2), gap_tol=None, **kw)
             for kw in ({}, {"u_bounds": (-0.5, 0.5)}, {"projection": "c3+"}, {"arrays": "compiled"})]

    def fail(*args, **kwargs):
        raise AssertionError("the array kernels ran")

    monkeypatch.setattr(c3_module, "admm", fail)
    monkeypatch.setattr(c3_module, "polish_plan", fail)
    x0 = np.array([0.2, -0.1, 0.4, 0.3])
    for ctrl in ctrls:
        assert ctrl._compiled is not None
        for arg in (x0, torch.tensor(x0), torch.tensor(np.stack([x0, -x0]))):
            assert ctrl.solve(arg).u.shape[-2:] == (5, 2)


def test_the_array_kernels_run_where_the_compiled_path_does_not_apply():
    model = learned_like(1)
    kw = dict(Q=np.ones(4), R=np.ones(2), gap_tol=None)
    for extra in ({"arrays": "numpy"}, {"arrays": "torch"}, {"qp_path": "cvxpy", "polish": 0},
                  {"projection": "qp", "polish": 0}):
        assert C3(model, 3, **extra, **kw)._compiled is None
    ctrl = C3(model, 3, **kw)
    # not float64 CPU states: the array path, its checks and its messages
    with pytest.raises(lcs_cvx.LCSInputError, match="expected dtype torch.float64"):
        ctrl.solve(torch.zeros(4, dtype=torch.float32))
    with pytest.raises(lcs_cvx.LCSInputError, match="x0: expected finite values"):
        ctrl.solve(np.array([0.0, np.nan, 0.0, 0.0]))
    with pytest.raises(lcs_cvx.LCSInputError, match=r"x0: expected shape \(N, 4\)"):
        ctrl.solve(np.zeros(3))
    plan = ctrl.solve([0.1, 0.2, 0.3, 0.4])  # a list: converted by the array path
    assert_same(plan, ctrl.solve(np.array([0.1, 0.2, 0.3, 0.4])))


def test_a_solve_the_compiled_path_cannot_finish_runs_on_the_array_kernels(monkeypatch):
    """Where the kernel reports a solve it leaves to the array kernels (an LCP its pivoting does
    not solve, a singular mode system), the array kernels plan it, with their own fallbacks."""
    import lcs_cvx.control.compiled_path as compiled_path
    from lcs_cvx._kernels.c3_admm import FALLBACK

    model = learned_like(2)
    fast, arrays = pair(model, 4)
    monkeypatch.setattr(compiled_path, "solve_states", lambda *args: (0, FALLBACK))
    x0 = np.array([0.3, 0.1, -0.2, 0.5])
    assert_same(fast.solve(x0), arrays.solve(x0))


def test_the_compiled_path_warns_as_the_array_kernels_do():
    """The plan-gap check and the QP steps' fallback warn on the compiled path too."""
    model = learned_like(1)
    x0 = np.array([1.0, -1.0, 0.5, 0.5])
    ctrl = C3(model, 8, Q=np.ones(4), R=0.1 * np.ones(2), projection="c3+", gap_tol=1e-6, polish=0)
    assert ctrl._compiled is not None
    with pytest.warns(lcs_cvx.PlanGapWarning, match="disagree with the model"):
        ctrl.solve(x0)
    assert ctrl.gap_warnings == 1
    stuck = C3(model, 3, Q=np.ones(4), R=np.ones(2), x_bounds=(100.0, 101.0), u_bounds=(-1, 1),
               projection="c3+", gap_tol=None)
    with pytest.warns(lcs_cvx.FallbackWarning, match="QP step"):
        plan = stuck.solve(np.zeros(4))
    assert plan.qp_failures == stuck.admm_iterations + 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        C3(model, 3, Q=np.ones(4), R=np.ones(2), gap_tol=None).solve(x0)
