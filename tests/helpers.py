"""Helpers shared by the tests of the losses, the violation solver and the layers
(``from helpers import ...``): the evaluation problems, the paper's objective and Lemma 3's
gradients written out independently of the library, and a high-precision certificate of the
(V) minimiser.

The library's losses are batch MEANS (the paper writes sums), so every closed form here is a
mean. Everything is float64 on one torch thread.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch

import lcs_cvx
from lcs_cvx.problems import violation_problem
from lcs_cvx.system import PARAMETER_NAMES

torch.set_num_threads(1)

F64 = torch.float64

#: name -> (gamma, eps, generator stiffness). "paper" is the paper's gamma = 1e-2, eps = 1e-4,
#: evaluated at a fresh model; "stiff" is gamma = 1e-6, eps = 1e-4 (1/(eps gamma) = 1e10)
#: evaluated at the ground truth drawn with stiffness 1e-6, so sigma_min(F + F^T) >= 2e-6 > gamma
#: (measured sigma_min: 7e-3, 0.48, 3.6e-6, 1.7e-2 for n_lam = 1, 4, 10, 20).
SETTINGS = {"paper": (1e-2, 1e-4, 0.5), "stiff": (1e-6, 1e-4, 1e-6)}
N_LAMS = (1, 4, 10, 20)
CASES = [(n, s) for s in SETTINGS for n in N_LAMS]


def make_problem(n_lam=3, n=40, model="init", seed=0, n_x=5, n_u=2):
    """Ground truth ``random_lcs(n_x, n_u, n_lam)`` (stiffness 0.5), noisy data from it (paper
    Sec. 5, noise 1e-2), and a model to evaluate: ``"init"`` a fresh ``LCS(stiffness=1.0,
    init_scale=0.3)`` or ``"perturbed"`` the truth plus ``0.1 N(0, 1)`` on every parameter
    (stiffness kept)."""
    truth = lcs_cvx.random_lcs(n_x, n_u, n_lam, stiffness=0.5, seed=seed)
    data = lcs_cvx.make_dataset(truth, n, noise=0.01, seed=seed + 1)
    if model == "init":
        m = lcs_cvx.LCS(n_x, n_u, n_lam, stiffness=1.0, init_scale=0.3, seed=seed + 2)
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


def autograd(info_fn, model, data, **kw):
    """``(loss, info, {name: grad})`` of one evaluation of ``info_fn``
    (:func:`lcs_cvx.violation_loss_info` or :func:`lcs_cvx.prediction_loss_info`)."""
    model.zero_grad()
    info = info_fn(model, data.x, data.u, data.x_next, **kw)
    info.loss.backward()
    return float(info.loss.detach()), info, grads(model)


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    """``max |a - b| / max |b|`` (``b`` the reference)."""
    return float((a - b).abs().max() / b.abs().max().clamp(min=1e-300))


def rel_dev(a: torch.Tensor, b: torch.Tensor) -> float:
    """Worst per-sample ``|a - b|_inf / (1 + |b|_inf)``."""
    return float(((a - b).abs().amax(-1) / (1.0 + b.abs().amax(-1))).max())


def lcp_terms(model, data):
    """``q = D x + E u + c`` and ``r = A x + B u + d - x'`` (detached)."""
    with torch.no_grad():
        q = data.x @ model.D.mT + data.u @ model.E.mT + model.c
        r = data.x @ model.A.mT + data.u @ model.B.mT + model.d - data.x_next
    return q, r


def violation_objective(model, data, lam, phi, gamma, eps):
    """Per-sample value of eq. (9b) at ``(lam, phi)``, written out from the paper:
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


def lemma3_gradients(model, data, lam, phi, gamma, eps, magnitude=False):
    """Eq. (10) as batch means, with F mapped back to G and H.

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


