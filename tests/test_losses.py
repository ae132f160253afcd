"""The learning losses of :mod:`lcs_cvx.losses` against the paper's lemmas.

- Lemma 3 (lemma.contactnet, eq. equ.diffvioloss): the autograd gradient of the violation loss
  ``L_eps`` (eq. equ.contactnet) is the envelope gradient -- checked against the closed form
  written out here, central finite differences and the cvxpylayers (diffcp + Clarabel) path.
- Lemma 1 (lemma.lcpdiff): the prediction loss ``L_pred`` (eq. equ.prednet) is differentiable
  under strict complementarity -- finite differences and the cvxpylayers path of (P).
- Lemma 5 (lemma.approximation): ``L_eps -> L_pred`` as ``eps -> 0``, with ``L_eps <= L_pred``.
- The solver paths ``"fast"``, ``"cvxpylayers"``, ``"cvxpylayers-scs"`` agree; the fast (V)
  solution is certified against a high-precision refinement of the paper's (lam, phi) QP.
- Input checks, the regulariser, devices and :class:`lcs_cvx.LossInfo`.

The library's losses are batch MEANS (the paper writes sums), so every closed form here is a
mean. Everything is float64 on one torch thread; cvxpylayers batches stay at 10-20 samples
(the layer solves a few hundred samples per second).
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch

import lcs_cvx
from lcs_cvx import LCSInputError, prediction_loss, regularizer, violation_loss
from lcs_cvx.lcp import active_set_solve, solve_lcp_brute
from lcs_cvx.pivoting import array_ops
from lcs_cvx.problems import violation_problem
from lcs_cvx.system import PARAMETER_NAMES
from lcs_cvx.violation import violation_kkt_residual

torch.set_num_threads(1)

F64 = torch.float64

#: Central-difference step on every parameter entry. Losses are O(1e2) here, so the round-off
#: of a difference quotient is ~1e-16 * 1e2 / 1e-6 = 1e-8 and the O(h^2) truncation ~1e-12:
#: measured |fd - autograd| / (1 + |autograd|) <= 3e-8 (violation and prediction loss).
FD_STEP = 1e-6
FD_TOL = 1e-6


# -- problems ------------------------------------------------------------------------------


def make_problem(n_lam=3, n=40, model="init", seed=0, n_x=5, n_u=2):
    """Ground truth ``random_lcs(n_x, n_u, n_lam)``, noisy data from it (paper Sec. 5, noise
    1e-2), and a model to evaluate: ``"init"`` a fresh ``LCS(init_scale=0.3)`` or ``"perturbed"``
    the truth plus ``0.1 N(0, 1)`` on every parameter (stiffness kept)."""
    truth = lcs_cvx.random_lcs(n_x, n_u, n_lam, seed=seed)
    data = lcs_cvx.make_dataset(truth, n, noise=0.01, seed=seed + 1)
    if model == "init":
        m = lcs_cvx.LCS(n_x, n_u, n_lam, init_scale=0.3, seed=seed + 2)
    else:
        m = lcs_cvx.LCS(n_x, n_u, n_lam, stiffness=float(truth.stiffness), init_scale=0.0)
        gen = torch.Generator().manual_seed(seed + 3)
        with torch.no_grad():
            for name in PARAMETER_NAMES:
                p = getattr(truth, name)
                getattr(m, name).copy_(p + 0.1 * torch.randn(p.shape, generator=gen, dtype=F64))
    return m, data


def grads(model):
    return {k: getattr(model, k).grad.detach().clone() for k in PARAMETER_NAMES}


def autograd(loss_fn, model, data, **kw):
    """``(loss, info, {name: grad})`` of one loss evaluation."""
    model.zero_grad()
    loss, info = loss_fn(model, data.x, data.u, data.x_next, return_info=True, **kw)
    loss.backward()
    return float(loss.detach()), info, grads(model)


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    """``max |a - b| / max |b|`` (``b`` the reference)."""
    return float((a - b).abs().max() / b.abs().max().clamp(min=1e-300))


def lcp_terms(model, data):
    """``q = D x + E u + c`` and ``r = A x + B u + d - x'`` (detached)."""
    with torch.no_grad():
        q = data.x @ model.D.mT + data.u @ model.E.mT + model.c
        r = data.x @ model.A.mT + data.u @ model.B.mT + model.d - data.x_next
    return q, r


