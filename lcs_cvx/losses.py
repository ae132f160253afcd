r"""The two learning losses of the paper and the regulariser.

- :func:`violation_loss` -- ``L_eps`` of eq. (equ.contactnet), the batch mean of the optimal
  value of (V). The solver runs without autograd; the (lam, phi) objective is then evaluated at
  the detached optimum with the envelope gradients of Lemma 3 as its backward
  (``grad_A = mean e_dyn x^T``, ``grad_D = mean e_lcp x^T``, ...; :class:`_EnvelopeLoss`, which
  equals autograd through the objective): no solver differentiation, no matrix inverse.
- :func:`prediction_loss` -- ``L_pred`` of eq. (equ.prednet), the batch mean of
  ``1/2 ||x'_theta - x'||^2`` with ``lam`` the exact LCP solution. Its gradient is the implicit
  function theorem on the solution's active set (Lemma 1): ``lam_I = -F_II^{-1} q_I`` is
  re-expressed differentiably on the free set found by the solver. An index with
  ``lam_i = w_i = 0`` (strict complementarity fails) is held at zero -- the one-sided derivative
  in which that constraint stays active; such samples are counted in :class:`LossInfo`.
- :func:`regularizer` -- ``omega ||C||_F^2`` (paper Sec. 5).

``solver`` selects the path: ``"fast"`` (batched kernels, default), ``"cvxpylayers"``
(diffcp + Clarabel over the declared problem) or ``"cvxpylayers-scs"`` (diffcp + SCS).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import torch

from ._checks import LCSInputError, as_batch, check_positive
from .layers import lcp_layer, solve_layer, violation_layer
from .lcp import lcp_residual, solve_lcp_fast
from .pivoting import ArrayOps, array_ops
from .problems import convex_lcp_problem, violation_problem
from .system import PARAMETER_NAMES, F_adjoint, F_matrix
from .violation import solve_arrays, violation_kkt_residual

__all__ = [
    "LossInfo",
    "LayerAccuracyWarning",
    "violation_loss",
    "prediction_loss",
    "regularizer",
    "SOLVERS",
]

SOLVERS = ("fast", "cvxpylayers", "cvxpylayers-scs")

#: A layer solution whose relative KKT residual exceeds this is reported (LayerAccuracyWarning).
LAYER_RESIDUAL_TOL = 1e-6


class LayerAccuracyWarning(RuntimeWarning):
    """A cvxpylayers solve came back inaccurate (diffcp does not check its cone solver's status)."""


def _check_layer(residual: torch.Tensor, what: str) -> float:
    bad = int((residual > LAYER_RESIDUAL_TOL).sum())
    worst = float(residual.max())
    if bad:
        warnings.warn(
            f"{what}: {bad} of {residual.numel()} layer solutions have a relative KKT residual "
            f"above {LAYER_RESIDUAL_TOL:g} (worst {worst:.2e}); the 'fast' path is exact",
            LayerAccuracyWarning,
            stacklevel=3,
        )
    return worst


#: A complementarity pair counts as degenerate when both ``lam_i`` and ``w_i`` are below this,
#: relative to ``1 + |q|_inf``.
DEGENERATE_TOL = 1e-9


@dataclass(frozen=True)
class LossInfo:
    """Diagnostics of one loss evaluation.

    Attributes:
        lam: ``(B, n_lam)`` the per-sample ``lam`` (detached).
        phi: ``(B, n_lam)`` (violation loss) or ``w = F lam + q`` (prediction loss), detached.
        iterations: pivoting sweeps of the fast solver (0 on the layer paths).
        n_fallback: samples the fast solver handed to the Clarabel reference.
        n_degenerate: samples with some ``lam_i = w_i = 0`` (prediction loss; 0 otherwise).
        max_residual: largest relative KKT residual over the batch (on every path; a layer
            solution above ``LAYER_RESIDUAL_TOL`` also raises a :class:`LayerAccuracyWarning`).
        active: the fast solver's final active sets, bool -- ``(B, 2 n_lam)`` ``[lam_i > 0,
            phi_i = 0]`` (violation) or ``(B, n_lam)`` ``lam_i > 0`` (prediction) -- to pass as
            ``warm_start`` when the same samples come again; None on the layer paths.
    """

    lam: torch.Tensor
    phi: torch.Tensor
    iterations: int = 0
    n_fallback: int = 0
    n_degenerate: int = 0
    max_residual: float = 0.0
    active: torch.Tensor | None = None
    loss: torch.Tensor | None = None


def _parameter_gradients(xp: ArrayOps, need: tuple[bool, ...], x, u, lam, G, g_r, g_q) -> tuple:
    """The gradients of ``A, B, C, d, D, E, G, H, c`` (None where ``need`` is False) of a loss
    whose sensitivities to ``r = A x + B u + d - x' + C lam`` and to ``q = D x + E u + c + F lam``
    (``lam`` held fixed) are ``g_r`` ``(B, n_x)`` and ``g_q`` ``(B, n)``: ``dA = g_r^T x``,
    ``dC = g_r^T lam``, ``dd = sum_t g_r``, ``dD = g_q^T x``, ``dF = g_q^T lam``, ..., and ``dG, dH``
    from ``dF`` (:func:`lcs_cvx.system.F_adjoint`). One small product per gradient, each
    contiguous as the parameters are laid out."""
    grT, gqT = g_r.mT, g_q.mT
    dG, dH = F_adjoint(gqT @ lam, G) if need[6] or need[7] else (None, None)
    return (grT @ x if need[0] else None, grT @ u if need[1] else None,
            grT @ lam if need[2] else None, xp.colsum(g_r) if need[3] else None,
            gqT @ x if need[4] else None, gqT @ u if need[5] else None,
            dG, dH, xp.colsum(g_q) if need[8] else None)


class _EnvelopeLoss(torch.autograd.Function):
    r"""Batch mean of (V)'s objective at a fixed optimum ``(lam, phi)``, with Lemma 3's gradients.

    ``apply(xp, arrays, gamma, eps, *params)``: the differentiable inputs are the model's
    parameters ``A, B, C, d, D, E, G, H, c`` (``params``); the value is computed from
    ``arrays = (x, u, q, r, F, C, G, lam, phi)``, the kernel arrays of :func:`_fast_arrays` (no
    copy of the parameters on CPU) and the optimum. Forward:
    ``mean_t 1/2 ||e_t||^2 + (lam_t^T phi_t + ||w_t||^2 / (2 gamma)) / eps`` with
    ``e = C lam + r`` and ``w = F lam + q - phi``. Backward, the envelope theorem (``lam`` and
    ``phi`` are optimal, so their variation does not contribute), with ``g_e = e / B`` and
    ``g_w = w / (gamma eps B)``::

        dA = g_e^T x,  dB = g_e^T u,  dC = g_e^T lam,  dd = sum_t g_e,
        dD = g_w^T x,  dE = g_w^T u,  dF = g_w^T lam,  dc = sum_t g_w,

    and ``dG, dH`` from ``dF`` by :func:`lcs_cvx.system.F_adjoint` -- one small product per
    gradient, no autograd graph. The same numbers as autograd through
    :meth:`ViolationProblem.objective` at the detached optimum (tested), at a fraction of the
    cost (the loss is called at every training step). Not twice differentiable; Lemma 4 lives
    in :mod:`lcs_cvx.hessian`.
    """

    @staticmethod
    def forward(ctx, xp, arrays, gamma: float, eps: float, *params):  # noqa: D102
        x, u, q, r, F, C, G, lam, phi = arrays
        e = r + lam @ C.mT
        w = q + lam @ F.mT - phi  # the association of the closed form
        n = lam.shape[0]
        total = 0.5 * xp.vdot(e, e) + (xp.vdot(lam, phi) + 0.5 / gamma * xp.vdot(w, w)) / eps
        # the residuals, already scaled by the gradient's 1/B and 1/(gamma eps B)
        ctx.saved = (xp, x, u, lam, G, e * (1.0 / n), w * (1.0 / (gamma * eps * n)))
        return xp.unwrap(total / n)

    @staticmethod
    def backward(ctx, grad):  # noqa: D102
        xp, x, u, lam, G, ge, gw = ctx.saved
        s = xp.scalar(grad)
        with xp.threads():
            grads = _parameter_gradients(xp, ctx.needs_input_grad[4:], x, u, lam, G, ge * s, gw * s)
        return (None,) * 4 + _tensors(xp, grads)


class _ImplicitLoss(torch.autograd.Function):
    r"""Batch mean of ``1/2 ||e_t||^2``, ``e = C lam + r``, at the exact LCP solution ``lam``, with
    Lemma 1's gradient in closed form.

    ``apply(xp, arrays, *params)``: the differentiable inputs are the model's parameters
    ``A, B, C, d, D, E, G, H, c`` (``params``); the value is computed from ``arrays = (x, u, r,
    F, C, G, lam, free)``, the kernel arrays of :func:`_fast_arrays` and the solution with its
    free sets (degenerate indices not free: held at zero, the one-sided derivative). On the free
    set ``I`` of a sample, ``F_II lam_I = -q_I`` and ``lam_J = 0``; with ``g_e = e / B``,
    ``g_lam = C^T g_e`` and the adjoint ``mu`` (``F_II^T mu_I = (g_lam)_I``, ``mu_J = 0``: one
    batched solve)::

        dA = g_e^T x,  dB = g_e^T u,  dC = g_e^T lam,  dd = sum_t g_e,
        dq = -mu:  dD = dq^T x,  dE = dq^T u,  dc = sum_t dq,  dF = dq^T lam,

    and ``dG, dH`` from ``dF`` by :func:`lcs_cvx.system.F_adjoint`. The same numbers as autograd
    through :func:`lcs_cvx.lcp.active_set_solve` (tested) without its graph.
    """

    @staticmethod
    def forward(ctx, xp, arrays, *params):  # noqa: D102
        x, u, r, F, C, G, lam, free = arrays
        e = r + lam @ C.mT
        n = lam.shape[0]
        total = 0.5 * xp.vdot(e, e)
        ctx.saved = (xp, x, u, lam, free, F, C, G, e * (1.0 / n))
        return xp.unwrap(total / n)

    @staticmethod
    def backward(ctx, grad):  # noqa: D102
        xp, x, u, lam, free, F, C, G, ge = ctx.saved
        n = F.shape[0]
        with xp.threads():
            ge = ge * xp.scalar(grad)
            F_II = xp.free_block(F.reshape(1, n * n), free)
            mu, _ = xp.solve(F_II.mT, xp.where(free, ge @ C, 0.0), spd=False)
            grads = _parameter_gradients(xp, ctx.needs_input_grad[2:], x, u, lam, G, ge, -mu)
        return (None,) * 2 + _tensors(xp, grads)


def _tensors(xp: ArrayOps, arrays: tuple) -> tuple:
    """The kernel arrays as tensors (None kept)."""
    return tuple(None if a is None else xp.unwrap(a) for a in arrays)


def _fast_arrays(model: Any, x: torch.Tensor, u: torch.Tensor, x_next: torch.Tensor):
    """What both fast losses start from, in the kernels' arrays (:func:`lcs_cvx.pivoting.array_ops`:
    NumPy on the tensors' memory for CPU, no autograd): ``(xp, params, p, x, u, F, q, r)`` with
    ``params`` the nine parameter tensors in :data:`PARAMETER_NAMES` order, ``p`` their arrays
    by name, ``q = D x + E u + c`` and ``r = A x + B u + d - x'``."""
    xp = array_ops(x)
    params = [getattr(model, k) for k in PARAMETER_NAMES]
    p = {k: xp.wrap(t) for k, t in zip(PARAMETER_NAMES, params, strict=True)}
    x, u, x_next = xp.wrap(x), xp.wrap(u), xp.wrap(x_next)
    F = F_matrix(p["G"], p["H"], float(model.stiffness))
    q = x @ p["D"].mT + u @ p["E"].mT + p["c"]  # the association of the closed form (Lemma 3's
    r = x @ p["A"].mT + u @ p["B"].mT + p["d"] - x_next  # w = F lam + q - phi cancels: keep it)
    return xp, params, p, x, u, F, q, r


def _inputs(model: Any, x: Any, u: Any, x_next: Any):
    kw = {"dtype": model.dtype, "device": model.device}
    x = as_batch("x", x, model.n_x, **kw)
    u = as_batch("u", u, model.n_u, batch=x.shape[0], **kw)
    x_next = as_batch("x_next", x_next, model.n_x, batch=x.shape[0], **kw)
    return x, u, x_next


def _check_warm_start(warm_start: Any, solver: str) -> None:
    if warm_start is not None and solver != "fast":
        raise LCSInputError(
            f"warm_start: only the 'fast' solver uses it, received solver={solver!r} with a warm start"
        )


def _check_solver(solver: str) -> str:
    if solver not in SOLVERS:
        raise LCSInputError(f"solver: expected one of {SOLVERS}, received {solver!r}")
    return "scs" if solver == "cvxpylayers-scs" else "clarabel"


def violation_loss(
    model: Any,
    x: Any,
    u: Any,
    x_next: Any,
    gamma: float = 1e-2,
    eps: float = 1e-4,
    solver: str = "fast",
    return_info: bool = False,
    warm_start: torch.Tensor | None = None,
) -> torch.Tensor | tuple[torch.Tensor, LossInfo]:
    r"""Violation-based loss ``L_eps`` (eq. equ.contactnet), averaged over the batch.

    .. math::
        l_\epsilon = \min_{\lambda, \phi \ge 0} \tfrac12\|A x + B u + C\lambda + d - x'\|^2
        + \tfrac1\epsilon\big(\lambda^\top\phi + \tfrac{1}{2\gamma}\|D x + E u + F\lambda + c - \phi\|^2\big)

    Args:
        model: an :class:`lcs_cvx.LCS`.
        x: ``(N, n_x)``; u: ``(N, n_u)``; x_next: ``(N, n_x)`` observed next states.
        gamma: ``0 < gamma < sigma_min(F + F^T)`` (Lemma 2; checked).
        eps: ``eps > 0`` weight of the complementarity violation.
        solver: ``"fast"``, ``"cvxpylayers"`` or ``"cvxpylayers-scs"``.
        return_info: also return a :class:`LossInfo`.
        warm_start: first guess of the fast solver's active sets, ``LossInfo.active`` of an
            earlier call on the same samples (:func:`lcs_cvx.fit` keeps one per sample). The
            value and gradients do not depend on it (to round-off); the solver's work does.

    Returns:
        Scalar tensor (and the info). Gradients w.r.t. the model's parameters are Lemma 3's.
    """
    backend = _check_solver(solver)
    _check_warm_start(warm_start, solver)
    check_positive("eps", eps)
    x, u, x_next = _inputs(model, x, u, x_next)
    if solver == "fast":
        loss, sol, lam, phi = _violation_fast(model, x, u, x_next, gamma, eps, warm_start, return_info)
        if not return_info:
            return loss
        resid = float(sol.residual.max())
        return loss, LossInfo(lam, phi, sol.iterations, sol.n_fallback, 0, resid, sol.active)
    F, C = model.F, model.C  # gamma < sigma_min(F + F^T) is checked by parameter_values
    q = x @ model.D.mT + u @ model.E.mT + model.c
    r = x @ model.A.mT + u @ model.B.mT + model.d - x_next
    decl = violation_problem(model.n_lam)
    values = decl.parameter_values(C, F, q, r, gamma, eps)
    lam = solve_layer(violation_layer(model.n_lam), [values[k] for k in decl.parameter_order], backend)
    lam = lam.clamp(min=0.0)
    phi = decl.phi(lam, F, q, gamma)
    resid = _check_layer(
        violation_kkt_residual({k: v.detach() for k, v in values.items()}, lam.detach()),
        "violation_loss",
    )
    loss = decl.objective(lam, phi, C, F, q, r, gamma, eps).mean()
    if not return_info:
        return loss
    return loss, LossInfo(lam.detach(), phi.detach(), 0, 0, 0, resid, None)


def _violation_fast(model, x, u, x_next, gamma: float, eps: float,
                    warm_start: torch.Tensor | None, residual: bool):
    """The fast path of :func:`violation_loss` on validated tensors: ``(loss, solution, lam,
    phi)``. :func:`lcs_cvx.fit` calls it directly (its data are validated once)."""
    decl = violation_problem(model.n_lam)
    xp, params, p, x, u, F, q, r = _fast_arrays(model, x, u, x_next)
    with xp.threads():
        # gamma < sigma_min(F + F^T) is checked there; F + F^T >= 2 s I by construction
        normal = decl.normal_equations(p["C"], F, q, r, gamma, eps, 2.0 * float(model.stiffness))
        sol = solve_arrays(xp, normal, device=model.device, residual=residual, warm_start=warm_start)
        lam = xp.wrap(sol.lam)
        phi = decl.phi(lam, F, q, gamma)
        loss = _EnvelopeLoss.apply(xp, (x, u, q, r, F, p["C"], p["G"], lam, phi), gamma, eps, *params)
    return loss, sol, sol.lam, xp.unwrap(phi)


def prediction_loss(
    model: Any,
    x: Any,
    u: Any,
    x_next: Any,
    solver: str = "fast",
    return_info: bool = False,
    warm_start: torch.Tensor | None = None,
) -> torch.Tensor | tuple[torch.Tensor, LossInfo]:
    r"""Prediction-based loss ``L_pred`` (eq. equ.prednet), averaged over the batch.

    ``mean_t 1/2 ||A x_t + B u_t + C lam_t + d - x'_t||^2`` with ``lam_t = LCP(F, D x_t + E u_t + c)``.
    The gradient differentiates through the LCP by the implicit function theorem on the active
    set (Lemma 1); on the ``"cvxpylayers"`` paths through diffcp on the declared problem (P).

    Args:
        model, x, u, x_next, solver, return_info, warm_start: as in :func:`violation_loss`
            (``warm_start`` ``(B, n_lam)``: the free sets).
    """
    backend = _check_solver(solver)
    _check_warm_start(warm_start, solver)
    x, u, x_next = _inputs(model, x, u, x_next)
    iterations = n_fb = 0
    active = None
    if solver == "fast":
        loss, sol, lam = _prediction_fast(model, x, u, x_next, warm_start)
        iterations, n_fb, resid, active = sol.iterations, sol.n_fallback, float(sol.residual.max()), sol.free
    else:
        F = model.F
        q = x @ model.D.mT + u @ model.E.mT + model.c
        decl = convex_lcp_problem(model.n_lam)
        values = decl.parameter_values(F, q)
        lam = solve_layer(lcp_layer(model.n_lam), [values[k] for k in decl.parameter_order], backend)
        resid = _check_layer(lcp_residual(F.detach(), q.detach(), lam.detach()), "prediction_loss")
        loss = _prediction_error(model, x, u, x_next, lam)
    if not return_info:
        return loss
    with torch.no_grad():
        lam_d = lam.detach()
        q = x @ model.D.mT + u @ model.E.mT + model.c
        w = lam_d @ model.F.mT + q
        tol = DEGENERATE_TOL * (1.0 + q.abs().amax(-1, keepdim=True))
        n_deg = int(((lam_d.abs() <= tol) & (w.abs() <= tol)).any(-1).sum())
    return loss, LossInfo(lam_d, w, iterations, n_fb, n_deg, resid, active)


def _prediction_error(model, x, u, x_next, lam: torch.Tensor) -> torch.Tensor:
    pred = x @ model.A.mT + u @ model.B.mT + lam @ model.C.mT + model.d
    return 0.5 * ((pred - x_next) ** 2).sum(-1).mean()


def _prediction_fast(model, x, u, x_next, warm_start: torch.Tensor | None):
    """The fast path of :func:`prediction_loss` on validated tensors: ``(loss, solution, lam)``
    (``lam`` detached; the loss carries Lemma 1's gradient, :class:`_ImplicitLoss`).
    :func:`lcs_cvx.fit` calls it directly."""
    xp, params, p, x, u, F, q, r = _fast_arrays(model, x, u, x_next)
    with xp.threads():
        sol = solve_lcp_fast(xp.unwrap(F), xp.unwrap(q), warm_start=warm_start)
        arrays = (x, u, r, F, p["C"], p["G"], xp.wrap(sol.lam), xp.wrap(sol.free))
        loss = _ImplicitLoss.apply(xp, arrays, *params)
    return loss, sol, sol.lam


def regularizer(model: Any, weight: float = 1e-5) -> torch.Tensor:
    """``omega ||C||_F^2`` -- pins the permutation/scaling freedom of ``lam`` (paper Sec. 5)."""
    if isinstance(weight, bool) or not isinstance(weight, (int, float)) or weight < 0:
        raise LCSInputError(f"weight: expected a number >= 0, received {weight!r}")
    return weight * (model.C**2).sum()


def violation_fast(model, x, u, x_next, *, gamma: float, eps: float, warm_start=None,
                   residual: bool = False) -> LossInfo:
    loss, sol, lam, phi = _violation_fast(model, x, u, x_next, gamma, eps, warm_start, residual)
    return LossInfo(lam, phi, sol.iterations, sol.n_fallback, 0, 0.0, sol.active, loss=loss)


def prediction_fast(model, x, u, x_next, *, warm_start=None) -> LossInfo:
    loss, sol, lam = _prediction_fast(model, x, u, x_next, warm_start)
    return LossInfo(lam, sol.w, sol.iterations, sol.n_fallback, 0, 0.0, sol.free, loss=loss)
