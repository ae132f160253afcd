r"""An ensemble of LCS trained as one: ``K`` models of the same sizes, their parameters stacked
along a leading model axis, and the two fast losses of all ``K`` models in one kernel call.

:class:`StackedLCS` holds ``theta_k = {A, B, C, d, D, E, G, H, c}_k`` as tensors ``(K, ...)``
(``A`` ``(K, n_x, n_x)``, ``c`` ``(K, n_lam)``, ...) and the stiffnesses ``s_k`` ``(K,)``.
:func:`violation_losses` and :func:`prediction_losses` evaluate model ``k``'s loss (eqs.
(9) and (6)) on its own minibatch ``(x[k], u[k], x_next[k])`` with its own
matrices: the samples of all models go through one call of the pivoting kernels
(:mod:`lcs_cvx._kernels.stacks`), and the values come back as ``(K,)``, one per model. The
gradient of their sum in the stacked parameters is, in slice ``k``, the gradient of model
``k``'s loss (Lemma 3, Lemma 1).

Every per-model operation of a stacked call is the operation of the model's own call
(:func:`lcs_cvx.losses.violation_fast`, :func:`~lcs_cvx.losses.prediction_fast`) on the same
rows, so model ``k`` gets the numbers of its own call -- in NumPy (CPU tensors), where each
product on a model's rows is one BLAS call as in its own call, bit for bit (tested). Adam is
elementwise: one ``torch.optim.Adam`` over the stacked parameters, stepped on the sum of the
``K`` losses, makes each model's step of its own Adam. :func:`lcs_cvx.fit_ensemble` trains
this way.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from . import losses as _losses
from ._checks import LCSInputError, check_positive
from ._kernels import calls
from ._kernels import lcp as kernel_lcp
from ._kernels import losses as kernel
from ._kernels import violation as kernel_violation
from ._kernels.arrays import TORCH, array_ops
from ._kernels.lcp import PIVOT_TOL as LCP_TOL
from ._kernels.pivoting import STALL
from ._kernels.violation import PIVOT_TOL as VIOLATION_TOL
from .lcp import finish as finish_lcp
from .losses import EnvelopeLoss, ImplicitLoss
from .problems import check_gamma, violation_problem
from .system import LCS, PARAMETER_NAMES
from .violation import finish as finish_violation

__all__ = ["StackedLCS", "StackedInfo", "violation_losses", "prediction_losses"]


class StackedLCS(nn.Module):
    """``K`` LCS of the same sizes with their parameters stacked: ``A`` ``(K, n_x, n_x)``, ...,
    ``c`` ``(K, n_lam)``, ``stiffness`` ``(K,)`` (copies of the models' values).

    Args:
        models: the :class:`lcs_cvx.LCS` to stack (same ``n_x, n_u, n_lam``, dtype and device;
            the same parameters fixed; no masks).

    Example:
        >>> import lcs_cvx
        >>> from lcs_cvx.stacked import StackedLCS
        >>> ens = StackedLCS([lcs_cvx.LCS(4, 2, 3, seed=k) for k in range(5)])
        >>> len(ens), tuple(ens.F.shape)
        (5, (5, 3, 3))
    """

    def __init__(self, models: Sequence[LCS]) -> None:
        super().__init__()
        models = list(models) if isinstance(models, (list, tuple)) else models
        if not isinstance(models, list) or not models:
            raise LCSInputError(f"models: expected a non-empty list of lcs_cvx.LCS, received {models!r}")
        first = models[0]
        for k, m in enumerate(models):
            if not isinstance(m, LCS):
                raise LCSInputError(f"models[{k}]: expected an lcs_cvx.LCS, received {type(m).__name__}")
            got = (m.n_x, m.n_u, m.n_lam, m.dtype, m.device)
            want = (first.n_x, first.n_u, first.n_lam, first.dtype, first.device)
            if got != want:
                raise LCSInputError(
                    f"models[{k}]: expected (n_x, n_u, n_lam, dtype, device) = {want} as models[0], "
                    f"received {got}"
                )
            if m.masks:
                why = " (its kinematics hold the configuration rows)" if m.kinematics is not None else ""
                raise LCSInputError(
                    f"models[{k}]: expected a model without masks (an ensemble does not train masked "
                    f"entries yet), received masks on {sorted(m.masks)}{why}; fit them one at a time"
                )
            fixed = [name for name in PARAMETER_NAMES if not getattr(m, name).requires_grad]
            fixed0 = [name for name in PARAMETER_NAMES if not getattr(first, name).requires_grad]
            if fixed != fixed0:
                raise LCSInputError(
                    f"models[{k}]: expected the fixed parameters of models[0] ({fixed0}), received {fixed}"
                )
        self.n_x, self.n_u, self.n_lam = first.n_x, first.n_u, first.n_lam
        with torch.no_grad():
            for name in PARAMETER_NAMES:
                value = torch.stack([getattr(m, name).detach() for m in models])
                setattr(self, name, nn.Parameter(value, requires_grad=getattr(first, name).requires_grad))
            self.register_buffer("stiffness", torch.stack([m.stiffness.detach() for m in models]))

    def __len__(self) -> int:
        return self.A.shape[0]

    @property
    def F(self) -> torch.Tensor:
        """``(K, n_lam, n_lam)``: each model's ``F = G G^T + H - H^T + s I``."""
        return kernel.F_matrix(TORCH, self.G, self.H, self.stiffness[:, None, None])

    def copy_to(self, k: int, model: LCS) -> LCS:
        """Write model ``k``'s parameters into ``model`` (in place; returns it)."""
        with torch.no_grad():
            for name in PARAMETER_NAMES:
                getattr(model, name).copy_(getattr(self, name)[k])
        return model

    def select(self, keep: Sequence[int]) -> StackedLCS:
        """A new ensemble of the models ``keep`` (their current parameters, copied)."""
        new = StackedLCS.__new__(StackedLCS)
        nn.Module.__init__(new)
        new.n_x, new.n_u, new.n_lam = self.n_x, self.n_u, self.n_lam
        index = torch.as_tensor(list(keep), dtype=torch.long, device=self.A.device)
        with torch.no_grad():
            for name in PARAMETER_NAMES:
                p = getattr(self, name)
                setattr(new, name, nn.Parameter(p[index].clone(), requires_grad=p.requires_grad))
            new.register_buffer("stiffness", self.stiffness[index].clone())
        return new


@dataclass(frozen=True)
class StackedInfo:
    """One evaluation of a loss for every model of an :class:`StackedLCS`.

    Attributes:
        loss: ``(K,)`` the models' losses (batch means), differentiable in the stacked parameters.
        active: the fast solver's final active sets, bool ``(K, B, 2 n_lam)`` (violation) or
            ``(K, B, n_lam)`` (prediction): the ``warm_start`` of the samples' next visit.
        n_fallback: per model, the samples handed to a reference solver.
        fallback_residual: per model, the largest relative KKT residual of those reference answers
            (0.0 if none).
    """

    loss: torch.Tensor
    active: torch.Tensor
    n_fallback: list[int]
    fallback_residual: list[float]


def _initial(cold: torch.Tensor, warm_start: torch.Tensor | None,
             warm: torch.Tensor | None) -> torch.Tensor | None:
    """The pivoting's first guess ``(K * B, k)``: ``warm_start`` ``(K, B, k)`` for the models
    with ``warm`` ``(K,)`` True, the cold guess ``cold`` ``(K * B, k)`` for the others."""
    if warm_start is None:
        return None
    K, B, k = warm_start.shape
    use = warm_start if warm is None else torch.where(
        warm.to(cold.device)[:, None, None], warm_start.to(cold.device), cold.reshape(K, B, k))
    return use.reshape(K * B, k)


def _model_rows(unconverged: torch.Tensor | None, K: int, B: int) -> dict[int, torch.Tensor]:
    """The unconverged samples (flat indices) of each model, as that model's row indices."""
    if unconverged is None:
        return {}
    model = torch.div(unconverged, B, rounding_mode="floor")
    return {k: unconverged[model == k] - k * B for k in torch.unique(model).tolist()}


def _compiled(fn_name: str, ens: StackedLCS, x: torch.Tensor, u: torch.Tensor,
              x_next: torch.Tensor, warm_start: torch.Tensor | None, warm: torch.Tensor | None,
              arrays: str, width: int, *options: Any) -> tuple[torch.Tensor, list[tuple]] | None:
    """Each model's compiled call (:func:`lcs_cvx._kernels.calls.compiled_call`) on its own rows, for
    float64 CPU tensors (the default there): model ``k`` gets the numbers of its own call, bit
    for bit. Returns the ``(K,)`` loss (its gradients the models' own, stacked) and each model's
    outputs; None where the array kernels run the stack (other dtypes and devices, or a sample
    that did not converge: they end it with the reference solvers)."""
    if arrays not in ("auto", "compiled"):
        return None
    if x.device.type != "cpu" or x.dtype != torch.float64:
        if arrays == "compiled":
            raise LCSInputError(f"arrays: 'compiled' runs float64 CPU tensors, received {x.dtype} "
                                f"on {x.device}")
        return None
    from ._kernels import compiled

    fn = getattr(compiled, fn_name)
    params = [getattr(ens, k) for k in PARAMETER_NAMES]
    stacked = calls.as_arrays(*params)
    outs = []
    for k, s in enumerate(ens.stiffness.tolist()):
        own_warm = None if warm_start is None or (warm is not None and not bool(warm[k])) else warm_start[k]
        status, out = calls.compiled_call(fn, [a[k] for a in stacked], s, x[k], u[k], x_next[k],
                                            own_warm, width, *options)
        if status:
            return None
        outs.append(out)
    grads = tuple(torch.stack([out[1][i] for out in outs]) for i in range(len(params)))
    values = torch.tensor([out[0] for out in outs], dtype=torch.float64)
    return calls.CompiledLoss.apply(values, grads, *params), outs


def violation_losses(ens: StackedLCS, x: torch.Tensor, u: torch.Tensor, x_next: torch.Tensor, *,
                     gamma: float, eps: float, warm_start: torch.Tensor | None = None,
                     warm: torch.Tensor | None = None, arrays: str = "auto") -> StackedInfo:
    """The violation loss ``L_eps`` (eq. (9)) of every model on its own minibatch.

    Package-internal, on validated tensors of the ensemble's dtype and device (the trainer checks
    its data once): ``x`` ``(K, B, n_x)``, ``u`` ``(K, B, n_u)``, ``x_next`` ``(K, B, n_x)``, row
    ``k`` model ``k``'s samples. ``warm_start`` ``(K, B, 2 n_lam)``: the active sets of an
    earlier solve of these samples, used for the models where ``warm`` ``(K,)`` is True (all if
    None); the others start from the cold guess, as :func:`lcs_cvx.losses.violation_fast` does
    without a warm start. ``arrays``: the kernels' array library.
    """
    check_positive("gamma", gamma)
    stiffness = ens.stiffness.tolist()
    for k, s in enumerate(stiffness):
        if not gamma < 2.0 * s:  # F + F^T >= 2 s I by construction: below, no check needed
            check_gamma(ens.F[k], gamma)
    K, B = x.shape[:2]
    n = ens.n_lam
    done = _compiled("violation", ens, x, u, x_next, warm_start, warm, arrays, 2 * n, gamma, eps,
                     VIOLATION_TOL, _losses.MAX_ITER, STALL)
    if done is not None:
        loss, outs = done
        return StackedInfo(loss, torch.stack([torch.from_numpy(out[4]) for out in outs]), [0] * K,
                           [0.0] * K)
    xp = array_ops(x, arrays)
    dtype = x.dtype
    params, (x, u, x_next) = _losses.promoted([getattr(ens, k) for k in PARAMETER_NAMES], x, u, x_next)
    with xp.threads():
        b = kernel.batch(xp, params, x, u, x_next, xp.wrap(ens.stiffness)[:, None, None])
        normal = kernel_violation.normal_equations(xp, b.C, b.F, b.q, b.r, gamma, eps)
        flat = {"LtL": normal["LtL"], "K": normal["K"], "Ltb": normal["Ltb"].reshape(K * B, n),
                "h": normal["h"].reshape(K * B, n)}
        cold = xp.unwrap(kernel_violation.cold_guess(xp, flat["K"], flat["h"]))
        pivoted = kernel_violation.solve_arrays(xp, flat, device=x.device, max_iter=_losses.MAX_ITER,
                                                warm_start=_initial(cold, warm_start, warm))
        n_fb, worst = [0] * K, [0.0] * K
        for k, rows in _model_rows(pivoted.unconverged, K, B).items():
            part = slice(k * B, (k + 1) * B)

            def values(k: int = k, part: slice = part) -> dict[str, torch.Tensor]:
                mine = {"LtL": flat["LtL"][k], "Ltb": flat["Ltb"][part], "K": flat["K"][k],
                        "h": flat["h"][part]}
                return violation_problem(n).factor({name: xp.unwrap(v) for name, v in mine.items()})

            own = kernel_violation.Pivoted(pivoted.lam[part], pivoted.active[part], rows,
                                           pivoted.iterations)
            sol = finish_violation(own, values, max_iter=_losses.MAX_ITER, residual=False)  # in place
            n_fb[k], worst[k] = sol.n_fallback, sol.fallback_residual
        lam = xp.wrap(pivoted.lam).reshape(K, B, n)
        phi = kernel_violation.phi(xp, lam, b.F, b.q, gamma)
        loss = EnvelopeLoss.apply(b, lam, phi, gamma, eps, *params)
    return StackedInfo(loss.to(dtype), pivoted.active.reshape(K, B, 2 * n), n_fb, worst)


def prediction_losses(ens: StackedLCS, x: torch.Tensor, u: torch.Tensor, x_next: torch.Tensor, *,
                      warm_start: torch.Tensor | None = None, warm: torch.Tensor | None = None,
                      arrays: str = "auto") -> StackedInfo:
    """The prediction loss ``L_pred`` (eq. (6)) of every model on its own minibatch (see
    :func:`violation_losses`); ``warm_start`` ``(K, B, n_lam)``: the free sets."""
    K, B = x.shape[:2]
    n = ens.n_lam
    done = _compiled("prediction", ens, x, u, x_next, warm_start, warm, arrays, n, LCP_TOL,
                     _losses.MAX_ITER, STALL, _losses.DEGENERATE_TOL)
    if done is not None:
        loss, outs = done
        return StackedInfo(loss, torch.stack([torch.from_numpy(out[4]) for out in outs]), [0] * K,
                           [0.0] * K)
    xp = array_ops(x, arrays)
    params = [getattr(ens, k) for k in PARAMETER_NAMES]
    with xp.threads():
        b = kernel.batch(xp, params, x, u, x_next, xp.wrap(ens.stiffness)[:, None, None])
        F, q = xp.unwrap(b.F), xp.unwrap(b.q).reshape(K * B, n)
        with torch.no_grad():
            pivoted = kernel_lcp.solve(F, q, max_iter=_losses.MAX_ITER, arrays=arrays,
                                       warm_start=_initial(q < 0, warm_start, warm))
            n_fb, worst = [0] * K, [0.0] * K
            for k, rows in _model_rows(pivoted.unconverged, K, B).items():
                part = slice(k * B, (k + 1) * B)
                own = kernel_lcp.Pivoted(pivoted.lam[part], pivoted.w[part], pivoted.free[part],
                                         rows, pivoted.iterations)
                sol = finish_lcp(F[k], q[part], own, max_iter=_losses.MAX_ITER, residual=False)  # in place
                n_fb[k], worst[k] = sol.n_fallback, sol.fallback_residual
        lam = xp.wrap(pivoted.lam).reshape(K, B, n)
        loss = ImplicitLoss.apply(b, lam, xp.wrap(pivoted.free).reshape(K, B, n), *params)
    return StackedInfo(loss, pivoted.free.reshape(K, B, n), n_fb, worst)