def violation_objective(model, data, lam, phi, gamma, eps):
    """Per-sample value of eq. (equ.contactnet.2) at ``(lam, phi)``, written out from the paper:
    ``1/2 |A x + B u + C lam + d - x'|^2 + (lam^T phi + |D x + E u + F lam + c - phi|^2 / (2 gamma)) / eps``.
    """
    with torch.no_grad():
        q, r = lcp_terms(model, data)
        e_dyn = r + lam @ model.C.mT
        w_res = q + lam @ model.F.mT - phi
        return (
            0.5 * (e_dyn**2).sum(-1)
            + ((lam * phi).sum(-1) + (w_res**2).sum(-1) / (2 * gamma)) / eps
        )


# -- Lemma 3: envelope gradients of the violation loss --------------------------------------


def lemma3_gradients(model, data, lam, phi, gamma, eps, magnitude=False):
    """Eq. (equ.diffvioloss) as batch means, with F mapped back to G and H.

    ``e_dyn = A x + B u + C lam + d - x'``, ``e_lcp = (D x + E u + F lam + c - phi) / (eps gamma)``;
    ``F = G G^T + H - H^T + s I`` gives ``grad_G = (grad_F + grad_F^T) G``,
    ``grad_H = grad_F - grad_F^T``.

    ``magnitude=True``: the same sums of products over the absolute values of their terms
    (``|q| + |lam| |F|^T + |phi|`` for the numerator of ``e_lcp``, ...) -- the scale of the
    round-off of the expressions, ``|computed - exact| <~ k u * magnitude``.
    """
    a = torch.abs if magnitude else (lambda t: t)
    with torch.no_grad():
        x, u, N = a(data.x), a(data.u), data.x.shape[0]
        q, r = (a(t) for t in lcp_terms(model, data))
        if magnitude:  # the terms of q and r themselves
            q = q + a(data.x) @ a(model.D).mT + a(data.u) @ a(model.E).mT + a(model.c)
            r = r + a(data.x) @ a(model.A).mT + a(data.u) @ a(model.B).mT + a(model.d) + a(data.x_next)
        e_dyn = r + a(lam) @ a(model.C).mT
        e_lcp = (q + a(lam) @ a(model.F).mT + a(phi) * (1 if magnitude else -1)) / (eps * gamma)
        gF = e_lcp.mT @ a(lam) / N
        return {
            "A": e_dyn.mT @ x / N,
            "B": e_dyn.mT @ u / N,
            "C": e_dyn.mT @ a(lam) / N,
            "d": e_dyn.mean(0),
            "D": e_lcp.mT @ x / N,
            "E": e_lcp.mT @ u / N,
            "G": (gF + gF.mT) @ a(model.G),
            "H": gF + gF.mT if magnitude else gF - gF.mT,
            "c": e_lcp.mean(0),
        }


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
    _, info, g = autograd(violation_loss, model, data, gamma=gamma, eps=eps)
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


