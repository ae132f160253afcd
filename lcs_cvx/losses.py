r"""The two learning losses of the paper and the regulariser.

- :func:`violation_loss` -- ``L_eps`` of eq. (9), the batch mean of the optimal
  value of (V). The solver runs without autograd; the (lam, phi) objective is then evaluated at
  the detached optimum with the envelope gradients of Lemma 3 as its backward
  (``grad_A = mean e_dyn x^T``, ``grad_D = mean e_lcp x^T``, ...), which equals autograd through
  the objective: no solver differentiation, no matrix inverse.
- :func:`prediction_loss` -- ``L_pred`` of eq. (6), the batch mean of
  ``1/2 ||x'_theta - x'||^2`` with ``lam`` the exact LCP solution. Its gradient is the implicit
  function theorem on the solution's active set (Lemma 1): ``lam_I = -F_II^{-1} q_I`` is
  differentiated on the free set found by the solver. An index with ``lam_i = w_i = 0``
  (strict complementarity fails) is held at zero -- the one-sided derivative in which that
  constraint stays active; such samples are counted in :class:`LossInfo`.
- :func:`regularizer` -- ``omega ||C||_F^2`` (paper Sec. 5).

:func:`violation_loss_info` and :func:`prediction_loss_info` take the same arguments and return
a :class:`LossInfo` (the loss and the solver's diagnostics). ``solver`` selects the path:
``"fast"`` (batched kernels, default), ``"cvxpylayers"`` (diffcp + Clarabel over the declared
problem) or ``"cvxpylayers-scs"`` (diffcp + SCS). On the fast path the arithmetic runs in the
compiled kernels (:mod:`lcs_cvx._kernels.compiled`, one model's float64 CPU tensors, through
:mod:`lcs_cvx._kernels.calls`) or the array kernels (:mod:`lcs_cvx._kernels.losses`); the
``torch.autograd.Function`` classes here only adapt them. :mod:`lcs_cvx.value_and_grad` returns
a loss and its gradient in one call, without autograd.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import torch

from ._checks import LayerAccuracyWarning, LCSInputError, as_transitions, check_positive
from ._kernels import calls
from ._kernels import losses as kernel
from ._kernels import violation as kernel_violation
from ._kernels.arrays import TORCH, array_ops
from ._kernels.lcp import PIVOT_TOL as LCP_TOL
from ._kernels.pivoting import STALL
from ._kernels.violation import PIVOT_TOL as VIOLATION_TOL
from .layers import lcp_layer, solve_layer, violation_layer
from .lcp import lcp_residual, solve_lcp_fast
from .problems import check_gamma, convex_lcp_problem, violation_problem
from .system import LCS, PARAMETER_NAMES
from .violation import finish, violation_kkt_residual

__all__ = [
    "LossInfo",
    "violation_loss",
    "violation_loss_info",
    "prediction_loss",
    "prediction_loss_info",
    "regularizer",
    "SOLVERS",
]

SOLVERS = ("fast", "cvxpylayers", "cvxpylayers-scs")

#: A layer solution whose relative KKT residual exceeds this is reported (LayerAccuracyWarning).
LAYER_RESIDUAL_TOL = 1e-6

#: A complementarity pair counts as degenerate when both ``lam_i`` and ``w_i`` are below this,
#: relative to ``1 + |q|_inf``.
DEGENERATE_TOL = 1e-9

#: Pivoting sweeps of the fast paths before a sample falls back to a reference solver.
MAX_ITER = 1000

#: The dtype the fast violation loss computes in, whatever the model's. Its gradient in ``D, E,
#: c, G, H`` is ``w / (gamma eps)`` with ``w = F lam + q - phi``, a cancellation down to the
#: size of ``gamma eps`` (1e-6 at the defaults): in float32 (round-off 1.2e-7 of ``|q|``) those
#: gradients come out wrong by 100 % and more, and pivoting cannot certify a candidate to its
#: tolerance (1e-11), so samples run to ``MAX_ITER`` and fall back. float32 models and data are
#: promoted to float64 and the loss and solution returned in their dtype (the gradient reaches
#: the float32 parameters through autograd's casts).
VIOLATION_DTYPE = torch.float64


def promoted(params: list[torch.Tensor], *data: torch.Tensor) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """``params`` and ``data`` in :data:`VIOLATION_DTYPE` (differentiable casts; the tensors
    themselves where they are float64 already)."""
    return ([p.to(VIOLATION_DTYPE) for p in params], [t.to(VIOLATION_DTYPE) for t in data])


@dataclass(frozen=True)
class LossInfo:
    """One loss evaluation and its diagnostics.

    Attributes:
        loss: the loss, a 0-dim tensor differentiable in the model's parameters.
        lam: ``(B, n_lam)`` the per-sample ``lam`` (detached).
        phi: ``(B, n_lam)`` the violation loss's ``phi`` (detached); None for the prediction loss.
        w: ``(B, n_lam)`` the prediction loss's ``w = F lam + q`` (detached); None for the
            violation loss.
        iterations: pivoting sweeps of the fast solver (0 on the layer paths).
        n_fallback: samples the fast solver handed to a reference solver.
        n_degenerate: samples with some ``lam_i = w_i = 0`` (prediction loss; 0 otherwise).
        max_residual: the largest relative KKT residual over every sample of the batch (a layer
            solution above ``LAYER_RESIDUAL_TOL`` also raises a
            :class:`lcs_cvx.LayerAccuracyWarning`); None where it was not computed (the
            package-internal fast paths, which skip it).
        fallback_residual: the largest relative KKT residual over the samples a reference
            solver answered (0.0 if none: converged pivoting is exact to its tolerance).
        active: the fast solver's final active sets, bool -- ``(B, 2 n_lam)`` ``[lam_i > 0,
            phi_i = 0]`` (violation) or ``(B, n_lam)`` ``lam_i > 0`` (prediction) -- to pass as
            ``warm_start`` when the same samples come again; None on the layer paths.
    """

    loss: torch.Tensor
    lam: torch.Tensor
    phi: torch.Tensor | None = None
    w: torch.Tensor | None = None
    iterations: int = 0
    n_fallback: int = 0
    n_degenerate: int = 0
    max_residual: float | None = None
    fallback_residual: float = 0.0
    active: torch.Tensor | None = None


def _check_layer(residual: torch.Tensor, what: str) -> float:
    bad = int((residual > LAYER_RESIDUAL_TOL).sum())
    worst = float(residual.max())
    if bad:
        # stacklevel 5: the user's call of the public loss (through _violation / _prediction)
        warnings.warn(
            f"{what}: {bad} of {residual.numel()} layer solutions have a relative KKT residual "
            f"above {LAYER_RESIDUAL_TOL:g} (worst {worst:.2e}); the 'fast' path is exact",
            LayerAccuracyWarning,
            stacklevel=5,
        )
    return worst


class EnvelopeLoss(torch.autograd.Function):
    """``apply(batch, lam, phi, gamma, eps, *params)``: the value of
    :func:`lcs_cvx._kernels.losses.envelope_forward` with Lemma 3's gradients
    (:func:`~lcs_cvx._kernels.losses.envelope_backward`) in the model's parameters ``params``
    (``A, B, C, d, D, E, G, H, c``). The same numbers as autograd through
    :meth:`lcs_cvx.problems.ViolationProblem.objective` at the detached optimum (tested), without
    its graph (the loss runs at every training step). Not twice differentiable; Lemma 4 lives
    in :mod:`lcs_cvx.hessian`."""

    @staticmethod
    def forward(ctx, batch, lam, phi, gamma: float, eps: float, *params):  # noqa: D102
        value, ctx.saved = kernel.envelope_forward(batch, lam, phi, gamma, eps)
        return value

    @staticmethod
    def backward(ctx, grad):  # noqa: D102
        return (None,) * 5 + kernel.envelope_backward(ctx.saved, grad, ctx.needs_input_grad[5:])


class ImplicitLoss(torch.autograd.Function):
    """``apply(batch, lam, free, *params)``: the value of
    :func:`lcs_cvx._kernels.losses.implicit_forward` with Lemma 1's gradient in closed form
    (:func:`~lcs_cvx._kernels.losses.implicit_backward`). The same numbers as autograd through
    :func:`lcs_cvx.lcp.active_set_solve` (tested) without its graph."""

    @staticmethod
    def forward(ctx, batch, lam, free, *params):  # noqa: D102
        value, ctx.saved = kernel.implicit_forward(batch, lam, free)
        return value

    @staticmethod
    def backward(ctx, grad):  # noqa: D102
        return (None,) * 3 + kernel.implicit_backward(ctx.saved, grad, ctx.needs_input_grad[3:])


def _normal_equations(model: Any, x: torch.Tensor, u: torch.Tensor, x_next: torch.Tensor,
                      gamma: float, eps: float) -> dict[str, torch.Tensor]:
    """(V)'s normal equations (:func:`lcs_cvx._kernels.violation.normal_equations`) as tensors."""
    xp = array_ops(x)
    params = [getattr(model, k) for k in PARAMETER_NAMES]
    with xp.threads():
        b = kernel.batch(xp, params, x, u, x_next, float(model.stiffness))
        normal = kernel_violation.normal_equations(xp, b.C, b.F, b.q, b.r, gamma, eps)
    return {k: xp.unwrap(v) for k, v in normal.items()}


