r"""The LCS of each sample (:class:`SampleLCS`: one built at each state, e.g. by
:class:`lcs_cvx.RigidBodyContact`), and its LCP, violation loss and prediction loss.

Sample ``t`` has its own ``C_t`` ``(m, n)``, ``F_t`` ``(n, n)`` (``F_t + F_t^T`` positive
definite), ``q_t`` and the contact-free prediction ``r0_t`` of the rows ``x'[rows]``; the rows
are weighted by a fixed metric ``W = diag(weight)``. Per sample, with ``e = W^{1/2}(r0 + C lam -
x'[rows])``:

- the LCP, eq. (2): ``0 <= lam _|_ F lam + q >= 0``, exact by block pivoting, each sample its own
  problem (the stacked kernels with one sample per model); :func:`solve_sample_lcp` is
  differentiable in ``F, q`` by the implicit function on the free set (Lemma 1);
- (V), eq. (9b): ``min_{lam, phi >= 0} 1/2 |e|^2 + (1/eps)(lam^T phi + |F lam + q - phi|^2 /
  (2 gamma))`` with ``0 < gamma < sigma_min(F_t + F_t^T)`` at every sample (Lemma 2). Solved
  without autograd (the stacked pivoting kernel of :mod:`lcs_cvx._kernels.violation`, unconverged
  samples by the Clarabel reference, counted); the objective is then evaluated in torch at the
  detached optimum, so autograd gives Lemma 3's envelope gradient through the matrices into the
  model's parameters (:func:`violation_loss_info`);
- the prediction loss, eq. (6): ``1/2 |e|^2`` at the exact LCP solution (:func:`prediction_loss_info`);
- Lemma 4's Hessian of ``L_eps`` in the model's learnable parameters (:func:`violation_hessian`).

``solver="cvxpylayers"`` solves the same declared problems (:func:`lcs_cvx.violation_problem`,
:func:`lcs_cvx.convex_lcp_problem`) as ``cvxpylayers`` layers with per-sample (batched)
parameters: the reference the fast path is checked against.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from ._checks import LCSInputError, SolverError, check_positive
from ._kernels import lcp as kernel_lcp
from ._kernels import violation as kernel_violation
from ._kernels.arrays import TORCH
from .layers import lcp_layer, solve_layer, violation_layer
from .losses import MAX_ITER, LossInfo
from .problems import convex_lcp_problem, violation_problem

__all__ = ["SampleLCS", "solve_sample_lcp", "violation_loss_info", "prediction_loss_info", "model_loss_info",
           "sample_residual", "violation_hessian"]

SOLVERS = ("fast", "cvxpylayers", "cvxpylayers-scs")


@dataclass(frozen=True)
class SampleLCS:
    r"""The velocity rows of eq. (1) at each sample, with per-sample matrices:

    ``x'[rows] = r0 + C lam``, ``0 <= lam _|_ F lam + q >= 0``.

    Attributes:
        rows: the state indices these rows predict (the velocities; the other rows follow from
            them exactly).
        r0: ``(N, m)`` the prediction without contact (``nu_free``).
        C: ``(N, m, n)``; F: ``(N, n, n)`` (``F + F^T`` positive definite); q: ``(N, n)``.
        weight: ``(m,)`` the weight of each row in the losses (a fixed metric on the velocities).
        sigma_min_bound: a lower bound of ``sigma_min(F + F^T)`` at every sample (Lemma 2's bound
            on ``gamma``).
    """

    rows: tuple[int, ...]
    r0: torch.Tensor
    C: torch.Tensor
    F: torch.Tensor
    q: torch.Tensor
    weight: torch.Tensor
    sigma_min_bound: float


def _fast_lcp(F: torch.Tensor, q: torch.Tensor, warm_start: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, int]:
    """``(lam, free, n_fallback)`` of the per-sample LCPs ``(F_t (N, n, n), q_t (N, n))``
    (detached): pivoting with one sample per model, unconverged samples by Clarabel on (P)."""
    with torch.no_grad():
        Fd, qd = F.detach(), q.detach()
        sol = kernel_lcp.solve(Fd, qd, max_iter=MAX_ITER, warm_start=warm_start)
        lam, free = sol.lam.clone(), sol.free.clone()
        n_fb = 0
        if sol.unconverged is not None:
            n_fb = int(sol.unconverged.numel())
            decl = convex_lcp_problem(q.shape[1])
            for i in sol.unconverged.tolist():
                lam[i] = decl.solve(Fd[i], qd[i:i + 1])[0].clamp(min=0.0)
                free[i] = lam[i] > (Fd[i] @ lam[i] + qd[i])
        return lam, free, n_fb


def solve_sample_lcp(lcs: SampleLCS) -> torch.Tensor:
    """``lam`` ``(N, n)`` of each sample's LCP ``(F_t, q_t)``, eq. (2); differentiable in ``F``
    and ``q`` (Lemma 1: ``lam_I = -F_II^{-1} q_I`` on the solution's free set)."""
    lam, free, _ = _fast_lcp(lcs.F, lcs.q)
    if torch.is_grad_enabled() and (lcs.F.requires_grad or lcs.q.requires_grad):
        from .lcp import active_set_solve

        return active_set_solve(lcs.F, lcs.q, free)
    return lam


def sample_residual(lcs: SampleLCS, x_next: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(C_w (N, m, n), r_w (N, m))``: ``W^{1/2} C`` and ``W^{1/2} (r0 - x'[rows])``."""
    w = lcs.weight.sqrt()
    rows = torch.as_tensor(lcs.rows, device=x_next.device)
    return w[:, None] * lcs.C, w * (lcs.r0 - x_next.index_select(1, rows))


def _normal(C: torch.Tensor, F: torch.Tensor, q: torch.Tensor, r: torch.Tensor, gamma: float,
            eps: float) -> dict[str, torch.Tensor]:
    """(V)'s normal equations per sample (the kernel's one formula, samples as a stack of models)."""
    N, n = q.shape
    out = kernel_violation.normal_equations(TORCH, C, F, q[:, None], r[:, None], gamma, eps)
    return {"LtL": out["LtL"], "Ltb": out["Ltb"].reshape(N, n), "K": out["K"], "h": out["h"].reshape(N, n)}


def _check(gamma: float, eps: float, lcs: SampleLCS, solver: str) -> None:
    check_positive("gamma", gamma)
    check_positive("eps", eps)
    if solver not in SOLVERS:
        raise LCSInputError(f"solver: expected one of {SOLVERS}, received {solver!r}")
    if not gamma < lcs.sigma_min_bound:
        raise LCSInputError(f"gamma: expected 0 < gamma < {lcs.sigma_min_bound:.6g}, the bound of sigma_min(F + F^T) "
                            f"at every state (Lemma 2: twice the model's least compliance), received {gamma!r}; "
                            "lower gamma or raise the compliance")


def violation_loss_info(lcs: SampleLCS, x_next: torch.Tensor, gamma: float, eps: float, *,
                        solver: str = "fast", warm_start: torch.Tensor | None = None) -> LossInfo:
    """The violation loss ``L_eps`` (eq. (9)), the mean over the samples of (V) with their own
    matrices, and its diagnostics; ``loss`` differentiable (Lemma 3's envelope gradient on the
    fast path; diffcp through the declared (V) on the layer paths). ``warm_start``: ``(N, 2 n)``
    bool ``[free, pos]`` of an earlier solve of the same samples."""
    _check(gamma, eps, lcs, solver)
    C, r = sample_residual(lcs, x_next)
    F, q = lcs.F, lcs.q
    n = q.shape[1]
    decl = violation_problem(n)
    if solver != "fast":
        values = decl.factor(_normal(C, F, q, r, gamma, eps))
        lam = solve_layer(violation_layer(n), [values[k] for k in decl.parameter_order],
                          "scs" if solver == "cvxpylayers-scs" else "clarabel").clamp(min=0.0)
        phi = kernel_violation.phi(TORCH, lam[:, None], F, q[:, None], gamma)[:, 0]
        loss = decl.objective(lam, phi, C, F, q, r, gamma, eps).mean()
        return LossInfo(loss, lam.detach(), phi=phi.detach())
    with torch.no_grad():
        normal = {k: v.detach() for k, v in _normal(C, F, q, r, gamma, eps).items()}
        sol = kernel_violation.solve(normal, max_iter=MAX_ITER, warm_start=warm_start)
        lam, active = sol.lam.clone(), sol.active.clone()
        n_fb = 0
        if sol.unconverged is not None:  # the Clarabel reference on those samples' declared (V)
            n_fb = int(sol.unconverged.numel())
            bad = sol.unconverged
            values = decl.factor({k: v[bad] for k, v in normal.items()})
            for j, i in enumerate(bad.tolist()):
                lam[i] = decl.solve({"L": values["L"][j], "b": values["b"][j:j + 1], "K": values["K"][j],
                                     "h": values["h"][j:j + 1]})[0]
                active[i] = torch.cat([lam[i] > 0, (normal["K"][i] @ lam[i] - normal["h"][i]) > 0])
        phi = kernel_violation.phi(TORCH, lam[:, None], F.detach(), q.detach()[:, None], gamma)[:, 0]
    loss = decl.objective(lam, phi, C, F, q, r, gamma, eps).mean()
    return LossInfo(loss, lam, phi=phi, iterations=sol.iterations, n_fallback=n_fb, active=active)


def prediction_loss_info(lcs: SampleLCS, x_next: torch.Tensor, *, solver: str = "fast",
                         warm_start: torch.Tensor | None = None) -> LossInfo:
    """The prediction loss (eq. (6)), the mean over the samples of ``1/2 |W^{1/2}(r0 + C lam -
    x'[rows])|^2`` at the exact LCP solution; differentiable (Lemma 1 on the fast path, diffcp
    through the declared (P) on the layer paths). ``warm_start``: ``(N, n)`` free sets."""
    if solver not in SOLVERS:
        raise LCSInputError(f"solver: expected one of {SOLVERS}, received {solver!r}")
    C, r = sample_residual(lcs, x_next)
    F, q = lcs.F, lcs.q
    n = q.shape[1]
    if solver != "fast":
        decl = convex_lcp_problem(n)
        values = decl.parameter_values(F, q)  # R^T R = F + F^T per sample
        lam = solve_layer(lcp_layer(n), [values[k] for k in decl.parameter_order],
                          "scs" if solver == "cvxpylayers-scs" else "clarabel")
        lam, free, n_fb = lam.clamp(min=0.0), None, 0
    else:
        lam_d, free, n_fb = _fast_lcp(F, q, warm_start)
        from .lcp import active_set_solve

        lam = active_set_solve(F, q, free) if torch.is_grad_enabled() and (F.requires_grad or q.requires_grad) else lam_d
    e = (C @ lam[..., None])[..., 0] + r
    loss = 0.5 * (e * e).sum(-1).mean()
    w = ((F @ lam[..., None])[..., 0] + q).detach()
    return LossInfo(loss, lam.detach(), w=w, active=free, n_fallback=n_fb)


def model_loss_info(kind: str, model: Any, x: torch.Tensor, u: torch.Tensor, x_next: torch.Tensor, *,
                    gamma: float = 1e-2, eps: float = 1e-4, solver: str = "fast",
                    warm_start: torch.Tensor | None = None) -> LossInfo:
    """:func:`violation_loss_info` (``kind="violation"``) or :func:`prediction_loss_info` of
    ``model.sample_lcs(x, u)`` on validated tensors: the losses of :mod:`lcs_cvx.losses` for a
    model with per-sample matrices (its ``loss_info``, and the trainer's steps)."""
    lcs = model.sample_lcs(x, u)
    if kind == "violation":
        return violation_loss_info(lcs, x_next, gamma, eps, solver=solver, warm_start=warm_start)
    return prediction_loss_info(lcs, x_next, solver=solver, warm_start=warm_start)


class _Matrices(nn.Module):
    """``model.sample_lcs`` as a module call (for :func:`torch.func.functional_call`)."""

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, x: torch.Tensor, u: torch.Tensor, x_next: torch.Tensor) -> tuple[torch.Tensor, ...]:
        lcs = self.model.sample_lcs(x, u)
        C, r = sample_residual(lcs, x_next)
        return C, lcs.F, lcs.q, r


def violation_hessian(model: Any, x: Any, u: Any, x_next: Any, gamma: float = 1e-2, eps: float = 1e-4
                      ) -> torch.Tensor:
    r"""Lemma 4's Hessian of ``L_eps`` (the batch mean of (V), :func:`violation_loss_info`) in the
    learnable parameters ``theta`` of a model with per-sample matrices (a
    :class:`lcs_cvx.RigidBodyContact`):

    ``hess L = mean_t [J_thth - (J_thz)_F (J_zz)_FF^{-1} (J_zth)_F]``

    at the solution ``z_t = (lam_t, phi_t)`` of each sample's (V), ``F_t`` its free set (the
    reduction of :mod:`lcs_cvx.hessian`), with ``J_zz`` per sample
    (:meth:`lcs_cvx.problems.ViolationProblem.hessian_zz` of ``(C_t, F_t)``). The matrices are
    nonlinear in ``theta`` here, so ``J_thth`` (``z`` fixed) and ``J_zth`` are taken by autograd
    through ``model.sample_lcs`` (reverse over reverse, one pass per parameter entry) rather
    than written out.

    ``theta``: the model's parameters with ``requires_grad``, in ``named_parameters()`` order,
    each flattened row-major. Returns ``(P, P)`` (no autograd graph), defined where strict
    complementarity holds on every sample (Lemma 3(b)). :func:`lcs_cvx.violation_hessian`
    calls this for such a model.
    """
    x, u, x_next = model.transitions(x, u, x_next)
    with torch.no_grad():
        lcs = model.sample_lcs(x, u)
        info = violation_loss_info(lcs, x_next, gamma, eps)  # checks gamma and eps
        z = torch.cat([info.lam, info.phi], dim=1)
        m = (z > 0).to(z.dtype)
        C, r = sample_residual(lcs, x_next)
        Jzz = violation_problem(info.lam.shape[1]).hessian_zz(C, lcs.F, gamma, eps)
        eye = torch.eye(z.shape[1], dtype=z.dtype, device=z.device)
        chol, bad = torch.linalg.cholesky_ex(Jzz * (m[:, :, None] * m[:, None, :]) + eye * (1.0 - m)[:, None, :])
    if bool((bad != 0).any()):  # not expected: (J_zz)_FF is positive definite (Lemma 3(a))
        raise SolverError(f"(J_zz)_FF not positive definite on {int((bad != 0).sum())} samples")
    named = [(k, p) for k, p in model.named_parameters() if p.requires_grad]
    theta = torch.cat([p.detach().reshape(-1) for _, p in named])
    call, n = _Matrices(model), info.lam.shape[1]
    decl = violation_problem(n)

    def objective(th: torch.Tensor, zz: torch.Tensor) -> torch.Tensor:
        values, i = {}, 0
        for k, p in named:
            values[f"model.{k}"] = th[i:i + p.numel()].reshape(p.shape)
            i += p.numel()
        Ct, Ft, qt, rt = torch.func.functional_call(call, values, (x, u, x_next))
        return decl.objective(zz[:, :n], zz[:, n:], Ct, Ft, qt, rt, gamma, eps).sum() / z.shape[0]

    with torch.enable_grad():
        th, zz = theta.clone().requires_grad_(True), z.clone().requires_grad_(True)
        g_th, g_z = torch.autograd.grad(objective(th, zz), (th, zz), create_graph=True)
        # directional derivatives along each e_p by reverse over reverse: J_thth's rows from
        # g_th; J_zth's columns as the vjp in w of (d g_z / d theta)^T w, which is linear in w
        w = torch.zeros_like(g_z, requires_grad=True)
        g_w = torch.autograd.grad(g_z, th, w, create_graph=True)[0]
        basis = torch.eye(theta.numel(), dtype=theta.dtype, device=theta.device)
        H = torch.stack([torch.autograd.grad(g_th, th, e, retain_graph=True)[0] for e in basis])
        Jzt = torch.stack([torch.autograd.grad(g_w, w, e, retain_graph=True)[0] for e in basis], dim=-1)
    Y = torch.linalg.solve_triangular(chol, m[:, :, None] * Jzt * z.shape[0], upper=False)  # (N, 2n, P)
    return (H - torch.einsum("tip,tiq->pq", Y, Y) / z.shape[0]).detach()
