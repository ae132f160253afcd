"""The cvxpylayers paths (:mod:`lcs_cvx.layers`): diffcp over the declared problems (P) and (V),
with Clarabel (``solver="cvxpylayers"``) or SCS (``"cvxpylayers-scs"``) as the cone solver.

Their answers are compared with the fast path, which is certified exact (``test_violation.py``),
in the paper's and a stiff setting; where Clarabel falls short the bound is measured and stated,
and the layer's inaccuracy must be reported (:class:`lcs_cvx.LayerAccuracyWarning`), never
silent. The layers' gradients against the closed forms are in ``test_losses.py``. Layer batches
stay at 10-20 samples (the layer solves a few hundred samples per second).
"""

from __future__ import annotations

import functools
import math
import warnings

import pytest
import torch
from helpers import (
    CASES,
    N_LAMS,
    SETTINGS,
    autograd,
    certified_violation_solution,
    lcp_terms,
    make_problem,
    rel_err,
    violation_case,
    violation_objective,
)

import lcs_cvx
from lcs_cvx import prediction_loss_info, violation_loss_info
from lcs_cvx.layers import lcp_layer, solve_layer
from lcs_cvx.lcp import solve_lcp_brute
from lcs_cvx.system import PARAMETER_NAMES
from lcs_cvx.violation import violation_kkt_residual

F64 = torch.float64


@functools.cache
def layer_case(n_lam, setting):
    """The cvxpylayers (diffcp + Clarabel) answer on :func:`helpers.violation_case`'s batch,
    compared with the fast one; computed once per (n_lam, setting)."""
    model, data, gamma, eps, values, info_f = violation_case(n_lam, setting)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", lcs_cvx.LayerAccuracyWarning)
        info_l = violation_loss_info(model, data.x, data.u, data.x_next, gamma=gamma, eps=eps,
                                     solver="cvxpylayers")
    loss_f, loss_l = float(info_f.loss.detach()), float(info_l.loss.detach())
    scale = 1.0 + info_f.lam.abs().amax(-1)

    def dev(a, b):  # per-sample |a - b|_inf relative to 1 + |lam|_inf, worst sample
        return float(((a - b).abs().amax(-1) / scale).max())

    obj_f = violation_objective(model, data, info_f.lam, info_f.phi, gamma, eps)
    obj_l = violation_objective(model, data, info_l.lam, info_l.phi, gamma, eps)
    return {
        "layer_lam": dev(info_l.lam, info_f.lam),
        "layer_lam_abs": float((info_l.lam - info_f.lam).abs().max()),
        "layer_phi": dev(info_l.phi, info_f.phi),
        "layer_loss": abs(loss_l - loss_f) / abs(loss_f),
        "kkt_fast": float(violation_kkt_residual(values, info_f.lam).max()),
        "kkt_layer": float(violation_kkt_residual(values, info_l.lam).max()),
        # per sample; >= 0 iff the fast point is the better minimiser of the paper's objective
        "excess": (obj_l - obj_f) / (1.0 + obj_f.abs()),
        "warned": any(issubclass(w.category, lcs_cvx.LayerAccuracyWarning) for w in caught),
        "max_residual": info_l.max_residual,
    }


#: Honest bounds for the cvxpylayers (diffcp + Clarabel) path against the certified fast
#: solution, |d lam|_inf / (1 + |lam|_inf), worst of 20 samples. Clarabel reaches the QP
#: reference's accuracy neither with lcs_cvx.layers.LAYER_SOLVERS as shipped (tolerances 1e-10)
#: nor with any setting tried (iterative refinement, equilibration off, regularisation,
#: presolve off, KKT solver): it ends on "AlmostSolved"/"NumericalError" for most samples,
#: which diffcp passes on without an error. Measured (lam, relative):
#:   paper (n = 1, 4, 10, 20): 1.8e-7, 4.2e-8, 1.2e-7, 5.8e-8 (absolute 2.3e-7 .. 4.8e-7);
#:          phi <= 1.3e-7; loss 2e-10 .. 1.2e-8 relative
#:   stiff: 1.6e-5, 9.0e-9, 3.6e-5, 7.0e-8 (absolute 5.4e-4, 1.4e-8, 1.8e-4, 4.7e-7); phi <= 1.4e-4;
#:          the loss is off by a factor 3.7e2, 0.17, 3.5e3, 4.0 (the loss at the truth is ~3e-4
#:          and 1/(eps gamma) = 1e10 amplifies the error in lam) -- not bounded, only its sign:
#:          the layer's point is never the better minimiser.
LAYER_BOUND = {
    "paper": {"lam": 1e-6, "phi": 1e-6, "loss": 1e-7},
    "stiff": {"lam": 1e-4, "phi": 1e-3},
}


