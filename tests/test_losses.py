"""The learning losses of :mod:`lcs_cvx.losses` against the paper's lemmas.

- Lemma 3, eq. (10): the gradient of the violation loss
  ``L_eps`` (eq. (9)) is the envelope gradient -- checked three ways: against the
  closed form written out here, central finite differences and the cvxpylayers (diffcp +
  Clarabel) path.
- Lemma 1: the prediction loss ``L_pred`` (eq. (6)) is differentiable
  under strict complementarity -- against autograd through the active-set map (the closed
  form), finite differences and the cvxpylayers path of (P).
- Lemma 5: ``L_eps -> L_pred`` as ``eps -> 0``, with ``L_eps <= L_pred``.
- Input checks, the regulariser, devices and array back-ends, :class:`lcs_cvx.LossInfo` (also of
  the trainer's fast paths) and warm starts.

The solvers behind the losses are tested in ``test_violation.py``, ``test_zoo.py`` and
``test_layers.py``. The library's losses are batch MEANS (the paper writes sums), so every
closed form here is a mean. Everything is float64 on one torch thread; cvxpylayers batches stay
at 10-20 samples (the layer solves a few hundred samples per second).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from helpers import (
    autograd,
    lcp_terms,
    lemma3_gradients,
    make_problem,
    rel_err,
    violation_objective,
)

import lcs_cvx
from lcs_cvx import (
    LCSInputError,
    prediction_loss,
    prediction_loss_info,
    regularizer,
    violation_loss,
    violation_loss_info,
)
from lcs_cvx.lcp import active_set_solve
from lcs_cvx.losses import prediction_fast, violation_fast
from lcs_cvx.system import PARAMETER_NAMES

torch.set_num_threads(1)

F64 = torch.float64

#: Central-difference step on every parameter entry. Losses are O(1e2) here, so the round-off
#: of a difference quotient is ~1e-16 * 1e2 / 1e-6 = 1e-8 and the O(h^2) truncation ~1e-12:
#: measured |fd - autograd| / (1 + |autograd|) <= 3e-8 (violation and prediction loss).
FD_STEP = 1e-6
FD_TOL = 1e-6


# -- Lemma 3: envelope gradients of the violation loss --------------------------------------


@pytest.mark.parametrize(
    "model_kind, n_lam, gamma, eps",
    [
        ("init", 3, 1e-2, 1e-1),
        ("init", 3, 1e-2, 1e-4),
        ("perturbed", 3, 1e-2, 1e-2),
        ("perturbed", 6, 0.5, 1e-3),
    ],
)
def test_violation_gradient_is_lemma3_closed_form(model_kind, n_lam, gamma, eps):
    model, data = make_problem(n_lam=n_lam, model=model_kind, seed=n_lam)
    assert gamma < model.sigma_min
    _, info, g = autograd(violation_loss_info, model, data, gamma=gamma, eps=eps)
    closed = lemma3_gradients(model, data, info.lam, info.phi, gamma, eps)
    scale = lemma3_gradients(model, data, info.lam, info.phi, gamma, eps, magnitude=True)
    for name in PARAMETER_NAMES:
        assert g[name].shape == closed[name].shape
        # The same expressions in another association and BLAS (the loss evaluates them in
        # NumPy): agreement to round-off, ~u = 1.1e-16 times the magnitude of their terms,
        # which 1/(eps gamma) = 1e6 makes large against the gradient. Measured <= 1.6e-16.
        err = (g[name] - closed[name]).abs() / scale[name].clamp(min=1e-300)
        assert float(err.max()) <= 1e-14, name
    # not vacuous: both the dynamics and the complementarity parts carry gradient
    assert float(closed["A"].abs().max()) > 1e-3 and float(closed["D"].abs().max()) > 1e-3


def _pattern_violation(info):
    return torch.cat([info.lam > 0, info.phi > 0], dim=-1)


def _pattern_prediction(info):
    return info.lam > 0


def finite_difference_check(info_fn, model, data, pattern, **kw):
    """Central differences of the loss VALUE on every entry of every parameter.

    Asserts that the active-set pattern of the solution is the same at ``theta +- h`` as at
    ``theta`` (the loss is smooth there, Lemmas 1 and 3) and returns the worst
    ``|fd - autograd| / (1 + |autograd|)`` per parameter.
    """
    _, info0, g = autograd(info_fn, model, data, **kw)
    base = pattern(info0)
    worst = {}
    with torch.no_grad():
        for name in PARAMETER_NAMES:
            p = getattr(model, name)
            fd = torch.zeros_like(p)
            for idx in np.ndindex(*p.shape):
                old = float(p[idx])
                vals = []
                for sign in (1.0, -1.0):
                    p[idx] = old + sign * FD_STEP
                    info = info_fn(model, data.x, data.u, data.x_next, **kw)
                    assert torch.equal(pattern(info), base), f"active set changed under {name}{idx}"
                    vals.append(float(info.loss))
                p[idx] = old
                fd[idx] = (vals[0] - vals[1]) / (2 * FD_STEP)
            worst[name] = float(((fd - g[name]).abs() / (1.0 + g[name].abs())).max())
    return worst


@pytest.mark.parametrize("model_kind", ["init", "perturbed"])
def test_violation_gradient_matches_finite_differences(model_kind):
    # eps = 0.1, gamma = 1e-2: 1/(eps gamma) = 1e3 keeps the loss mildly stiff, so h = 1e-6 is
    # in the flat part of the error curve (measured 2.3e-9 .. 3e-8 for h = 1e-5 .. 1e-6).
    model, data = make_problem(model=model_kind)
    worst = finite_difference_check(
        violation_loss_info, model, data, _pattern_violation, gamma=1e-2, eps=1e-1
    )
    assert set(worst) == set(PARAMETER_NAMES)
    for name, err in worst.items():
        assert err <= FD_TOL, (name, err)


def test_violation_gradient_matches_cvxpylayers_path():
    """Autograd through diffcp (dense mode, Clarabel) on (V) equals the envelope gradient.

    The layer path differentiates the solution map as well; at the optimum that part vanishes
    (envelope theorem), so the difference is driven by the layer's accuracy on ``lam``, which
    Clarabel through diffcp's second-order-cone form leaves at ~1e-7 (see the agreement tests
    below). Measured per-parameter relative gradient error at eps = 1e-2: <= 2e-7 (D, E: 1e-7 ..
    2e-7; G, c: 3e-8 .. 4e-8; A, B, C, d, H: <= 1e-9); at eps = 1e-1: <= 3e-9. Asserted: 1e-6.
    (Before the (V) declaration was scaled by eps and the layer's Clarabel tolerances tightened
    to 1e-10, ~1e-5 was seen at eps = 1e-2.)
    """
    model, data = make_problem(n=20)
    for eps in (1e-1, 1e-2):
        lf, info_f, gf = autograd(violation_loss_info, model, data, gamma=1e-2, eps=eps)
        ll, info_l, gl = autograd(
            violation_loss_info, model, data, gamma=1e-2, eps=eps, solver="cvxpylayers"
        )
        assert abs(ll - lf) <= 1e-8 * abs(lf)
        for name in PARAMETER_NAMES:
            assert rel_err(gl[name], gf[name]) <= 1e-6, (eps, name, rel_err(gl[name], gf[name]))


# -- Lemma 1: the prediction loss ----------------------------------------------------------


@pytest.mark.parametrize("model_kind", ["init", "perturbed"])
def test_prediction_gradient_matches_finite_differences(model_kind):
    model, data = make_problem(model=model_kind)
    _, info, _ = autograd(prediction_loss_info, model, data)
    # Lemma 1's hypothesis, strict complementarity, with a margin far above the FD step.
    lam, w = info.lam, info.w
    margin = torch.where(info.lam > 0, lam, w)
    assert float(margin.min()) > 1e-4
    assert bool((info.lam > 0).any()) and bool((info.lam == 0).any())  # both kinds of index occur
    worst = finite_difference_check(prediction_loss_info, model, data, _pattern_prediction)
    for name, err in worst.items():
        assert err <= FD_TOL, (name, err)


@pytest.mark.parametrize("model_kind", ["init", "perturbed"])
def test_prediction_gradient_is_autograd_through_the_active_set_map(model_kind):
    """The fast path's closed form (adjoint solve, Lemma 1) equals autograd through
    ``active_set_solve`` on the same free sets -- the implicit function written as a graph.
    Same arithmetic up to association: measured <= 1e-15 relative."""
    model, data = make_problem(model=model_kind)
    _, info, g = autograd(prediction_loss_info, model, data)
    model.zero_grad()
    x, u, m = data.x, data.u, model
    q = x @ m.D.mT + u @ m.E.mT + m.c
    lam = active_set_solve(m.F, q, info.active)
    loss = 0.5 * ((x @ m.A.mT + u @ m.B.mT + lam @ m.C.mT + m.d - data.x_next) ** 2).sum(-1).mean()
    loss.backward()
    for name in PARAMETER_NAMES:
        ref = getattr(model, name).grad
        assert rel_err(g[name], ref) <= 1e-11, name
    assert float(g["D"].abs().max()) > 1e-3 and float(g["G"].abs().max()) > 1e-3  # not vacuous


def test_prediction_gradient_matches_cvxpylayers_path():
    """Active-set implicit function (fast path) vs diffcp on (P).

    Measured per-parameter relative error: <= 2e-6 (D, E, c: 9e-7 .. 2e-6; G: 8e-8; A, B, C, d,
    H: <= 3e-9) -- Clarabel's accuracy on (P) through the cone form. Asserted: 1e-5.
    """
    model, data = make_problem(n=20)
    lf, info_f, gf = autograd(prediction_loss_info, model, data)
    ll, info_l, gl = autograd(prediction_loss_info, model, data, solver="cvxpylayers")
    assert abs(ll - lf) <= 1e-8 * abs(lf)
    assert float((info_l.lam - info_f.lam).abs().max()) <= 1e-6
    for name in PARAMETER_NAMES:
        assert rel_err(gl[name], gf[name]) <= 1e-5, (name, rel_err(gl[name], gf[name]))


# -- Lemma 5: L_eps -> L_pred, from below ----------------------------------------------------

EPS_SWEEP = (1e-2, 1e-3, 1e-4, 1e-5)


@pytest.mark.parametrize("model_kind", ["init", "perturbed"])
def test_violation_loss_converges_linearly_to_prediction_loss(model_kind):
    """``L_pred - L_eps = O(eps)``: the penalty argument behind Lemma 5(b).

    Measured: the gap falls by 10.000 +- 3e-4 per decade and the log-log slope over
    eps = 1e-2 .. 1e-5 is 1.0000 (both models).
    """
    model, data = make_problem(model=model_kind)
    with torch.no_grad():
        l_pred = float(prediction_loss(model, data.x, data.u, data.x_next))
        gaps = np.array(
            [
                l_pred
                - float(violation_loss(model, data.x, data.u, data.x_next, gamma=1e-2, eps=e))
                for e in EPS_SWEEP
            ]
        )
    assert bool((gaps > 0).all()), gaps
    slope = np.polyfit(np.log(EPS_SWEEP), np.log(gaps), 1)[0]
    assert abs(slope - 1.0) <= 0.02, slope
    ratios = gaps[:-1] / gaps[1:]
    assert np.allclose(ratios, 10.0, rtol=0.01), ratios
    assert gaps[-1] <= 1e-5 * abs(l_pred)  # L_eps -> L_pred


@pytest.mark.parametrize("eps", (1e-1,) + EPS_SWEEP)
def test_violation_loss_is_below_prediction_loss_per_sample(eps):
    """``l_eps <= l_pred`` for every sample and every eps.

    Why: the per-sample value is a min over ``(lam, phi) >= 0`` of
    ``1/2 |e_dyn|^2 + (1/eps) V(lam, phi)`` with ``V >= 0``; the LCP solution with
    ``phi = F lam + q`` is feasible, has ``V = 0`` (Lemma 2) and dynamics term
    ``1/2 |x'_theta - x'|^2`` -- the prediction loss with the same 1/2. Checked here: the
    objective written out from the paper at that point equals the per-sample prediction loss,
    and the violation loss's own minimiser is never above it.
    """
    model, data = make_problem(model="perturbed")
    gamma = 1e-2
    with torch.no_grad():
        info_p = prediction_loss_info(model, data.x, data.u, data.x_next)
        info_v = violation_loss_info(model, data.x, data.u, data.x_next, gamma=gamma, eps=eps)
        l_pred, l_eps = info_p.loss, info_v.loss
        lam_lcp, w = info_p.lam, info_p.w
        pred = data.x @ model.A.mT + data.u @ model.B.mT + lam_lcp @ model.C.mT + model.d
        per_pred = 0.5 * ((pred - data.x_next) ** 2).sum(-1)
    assert float(per_pred.mean()) == pytest.approx(float(l_pred), rel=1e-13)
    at_lcp = violation_objective(model, data, lam_lcp, w.clamp(min=0.0), gamma, eps)
    # V(lam_LCP, w) = 0 up to round-off: the objective there is the prediction loss
    assert torch.allclose(at_lcp, per_pred, rtol=1e-9, atol=1e-9)
    per_viol = violation_objective(model, data, info_v.lam, info_v.phi, gamma, eps)
    assert float(per_viol.mean()) == pytest.approx(float(l_eps), rel=1e-12)
    assert bool((per_viol <= per_pred * (1 + 1e-12) + 1e-12).all())
    assert float(l_eps) < float(l_pred)


# -- input checks and the regulariser ---------------------------------------------------------


def test_gamma_at_or_above_sigma_min_raises():
    model, data = make_problem(n=5)
    smin = model.sigma_min
    for gamma in (smin, 1.5 * smin):
        with pytest.raises(
            LCSInputError, match=r"gamma: expected 0 < gamma < sigma_min\(F \+ F\^T\)"
        ):
            violation_loss(model, data.x, data.u, data.x_next, gamma=gamma, eps=1e-2)
    with pytest.raises(LCSInputError, match="gamma"):
        violation_loss(model, data.x, data.u, data.x_next, gamma=0.0, eps=1e-2)
    # just below is accepted
    with torch.no_grad():
        assert math.isfinite(
            float(violation_loss(model, data.x, data.u, data.x_next, gamma=0.99 * smin, eps=1e-2))
        )


@pytest.mark.parametrize("loss_fn", [violation_loss, prediction_loss])
def test_unknown_solver_raises_naming_solver(loss_fn):
    model, data = make_problem(n=5)
    with pytest.raises(
        LCSInputError, match=r"solver: expected one of .*'fast'.*received 'clarabel'"
    ):
        loss_fn(model, data.x, data.u, data.x_next, solver="clarabel")


@pytest.mark.parametrize("eps", [0.0, -1e-3, float("nan"), float("inf")])
def test_nonpositive_eps_raises(eps):
    model, data = make_problem(n=5)
    with pytest.raises(LCSInputError, match="eps: expected a finite number > 0"):
        violation_loss(model, data.x, data.u, data.x_next, eps=eps)


@pytest.mark.parametrize("loss_fn", [violation_loss, prediction_loss])
@pytest.mark.parametrize("arg", ["x", "u", "x_next"])
def test_non_finite_input_raises(loss_fn, arg):
    model, data = make_problem(n=5)
    inputs = {"x": data.x.clone(), "u": data.u.clone(), "x_next": data.x_next.clone()}
    inputs[arg][2, 0] = float("nan")
    with pytest.raises(LCSInputError, match=rf"^{arg}: expected finite values, received 1 NaN/inf"):
        loss_fn(model, inputs["x"], inputs["u"], inputs["x_next"])


@pytest.mark.parametrize("reg", [0.0, 1e-5, 0.3])
def test_regularizer_value_and_gradient(reg):
    model, _ = make_problem(n=5)
    model.zero_grad()
    value = regularizer(model, reg=reg)
    assert float(value.detach()) == pytest.approx(
        reg * float((model.C.detach() ** 2).sum()), rel=1e-14
    )
    assert float(value.detach()) == pytest.approx(
        reg * float(torch.linalg.matrix_norm(model.C.detach())) ** 2, rel=1e-12
    )
    value.backward()
    assert torch.allclose(model.C.grad, 2 * reg * model.C.detach(), rtol=1e-14, atol=0)
    for name in PARAMETER_NAMES:
        if name != "C":
            assert getattr(model, name).grad is None
    # default omega = 1e-5 (paper Sec. 5)
    assert float(regularizer(model).detach()) == pytest.approx(
        1e-5 * float((model.C.detach() ** 2).sum()), rel=1e-14
    )


@pytest.mark.parametrize("reg", [-1e-3, True, "1e-5"])
def test_regularizer_rejects_bad_reg(reg):
    model, _ = make_problem(n=5)
    with pytest.raises(LCSInputError, match=r"reg: expected a number >= 0"):
        regularizer(model, reg)


# -- devices -------------------------------------------------------------------------------

DEVICES = [
    "cpu",
    pytest.param(
        "cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
    ),
]


@pytest.mark.parametrize("device", DEVICES)
def test_fast_paths_on_device(device):
    """The fast paths run on ``device`` and agree with the CPU float64 result."""
    model, data = make_problem(n=30)
    ref = {}
    cases = ((violation_loss_info, {"gamma": 1e-2, "eps": 1e-3}), (prediction_loss_info, {}))
    for info_fn, kw in cases:
        ref[info_fn.__name__] = autograd(info_fn, model, data, **kw)
    model_d = model.to(device)
    data_d = data.to(device)
    for info_fn, kw in cases:
        model_d.zero_grad()
        info = info_fn(model_d, data_d.x, data_d.u, data_d.x_next, **kw)
        loss = info.loss
        assert loss.device.type == device and info.lam.device.type == device
        loss.backward()
        l0, info0, g0 = ref[info_fn.__name__]
        assert float(loss.detach()) == pytest.approx(l0, rel=1e-10)
        assert torch.allclose(info.lam.cpu(), info0.lam, rtol=1e-10, atol=1e-10)
        for name in PARAMETER_NAMES:
            g = getattr(model_d, name).grad
            assert g.device.type == device
            assert rel_err(g.cpu(), g0[name]) <= 1e-9, name


@pytest.mark.parametrize("solver", ["fast", "cvxpylayers"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_losses_are_scalars_with_a_graph(solver, dtype):
    """Each loss is a 0-dim tensor of the model's dtype that requires grad (the fast paths
    compute it in NumPy arrays and hand back a tensor)."""
    model, data = make_problem(n=10, seed=4)
    model = model.to(dtype)
    x, u, xn = (t.to(dtype) for t in (data.x, data.u, data.x_next))
    for loss in (violation_loss(model, x, u, xn, gamma=1e-2, eps=1e-2, solver=solver),
                 prediction_loss(model, x, u, xn, solver=solver)):
        assert loss.shape == () and loss.dtype == dtype and loss.requires_grad
        loss.backward()
        assert all(getattr(model, k).grad.dtype == dtype for k in PARAMETER_NAMES)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_fast_losses_in_torch_arrays_match_numpy(dtype):
    """The fast losses run in NumPy arrays on CPU and in torch tensors elsewhere (CUDA): forced
    onto torch tensors on CPU (``arrays="torch"``), the same values, solutions and gradients (to
    round-off) as in NumPy arrays, the CPU default."""
    model, data = make_problem(n=40, n_lam=5, model="perturbed", seed=3)
    model = model.to(dtype)
    x, u, xn = (t.to(dtype) for t in (data.x, data.u, data.x_next))
    cases = ((violation_fast, {"gamma": 1e-2, "eps": 1e-3}), (prediction_fast, {}))
    for fn, kw in cases:
        out = {}
        for arrays in ("auto", "torch"):
            model.zero_grad()
            info = fn(model, x, u, xn, arrays=arrays, **kw)
            info.loss.backward()
            out[arrays] = (float(info.loss.detach()), info, {k: getattr(model, k).grad.clone() for k in PARAMETER_NAMES})
        (v0, info0, g0), (value, info, g) = out["auto"], out["torch"]
        slack = info.phi if fn is violation_fast else info.w
        assert info.lam.dtype == dtype and slack.dtype == dtype and info.loss.dtype == dtype
        if dtype == torch.float32:  # the same algorithm: single-precision round-off
            assert value == pytest.approx(v0, rel=1e-5)
            assert torch.equal(info.active, info0.active)
            continue
        assert value == pytest.approx(v0, rel=1e-12)
        assert float((info.lam - info0.lam).abs().max()) <= 1e-12
        assert torch.equal(info.active, info0.active) and info.iterations == info0.iterations
        if fn is violation_fast:  # round-off times 1/(eps gamma): against its terms' magnitude
            scale = lemma3_gradients(model, data, info0.lam, info0.phi, magnitude=True, **kw)
            for name in PARAMETER_NAMES:
                assert float(((g[name] - g0[name]).abs() / scale[name]).max()) <= 1e-14, name
        else:
            for name in PARAMETER_NAMES:
                assert rel_err(g[name], g0[name]) <= 1e-12, name


# -- LossInfo -------------------------------------------------------------------------------


def test_loss_info_violation_fast_and_layer():
    model, data = make_problem(n=20)
    N, n = 20, model.n_lam
    gamma, eps = 1e-2, 1e-3
    info = violation_loss_info(model, data.x, data.u, data.x_next, gamma=gamma, eps=eps)
    loss = info.loss
    assert isinstance(info, lcs_cvx.LossInfo)
    assert loss.shape == () and loss.requires_grad
    assert info.lam.shape == (N, n) and info.phi.shape == (N, n)
    assert not info.lam.requires_grad and not info.phi.requires_grad
    assert bool((info.lam >= 0).all()) and bool((info.phi >= 0).all())
    # phi is the exact minimiser over phi for the returned lam: max(0, F lam + q - gamma lam)
    q, _ = lcp_terms(model, data)
    phi_star = (info.lam @ model.F.detach().mT + q - gamma * info.lam).clamp(min=0.0)
    assert torch.allclose(info.phi, phi_star, rtol=0, atol=1e-12)
    assert info.n_fallback == 0 and info.n_degenerate == 0
    assert 0.0 <= info.max_residual <= 1e-13
    assert isinstance(info.iterations, int) and info.iterations >= 0
    # the mean of the per-sample objective at (info.lam, info.phi) is the loss
    per = violation_objective(model, data, info.lam, info.phi, gamma, eps)
    assert float(per.mean()) == pytest.approx(float(loss.detach()), rel=1e-12)
    # the plain loss: the same scalar
    with torch.no_grad():
        again = violation_loss(model, data.x, data.u, data.x_next, gamma=gamma, eps=eps)
    assert float(again) == float(loss.detach())
    info_l = violation_loss_info(
        model, data.x, data.u, data.x_next, gamma=gamma, eps=eps, solver="cvxpylayers"
    )
    assert info_l.lam.shape == (N, n) and info_l.loss.requires_grad and info_l.active is None
    assert (info_l.iterations, info_l.n_fallback, info_l.n_degenerate) == (0, 0, 0)
    # the layer's own KKT residual is reported: small here, but not round-off small
    assert 0.0 < info_l.max_residual <= lcs_cvx.losses.LAYER_RESIDUAL_TOL


def _degenerate_model():
    """A 3-variable model with ``c = (0, 1, 2)``: at ``x = 0, u = 0``, ``q = c`` exactly,
    whose LCP solution is ``lam = 0``, ``w = q``: index 0 has ``lam_0 = w_0 = 0``."""
    model = lcs_cvx.LCS(4, 2, 3, stiffness=1.0, init_scale=0.5, seed=11)
    with torch.no_grad():
        model.c.copy_(torch.tensor([0.0, 1.0, 2.0], dtype=F64))
    return model


def _degenerate_model_active():
    """Index 0 degenerate next to an active index: ``lam* = (0, 1, 0)``, ``w* = (0, 0, 1)``;
    ``c = w* - F lam*`` so that ``q = c`` at ``x = 0, u = 0`` (``w_0 = 0`` up to round-off)."""
    model = lcs_cvx.LCS(4, 2, 3, stiffness=1.0, init_scale=0.5, seed=12)
    with torch.no_grad():
        lam = torch.tensor([0.0, 1.0, 0.0], dtype=F64)
        w = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
        model.c.copy_(w - model.F @ lam)
    return model


@pytest.mark.parametrize(
    "build, lam_star",
    [(_degenerate_model, (0.0, 0.0, 0.0)), (_degenerate_model_active, (0.0, 1.0, 0.0))],
)
def test_loss_info_counts_degenerate_samples(build, lam_star):
    model = build()
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(12, 4, generator=g, dtype=F64) * 2 - 1) * 10
    u = (torch.rand(12, 2, generator=g, dtype=F64) * 2 - 1) * 5
    degenerate = [1, 5, 6, 10]
    x[degenerate] = 0.0
    u[degenerate] = 0.0
    x_next = torch.randn(12, 4, generator=g, dtype=F64)
    info = prediction_loss_info(model, x, u, x_next)
    loss = info.loss
    assert info.n_degenerate == len(degenerate)
    assert torch.allclose(
        info.lam[degenerate], torch.tensor(lam_star, dtype=F64).expand(4, 3), atol=1e-12
    )
    assert float(info.w[degenerate, 0].abs().max()) <= 1e-12  # w_0 = 0 there
    # the non-degenerate samples are not counted
    rest = [i for i in range(12) if i not in degenerate]
    info_rest = prediction_loss_info(model, x[rest], u[rest], x_next[rest])
    assert info_rest.n_degenerate == 0
    # the one-sided derivative is finite
    loss.backward()
    for name in PARAMETER_NAMES:
        assert bool(torch.isfinite(getattr(model, name).grad).all()), name
    # the violation loss never reports degeneracy
    info_v = violation_loss_info(model, x, u, x_next, gamma=1e-2, eps=1e-2)
    assert info_v.n_degenerate == 0


def test_loss_info_prediction_fields():
    model, data = make_problem(n=20)
    info = prediction_loss_info(model, data.x, data.u, data.x_next)
    q, _ = lcp_terms(model, data)
    with torch.no_grad():  # the plain loss: the same scalar
        assert float(prediction_loss(model, data.x, data.u, data.x_next)) == float(info.loss.detach())
    # phi is w = F lam + q; lam solves the LCP
    assert info.phi is None
    assert torch.allclose(info.w, info.lam @ model.F.detach().mT + q, rtol=0, atol=1e-12)
    assert bool((info.lam >= 0).all())
    assert float(info.w.min()) >= -1e-10
    assert float((info.lam * info.w).abs().max()) <= 1e-9
    assert info.n_fallback == 0 and info.n_degenerate == 0 and info.max_residual <= 1e-13
    assert not info.lam.requires_grad


@pytest.mark.parametrize("loss", ["violation", "prediction"])
def test_trainer_fast_paths_report_the_fallbacks_residual(monkeypatch, loss):
    """``violation_fast`` / ``prediction_fast`` (the trainer's, on validated tensors): the public
    loss's value, gradient and active sets; without the full residual, ``max_residual`` is None and
    ``fallback_residual`` the worst residual of the samples a reference solved -- 0.0 when
    pivoting converged on all."""
    model, data = make_problem(n_lam=6, model="perturbed", seed=11)
    x, u, xn = data.x, data.u, data.x_next
    if loss == "violation":
        fast, public, kw = violation_fast, violation_loss_info, {"gamma": 1e-2, "eps": 1e-3}
    else:
        fast, public, kw = prediction_fast, prediction_loss_info, {}
    ref = public(model, x, u, xn, **kw)
    info = fast(model, x, u, xn, **kw)
    assert float(info.loss.detach()) == float(ref.loss.detach())
    assert torch.equal(info.lam, ref.lam) and torch.equal(info.active, ref.active)
    assert info.n_fallback == 0 and info.max_residual is None and info.fallback_residual == 0.0
    assert ref.fallback_residual == 0.0 <= ref.max_residual
    model.zero_grad()
    info.loss.backward()
    g_fast = {k: getattr(model, k).grad.clone() for k in PARAMETER_NAMES}
    model.zero_grad()
    ref.loss.backward()
    for k in PARAMETER_NAMES:
        assert torch.equal(g_fast[k], getattr(model, k).grad), k
    monkeypatch.setattr(lcs_cvx.losses, "MAX_ITER", 0)  # every sample that must pivot falls back
    with pytest.warns(lcs_cvx.FallbackWarning, match="did not converge"):
        lean = fast(model, x, u, xn, **kw)
        full = fast(model, x, u, xn, residual=True, **kw)
    assert lean.n_fallback == full.n_fallback >= 1
    assert float((lean.lam - ref.lam).abs().max()) <= 1e-6 * (1 + float(ref.lam.abs().max()))
    if loss == "violation":  # Clarabel's answers: accurate, not round-off exact
        assert 0.0 < lean.fallback_residual == pytest.approx(full.fallback_residual, rel=1e-12)
        assert lean.fallback_residual <= full.max_residual
    else:  # n_lam = 6: enumeration, exact; the samples whose first guess q < 0 was wrong
        q, _ = lcp_terms(model, data)
        fell_back = ((ref.lam > 0) != (q < 0)).any(-1)
        assert int(fell_back.sum()) == lean.n_fallback
        expected = float(lcs_cvx.lcp.lcp_residual(model.F.detach(), q[fell_back], lean.lam[fell_back]).max())
        # round-off both (the loss forms F in its arrays, model.F is torch's: 1 ulp apart)
        assert lean.fallback_residual == pytest.approx(expected, abs=1e-15)
        assert lean.fallback_residual <= full.max_residual <= 1e-13


# -- warm starts of the fast solvers ---------------------------------------------------------


@pytest.mark.parametrize("loss_fn", ["violation", "prediction"])
def test_warm_start_changes_the_work_not_the_result(loss_fn):
    """From the final active sets of an earlier call the solver needs no pivoting sweep; from a
    perturbed model's sets, some; the loss and every gradient agree with a cold start."""
    model, data = make_problem(n_lam=6, model="perturbed", seed=11)
    other, _ = make_problem(n_lam=6, model="perturbed", seed=12)

    def run(m, warm=None):
        m.zero_grad()
        if loss_fn == "violation":
            info = violation_loss_info(m, data.x, data.u, data.x_next, gamma=1e-2, eps=1e-3,
                                       warm_start=warm)
        else:
            info = prediction_loss_info(m, data.x, data.u, data.x_next, warm_start=warm)
        value = info.loss
        value.backward()
        return value.detach(), {k: p.grad.clone() for k, p in m.named_parameters()}, info

    cold_value, cold_grad, cold = run(model)
    assert cold.active.dtype == torch.bool
    assert cold.active.shape == (len(data.x), (2 if loss_fn == "violation" else 1) * 6)
    assert cold.iterations >= 1
    _, _, stale = run(other)
    for warm, sweeps in ((cold.active, 0), (stale.active, None)):
        value, grad, info = run(model, warm)
        if sweeps is not None:
            assert info.iterations == sweeps
        assert torch.equal(info.active, cold.active)
        assert abs(float(value - cold_value)) <= 1e-12 * (1 + abs(float(cold_value)))
        for k in grad:
            assert rel_err(grad[k], cold_grad[k]) <= 1e-10, k


def test_invalid_warm_start_raises():
    model, data = make_problem(n_lam=3, model="init", seed=0)
    n = len(data.x)
    with pytest.raises(LCSInputError, match=rf"warm_start: expected a bool tensor of shape \({n}, 6\)"):
        violation_loss(model, data.x, data.u, data.x_next, warm_start=torch.zeros(n, 3, dtype=torch.bool))
    with pytest.raises(LCSInputError, match=r"warm_start: expected a bool tensor .*received torch.float64"):
        prediction_loss(model, data.x, data.u, data.x_next, warm_start=torch.zeros(n, 3, dtype=torch.float64))
    with pytest.raises(LCSInputError, match=r"warm_start: only the 'fast' solver uses it"):
        prediction_loss(model, data.x, data.u, data.x_next, solver="cvxpylayers",
                        warm_start=torch.zeros(n, 3, dtype=torch.bool))


# -- float32 -------------------------------------------------------------------------------


@pytest.mark.parametrize("device", DEVICES)
def test_violation_loss_of_a_float32_model_has_float64_accurate_gradients(device):
    """A float32 model's violation loss is computed in float64 (``VIOLATION_DTYPE``) and returned
    in float32. Computed in float32 itself, its gradient in ``D, E, c, G, H`` (``w / (gamma
    eps)``, a cancellation to ``gamma eps``) was off by 60--1100 %, and at ``n_lam = 20`` one
    sample of 2,000 ran to ``MAX_ITER`` and fell back to Clarabel (a FallbackWarning, an error
    here)."""
    from lcs_cvx.bench import perturbed
    from lcs_cvx.stacked import StackedLCS, violation_losses

    truth = lcs_cvx.random_lcs(10, 4, 20, stiffness=0.5, seed=0)
    data = lcs_cvx.make_dataset(truth, 2000, noise=1e-2, seed=1)
    ref = perturbed(truth, 0.05, 2)
    value, grads = lcs_cvx.violation_value_and_grad(ref, data.x, data.u, data.x_next)
    m32 = perturbed(truth, 0.05, 2).to(device=device, dtype=torch.float32)
    x, u, xn = (t.to(device=device, dtype=torch.float32) for t in (data.x, data.u, data.x_next))
    info = violation_loss_info(m32, x, u, xn)
    info.loss.backward()
    assert info.loss.dtype == info.lam.dtype == torch.float32 and info.n_fallback == 0
    assert float(info.loss.detach()) == pytest.approx(float(value), rel=1e-5)
    for name in PARAMETER_NAMES:
        g = getattr(m32, name).grad
        assert g.dtype == torch.float32 and g.device.type == device
        assert rel_err(g.double().cpu(), grads[name]) <= 1e-5, name
    # the ensembles' path (one stacked model here) promotes the same way
    ens = StackedLCS([perturbed(truth, 0.05, 2).to(device=device, dtype=torch.float32)])
    stacked = violation_losses(ens, x[None], u[None], xn[None], gamma=1e-2, eps=1e-4)
    assert stacked.loss.dtype == torch.float32 and stacked.n_fallback == [0]
    assert float(stacked.loss.detach().sum()) == pytest.approx(float(value), rel=1e-5)
