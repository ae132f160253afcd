"""The affine baseline: one affine map ``x' = A x + B u + d`` fitted by least squares,

    [A B d]^T = argmin_W  sum_t || [x_t; u_t; 1]^T W - x'_t ||^2,

the best single-mode model of the data (an LCS with no active mode anywhere).
"""

from __future__ import annotations

from typing import Any

import torch

from ...metrics import affine_lstsq

__all__ = ["AffineModel", "fit"]


class AffineModel:
    """``x' = [x, u, 1] W`` with ``W`` ``(n_x + n_u + 1, n_x)`` float64."""

    dtype = torch.float64

    def __init__(self, W: torch.Tensor) -> None:
        self.W = W

    def step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Next states ``(N, n_x)`` of states ``x`` ``(N, n_x)`` and inputs ``u`` ``(N, n_u)``."""
        ones = torch.ones(x.shape[0], 1, dtype=self.dtype)
        return torch.cat([x.to(self.dtype), u.to(self.dtype), ones], dim=1) @ self.W


def fit(train: Any, options: dict[str, Any], *, seed: int, modes: int) -> tuple[AffineModel, dict]:
    """Least squares on ``train`` (an :class:`lcs_cvx.Dataset`, :func:`lcs_cvx.metrics.affine_lstsq`);
    ``options``, ``seed`` and ``modes`` are unused (the fit is deterministic and has one piece)."""
    return AffineModel(affine_lstsq(train)), {}