def violation_fast(model: Any, x: torch.Tensor, u: torch.Tensor, x_next: torch.Tensor, *,
                   gamma: float, eps: float, warm_start: torch.Tensor | None = None,
                   residual: bool = False, arrays: str = "auto", threads: int | None = None) -> LossInfo:
    """The fast path of :func:`violation_loss_info` on validated tensors of the model's dtype
    and device (package-internal: the trainer validates its data once). ``residual``: also
    compute every sample's KKT residual (``max_residual``; else None); ``arrays``: ``"auto"``
    (the compiled kernel,
    :mod:`lcs_cvx._kernels.compiled`, for one model's float64 CPU tensors; else the array kernels
    in NumPy on the CPU, in torch elsewhere), ``"compiled"``, or the array library of
    :func:`lcs_cvx.lcp.solve_lcp_fast` (``"numpy"``, ``"torch"``); ``threads``: the compiled
    kernel's (:func:`lcs_cvx._kernels.calls.compiled_call`; None: ``torch.get_num_threads()``)."""
    stiffness = float(model.stiffness)
    check_positive("gamma", gamma)
    if not gamma < 2.0 * stiffness:  # F + F^T >= 2 s I by construction: below, no check needed
        check_gamma(model.F, gamma)
    n = model.n_lam
    if calls.use_compiled(model, x, arrays):
        done = calls.call_on_model("violation", model, x, u, x_next, warm_start, 2 * n, gamma, eps,
                                   VIOLATION_TOL, MAX_ITER, STALL, threads=threads)
        if done is not None:
            params, (value, grads, lam, phi, active, _, sweeps) = done
            loss = calls.CompiledLoss.apply(calls.scalar(value), grads, *params)
            lam = torch.from_numpy(lam)
            worst = None
            if residual:
                values = violation_problem(n).factor(_normal_equations(model, x, u, x_next, gamma, eps))
                worst = float(violation_kkt_residual(values, lam).max())
            return LossInfo(loss, lam, phi=torch.from_numpy(phi), iterations=sweeps,
                            max_residual=worst, active=torch.from_numpy(active))
    xp = array_ops(x, arrays)
    dtype = x.dtype
    params, (x, u, x_next) = promoted([getattr(model, k) for k in PARAMETER_NAMES], x, u, x_next)
    with xp.threads():
        b = kernel.batch(xp, params, x, u, x_next, stiffness)
        normal = kernel_violation.normal_equations(xp, b.C, b.F, b.q, b.r, gamma, eps)
        pivoted = kernel_violation.solve_arrays(xp, normal, device=x.device, max_iter=MAX_ITER,
                                                warm_start=warm_start)

        def values() -> dict[str, torch.Tensor]:  # only for a fallback or the residual
            return violation_problem(n).factor({k: xp.unwrap(v) for k, v in normal.items()})

        sol = finish(pivoted, values, max_iter=MAX_ITER, residual=residual)
        lam = xp.wrap(sol.lam)
        phi = kernel_violation.phi(xp, lam, b.F, b.q, gamma)
        loss = EnvelopeLoss.apply(b, lam, phi, gamma, eps, *params)
    worst = float(sol.residual.max()) if residual else None
    return LossInfo(loss.to(dtype), sol.lam.to(dtype), phi=xp.unwrap(phi).to(dtype), iterations=sol.iterations,
                    n_fallback=sol.n_fallback, max_residual=worst,
                    fallback_residual=sol.fallback_residual, active=sol.active)