def finite_difference_check(loss_fn, model, data, pattern, **kw):
    """Central differences of the loss VALUE on every entry of every parameter.

    Asserts that the active-set pattern of the solution is the same at ``theta +- h`` as at
    ``theta`` (the loss is smooth there, Lemmas 1 and 3) and returns the worst
    ``|fd - autograd| / (1 + |autograd|)`` per parameter.
    """
    _, info0, g = autograd(loss_fn, model, data, **kw)
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
                    loss, info = loss_fn(model, data.x, data.u, data.x_next, return_info=True, **kw)
                    assert torch.equal(pattern(info), base), f"active set changed under {name}{idx}"
                    vals.append(float(loss))
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
        violation_loss, model, data, _pattern_violation, gamma=1e-2, eps=1e-1
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
        lf, info_f, gf = autograd(violation_loss, model, data, gamma=1e-2, eps=eps)
        ll, info_l, gl = autograd(
            violation_loss, model, data, gamma=1e-2, eps=eps, solver="cvxpylayers"
        )
        assert abs(ll - lf) <= 1e-8 * abs(lf)
        for name in PARAMETER_NAMES:
            assert rel_err(gl[name], gf[name]) <= 1e-6, (eps, name, rel_err(gl[name], gf[name]))


# -- Lemma 1: the prediction loss ----------------------------------------------------------


@pytest.mark.parametrize("model_kind", ["init", "perturbed"])
def test_prediction_gradient_matches_finite_differences(model_kind):
    model, data = make_problem(model=model_kind)
    _, info, _ = autograd(prediction_loss, model, data)
    # Lemma 1's hypothesis, strict complementarity, with a margin far above the FD step.
    lam, w = info.lam, info.phi
    margin = torch.where(info.lam > 0, lam, w)
    assert float(margin.min()) > 1e-4
    assert bool((info.lam > 0).any()) and bool((info.lam == 0).any())  # both kinds of index occur
    worst = finite_difference_check(prediction_loss, model, data, _pattern_prediction)
    for name, err in worst.items():
        assert err <= FD_TOL, (name, err)


@pytest.mark.parametrize("model_kind", ["init", "perturbed"])
def test_prediction_gradient_is_autograd_through_the_active_set_map(model_kind):
    """The fast path's closed form (adjoint solve, Lemma 1) equals autograd through
    ``active_set_solve`` on the same free sets -- the implicit function written as a graph.
    Same arithmetic up to association: measured <= 1e-15 relative."""
    model, data = make_problem(model=model_kind)
    _, info, g = autograd(prediction_loss, model, data)
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
    lf, info_f, gf = autograd(prediction_loss, model, data)
    ll, info_l, gl = autograd(prediction_loss, model, data, solver="cvxpylayers")
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
        l_pred, info_p = prediction_loss(model, data.x, data.u, data.x_next, return_info=True)
        l_eps, info_v = violation_loss(
            model, data.x, data.u, data.x_next, gamma=gamma, eps=eps, return_info=True
        )
        lam_lcp, w = info_p.lam, info_p.phi
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


# -- solver paths agree ------------------------------------------------------------------------

#: name -> (gamma, eps, generator stiffness). "paper" is the paper's gamma = 1e-2, eps = 1e-4,
#: evaluated at a fresh model; "stiff" is gamma = 1e-6, eps = 1e-4 (1/(eps gamma) = 1e10)
#: evaluated at the ground truth drawn with stiffness 1e-6, so sigma_min(F + F^T) >= 2e-6 > gamma
#: (measured sigma_min: 7e-3, 0.48, 3.6e-6, 1.7e-2 for n_lam = 1, 4, 10, 20).
SETTINGS = {"paper": (1e-2, 1e-4, 0.5), "stiff": (1e-6, 1e-4, 1e-6)}
N_LAMS = (1, 4, 10, 20)