@pytest.mark.parametrize("n_lam, setting", CASES)
def test_cvxpylayers_violation_path_agrees_with_fast(n_lam, setting):
    res = layer_case(n_lam, setting)
    bound = LAYER_BOUND[setting]
    assert res["layer_lam"] <= bound["lam"], res["layer_lam"]
    assert res["layer_phi"] <= bound["phi"], res["layer_phi"]
    if "loss" in bound:
        assert res["layer_loss"] <= bound["loss"], res["layer_loss"]
    # Which side is accurate: the fast point is never the worse minimiser of the paper's
    # objective, and its KKT residual is the smaller one.
    assert float(res["excess"].min()) >= -1e-12
    assert res["kkt_fast"] <= res["kkt_layer"]
    # an inaccurate layer solution is said (LayerAccuracyWarning), an accurate one is not
    assert res["max_residual"] == pytest.approx(res["kkt_layer"], rel=1e-12)
    assert res["warned"] == (res["kkt_layer"] > lcs_cvx.losses.LAYER_RESIDUAL_TOL)


@pytest.mark.xfail(
    strict=True,
    reason="Clarabel through diffcp's cone form reaches ~1e-7 on lam in the paper setting and "
    "up to ~5e-4 (absolute) in the stiff one, not 1e-8; see LAYER_BOUND",
)
def test_cvxpylayers_path_meets_the_1e8_requirement():
    worst = max(layer_case(n, s)["layer_lam_abs"] for n, s in CASES)
    assert worst <= 1e-8, worst


@pytest.mark.parametrize("n_lam", N_LAMS)
def test_fast_exact_where_the_layer_breaks_down(n_lam):
    """gamma = 1e-6, eps = 1e-4 at a model on the edge of Lemma 2: G with a zero column makes
    G G^T singular, so sigma_min(F + F^T) = 2 s = 1e-5 = 10 gamma exactly.

    The fast solution is still certified exact (measured <= 6e-11 absolute with |lam| up to
    1.9e5), and so close is the Clarabel reference (measured <= 1.1e-5 absolute). The
    cvxpylayers path returns whatever Clarabel ended on -- mostly "AlmostSolved" or
    "NumericalError", passed on by diffcp without an error -- measured |d lam| = 8.6e4 (n = 1,
    |lam| = 1.9e5), 0.45, 4.8e-4, 0.13 for n = 1, 4, 10, 20, and a loss up to 3x too large.
    Asserted of the layer: only that its point is never the better minimiser.
    """
    gamma, eps = 1e-6, 1e-4
    truth = lcs_cvx.random_lcs(6, 2, n_lam, stiffness=0.5, seed=n_lam)
    data = lcs_cvx.make_dataset(truth, 20, noise=0.01, seed=100 + n_lam)
    model = lcs_cvx.random_lcs(6, 2, n_lam, stiffness=5e-6, seed=50 + n_lam)
    with torch.no_grad():
        model.G[:, -1] = 0.0
    model.requires_grad_(True)
    assert model.sigma_min == pytest.approx(10 * gamma, rel=1e-6)
    info = violation_loss_info(model, data.x, data.u, data.x_next, gamma=gamma, eps=eps)
    assert info.n_fallback == 0 and info.max_residual <= 1e-13
    lam_x, phi_x, certified = certified_violation_solution(
        model, data, info.lam, info.phi, gamma, eps
    )
    assert bool(certified.all())
    scale = 1.0 + info.lam.abs().amax(-1)
    assert float(((info.lam - lam_x).abs().amax(-1) / scale).max()) <= 1e-12
    assert float(((info.phi - phi_x).abs().amax(-1) / scale).max()) <= 1e-12
    # the layer's inaccuracy is not silent: its KKT residual is checked and reported
    with pytest.warns(lcs_cvx.LayerAccuracyWarning, match="KKT residual"):
        info_l = violation_loss_info(model, data.x, data.u, data.x_next, gamma=gamma, eps=eps,
                                     solver="cvxpylayers")
    assert info_l.max_residual > lcs_cvx.losses.LAYER_RESIDUAL_TOL
    obj_f = violation_objective(model, data, info.lam, info.phi, gamma, eps)
    obj_l = violation_objective(model, data, info_l.lam, info_l.phi, gamma, eps)
    assert bool((obj_l >= obj_f - 1e-12 * (1.0 + obj_f.abs())).all())


