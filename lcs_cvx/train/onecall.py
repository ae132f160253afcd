r"""Adam's steps on the one-call path: a step of :func:`lcs_cvx.fit`'s Adam and polish phases for
one float64 CPU model, without autograd.

A step minimises ``L(theta) + omega ||C||_F^2`` (eq. (4)) on a minibatch: the loss and its
gradient in every parameter come from one call of the compiled kernel (the numbers of
:func:`lcs_cvx.violation_value_and_grad` or :func:`lcs_cvx.prediction_value_and_grad`: Lemma 3's
envelope gradient, or Lemma 1's implicit one), the regulariser's gradient ``2 omega C`` is added,
fixed parameters are skipped and masked entries get a zero gradient
(:mod:`lcs_cvx.parameter_constraints`), and Adam's update
(:func:`lcs_cvx._kernels.adam.adam_update`) changes the parameters and the optimiser's own state
in place. The result is that of ``loss.backward(); adam.step()`` to round-off, and a checkpoint
holds the same optimiser state.

:func:`adam_step` returns None, having changed nothing, where this path does not apply: another
dtype or device, the optimiser's first step (which creates its state) or options other than
plain Adam's, or a sample the compiled kernel leaves unconverged (the autograd step then ends
it with the reference solvers and says so).
"""

from __future__ import annotations

import operator
import weakref
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from .. import losses
from .._kernels import calls
from .._kernels.adam import adam_update
from .._kernels.products import stiffness_matrix
from .._kernels.rows import all_seen
from .._kernels.training import PREDICTION, VIOLATION
from .._kernels.training import adam_steps as _compiled_steps
from ..parameter_constraints import project_
from ..problems import check_gamma
from ..system import LCS, PARAMETER_NAMES

__all__ = ["adam_step", "adam_steps", "adam_update_from_grads", "data_arrays"]

#: Per optimiser: its state table and trainable parameters when last seen, and the flat views of
#: their moments and step counts (made again when either changes, e.g. after loading a checkpoint).
_VIEWS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

#: A parameter's position among the compiled kernels' parameters and gradients.
_INDEX = {name: k for k, name in enumerate(PARAMETER_NAMES)}


def data_arrays(data: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``(x, u, x_next)`` of a :class:`lcs_cvx.Dataset` as arrays on its memory where it is
    float64 on the CPU (None elsewhere: the steps then take the autograd path)."""
    x = data.x
    if x.dtype != torch.float64 or not x.is_cpu:
        return None
    return tuple(np.ascontiguousarray(t.detach().numpy()) for t in (data.x, data.u, data.x_next))


def _plain_adam(adam: torch.optim.Optimizer) -> bool:
    if type(adam) is not torch.optim.Adam or len(adam.param_groups) != 1:
        return False
    g = adam.param_groups[0]
    return (g["weight_decay"] == 0 and not g["amsgrad"] and not g["maximize"] and not g["capturable"]
            and not g["differentiable"] and not g["fused"] and not g.get("decoupled_weight_decay", False))


def _views(adam: torch.optim.Adam, trainable: list[torch.Tensor]) -> tuple | None:
    """The flat views ``(exp_avgs, exp_avg_sqs, steps)`` of ``trainable``'s Adam state (None
    when a parameter has none yet)."""
    seen = _VIEWS.get(adam)
    if seen is not None and seen[0] is adam.state and len(seen[1]) == len(trainable) \
            and all(map(operator.is_, trainable, seen[1])):
        return seen[2]
    states = [adam.state.get(p) for p in trainable]
    if any(not st or not isinstance(st.get("step"), torch.Tensor) for st in states):
        return None
    views = (tuple(st["exp_avg"].view(-1).numpy() for st in states),
             tuple(st["exp_avg_sq"].view(-1).numpy() for st in states),
             tuple(st["step"].view(1).numpy() for st in states))
    _VIEWS[adam] = (adam.state, list(trainable), views)
    return views


def _update(adam: torch.optim.Adam, params: list[torch.Tensor], arrays: list[np.ndarray],
            grads: list[np.ndarray]) -> bool:
    """Adam's update of ``params`` (float64 CPU tensors; ``arrays`` on their memory) with the
    gradients ``grads`` (arrays of their shapes) on the optimiser's own state, compiled; False
    (nothing changed) where the state is not there yet or the step counts differ."""
    views = _views(adam, params) if params else None
    if views is None:
        return False
    group = adam.param_groups[0]
    beta1, beta2 = group["betas"]
    step = float(views[2][0][0]) + 1.0  # the bias corrections as torch computes them
    bias_correction1 = 1 - beta1**step
    bias_correction2 = 1 - beta2**step
    step_size = group["lr"] / bias_correction1
    flat_params = tuple(a.reshape(-1) for a in arrays)
    flat_grads = tuple(np.ascontiguousarray(g).reshape(-1) for g in grads)
    return adam_update(flat_params, flat_grads, views[0], views[1], views[2], beta1, beta2, group["eps"],
                       step_size, bias_correction2**0.5, step)


def adam_update_from_grads(adam: torch.optim.Adam) -> None:
    """``adam.step()`` on the parameters' ``.grad``: the compiled update for plain Adam on
    float64 CPU parameters whose state exists (the numbers of :func:`adam_step`'s update, bit for
    bit, on equal gradients), torch's own step otherwise."""
    params = [p for p in adam.param_groups[0]["params"] if p.grad is not None] if _plain_adam(adam) else []
    if not (params and all(p.dtype == torch.float64 and p.is_cpu for p in params)
            and _update(adam, params, [p.detach().numpy() for p in params], [p.grad.numpy() for p in params])):
        adam.step()