def prediction_fast(model: Any, x: torch.Tensor, u: torch.Tensor, x_next: torch.Tensor, *,
                    warm_start: torch.Tensor | None = None, residual: bool = False,
                    arrays: str = "auto", threads: int | None = None) -> LossInfo:
    """The fast path of :func:`prediction_loss_info` on validated tensors (see
    :func:`violation_fast`); ``warm_start`` ``(B, n_lam)``: the free sets."""
    if calls.use_compiled(model, x, arrays):
        done = calls.call_on_model("prediction", model, x, u, x_next, warm_start, model.n_lam,
                                   LCP_TOL, MAX_ITER, STALL, DEGENERATE_TOL, threads=threads)
        if done is not None:
            params, (value, grads, lam, w, free, _, sweeps, n_deg) = done
            loss = calls.CompiledLoss.apply(calls.scalar(value), grads, *params)
            lam, w = torch.from_numpy(lam), torch.from_numpy(w)
            worst = None
            if residual:
                with torch.no_grad():
                    q = x @ model.D.mT + u @ model.E.mT + model.c
                    worst = float(lcp_residual(model.F, q, lam, w).max())
            return LossInfo(loss, lam, w=w, iterations=sweeps, n_degenerate=n_deg,
                            max_residual=worst, active=torch.from_numpy(free))
    xp = array_ops(x, arrays)
    params = [getattr(model, k) for k in PARAMETER_NAMES]
    with xp.threads():
        b = kernel.batch(xp, params, x, u, x_next, float(model.stiffness))
        sol = solve_lcp_fast(xp.unwrap(b.F), xp.unwrap(b.q), max_iter=MAX_ITER,
                             warm_start=warm_start, residual=residual, arrays=arrays)
        lam = xp.wrap(sol.lam)
        loss = ImplicitLoss.apply(b, lam, xp.wrap(sol.free), *params)
        n_deg = kernel.degenerate_count(xp, lam, xp.wrap(sol.w), b.q, DEGENERATE_TOL)
    worst = float(sol.residual.max()) if residual else None
    return LossInfo(loss, sol.lam, w=sol.w, iterations=sol.iterations, n_fallback=sol.n_fallback,
                    n_degenerate=n_deg, max_residual=worst,
                    fallback_residual=sol.fallback_residual, active=sol.free)