@pytest.mark.parametrize("n_lam", N_LAMS)
@pytest.mark.parametrize("setting", list(SETTINGS))
def test_prediction_paths_agree(n_lam, setting):
    """LossInfo.lam of the prediction loss: fast == brute-force enumeration (the same
    active-set solve, measured 0 difference) for n_lam <= 10; fast vs the cvxpylayers path of
    (P): measured relative <= 7.5e-9 (paper; loss <= 1e-10), <= 3.1e-7 (stiff; absolute 8e-4 at
    n = 1 where |lam| = 3.5e3; loss <= 1.6e-3)."""
    _, _, stiffness = SETTINGS[setting]
    truth = lcs_cvx.random_lcs(6, 2, n_lam, stiffness=stiffness, seed=n_lam)
    data = lcs_cvx.make_dataset(truth, 20, noise=0.01, seed=100 + n_lam)
    model = truth if setting == "stiff" else lcs_cvx.LCS(6, 2, n_lam, stiffness=1.0, init_scale=0.3,
                                                         seed=n_lam)
    with torch.no_grad():
        info_f = prediction_loss_info(model, data.x, data.u, data.x_next)
        info_l = prediction_loss_info(model, data.x, data.u, data.x_next, solver="cvxpylayers")
    loss_f, loss_l = float(info_f.loss), float(info_l.loss)
    scale = 1.0 + info_f.lam.abs().amax(-1)
    if n_lam <= 10:
        q, _ = lcp_terms(model, data)
        brute = solve_lcp_brute(model.F.detach(), q)
        assert float(((brute.lam - info_f.lam).abs().amax(-1) / scale).max()) <= 1e-12
    layer = float(((info_l.lam - info_f.lam).abs().amax(-1) / scale).max())
    assert layer <= (1e-7 if setting == "paper" else 1e-5), layer
    assert abs(loss_l - loss_f) <= (1e-8 if setting == "paper" else 1e-2) * abs(loss_f)
    assert info_f.n_fallback == 0 and info_f.max_residual <= 1e-13


def test_scs_path_runs_and_agrees_loosely():
    """diffcp + SCS (eps 1e-10, 1e5 iterations). A first-order method, so only a loose
    tolerance is promised: 1e-6 relative on lam, loss and gradients. Measured here: lam
    <= 3e-11, loss <= 7e-12, gradients <= 5e-9 (violation) and <= 4e-11 (prediction)."""
    model, data = make_problem(n=10)
    for info_fn, kw in ((violation_loss_info, {"gamma": 1e-2, "eps": 1e-2}), (prediction_loss_info, {})):
        lf, info_f, gf = autograd(info_fn, model, data, **kw)
        ls, info_s, gs = autograd(info_fn, model, data, solver="cvxpylayers-scs", **kw)
        assert math.isfinite(ls)
        assert info_s.iterations == 0 and info_s.n_fallback == 0
        assert abs(ls - lf) <= 1e-6 * abs(lf)
        assert float((info_s.lam - info_f.lam).abs().max()) <= 1e-6 * (
            1 + float(info_f.lam.abs().max())
        )
        for name in PARAMETER_NAMES:
            assert rel_err(gs[name], gf[name]) <= 1e-6, (info_fn.__name__, name)


def test_unknown_cone_solver_raises_naming_it():
    values = lcs_cvx.convex_lcp_problem(2).parameter_values(
        torch.eye(2, dtype=F64), torch.zeros(1, 2, dtype=F64))
    with pytest.raises(lcs_cvx.LCSInputError, match=r"cone_solver: expected one of \['clarabel', 'scs'\], received 'ecos'"):
        solve_layer(lcp_layer(2), [values[k] for k in ("R", "F", "q")], cone_solver="ecos")
