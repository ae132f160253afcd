"""The affine baseline: one affine map ``x' = A x + B u + d`` fitted by least squares,

    [A B d]^T = argmin_W  sum_t || [x_t; u_t; 1]^T W - x'_t ||^2,

the best single-mode model of the data (an LCS with no active mode anywhere).
"""

from __future__ import annotations

from typing import Any

from ...metrics import AffineMap, affine_lstsq

__all__ = ["AffineModel", "fit"]


#: The baseline's model: :class:`lcs_cvx.metrics.AffineMap`.
AffineModel = AffineMap


def fit(train: Any, options: dict[str, Any], *, seed: int, modes: int) -> tuple[AffineModel, dict]:
    """Least squares on ``train`` (an :class:`lcs_cvx.Dataset`, :func:`lcs_cvx.metrics.affine_lstsq`);
    ``options``, ``seed`` and ``modes`` are unused (the fit is deterministic and has one piece)."""
    return affine_lstsq(train), {}
