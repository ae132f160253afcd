"""The two losses (:mod:`lcs_cvx.losses`; eqs. (9) and (6)) and their gradients in every
parameter (Lemma 3's envelope gradient, Lemma 1's implicit one) in one call, without autograd:
what a training step needs. One model's float64 CPU tensors run the compiled kernel (solve,
loss and gradient in one call, :mod:`lcs_cvx._kernels.compiled`); anything else the same loss
through autograd.
"""

from __future__ import annotations

from typing import Any

import torch

from ._checks import check_positive
from ._kernels import calls
from .losses import (
    DEGENERATE_TOL,
    LCP_TOL,
    MAX_ITER,
    STALL,
    VIOLATION_TOL,
    prediction_loss,
    violation_loss,
)
from .system import PARAMETER_NAMES

__all__ = ["violation_value_and_grad", "prediction_value_and_grad"]


def _value_and_grad(model: Any, x: Any, u: Any, x_next: Any, kernel_fn: Any, width: int,
                    options: tuple, loss_fn: Any, gamma: float | None = None, threads: int | None = None
                    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The compiled kernel's value and gradients where it runs, else autograd through ``loss_fn``
    (the same numbers to round-off; ``loss_fn`` checks its own arguments); ``gamma``: the
    violation loss's, checked against the model's ``F`` (Lemma 2)."""
    if calls.ready(model, x, u, x_next, one_model=True):
        done = calls.call_on_model(kernel_fn, model, x, u, x_next, None, width, *options, gamma=gamma,
                                   threads=threads)
        if done is not None:
            out = done[1]
            return calls.scalar(out[0]), dict(zip(PARAMETER_NAMES, out[1], strict=True))
    params = [getattr(model, k) for k in PARAMETER_NAMES]
    with torch.enable_grad():
        value = loss_fn()
        grads = torch.autograd.grad(value, params, allow_unused=True)
    return value.detach(), {k: torch.zeros_like(p) if g is None else g
                            for k, g, p in zip(PARAMETER_NAMES, grads, params, strict=True)}


def violation_value_and_grad(model: Any, x: Any, u: Any, x_next: Any, gamma: float = 1e-2,
                             eps: float = 1e-4, threads: int | None = None
                             ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """:func:`violation_loss` (fast path) and its gradient in every parameter, in one call and
    without autograd: what one training step needs.

    Returns ``(value, grads)``: the 0-dim loss (no graph) and ``grads[name]``, the gradient in
    the parameter ``name`` (``A, B, C, d, D, E, G, H, c``; Lemma 3's), shaped as the parameter --
    the numbers of ``violation_loss(...).backward()``, to round-off. One model's float64 CPU
    tensors run the compiled kernel (:mod:`lcs_cvx._kernels.compiled`, solve, loss and gradient
    in one call); anything else (other dtypes and devices, inputs to convert) the same loss
    through autograd, a float32 model's computed in float64 and returned in float32
    (:data:`lcs_cvx.losses.VIOLATION_DTYPE`). ``threads``: as :func:`violation_loss`'s.
    """
    check_positive("eps", eps)
    check_positive("gamma", gamma)
    calls.resolve_threads(threads)
    return _value_and_grad(
        model, x, u, x_next, "violation", 2 * model.n_lam,
        (gamma, eps, VIOLATION_TOL, MAX_ITER, STALL),
        lambda: violation_loss(model, x, u, x_next, gamma=gamma, eps=eps, threads=threads), gamma=gamma,
        threads=threads)


def prediction_value_and_grad(model: Any, x: Any, u: Any, x_next: Any, threads: int | None = None
                              ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """:func:`prediction_loss` (fast path) and its gradient in every parameter (Lemma 1's), in
    one call and without autograd; as :func:`violation_value_and_grad`."""
    calls.resolve_threads(threads)
    return _value_and_grad(
        model, x, u, x_next, "prediction", model.n_lam,
        (LCP_TOL, MAX_ITER, STALL, DEGENERATE_TOL),
        lambda: prediction_loss(model, x, u, x_next, threads=threads), threads=threads)