def adam_step(adam: torch.optim.Adam, model: LCS, loss: str, x: np.ndarray, u: np.ndarray,
              x_next: np.ndarray, warm: np.ndarray | None, *, gamma: float, eps: float, reg: float,
              threads: int | None = None, rows: np.ndarray | None = None,
              tables: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[float, float, np.ndarray | None] | None:
    """One Adam step of ``model`` on the minibatch ``(x (B, n_x), u (B, n_u), x_next (B, n_x))``
    (float64 arrays) of ``loss`` (``"violation"`` with ``gamma`` and ``eps``, or
    ``"prediction"``) plus ``reg ||C||_F^2``, at the learning rate of ``adam``'s group.
    ``warm``: the samples' active sets from their last visit ``(B, width)`` bool, or None.

    ``rows``: the minibatch is the rows ``rows`` of ``x``, ``u``, ``x_next`` (all the data),
    read where they lie (:func:`lcs_cvx._kernels.calls.compiled_call`'s ``rows``); ``tables``:
    then the trainer's ``(active (N, width), seen (N,))``, the warm start where every row was
    seen (``warm`` is then not used), and the step's active sets written into them (also when
    the step is not made: the loss and gradient do not depend on the warm start, to round-off).

    Returns ``(regularised loss, finite F after the step, active sets (B, width))`` (with
    ``rows``: None for the active sets), or None (nothing changed) where the
    autograd step must run instead (module docstring)."""
    if model.A.dim() != 2 or model.A.dtype != torch.float64 or not model.A.is_cpu or not _plain_adam(adam):
        return None
    params, arrays, s = calls.model_arrays(model)
    trainable = [k for k, p in enumerate(params) if p.requires_grad]
    if not trainable or _views(adam, [params[k] for k in trainable]) is None:
        return None
    stiffness = float(s)
    n = model.n_lam
    if loss == "violation":
        if not gamma < 2.0 * stiffness:  # F + F^T >= 2 s I by construction: below, nothing to check
            check_gamma(model.F, gamma)
        fn, width = calls.compiled().violation, 2 * n
        options = (gamma, eps, losses.VIOLATION_TOL, losses.MAX_ITER, losses.STALL)
    else:  # the fast losses' own tolerances and sweeps (read here: one source)
        fn, width = calls.compiled().prediction, n
        options = (losses.LCP_TOL, losses.MAX_ITER, losses.STALL, losses.DEGENERATE_TOL)
    if tables is not None:
        warm = tables[0] if all_seen(tables[1], rows) else None
    if warm is None:
        warm = calls.COLD
    status, out = calls.compiled_call(fn, arrays, stiffness, x, u, x_next, warm, width, *options,
                                      threads=threads, tensors=False, rows=rows, store=tables,
                                      per_sample=rows is None)
    if status:
        return None
    value, grads, active = out[0], list(out[1]), out[4]
    C = arrays[2]
    if reg:  # reg ||C||^2: its gradient reg (2 C), as autograd forms it
        value += reg * float((C * C).sum())
        grads[2] = grads[2] + reg * (2.0 * C)
    for name, mask in model.masks.items():
        k = _INDEX[name]
        grads[k] = np.where(mask.numpy(), grads[k], 0.0)
    if not _update(adam, [params[k] for k in trainable], [arrays[k] for k in trainable],
                   [grads[k] for k in trainable]):
        return None  # the parameters' step counts differ: torch's own step handles that
    if model.masks:
        project_(model)
    finite_F = bool(np.isfinite(stiffness_matrix(arrays[6], arrays[7], stiffness)).all())
    return value, finite_F, active


def adam_steps(adam: torch.optim.Adam, model: LCS, loss: str, data: tuple[np.ndarray, np.ndarray, np.ndarray],
               rows: np.ndarray, active: np.ndarray, seen: np.ndarray, *, gamma: float, eps: Sequence[float],
               lr: Sequence[float], reg: float) -> tuple[int, np.ndarray, bool] | None:
    """Steps ``s = 0 .. K - 1`` of :func:`adam_step` in one compiled call
    (:func:`lcs_cvx._kernels.training.adam_steps`; the same numbers, bit for bit): minibatch
    ``rows[s]`` ``(K, B)`` of ``data`` (``(x, u, x_next)`` arrays), ``eps[s]`` and learning rate
    ``lr[s]``; the warm starts from, and the new active sets into, ``active (N, width)`` and
    ``seen (N,)`` in place.

    Returns ``(done, losses, diverged)`` (:func:`lcs_cvx._kernels.training.adam_steps`; the
    group's learning rate left at the last step's), or None (nothing changed) where
    :func:`adam_step` would return None for the first step."""
    if model.A.dim() != 2 or model.A.dtype != torch.float64 or not model.A.is_cpu or not _plain_adam(adam):
        return None
    params, arrays, s = calls.model_arrays(model)
    trainable = [p.requires_grad for p in params]
    if not any(trainable):
        return None
    views = _views(adam, [p for p, t in zip(params, trainable, strict=True) if t])
    if views is None:
        return None
    step0 = float(views[2][0][0])
    if any(float(v[0]) != step0 for v in views[2]):
        return None
    stiffness = float(s)
    if loss == "violation" and not gamma < 2.0 * stiffness:
        check_gamma(model.F, gamma)
    # Adam's state in PARAMETER_NAMES order; a fixed parameter's (never read) is a placeholder
    it = iter(range(len(views[0])))
    slot = [next(it) if t else None for t in trainable]
    exp_avgs = tuple(views[0][j] if j is not None else a.reshape(-1) * 0.0 for j, a in zip(slot, arrays, strict=True))
    exp_avg_sqs = tuple(views[1][j] if j is not None else a.reshape(-1) * 0.0 for j, a in zip(slot, arrays, strict=True))
    counts = tuple(views[2][j] if j is not None else np.zeros(1, np.float32) for j in slot)
    masks = tuple(model.masks[name].numpy().reshape(-1) if name in model.masks else np.ones(a.size, np.bool_)
                  for name, a in zip(PARAMETER_NAMES, arrays, strict=True))
    group = adam.param_groups[0]
    beta1, beta2 = group["betas"]
    t = [step0 + 1.0 + k for k in range(len(rows))]  # each step's bias corrections, as torch computes them
    step_sizes = np.array([lr_k / (1 - beta1**t_k) for lr_k, t_k in zip(lr, t, strict=True)])
    bc2 = np.array([(1 - beta2**t_k) ** 0.5 for t_k in t])
    A, B, C, d, D, E, G, H, c = arrays
    done, values, diverged = _compiled_steps(
        VIOLATION if loss == "violation" else PREDICTION, A, B, C, d, D, E, c, G, H, stiffness, *data,
        np.ascontiguousarray(rows), active, seen, gamma, np.asarray(eps, dtype=np.float64), _tolerance(loss),
        losses.MAX_ITER, losses.STALL, losses.DEGENERATE_TOL, float(reg), masks, np.array(trainable),
        exp_avgs, exp_avg_sqs, counts, beta1, beta2, group["eps"], step_sizes, bc2, step0)
    if done:
        group["lr"] = lr[done - 1]
    return int(done), values, bool(diverged)


def _tolerance(loss: str) -> float:
    """The fast losses' pivoting tolerance of ``loss``."""
    return losses.VIOLATION_TOL if loss == "violation" else losses.LCP_TOL