def _check_solver(solver: str, warm_start: Any) -> str:
    """The cone solver of ``solver`` (``"clarabel"`` for the fast path, unused there)."""
    if solver not in SOLVERS:
        raise LCSInputError(f"solver: expected one of {SOLVERS}, received {solver!r}")
    if warm_start is not None and solver != "fast":
        raise LCSInputError(
            f"warm_start: only the 'fast' solver uses it, received solver={solver!r} with a warm start"
        )
    return "scs" if solver == "cvxpylayers-scs" else "clarabel"


def _per_sample(kind, model, x, u, x_next, gamma, eps, solver, warm_start) -> LossInfo:
    """The loss of a model of per-sample matrices: its own ``loss_info`` (:mod:`lcs_cvx.per_sample`)."""
    _check_solver(solver, warm_start)
    return model.loss_info(kind, x, u, x_next, gamma=gamma, eps=eps, solver=solver, warm_start=warm_start)


def _violation(model, x, u, x_next, gamma, eps, solver, warm_start, residual, threads) -> LossInfo:
    if not isinstance(model, LCS) and callable(getattr(model, "loss_info", None)):
        return _per_sample("violation", model, x, u, x_next, gamma, eps, solver, warm_start)
    cone_solver = _check_solver(solver, warm_start)
    calls.resolve_threads(threads)
    check_positive("eps", eps)
    if not (solver == "fast" and calls.ready(model, x, u, x_next)):
        x, u, x_next = as_transitions(model, x, u, x_next)
    if solver == "fast":
        return violation_fast(model, x, u, x_next, gamma=gamma, eps=eps, warm_start=warm_start,
                              residual=residual, threads=threads)
    F, C = model.F, model.C  # gamma < sigma_min(F + F^T) is checked by parameter_values
    q = x @ model.D.mT + u @ model.E.mT + model.c
    r = x @ model.A.mT + u @ model.B.mT + model.d - x_next
    decl = violation_problem(model.n_lam)
    values = decl.parameter_values(C, F, q, r, gamma, eps)
    lam = solve_layer(violation_layer(model.n_lam), [values[k] for k in decl.parameter_order],
                      cone_solver).clamp(min=0.0)
    phi = decl.phi(lam, F, q, gamma)
    worst = _check_layer(
        violation_kkt_residual({k: v.detach() for k, v in values.items()}, lam.detach()),
        "violation_loss",
    )
    loss = decl.objective(lam, phi, C, F, q, r, gamma, eps).mean()
    return LossInfo(loss, lam.detach(), phi=phi.detach(), max_residual=worst)


