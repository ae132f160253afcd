"""Evaluation metrics of the paper (Sec. 5): e_test and the number of hybrid modes; and e_test of
the one-mode reference, the least-squares affine map."""

from __future__ import annotations

from typing import Any

import torch

from ._checks import LCSInputError
from .system import ACTIVE_TOL

__all__ = ["relative_error", "count_modes", "AffineMap", "affine_lstsq", "affine_error"]


def relative_error(model: Any, dataset: Any) -> float:
    """The paper's mean relative prediction error

        e_test = sum_t ||x'_theta(x_t, u_t) - x'_t||^2 / sum_t ||x'_t||^2,

    with ``x'_theta`` from the exact LCP solution of ``model`` (an :class:`lcs_cvx.LCS`), computed on
    the model's device whatever the dataset's.
    """
    if len(dataset) == 0:
        raise LCSInputError("dataset: expected at least one sample, received an empty dataset")
    with torch.no_grad():
        x = dataset.x.to(model.dtype)
        u = dataset.u.to(model.dtype)
        pred = model.step(x, u)  # on the model's device
        target = dataset.x_next.to(dtype=model.dtype, device=pred.device)
        num = ((pred - target) ** 2).sum()
        den = (target**2).sum()
    if float(den) == 0.0:
        raise LCSInputError("dataset: expected x_next not identically zero (e_test divides by it)")
    return float(num / den)


def count_modes(model: Any, dataset: Any, tol: float = ACTIVE_TOL) -> int:
    """Number of distinct active sets ``{i : lam_i > tol}`` (the hybrid modes) of ``model`` (an
    :class:`lcs_cvx.LCS`) over the inputs ``(x, u)`` of ``dataset`` (an :class:`lcs_cvx.Dataset`),
    with ``lam`` the exact LCP solution (:meth:`lcs_cvx.LCS.active_set`)."""
    with torch.no_grad():
        active = model.active_set(dataset.x.to(model.dtype), dataset.u.to(model.dtype), tol=tol)
    if active.shape[0] == 0:
        return 0
    return int(torch.unique(active, dim=0).shape[0])



class AffineMap:
    """``x' = [x, u, 1] W``, ``W = [A B d]^T`` ``(n_x + n_u + 1, n_x)`` float64: a model with one
    mode (an LCS with no unit active anywhere), as :func:`relative_error` takes it. A reference,
    not a model with a device of its own: it steps on the device of the states it is given."""

    dtype = torch.float64

    def __init__(self, W: torch.Tensor) -> None:
        self.W = W

    @classmethod
    def features(cls, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """``[x, u, 1]`` ``(N, n_x + n_u + 1)`` float64 (detached)."""
        ones = torch.ones(x.shape[0], 1, dtype=cls.dtype, device=x.device)
        return torch.cat([x.detach().to(cls.dtype), u.detach().to(cls.dtype), ones], dim=1)

    def step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Next states ``(N, n_x)`` of states ``x`` ``(N, n_x)`` and inputs ``u`` ``(N, n_u)``, on
        ``x``'s device (``W`` is moved there)."""
        return self.features(x, u.to(x.device)) @ self.W.to(x.device)


def affine_lstsq(dataset: Any) -> AffineMap:
    """The least-squares affine map of ``dataset``: ``W = argmin sum_t || [x_t; u_t; 1]^T W -
    x'_t ||^2``, the best model with one mode."""
    Z = AffineMap.features(dataset.x, dataset.u)
    return AffineMap(torch.linalg.lstsq(Z, dataset.x_next.detach().to(AffineMap.dtype)).solution)


def affine_error(train: Any, test: Any) -> float:
    """e_test on ``test`` (:func:`relative_error`) of the affine map :func:`affine_lstsq` fitted on
    ``train`` (both :class:`lcs_cvx.Dataset`): the error level of a model whose complementarity
    units explain nothing."""
    return relative_error(affine_lstsq(train), test)