def certified_violation_solution(model, data, lam, phi, gamma, eps, dps=50, sweeps=6):
    """A certificate for the (V) minimiser, independent of the library's DPP form.

    Works on the paper's (lam, phi) QP (eq. equ.contactnet.2) with Hessian
    ``Q = [[C^T C + F^T F/(eps gamma), (I - F^T/gamma)/eps], [(I - F/gamma)/eps, I/(eps gamma)]]``.
    On the support ``J`` of the given point, iterative refinement with gradients evaluated in
    ``dps``-digit arithmetic (mpmath) and float64 corrections from ``Q_JJ`` (which converge
    while cond(Q_JJ) * 1e-16 < 1: ~1e11 here at worst). The refined point is the exact minimiser
    (strong convexity, Lemma 3a) iff ``z_J > 0`` and ``grad_{not J} >= 0``; returns
    ``(lam, phi, certified)`` with ``certified`` per sample.
    """
    mpmath = pytest.importorskip("mpmath")
    ctx = mpmath.mp.clone()
    ctx.dps = dps
    mpf = ctx.mpf
    C = model.C.detach().numpy()
    F = model.F.detach().numpy()
    q, r = (t.numpy() for t in lcp_terms(model, data))
    n, inv_eg, inv_g, inv_e = (
        F.shape[0],
        mpf(1) / (mpf(eps) * mpf(gamma)),
        mpf(1) / mpf(gamma),
        mpf(1) / mpf(eps),
    )
    eye = np.eye(n)
    Q = np.block(
        [
            [C.T @ C + F.T @ F / (eps * gamma), (eye - F.T / gamma) / eps],
            [(eye - F / gamma) / eps, eye / (eps * gamma)],
        ]
    )
    Cm, Fm = ctx.matrix(C.tolist()), ctx.matrix(F.tolist())

    def gradient(z, k):  # exact-ish gradient of the (lam, phi) objective at z for sample k
        lam_m, phi_m = ctx.matrix(z[:n]), ctx.matrix(z[n:])
        e_dyn = Cm * lam_m + ctx.matrix(r[k].tolist())
        w_res = Fm * lam_m + ctx.matrix(q[k].tolist()) - phi_m
        g_lam = Cm.T * e_dyn + (phi_m + Fm.T * w_res * inv_g) * inv_e
        g_phi = (lam_m - w_res * inv_g) * inv_e
        return [g_lam[i] for i in range(n)] + [g_phi[i] for i in range(n)]

    z_all, ok_all = [], []
    for k in range(q.shape[0]):
        z0 = np.concatenate([lam[k].numpy(), phi[k].numpy()])
        J = [int(j) for j in np.nonzero(z0 > 0)[0]]
        z = [mpf(0)] * (2 * n)
        for j in J:
            z[j] = mpf(float(z0[j]))
        for _ in range(sweeps):
            if not J:
                break
            g = gradient(z, k)
            delta = np.linalg.solve(Q[np.ix_(J, J)], -np.array([float(g[j]) for j in J]))
            for a, j in enumerate(J):
                z[j] += mpf(float(delta[a]))
        g = gradient(z, k)
        scale = float(inv_eg) * (1.0 + np.abs(q[k]).max() + np.abs(z0).max())
        ok = (
            all(z[j] > 0 for j in J)
            and all(float(g[j]) >= -1e-13 * scale for j in range(2 * n) if j not in J)
            and all(abs(float(g[j])) <= 1e-20 * scale for j in J)
        )
        z_all.append([float(v) for v in z])
        ok_all.append(ok)
    Z = torch.tensor(np.array(z_all), dtype=F64)
    return Z[:, :n], Z[:, n:], torch.tensor(ok_all)