def violation_loss(
    model: Any,
    x: Any,
    u: Any,
    x_next: Any,
    gamma: float = 1e-2,
    eps: float = 1e-4,
    solver: str = "fast",
    warm_start: torch.Tensor | None = None,
    threads: int | None = None,
) -> torch.Tensor:
    r"""Violation-based loss ``L_eps`` (eq. (9)), averaged over the batch.

    $$
    l_\epsilon = \min_{\lambda, \phi \ge 0} \tfrac12\|A x + B u + C\lambda + d - x'\|^2
    + \tfrac1\epsilon\big(\lambda^\top\phi + \tfrac{1}{2\gamma}\|D x + E u + F\lambda + c - \phi\|^2\big)
    $$

    Args:
        model: an :class:`lcs_cvx.LCS`, or a model whose matrices differ per sample
            (:class:`lcs_cvx.RigidBodyContact`: (V) of each sample's LCS on its velocity rows,
            :mod:`lcs_cvx.per_sample`).
        x: ``(N, n_x)``; u: ``(N, n_u)``; x_next: ``(N, n_x)`` observed next states.
        gamma: ``0 < gamma < sigma_min(F + F^T)`` (Lemma 2; checked).
        eps: ``eps > 0`` weight of the complementarity violation.
        solver: ``"fast"``, ``"cvxpylayers"`` or ``"cvxpylayers-scs"``.
        warm_start: first guess of the fast solver's active sets, ``LossInfo.active`` of an
            earlier call on the same samples (:func:`violation_loss_info`). The value and
            gradients do not depend on it (to round-off); the solver's work does.
        threads: threads of the fast solver on a large batch (float64 CPU): a batch of at
            least ``2 * lcs_cvx._kernels.calls.MIN_CHUNK`` samples is solved in parts of a few
            thousand, shared among the threads; the parts depend on the batch only, so every
            thread count gives the same numbers (and a whole call's to round-off). Default
            ``torch.get_num_threads()``, which ``OMP_NUM_THREADS`` and ``torch.set_num_threads``
            set.

    Returns:
        Scalar tensor of the model's dtype; its gradients w.r.t. the model's parameters are
        Lemma 3's. The fast path computes a float32 model's loss in float64
        (:data:`VIOLATION_DTYPE`: the gradient in ``D, E, c, G, H`` cancels below float32's
        resolution).
    """
    if solver == "fast" and calls.ready(model, x, u, x_next, one_model=True):  # no diagnostics' tensors
        check_positive("eps", eps)
        check_positive("gamma", gamma)
        loss = calls.loss_on_model("violation", model, x, u, x_next, warm_start, threads, gamma, eps,
                                   VIOLATION_TOL, MAX_ITER, STALL, gamma=gamma)
        if loss is not None:
            return loss
    return _violation(model, x, u, x_next, gamma, eps, solver, warm_start, False, threads).loss


def violation_loss_info(model: Any, x: Any, u: Any, x_next: Any, gamma: float = 1e-2, eps: float = 1e-4,
                        solver: str = "fast", warm_start: torch.Tensor | None = None,
                        threads: int | None = None) -> LossInfo:
    """:func:`violation_loss` (same arguments) with its diagnostics: a :class:`LossInfo` whose
    ``loss`` is the differentiable scalar and ``max_residual`` every sample's KKT residual."""
    return _violation(model, x, u, x_next, gamma, eps, solver, warm_start, True, threads)


