"""Open-loop rollouts of eq. (1): a model's step applied from initial states under input
sequences, ``x_{t+1} = step(x_t, u_t)``, for an :class:`lcs_cvx.LCS` and any model with the same
``step`` (:class:`lcs_cvx.RigidBodyContact`)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ._checks import LCSInputError, as_batch

__all__ = ["rollout"]


def rollout(model: Any, x0: Any, us: Any) -> torch.Tensor:
    """``model.step`` from ``x0`` ``(N, n_x)`` under ``us`` ``(N, T, n_u)`` (one run: ``(n_x,)``
    and ``(T, n_u)``), ``(N, T + 1, n_x)``: an :class:`LCS`'s rollout and that of any model with
    its ``step``, ``n_x``, ``n_u``, ``dtype`` and ``device`` (:class:`lcs_cvx.RigidBodyContact`)."""
    single = not (isinstance(x0, torch.Tensor) and x0.dim() == 2) and np.ndim(x0) == 1
    x = as_batch("x0", x0, model.n_x, dtype=model.dtype, device=model.device)
    us_t = torch.as_tensor(us, dtype=model.dtype, device=model.device) if not isinstance(us, torch.Tensor) else us
    if us_t.dim() == 2:
        us_t = us_t.unsqueeze(0)
    if us_t.dim() != 3 or us_t.shape[0] != x.shape[0] or us_t.shape[2] != model.n_u:
        raise LCSInputError(
            f"us: expected shape ({x.shape[0]}, T, {model.n_u}) or (T, {model.n_u}), "
            f"received shape {tuple(torch.as_tensor(us).shape)}"
        )
    xs = [x]
    for t in range(us_t.shape[1]):
        xs.append(model.step(xs[-1], us_t[:, t]))
    out = torch.stack(xs, dim=1)
    return out[0] if single else out