@functools.cache
def agreement_case(n_lam, setting):
    """Every solver's answer on one batch of 20 samples, computed once per (n_lam, setting)."""
    gamma, eps, stiffness = SETTINGS[setting]
    truth = lcs_cvx.random_lcs(6, 2, n_lam, stiffness=stiffness, seed=n_lam)
    data = lcs_cvx.make_dataset(truth, 20, noise=0.01, seed=100 + n_lam)
    if setting == "stiff":
        model = truth.requires_grad_(True)  # gradients on: the layer's training configuration
    else:
        model = lcs_cvx.LCS(6, 2, n_lam, init_scale=0.3, seed=n_lam)
    assert gamma < model.sigma_min
    loss_f, info_f = violation_loss(
        model, data.x, data.u, data.x_next, gamma=gamma, eps=eps, return_info=True
    )
    loss_l, info_l = violation_loss(
        model,
        data.x,
        data.u,
        data.x_next,
        gamma=gamma,
        eps=eps,
        solver="cvxpylayers",
        return_info=True,
    )
    loss_f, loss_l = float(loss_f.detach()), float(loss_l.detach())
    lam_x, phi_x, certified = certified_violation_solution(
        model, data, info_f.lam, info_f.phi, gamma, eps
    )
    decl = violation_problem(n_lam)
    q, r = lcp_terms(model, data)
    values = decl.parameter_values(model.C.detach(), model.F.detach(), q, r, gamma, eps)
    lam_ref = torch.as_tensor(decl.solve(values), dtype=F64)  # the Clarabel reference (QP form)
    scale = 1.0 + info_f.lam.abs().amax(-1)

    def dev(a, b):  # per-sample |a - b|_inf relative to 1 + |lam|_inf, worst sample
        return float(((a - b).abs().amax(-1) / scale).max())

    obj_f = violation_objective(model, data, info_f.lam, info_f.phi, gamma, eps)
    obj_l = violation_objective(model, data, info_l.lam, info_l.phi, gamma, eps)
    return {
        "model": model,
        "certified": certified,
        "fast_vs_exact": dev(info_f.lam, lam_x),
        "fast_vs_exact_phi": dev(info_f.phi, phi_x),
        "layer_lam": dev(info_l.lam, info_f.lam),
        "layer_lam_abs": float((info_l.lam - info_f.lam).abs().max()),
        "layer_phi": dev(info_l.phi, info_f.phi),
        "layer_loss": abs(loss_l - loss_f) / abs(loss_f),
        "ref_lam": dev(lam_ref, info_f.lam),
        "kkt_fast": float(violation_kkt_residual(values, info_f.lam).max()),
        "kkt_layer": float(violation_kkt_residual(values, info_l.lam).max()),
        "kkt_ref": float(violation_kkt_residual(values, lam_ref).max()),
        # per sample; >= 0 iff the fast point is the better minimiser of the paper's objective
        "excess": (obj_l - obj_f) / (1.0 + obj_f.abs()),
        "info_f": info_f,
    }


CASES = [(n, s) for s in SETTINGS for n in N_LAMS]


@pytest.mark.parametrize("n_lam, setting", CASES)
def test_fast_violation_solution_is_certified_exact(n_lam, setting):
    """The fast kernel's (lam, phi) is the exact minimiser to round-off in every setting,
    the stiff one included. Measured: <= 1e-14 relative to 1 + |lam|_inf; KKT <= 8e-16."""
    res = agreement_case(n_lam, setting)
    assert bool(res["certified"].all())
    assert res["fast_vs_exact"] <= 1e-12
    assert res["fast_vs_exact_phi"] <= 1e-12
    assert res["kkt_fast"] <= 1e-13
    info = res["info_f"]
    assert info.n_fallback == 0


def test_certificate_rejects_a_wrong_point():
    """The certificate is not vacuous: a wrong support fails it, and a point off by ``delta``
    on the right support is refined back (the measured distance is ``delta``)."""
    model, data = make_problem(n=8)
    gamma, eps = 1e-2, 1e-3
    _, info = violation_loss(
        model, data.x, data.u, data.x_next, gamma=gamma, eps=eps, return_info=True
    )
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
    res = agreement_case(n_lam, setting)
    bound = LAYER_BOUND[setting]
    assert res["layer_lam"] <= bound["lam"], res["layer_lam"]
    assert res["layer_phi"] <= bound["phi"], res["layer_phi"]
    if "loss" in bound:
        assert res["layer_loss"] <= bound["loss"], res["layer_loss"]
    # Which side is accurate: the fast point is never the worse minimiser of the paper's
    # objective, and its KKT residual is the smaller one.
    assert float(res["excess"].min()) >= -1e-12
    assert res["kkt_fast"] <= res["kkt_layer"]