def certified_violation_solution(model, data, lam, phi, gamma, eps, dps=50, sweeps=6):
    """A certificate for the (V) minimiser, independent of the library's DPP form.

    Works on the paper's (lam, phi) QP (eq. (9b)) with Hessian
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
def violation_case(n_lam, setting):
    """One batch of 20 samples per ``(n_lam, setting)`` of :data:`SETTINGS`, with the fast path's
    answer: ``(model, data, gamma, eps, values, info)`` (``values``: (V)'s parameter values;
    ``info``: :func:`lcs_cvx.violation_loss_info`). Computed once; the model is the ground truth
    (gradients on: the layer's training configuration) in the stiff setting, a fresh
    ``LCS(stiffness=1.0, init_scale=0.3)`` in the paper's."""
    gamma, eps, stiffness = SETTINGS[setting]
    truth = lcs_cvx.random_lcs(6, 2, n_lam, stiffness=stiffness, seed=n_lam)
    data = lcs_cvx.make_dataset(truth, 20, noise=0.01, seed=100 + n_lam)
    if setting == "stiff":
        model = truth.requires_grad_(True)
    else:
        model = lcs_cvx.LCS(6, 2, n_lam, stiffness=1.0, init_scale=0.3, seed=n_lam)
    assert gamma < model.sigma_min
    info = lcs_cvx.violation_loss_info(model, data.x, data.u, data.x_next, gamma=gamma, eps=eps)
    q, r = lcp_terms(model, data)
    values = violation_problem(n_lam).parameter_values(model.C.detach(), model.F.detach(), q, r, gamma, eps)
    return model, data, gamma, eps, values, info


def violation_values(n_lam: int, setting: str, batch: int = 200, perturb: float = 0.05):
    """(V)'s parameter values for a random truth (the settings of :data:`SETTINGS`) moved by
    ``perturb * N(0, 1)`` in every parameter: a mid-training model, whose active sets are
    neither trivial nor the truth's."""
    gamma, eps, stiffness = SETTINGS[setting]
    truth = lcs_cvx.random_lcs(10, 4, n_lam, stiffness=stiffness, seed=n_lam)
    data = lcs_cvx.make_dataset(truth, batch, noise=1e-2, seed=7 + n_lam)
    gen = torch.Generator().manual_seed(n_lam)
    with torch.no_grad():
        for p in truth.parameters():
            p.add_(perturb * torch.randn(p.shape, generator=gen, dtype=F64))
        assert gamma < truth.sigma_min
        q = truth.lcp_offset(data.x, data.u)
        r = data.x @ truth.A.mT + data.u @ truth.B.mT + truth.d - data.x_next
        return violation_problem(n_lam).parameter_values(truth.C, truth.F, q, r, gamma, eps)


def simulated_runs(truth, lengths, seed=0, noise=0.0, x_range=2.0, u_range=1.0):
    """``lcs_cvx.Trajectories`` of ``truth`` from starts ``U[-x_range, x_range]`` under inputs
    ``U[-u_range, u_range]``, one run per entry of ``lengths`` (steps), states with Gaussian
    ``noise``."""
    rng = np.random.default_rng(seed)
    xs, us = [], []
    for T in lengths:
        u = rng.uniform(-u_range, u_range, (T, truth.n_u))
        x = truth.rollout(rng.uniform(-x_range, x_range, truth.n_x), u).detach().numpy()
        xs.append(x + noise * rng.standard_normal(x.shape))
        us.append(u)
    return lcs_cvx.Trajectories(xs, us)


def learned_like(seed=0, n_x=4, n_u=1, n_lam=3, skew=0.0):
    """An LCS with a learned model's traits for the controller's tests: dense ``F`` (``F + F^T``
    positive definite; ``skew (M - M^T)`` added: not symmetric), ``E`` not zero, units active at
    the origin."""
    rng = np.random.default_rng(seed)
    M = rng.standard_normal((n_lam, n_lam))
    F = M @ M.T + 0.5 * np.eye(n_lam)
    if skew:
        F = F + skew * (M - M.T)
    return lcs_cvx.LCS.from_matrices(
        A=np.eye(n_x) + 0.05 * rng.standard_normal((n_x, n_x)), B=0.1 * rng.standard_normal((n_x, n_u)),
        C=0.1 * rng.standard_normal((n_x, n_lam)), d=0.05 * rng.standard_normal(n_x),
        D=rng.standard_normal((n_lam, n_x)), E=rng.standard_normal((n_lam, n_u)),
        F=F, c=-np.abs(rng.standard_normal(n_lam)))