def _prediction(model, x, u, x_next, solver, warm_start, residual, threads) -> LossInfo:
    if not isinstance(model, LCS) and callable(getattr(model, "loss_info", None)):
        return _per_sample("prediction", model, x, u, x_next, 1e-2, 1e-4, solver, warm_start)
    cone_solver = _check_solver(solver, warm_start)
    calls.resolve_threads(threads)
    if not (solver == "fast" and calls.ready(model, x, u, x_next)):
        x, u, x_next = as_transitions(model, x, u, x_next)
    if solver == "fast":
        return prediction_fast(model, x, u, x_next, warm_start=warm_start, residual=residual,
                               threads=threads)
    F = model.F
    q = x @ model.D.mT + u @ model.E.mT + model.c
    decl = convex_lcp_problem(model.n_lam)
    values = decl.parameter_values(F, q)
    lam = solve_layer(lcp_layer(model.n_lam), [values[k] for k in decl.parameter_order], cone_solver)
    worst = _check_layer(lcp_residual(F.detach(), q.detach(), lam.detach()), "prediction_loss")
    pred = x @ model.A.mT + u @ model.B.mT + lam @ model.C.mT + model.d
    loss = 0.5 * ((pred - x_next) ** 2).sum(-1).mean()
    with torch.no_grad():
        lam_d, q_d = lam.detach(), q.detach()
        w = lam_d @ F.detach().mT + q_d
        n_deg = kernel.degenerate_count(TORCH, lam_d, w, q_d, DEGENERATE_TOL)
    return LossInfo(loss, lam_d, w=w, n_degenerate=n_deg, max_residual=worst)


def prediction_loss(
    model: Any,
    x: Any,
    u: Any,
    x_next: Any,
    solver: str = "fast",
    warm_start: torch.Tensor | None = None,
    threads: int | None = None,
) -> torch.Tensor:
    r"""Prediction-based loss ``L_pred`` (eq. (6)), averaged over the batch.

    $$
    L_\text{pred} = \operatorname{mean}_t \tfrac12 \|A x_t + B u_t + C \lambda_t + d - x'_t\|^2,
    \qquad \lambda_t = \operatorname{LCP}(F,\; D x_t + E u_t + c).
    $$

    The gradient differentiates through the LCP by the implicit function theorem on the active
    set (Lemma 1); on the ``"cvxpylayers"`` paths through diffcp on the declared problem (P).

    Args:
        model, x, u, x_next, solver, warm_start, threads: as in :func:`violation_loss` (``warm_start``
            ``(B, n_lam)``: the free sets, :func:`prediction_loss_info`'s ``active``).
    """
    if solver == "fast" and calls.ready(model, x, u, x_next, one_model=True):  # no diagnostics' tensors
        loss = calls.loss_on_model("prediction", model, x, u, x_next, warm_start, threads, LCP_TOL, MAX_ITER,
                                   STALL, DEGENERATE_TOL)
        if loss is not None:
            return loss
    return _prediction(model, x, u, x_next, solver, warm_start, False, threads).loss


def prediction_loss_info(model: Any, x: Any, u: Any, x_next: Any, solver: str = "fast",
                         warm_start: torch.Tensor | None = None, threads: int | None = None) -> LossInfo:
    """:func:`prediction_loss` (same arguments) with its diagnostics: a :class:`LossInfo` whose
    ``loss`` is the differentiable scalar, ``w = F lam + q`` and ``max_residual``
    every sample's LCP residual."""
    return _prediction(model, x, u, x_next, solver, warm_start, True, threads)


def regularizer(model: Any, reg: float = 1e-5) -> torch.Tensor:
    """``reg ||C||_F^2`` (the paper's ``omega``) -- pins the permutation/scaling freedom of
    ``lam`` (paper Sec. 5)."""
    if isinstance(reg, bool) or not isinstance(reg, (int, float)) or reg < 0:
        raise LCSInputError(f"reg: expected a number >= 0, received {reg!r}")
    C = getattr(model, "C", None)
    if not isinstance(C, torch.Tensor):  # a model of per-sample matrices: no free C to pin
        return torch.zeros((), dtype=model.dtype, device=model.device)
    return reg * (C**2).sum()