@pytest.mark.parametrize("n_lam, setting", CASES)
def test_clarabel_reference_agrees_with_fast(n_lam, setting):
    """The independent Clarabel reference (cvxpy, QP form, tolerances 1e-10) on the same
    declaration. Measured relative: paper <= 1.3e-9; stiff <= 2.3e-7 (n = 10)."""
    res = agreement_case(n_lam, setting)
    assert res["ref_lam"] <= (1e-8 if setting == "paper" else 1e-6), res["ref_lam"]
    assert res["kkt_fast"] <= res["kkt_ref"] + 1e-15


@pytest.mark.xfail(
    strict=True,
    reason="Clarabel through diffcp's cone form reaches ~1e-7 on lam in the paper setting and "
    "up to ~5e-4 (absolute) in the stiff one, not the issue's 1e-8; see LAYER_BOUND",
)
def test_cvxpylayers_path_meets_the_1e8_requirement():
    worst = max(agreement_case(n, s)["layer_lam_abs"] for n, s in CASES)
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
    truth = lcs_cvx.random_lcs(6, 2, n_lam, seed=n_lam)
    data = lcs_cvx.make_dataset(truth, 20, noise=0.01, seed=100 + n_lam)
    model = lcs_cvx.random_lcs(6, 2, n_lam, stiffness=5e-6, seed=50 + n_lam)
    with torch.no_grad():
        model.G[:, -1] = 0.0
    model.requires_grad_(True)
    assert model.sigma_min == pytest.approx(10 * gamma, rel=1e-6)
    _, info = violation_loss(
        model, data.x, data.u, data.x_next, gamma=gamma, eps=eps, return_info=True
    )
    assert info.n_fallback == 0 and info.max_residual <= 1e-13
    lam_x, phi_x, certified = certified_violation_solution(
        model, data, info.lam, info.phi, gamma, eps
    )
    assert bool(certified.all())
    scale = 1.0 + info.lam.abs().amax(-1)
    assert float(((info.lam - lam_x).abs().amax(-1) / scale).max()) <= 1e-12
    assert float(((info.phi - phi_x).abs().amax(-1) / scale).max()) <= 1e-12
    # the layer's inaccuracy is not silent: its KKT residual is checked and reported
    with pytest.warns(lcs_cvx.losses.LayerAccuracyWarning, match="KKT residual"):
        _, info_l = violation_loss(
            model,
            data.x,
            data.u,
            data.x_next,
            gamma=gamma,
            eps=eps,
            solver="cvxpylayers",
            return_info=True,
        )
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
    model = truth if setting == "stiff" else lcs_cvx.LCS(6, 2, n_lam, init_scale=0.3, seed=n_lam)
    with torch.no_grad():
        loss_f, info_f = prediction_loss(model, data.x, data.u, data.x_next, return_info=True)
        loss_l, info_l = prediction_loss(
            model, data.x, data.u, data.x_next, solver="cvxpylayers", return_info=True
        )
    scale = 1.0 + info_f.lam.abs().amax(-1)
    if n_lam <= 10:
        q, _ = lcp_terms(model, data)
        brute = solve_lcp_brute(model.F.detach(), q)
        assert float(((brute.lam - info_f.lam).abs().amax(-1) / scale).max()) <= 1e-12
    layer = float(((info_l.lam - info_f.lam).abs().amax(-1) / scale).max())
    assert layer <= (1e-7 if setting == "paper" else 1e-5), layer
    assert abs(float(loss_l) - float(loss_f)) <= (1e-8 if setting == "paper" else 1e-2) * abs(
        float(loss_f)
    )
    assert info_f.n_fallback == 0 and info_f.max_residual <= 1e-13


# -- the SCS path ---------------------------------------------------------------------------


