r"""Second-order steps on ``L_eps + omega ||C||_F^2``: Gauss--Newton and damped Newton (Lemma 4).

Both are Levenberg--Marquardt iterations: a step is tried, kept if the regularised loss
decreases, otherwise undone with the damping ``mu`` raised ten-fold; after a kept step ``mu``
falls three-fold. Each call makes one kept step or gives up after ``max_tries``.

Gauss--Newton. ``l_t = 1/2 ||rho_t||^2 + lam_t^T phi_t / eps`` with the residuals
``rho_t = [e_dyn; (F lam + q - phi) / sqrt(eps gamma)]`` evaluated at the solution
``z_t(theta) = (lam_t, phi_t)``. The Gauss--Newton matrix is ``mean_t J_t^T J_t`` (PSD) with the
*total* Jacobian ``J_t = d rho_t / d theta = rho_theta + rho_z dz_t/dtheta`` and
``dz_F/dtheta = -(J_zz)_FF^{-1} (J_ztheta)_F`` (the sensitivity of Lemma 4's proof); the gradient
is Lemma 3's. Why not the cheaper matrix with ``z`` held fixed (``I (x) mean zeta zeta^T`` with
``zeta = [x; u; lam; 1]``, Kronecker-structured, a majorise--minimise step)? Its curvature in
``(D, E, F, c)`` is ``1/(eps gamma)`` while ``L_eps``'s is not: it ignores that ``z`` follows
``theta``, so its steps are tiny and it stalls far from the minimum, where this Gauss--Newton and
Newton converge (the documentation's Benchmarks page, "Measurements behind the training
defaults", has the comparison).

Newton. The full Hessian of Lemma 4 (:func:`lcs_cvx.violation_hessian`, dense for up to
``dense_max`` parameters) or its products (:func:`lcs_cvx.hessian.hvp_operator`, truncated
conjugate gradients) in the model's own parameters, damped by ``mu`` until positive definite, with a
backtracking (Armijo) line search on the regularised loss.

Known structure (:mod:`lcs_cvx.parameter_constraints`). Both steps move only the free coordinates ``f``
(:func:`lcs_cvx.parameter_constraints.free_vector`: not fixed, not masked): the step solves
``(M_ff + mu I) d_f = -g_f`` -- the dense matrix indexed, or conjugate gradients on the operator
projected onto the free coordinates -- and ``d`` is exactly 0 elsewhere, so fixed parameters come
back bit-identical and masked entries stay 0. This is the step of the reduced problem in the free
coordinates alone (its Gauss--Newton matrix and Hessian are the principal submatrices).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from ._checks import as_transitions
from .hessian import (
    flatten_parameters,
    hvp_operator,
    objective_jacobians,
    objective_linearisation,
    parameter_slices,
    setup,
    violation_hessian,
)
from .losses import regularizer, violation_fast
from .parameter_constraints import check_learnable, free_vector
from .system import LCS, PARAMETER_NAMES

__all__ = [
    "StepResult",
    "gauss_newton_matrix",
    "gauss_newton_operator",
    "gauss_newton_step",
    "newton_step",
]


@dataclass(frozen=True)
class StepResult:
    """Outcome of one second-order step.

    Attributes:
        loss: regularised loss after the step (before it if ``accepted`` is False).
        accepted: whether a decreasing step was found.
        damping: the damping ``mu`` to use next.
        tries: trial steps evaluated.
        n_fallback: samples the fast solver handed to the reference over the step's solves of (V).
        fallback_residual: the worst relative KKT residual of those reference answers (0.0: none).
    """

    loss: float
    accepted: bool
    damping: float
    tries: int
    n_fallback: int = 0
    fallback_residual: float = 0.0


class _Objective:
    """``L_eps + omega ||C||^2`` on one batch (validated once), counting the fallbacks of its
    solves of (V)."""

    def __init__(self, model: LCS, x, u, x_next, gamma: float, eps: float, reg: float) -> None:
        self.model, self.gamma, self.eps, self.reg = model, gamma, eps, reg
        self.x, self.u, self.x_next = as_transitions(model, x, u, x_next)
        self.n_fallback, self.fallback_residual = 0, 0.0

    def __call__(self) -> torch.Tensor:
        info = violation_fast(self.model, self.x, self.u, self.x_next, gamma=self.gamma, eps=self.eps)
        self.n_fallback += info.n_fallback
        self.fallback_residual = max(self.fallback_residual, info.fallback_residual)
        return info.loss + regularizer(self.model, self.reg)

    def result(self, loss: float, accepted: bool, damping: float, tries: int) -> StepResult:
        return StepResult(loss, accepted, damping, tries, self.n_fallback, self.fallback_residual)


def _assign(model: LCS, values: dict[str, torch.Tensor]) -> None:
    with torch.no_grad():
        for k, v in values.items():
            getattr(model, k).copy_(v)


def _snapshot(model: LCS) -> dict[str, torch.Tensor]:
    return {k: getattr(model, k).detach().clone() for k in PARAMETER_NAMES}


def _rho_z(model: LCS, gamma: float, eps: float) -> torch.Tensor:
    """``d rho / d z`` ``(n_x + n, 2 n)``, the same for every sample."""
    n, scale = model.n_lam, 1.0 / math.sqrt(eps * gamma)
    with torch.no_grad():
        kw = {"dtype": model.dtype, "device": model.device}
        eye = torch.eye(n, **kw)
        top = torch.cat([model.C, torch.zeros(model.n_x, n, **kw)], 1)
        return torch.cat([top, torch.cat([model.F * scale, -eye * scale], 1)], 0)


def gauss_newton_matrix(
    model: LCS, x: torch.Tensor, u: torch.Tensor, x_next: torch.Tensor, gamma: float, eps: float
) -> torch.Tensor:
    """``mean_t J_t^T J_t`` ``(P, P)`` with the total residual Jacobian (module docstring).

    Costs ``O(N r P^2)``: for small models; :func:`gauss_newton_operator` for large ones.
    """
    x, u, x_next, z, m, chol = setup(model, x, u, x_next, gamma, eps)
    J_theta, Jzt = objective_jacobians(model, x, u, x_next, z, gamma, eps)  # z fixed
    with torch.no_grad():
        # J_t = rho_theta + rho_z dz/dtheta with dz_F = -(J_zz)_FF^{-1} (J_ztheta)_F:
        # first the small per-sample (r, 2n) factor rho_z (m o M^{-1} o m), then one bmm
        inv_masked = torch.cholesky_solve(torch.diag_embed(m), chol) * m[:, :, None]
        Jt = torch.baddbmm(J_theta, _rho_z(model, gamma, eps) @ inv_masked, Jzt, alpha=-1.0)
        Jt = Jt.reshape(-1, Jt.shape[-1])
        return (Jt.mT @ Jt) / x.shape[0]


def gauss_newton_operator(
    model: LCS, x: torch.Tensor, u: torch.Tensor, x_next: torch.Tensor, gamma: float, eps: float
) -> Callable[[torch.Tensor], torch.Tensor]:
    """``v -> mean_t J_t^T J_t v`` without forming the matrix: ``J v`` by the closed-form
    products of :func:`lcs_cvx.hessian.objective_linearisation` and a batched Cholesky solve,
    ``J^T w`` by their transposes. ``O(N r n)`` per product."""
    x, u, x_next, z, m, chol = setup(model, x, u, x_next, gamma, eps)
    jvp, vjp = objective_linearisation(model, x, u, x_next, z, gamma, eps)
    rho_z = _rho_z(model, gamma, eps)
    N = x.shape[0]
    with torch.no_grad():  # m o (J_zz)_FF^{-1} o m per sample, factored once for all products
        inv_masked = torch.cholesky_solve(torch.diag_embed(m), chol) * m[:, :, None]

    def solve(y: torch.Tensor) -> torch.Tensor:
        return (inv_masked @ y.unsqueeze(-1)).squeeze(-1)

    def matvec(v: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            Jv_theta, Jzt_v = jvp(v)
            w = Jv_theta - solve(Jzt_v) @ rho_z.mT  # J v, (B, r)
            return vjp(w, -solve(w @ rho_z)) / N

    return matvec


def gauss_newton_step(
    model: LCS,
    x: torch.Tensor,
    u: torch.Tensor,
    x_next: torch.Tensor,
    *,
    gamma: float,
    eps: float,
    reg: float,
    damping: float,
    dense_max: int = 500,
    cg_iters: int = 100,
    max_tries: int = 8,
) -> StepResult:
    """One Levenberg--Marquardt step ``(GN + diag(2 omega P_C) + mu I) d = -g``; see the module
    docstring. ``x, u, x_next``: the full batch or a large one; ``damping``: ``mu >= 0``;
    ``dense_max``: the largest parameter count for which GN is formed and factored (above it:
    conjugate gradients on :func:`gauss_newton_operator`, ``cg_iters`` of them).

    The model is updated in place when the step decreases the regularised loss.
    """
    P = sum(getattr(model, k).numel() for k in PARAMETER_NAMES)
    if P <= dense_max:
        return _damped_step(
            model, x, u, x_next, gamma=gamma, eps=eps, reg=reg, damping=damping,
            matrix=lambda: gauss_newton_matrix(model, x, u, x_next, gamma, eps),
            line_search=False, max_tries=max_tries,
        )
    op = gauss_newton_operator(model, x, u, x_next, gamma, eps)
    return _damped_step(
        model, x, u, x_next, gamma=gamma, eps=eps, reg=reg, damping=damping, matrix=None,
        line_search=False, max_tries=max_tries, hvp=op, cg_iters=cg_iters,
    )


def _cg(hvp, g: torch.Tensor, iters: int, tol: float = 1e-3) -> torch.Tensor:
    """Truncated conjugate gradients for ``H d = -g`` to relative residual ``tol`` (an inexact
    Newton step); stops at negative curvature (Steihaug)."""
    d = torch.zeros_like(g)
    r = -g.clone()
    p = r.clone()
    rr = float(r @ r)
    for _ in range(iters):
        Hp = hvp(p)
        curv = float(p @ Hp)
        if curv <= 0:
            return d if float(d @ d) > 0 else -g
        alpha = rr / curv
        d = d + alpha * p
        r = r - alpha * Hp
        rr_new = float(r @ r)
        if rr_new <= tol * tol * float(g @ g):
            break
        p = r + (rr_new / rr) * p
        rr = rr_new
    return d


def newton_step(
    model: LCS,
    x: torch.Tensor,
    u: torch.Tensor,
    x_next: torch.Tensor,
    *,
    gamma: float,
    eps: float,
    reg: float,
    damping: float,
    dense_max: int = 500,
    cg_iters: int = 50,
    max_tries: int = 8,
) -> StepResult:
    """One damped Newton step with Lemma 4's Hessian and an Armijo line search.

    Args: as :func:`gauss_newton_step`; ``dense_max``: largest parameter count for which the
    Hessian is formed (above it: CG on Hessian-vector products, ``cg_iters`` of them).
    """
    P = sum(getattr(model, k).numel() for k in PARAMETER_NAMES)
    matrix = None
    if P <= dense_max:
        matrix = lambda: violation_hessian(model, x, u, x_next, gamma, eps)  # noqa: E731
    return _damped_step(
        model, x, u, x_next, gamma=gamma, eps=eps, reg=reg, damping=damping, matrix=matrix,
        line_search=True, max_tries=max_tries,
        hvp=None if matrix is not None else hvp_operator(model, x, u, x_next, gamma, eps),
        cg_iters=cg_iters,
    )


def _damped_step(
    model: LCS,
    x: torch.Tensor,
    u: torch.Tensor,
    x_next: torch.Tensor,
    *,
    gamma: float,
    eps: float,
    reg: float,
    damping: float,
    matrix: Callable[[], torch.Tensor] | None,
    line_search: bool,
    max_tries: int,
    hvp: Callable[[torch.Tensor], torch.Tensor] | None = None,
    cg_iters: int = 50,
) -> StepResult:
    """Levenberg--Marquardt loop shared by both steps: solve ``(M + mu I) d = -g`` (dense
    Cholesky, or CG on ``hvp``), try ``theta + t d`` (``t = 1``, halved ``line_search`` times),
    keep it if the regularised loss decreases (Armijo), else raise ``mu``. Only the free
    coordinates move (module docstring)."""
    check_learnable(model)
    params = [getattr(model, k) for k in PARAMETER_NAMES]
    theta0 = flatten_parameters(model)
    slices = parameter_slices(model)
    free = free_vector(model)
    constrained = not bool(free.all())
    objective = _Objective(model, x, u, x_next, gamma, eps, reg)
    loss = objective()
    learned = [p for p in params if p.requires_grad]  # a fixed parameter has no gradient
    grads = iter(torch.autograd.grad(loss, learned))
    g = torch.cat([next(grads).reshape(-1) if p.requires_grad else torch.zeros_like(p).reshape(-1)
                   for p in params]).detach()
    if constrained:
        g = torch.where(free, g, 0.0)
        idx = free.nonzero().squeeze(1)
    loss0 = float(loss.detach())
    reg_diag = torch.zeros_like(theta0)
    reg_diag[slices["C"]] = 2.0 * reg  # Hessian of omega ||C||^2
    Mx = None
    if matrix is not None:
        Mx = matrix() + torch.diag(reg_diag)
        Mx = 0.5 * (Mx + Mx.mT)
        if constrained:  # the reduced problem's matrix: the principal submatrix
            Mx = Mx[idx][:, idx]
        eye = torch.eye(Mx.shape[0], dtype=theta0.dtype, device=theta0.device)
    old = _snapshot(model)
    mu = float(damping)
    for tries in range(1, max_tries + 1):
        if Mx is not None:
            chol, info = torch.linalg.cholesky_ex(Mx + mu * eye)
            if int(info) != 0:
                mu = max(10.0 * mu, 1e-8)
                continue
            if constrained:
                d = torch.zeros_like(g)
                d[idx] = -torch.cholesky_solve(g[idx, None], chol).squeeze(1)
            else:
                d = -torch.cholesky_solve(g[:, None], chol).squeeze(1)
        else:
            assert hvp is not None
            if constrained:  # CG on the operator projected onto the free coordinates
                d = _cg(lambda v, mu=mu: torch.where(free, hvp(v) + (reg_diag + mu) * v, 0.0),
                        g, cg_iters)
                d = torch.where(free, d, 0.0)
            else:
                d = _cg(lambda v, mu=mu: hvp(v) + (reg_diag + mu) * v, g, cg_iters)
        slope = float(g @ d)
        if not slope < 0:
            mu = max(10.0 * mu, 1e-8)
            continue
        t = 1.0
        for _ in range(12 if line_search else 1):
            theta = theta0 + t * d
            _assign(model, {k: theta[sl].reshape(old[k].shape) for k, sl in slices.items()
                            if params[PARAMETER_NAMES.index(k)].requires_grad})  # fixed: untouched
            with torch.no_grad():
                ok = model.sigma_min > gamma
                loss1 = float(objective()) if ok else math.inf
            if loss1 <= loss0 + 1e-4 * t * slope:
                return objective.result(loss1, True, mu / 3.0 if t == 1.0 else mu, tries)
            t *= 0.5
        _assign(model, old)
        mu = max(10.0 * mu, 1e-8)
    _assign(model, old)
    return objective.result(loss0, False, mu, max_tries)
