r"""The parameters of eq. (1) and the parameterisation of ``F`` (paper Sec. 5).

    theta = {A, B, C, d, D, E, G, H, c},      F = G G^T + H - H^T + s I

``F + F^T = 2 (G G^T + s I) >= 2 s I > 0`` for every ``G`` and ``H`` and a fixed ``stiffness``
``s > 0``: Assumption 1 holds by construction. :func:`F_matrix` forms ``F``, :func:`F_adjoint`
is its chain rule and :func:`split_F` its inverse; :class:`lcs_cvx.LCS` holds the parameters.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ._checks import LCSInputError
from ._kernels import losses as kernel
from ._kernels.arrays import TORCH
from .problems import sym_min_eig

__all__ = ["PARAMETER_NAMES", "MASKABLE", "MATRIX_NAMES", "parameter_shapes", "F_matrix", "F_adjoint",
           "split_F", "factor_F", "lcs_sizes"]

#: Learnable parameters, in the order used for flattening (Lemma 4's Hessian).
PARAMETER_NAMES = ("A", "B", "C", "d", "D", "E", "G", "H", "c")
#: Parameters that take a sparsity mask (:meth:`lcs_cvx.LCS.mask`). ``G`` and ``H`` do not: they
#: parameterise ``F`` as a whole (fix them, or ``F``, instead).
MASKABLE = ("A", "B", "C", "d", "D", "E", "c")
#: Matrices of the LCS as exported by :meth:`lcs_cvx.LCS.to_matrices`.
MATRIX_NAMES = ("A", "B", "C", "d", "D", "E", "F", "c")


def parameter_shapes(n_x: int, n_u: int, n_lam: int) -> dict[str, tuple[int, ...]]:
    """The shape of every parameter of :data:`PARAMETER_NAMES` and of ``F``, by name."""
    return {
        "A": (n_x, n_x),
        "B": (n_x, n_u),
        "C": (n_x, n_lam),
        "d": (n_x,),
        "D": (n_lam, n_x),
        "E": (n_lam, n_u),
        "G": (n_lam, n_lam),
        "H": (n_lam, n_lam),
        "F": (n_lam, n_lam),
        "c": (n_lam,),
    }


def F_matrix(G: torch.Tensor, H: torch.Tensor, stiffness: torch.Tensor | float) -> torch.Tensor:
    """``F = G G^T + H - H^T + s I`` (Sec. 5) from ``G``, ``H`` ``(n, n)`` (differentiable)."""
    return kernel.F_matrix(TORCH, G, H, stiffness)


def F_adjoint(T_F: torch.Tensor, G: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The chain rule of ``F = G G^T + H - H^T + s I`` (Sec. 5): given ``T_F[..., j, m] =
    d(.)/dF_jm`` ``(..., n, n)``, return ``d(.)/dG = (T_F + T_F^T) G`` and
    ``d(.)/dH = T_F - T_F^T``, each ``(..., n, n)``."""
    return kernel.F_adjoint(T_F, G)


def split_F(F: torch.Tensor, stiffness: float, strict: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """``(G, H)`` with ``G G^T + H - H^T + s I = F`` for ``F`` ``(n, n)`` whose symmetric part is
    ``>= s I``, the inverse of :func:`F_matrix`: ``H = (F - F^T) / 4`` and ``G = V sqrt(D)`` from
    the eigen-decomposition ``V D V^T`` of ``(F + F^T) / 2 - s I``. Below ``s I`` the symmetric
    part's eigenvalues are raised to ``s``: the nearest ``F`` of the model's set in the symmetric
    part; with ``strict``, an :class:`LCSInputError` instead (beyond round-off)."""
    n = F.shape[0]
    if strict:
        low, s = 0.5 * float(sym_min_eig(F)), float(stiffness)  # of the symmetric part (F + F^T) / 2
        if low < s - 1e-12 * (1.0 + float(F.abs().max())):
            raise LCSInputError(
                f"F: expected a symmetric part (F + F^T) / 2 >= s I with s = {s:.6g} (the "
                f"model's stiffness), received smallest eigenvalue {low:.6g}; build the model "
                "with a smaller stiffness")
    sym = 0.5 * (F + F.mT) - float(stiffness) * torch.eye(n, dtype=F.dtype, device=F.device)
    vals, vecs = torch.linalg.eigh(sym)
    return vecs * vals.clamp(min=0.0).sqrt(), 0.25 * (F - F.mT)


def factor_F(F: torch.Tensor) -> tuple[float, torch.Tensor, torch.Tensor]:
    """``(s, G, H)`` with ``G G^T + H - H^T + s I = F`` for ``F`` ``(n, n)`` float64 with ``F + F^T``
    positive definite (Assumption 1; else :class:`LCSInputError`): ``s = sigma_min(F + F^T) / 4``,
    ``H = (F - F^T) / 4`` and ``G`` the Cholesky factor of ``(F + F^T) / 2 - s I``."""
    smin = float(sym_min_eig(F))
    if not smin > 0:
        raise LCSInputError(
            "F: expected F + F^T positive definite (Assumption 1), received "
            f"sigma_min(F + F^T) = {smin:.6g}"
        )
    s = smin / 4.0
    sym = 0.5 * (F + F.mT) - s * torch.eye(F.shape[0], dtype=F.dtype, device=F.device)
    return s, torch.linalg.cholesky(sym), 0.25 * (F - F.mT)


def lcs_sizes(A: Any, B: Any, C: Any) -> tuple[int, int, int]:
    """``(n_x, n_u, n_lam)`` from the shapes of ``A`` ``(n_x, n_x)``, ``B`` ``(n_x, n_u)`` and
    ``C`` ``(n_x, n_lam)`` (arrays or tensors); :class:`LCSInputError` for another rank or a
    non-square ``A``."""
    dims = {k: tuple(np.shape(v.detach().cpu() if isinstance(v, torch.Tensor) else np.asarray(v, dtype=np.float64)))
            for k, v in (("A", A), ("C", C), ("B", B))}
    if len(dims["A"]) != 2 or dims["A"][0] != dims["A"][1]:
        raise LCSInputError(f"A: expected a square (n_x, n_x) matrix, received shape {dims['A']}")
    for k, want in (("C", "(n_x, n_lam)"), ("B", "(n_x, n_u)")):
        if len(dims[k]) != 2:
            raise LCSInputError(f"{k}: expected shape {want}, received shape {dims[k]}")
    return dims["A"][0], dims["B"][1], dims["C"][1]