def test_scs_path_runs_and_agrees_loosely():
    """diffcp + SCS (eps 1e-10, 1e5 iterations). A first-order method, so only a loose
    tolerance is promised: 1e-6 relative on lam, loss and gradients. Measured here: lam
    <= 3e-11, loss <= 7e-12, gradients <= 5e-9 (violation) and <= 4e-11 (prediction)."""
    model, data = make_problem(n=10)
    for loss_fn, kw in ((violation_loss, {"gamma": 1e-2, "eps": 1e-2}), (prediction_loss, {})):
        lf, info_f, gf = autograd(loss_fn, model, data, **kw)
        ls, info_s, gs = autograd(loss_fn, model, data, solver="cvxpylayers-scs", **kw)
        assert math.isfinite(ls)
        assert info_s.iterations == 0 and info_s.n_fallback == 0
        assert abs(ls - lf) <= 1e-6 * abs(lf)
        assert float((info_s.lam - info_f.lam).abs().max()) <= 1e-6 * (
            1 + float(info_f.lam.abs().max())
        )
        for name in PARAMETER_NAMES:
            assert rel_err(gs[name], gf[name]) <= 1e-6, (loss_fn.__name__, name)


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


@pytest.mark.parametrize("weight", [0.0, 1e-5, 0.3])
def test_regularizer_value_and_gradient(weight):
    model, _ = make_problem(n=5)
    model.zero_grad()
    value = regularizer(model, weight)
    assert float(value.detach()) == pytest.approx(
        weight * float((model.C.detach() ** 2).sum()), rel=1e-14
    )
    assert float(value.detach()) == pytest.approx(
        weight * float(torch.linalg.matrix_norm(model.C.detach())) ** 2, rel=1e-12
    )
    value.backward()
    assert torch.allclose(model.C.grad, 2 * weight * model.C.detach(), rtol=1e-14, atol=0)
    for name in PARAMETER_NAMES:
        if name != "C":
            assert getattr(model, name).grad is None
    # default omega = 1e-5 (paper Sec. 5)
    assert float(regularizer(model).detach()) == pytest.approx(
        1e-5 * float((model.C.detach() ** 2).sum()), rel=1e-14
    )


@pytest.mark.parametrize("weight", [-1e-3, True, "1e-5"])
def test_regularizer_rejects_bad_weight(weight):
    model, _ = make_problem(n=5)
    with pytest.raises(LCSInputError, match="weight"):
        regularizer(model, weight)


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
    for loss_fn, kw in ((violation_loss, {"gamma": 1e-2, "eps": 1e-3}), (prediction_loss, {})):
        ref[loss_fn.__name__] = autograd(loss_fn, model, data, **kw)
    model_d = model.to(device)
    data_d = data.to(device)
    for loss_fn, kw in ((violation_loss, {"gamma": 1e-2, "eps": 1e-3}), (prediction_loss, {})):
        model_d.zero_grad()
        loss, info = loss_fn(model_d, data_d.x, data_d.u, data_d.x_next, return_info=True, **kw)
        assert loss.device.type == device and info.lam.device.type == device
        loss.backward()
        l0, info0, g0 = ref[loss_fn.__name__]
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


def test_fast_losses_in_torch_arrays_match_numpy(monkeypatch):
    """The fast losses run in NumPy arrays on CPU and in torch tensors elsewhere (CUDA): forced
    onto torch tensors on CPU, the same values, solutions and gradients (to round-off)."""
    model, data = make_problem(n=40, n_lam=5, model="perturbed", seed=3)
    cases = ((violation_loss, {"gamma": 1e-2, "eps": 1e-3}), (prediction_loss, {}))
    ref = {fn.__name__: autograd(fn, model, data, **kw) for fn, kw in cases}
    forced = []

    def torch_ops(t, backend="auto"):
        forced.append(t.device)
        return array_ops(t, "torch")

    monkeypatch.setattr(lcs_cvx.losses, "array_ops", torch_ops)
    for fn, kw in cases:
        value, info, g = autograd(fn, model, data, **kw)
        assert forced.pop() == torch.device("cpu")
        v0, info0, g0 = ref[fn.__name__]
        assert value == pytest.approx(v0, rel=1e-12)
        assert float((info.lam - info0.lam).abs().max()) <= 1e-12
        if fn is violation_loss:  # round-off times 1/(eps gamma): against its terms' magnitude
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
    loss, info = violation_loss(
        model, data.x, data.u, data.x_next, gamma=gamma, eps=eps, return_info=True
    )
    assert isinstance(info, lcs_cvx.LossInfo)
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
    # without return_info: the same scalar
    with torch.no_grad():
        again = violation_loss(model, data.x, data.u, data.x_next, gamma=gamma, eps=eps)
    assert float(again) == float(loss.detach())
    _, info_l = violation_loss(
        model,
        data.x,
        data.u,
        data.x_next,
        gamma=gamma,
        eps=eps,
        solver="cvxpylayers",
        return_info=True,
    )
    assert info_l.lam.shape == (N, n)
    assert (info_l.iterations, info_l.n_fallback, info_l.n_degenerate) == (0, 0, 0)
    # the layer's own KKT residual is reported: small here, but not round-off small
    assert 0.0 < info_l.max_residual <= lcs_cvx.losses.LAYER_RESIDUAL_TOL


def _degenerate_model():
    """A 3-variable model with ``c = (0, 1, 2)``: at ``x = 0, u = 0``, ``q = c`` exactly,
    whose LCP solution is ``lam = 0``, ``w = q``: index 0 has ``lam_0 = w_0 = 0``."""
    model = lcs_cvx.LCS(4, 2, 3, init_scale=0.5, seed=11)
    with torch.no_grad():
        model.c.copy_(torch.tensor([0.0, 1.0, 2.0], dtype=F64))
    return model


def _degenerate_model_active():
    """Index 0 degenerate next to an active index: ``lam* = (0, 1, 0)``, ``w* = (0, 0, 1)``;
    ``c = w* - F lam*`` so that ``q = c`` at ``x = 0, u = 0`` (``w_0 = 0`` up to round-off)."""
    model = lcs_cvx.LCS(4, 2, 3, init_scale=0.5, seed=12)
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
    loss, info = prediction_loss(model, x, u, x_next, return_info=True)
    assert info.n_degenerate == len(degenerate)
    assert torch.allclose(
        info.lam[degenerate], torch.tensor(lam_star, dtype=F64).expand(4, 3), atol=1e-12
    )
    assert float(info.phi[degenerate, 0].abs().max()) <= 1e-12  # w_0 = 0 there
    # the non-degenerate samples are not counted
    rest = [i for i in range(12) if i not in degenerate]
    _, info_rest = prediction_loss(model, x[rest], u[rest], x_next[rest], return_info=True)
    assert info_rest.n_degenerate == 0
    # the one-sided derivative is finite
    loss.backward()
    for name in PARAMETER_NAMES:
        assert bool(torch.isfinite(getattr(model, name).grad).all()), name
    # the violation loss never reports degeneracy
    _, info_v = violation_loss(model, x, u, x_next, gamma=1e-2, eps=1e-2, return_info=True)
    assert info_v.n_degenerate == 0


def test_loss_info_prediction_fields():
    model, data = make_problem(n=20)
    loss, info = prediction_loss(model, data.x, data.u, data.x_next, return_info=True)
    q, _ = lcp_terms(model, data)
    # phi is w = F lam + q; lam solves the LCP
    assert torch.allclose(info.phi, info.lam @ model.F.detach().mT + q, rtol=0, atol=1e-12)
    assert bool((info.lam >= 0).all())
    assert float(info.phi.min()) >= -1e-10
    assert float((info.lam * info.phi).abs().max()) <= 1e-9
    assert info.n_fallback == 0 and info.n_degenerate == 0 and info.max_residual <= 1e-13
    assert not info.lam.requires_grad


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
            value, info = violation_loss(m, data.x, data.u, data.x_next, gamma=1e-2, eps=1e-3,
                                         return_info=True, warm_start=warm)
        else:
            value, info = prediction_loss(m, data.x, data.u, data.x_next, return_info=True,
                                          warm_start=warm)
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
