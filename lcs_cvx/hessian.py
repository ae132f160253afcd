r"""Hessian of the violation-based loss, Lemma 4 (lemma.cn.hessian), and its products with vectors.

Per sample ``t`` the violation problem (V), eq. (equ.contactnet.2), is

    l_t(theta) = min_{z >= 0} J_t(theta, z),      z = (lam, phi) in R^{2 n_lam},
    J_t = 1/2 ||C lam + r_t||^2 + (1/eps) (lam^T phi + ||F lam + q_t - phi||^2 / (2 gamma)),

with ``r_t = A x_t + B u_t + d - x'_t`` and ``q_t = D x_t + E u_t + c``
(:meth:`lcs_cvx.problems.ViolationProblem.objective`, ``phi`` kept as a variable). The package's
``L_eps`` is the batch *mean* of ``l_t`` (:func:`lcs_cvx.violation_loss`; the paper sums).

Lemma 4. With ``z_t`` the solution, the envelope theorem gives ``grad L = mean_t J_theta``
(Lemma 3) and, differentiating once more,

    hess L = mean_t [ J_thth - J_thz (diag(J_z) + diag(z_t) J_zz)^{-1} diag(z_t) J_zth ].

Reduction used here. Under strict complementarity every component of ``z_t`` is either free
(``z_i > 0``, ``(J_z)_i = 0``) or bound-active (``z_i = 0``, ``(J_z)_i > 0``). A bound-active
row of ``diag(J_z) + diag(z) J_zz`` is ``(J_z)_i e_i^T`` and the matching row of the right-hand
side ``diag(z) J_zth`` is zero, so ``dz_i/dtheta = 0``: that row drops out. A free row is
``z_i (J_zz)_{i,:}`` with right-hand side ``z_i (J_zth)_i``; dividing by ``z_i > 0`` leaves
``(J_zz)_{FF} dz_F/dtheta = -(J_zth)_F``. Hence, with ``F_t`` the free set of sample ``t``,

    hess L = mean_t [ J_thth - (J_thz)_{:,F_t} (J_zz)_{F_t F_t}^{-1} (J_zth)_{F_t,:} ].

``J_zz`` does not depend on the sample (:func:`objective_hessian_zz`); ``(J_zz)_{FF}`` is a
principal submatrix of a positive definite matrix (Lemma 3(a), ``gamma < sigma_min(F + F^T)``),
so the correction is positive semidefinite. Each sample's masked system is solved batched as
``M_t = (m m^T) o J_zz + diag(1 - m)`` with ``m`` the 0/1 free mask, a Cholesky factor per
sample. ``J_thth`` (z fixed) and ``J_zth`` come from ``torch.func`` on ``J`` evaluated through
the model itself (``F = G G^T + H - H^T + s I`` included, so second derivatives through ``G``
are there). At an index where strict complementarity fails (``z_i = 0 = (J_z)_i``) the solver's
classification is held, i.e. the one-sided Hessian in which that bound stays active.

Parameter ordering: ``theta`` is the concatenation, in the order of
:data:`lcs_cvx.system.PARAMETER_NAMES` = ``(A, B, C, d, D, E, G, H, c)``, of each parameter
flattened row-major (``.reshape(-1)``, so ``A[i, j]`` sits at ``i * n_x + j`` of A's slice).
:func:`parameter_slices` maps names to slices; every parameter is included, whatever its
``requires_grad``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import nn

from ._checks import LCSInputError, SolverError, as_matrix
from .losses import _inputs, violation_loss
from .problems import ViolationProblem
from .system import LCS, PARAMETER_NAMES

__all__ = [
    "violation_hessian",
    "violation_hvp",
    "hvp_operator",
    "parameter_slices",
    "flatten_parameters",
    "unflatten",
    "objective_hessian_zz",
]


def parameter_slices(model: LCS) -> dict[str, slice]:
    """``{name: slice}`` of each parameter in the flat ``theta`` (order of ``PARAMETER_NAMES``)."""
    out, start = {}, 0
    for name in PARAMETER_NAMES:
        k = getattr(model, name).numel()
        out[name] = slice(start, start + k)
        start += k
    return out


def flatten_parameters(model: LCS) -> torch.Tensor:
    """The model's parameters as one detached ``(P,)`` vector (see :func:`parameter_slices`)."""
    return torch.cat([getattr(model, k).detach().reshape(-1) for k in PARAMETER_NAMES])


def unflatten(model: LCS, theta: torch.Tensor) -> dict[str, torch.Tensor]:
    """Inverse of :func:`flatten_parameters`: ``{name: tensor of the parameter's shape}``."""
    return {
        k: theta[s].reshape(getattr(model, k).shape) for k, s in parameter_slices(model).items()
    }


def objective_hessian_zz(
    C: torch.Tensor, F: torch.Tensor, gamma: float, eps: float
) -> torch.Tensor:
    """``J_zz`` ``(2 n, 2 n)`` of (V) in ``z = (lam, phi)``; the same for every sample::

        [[C^T C + F^T F / (eps gamma),  (I - F^T / gamma) / eps],
         [(I - F / gamma) / eps,        I / (eps gamma)        ]]

    Args: C ``(n_x, n)``, F ``(n, n)``. Positive definite iff ``C^T C + (F + F^T - gamma I)/eps``
    is (its Schur complement), which ``0 < gamma < sigma_min(F + F^T)`` guarantees.
    """
    eye = torch.eye(F.shape[0], dtype=F.dtype, device=F.device)
    top = torch.cat([C.mT @ C + F.mT @ F / (eps * gamma), (eye - F.mT / gamma) / eps], dim=1)
    bottom = torch.cat([(eye - F / gamma) / eps, eye / (eps * gamma)], dim=1)
    return torch.cat([top, bottom], dim=0)


class _Objective(nn.Module):
    """``J_t(theta, z)`` ``(B,)`` through ``model`` (for ``torch.func.functional_call``)."""

    def __init__(self, model: LCS) -> None:
        super().__init__()
        self.model = model

    def forward(self, z, x, u, x_next, gamma, eps):
        m, n = self.model, self.model.n_lam
        q = x @ m.D.mT + u @ m.E.mT + m.c
        r = x @ m.A.mT + u @ m.B.mT + m.d - x_next
        return ViolationProblem.objective(z[:, :n], z[:, n:], m.C, m.F, q, r, gamma, eps)


def _setup(model: Any, x: Any, u: Any, x_next: Any, gamma: float, eps: float):
    """Validate, solve (V) once (no grad) and return what both entry points need.

    Returns ``(theta0 (P,), J(theta, z) -> (B,), z (B, 2n), m (B, 2n) 0/1, chol (B, 2n, 2n))``.
    """
    if not isinstance(model, LCS):
        raise LCSInputError(f"model: expected an lcs_cvx.LCS, received {type(model).__name__}")
    x, u, x_next = _inputs(model, x, u, x_next)
    with torch.no_grad():  # checks gamma and eps; z is exactly the loss's (lam, phi)
        _, info = violation_loss(model, x, u, x_next, gamma, eps, solver="fast", return_info=True)
    kw = {"dtype": model.dtype, "device": model.device}
    z = torch.cat([info.lam, info.phi], dim=1)
    m = (z > 0).to(z.dtype)
    theta0 = flatten_parameters(model)
    wrapped = _Objective(model)

    def J(theta: torch.Tensor, zz: torch.Tensor) -> torch.Tensor:
        params = {f"model.{k}": v for k, v in unflatten(model, theta).items()}
        return torch.func.functional_call(wrapped, params, (zz, x, u, x_next, gamma, eps))

    with torch.no_grad():
        Jzz = objective_hessian_zz(model.C, model.F, gamma, eps)
        eye = torch.eye(z.shape[1], **kw)
        M = Jzz * (m[:, :, None] * m[:, None, :]) + eye * (1.0 - m)[:, None, :]
        chol, bad = torch.linalg.cholesky_ex(M)
    if bool((bad != 0).any()):  # not expected: (J_zz)_FF is positive definite (Lemma 3(a))
        raise SolverError(
            f"(J_zz)_FF not positive definite on {int((bad != 0).sum())} samples; "
            f"check gamma < sigma_min(F + F^T) = {model.sigma_min:.6g}"
        )
    return theta0, J, z, m, chol


def _grads(J: Callable, z: torch.Tensor):
    """``theta -> mean_t J_theta`` ``(P,)`` and ``theta -> J_z`` ``(B, 2n)``, both at fixed ``z``."""
    grad_theta = torch.func.grad(lambda th: J(th, z).mean())
    grad_z = lambda th: torch.func.grad(lambda zz: J(th, zz).sum())(z)  # noqa: E731
    return grad_theta, grad_z


def violation_hessian(
    model: LCS, x: Any, u: Any, x_next: Any, gamma: float = 1e-2, eps: float = 1e-4
) -> torch.Tensor:
    r"""Hessian of ``L_eps`` (batch mean, as :func:`lcs_cvx.violation_loss`), Lemma 4.

    ``mean_t [J_thth - (J_thz)_F (J_zz)_FF^{-1} (J_zth)_F]`` -- see the module docstring for the
    reduction of Lemma 4's formula under strict complementarity and for the ordering of ``theta``
    (:data:`lcs_cvx.system.PARAMETER_NAMES`, row-major; :func:`parameter_slices`).

    Args:
        model: an :class:`lcs_cvx.LCS`.
        x: ``(N, n_x)``; u: ``(N, n_u)``; x_next: ``(N, n_x)``.
        gamma: ``0 < gamma < sigma_min(F + F^T)`` (Lemma 2; checked). eps: ``> 0``.

    Returns:
        ``(P, P)`` tensor of the model's dtype, no autograd graph. Defined where strict
        complementarity holds on every sample (Lemma 3(b)).

    Example:
        >>> import lcs_cvx
        >>> sys = lcs_cvx.random_lcs(3, 2, 2, seed=0)
        >>> data = lcs_cvx.make_dataset(sys, 20)
        >>> violation_hessian(sys, data.x, data.u, data.x_next, eps=0.1).shape
        torch.Size([44, 44])
    """
    theta0, J, z, m, chol = _setup(model, x, u, x_next, gamma, eps)
    grad_theta, grad_z = _grads(J, z)
    H = torch.func.jacfwd(grad_theta)(theta0)  # J_thth, z fixed
    Jzt = torch.func.jacfwd(grad_z)(theta0)  # (B, 2n, P)
    # Y_t = chol_t^{-1} (m o J_zth): the correction mean_t Y_t^T Y_t is symmetric PSD by form
    Y = torch.linalg.solve_triangular(chol, m[:, :, None] * Jzt, upper=False)
    return H - torch.einsum("bkp,bkq->pq", Y, Y) / z.shape[0]


def hvp_operator(
    model: LCS, x: Any, u: Any, x_next: Any, gamma: float = 1e-2, eps: float = 1e-4
) -> Callable[[torch.Tensor], torch.Tensor]:
    """``v -> hess L_eps @ v`` (Lemma 4) with the solve and factorisations done once, for
    iterative methods that need many products at the same ``theta`` (see :func:`violation_hvp`)."""
    theta0, J, z, m, chol = _setup(model, x, u, x_next, gamma, eps)
    grad_theta, grad_z = _grads(J, z)
    _, vjp = torch.func.vjp(grad_z, theta0)

    def matvec(v: torch.Tensor) -> torch.Tensor:
        _, Hv = torch.func.jvp(grad_theta, (theta0,), (v,))
        _, Jzt_v = torch.func.jvp(grad_z, (theta0,), (v,))  # (B, 2n)
        s = torch.cholesky_solve((m * Jzt_v).unsqueeze(-1), chol).squeeze(-1) * m
        return Hv - vjp(s)[0] / z.shape[0]

    return matvec


def violation_hvp(
    model: LCS,
    x: Any,
    u: Any,
    x_next: Any,
    v: Any,
    gamma: float = 1e-2,
    eps: float = 1e-4,
) -> torch.Tensor:
    r"""Hessian-vector product ``hess L_eps @ v`` (Lemma 4) without forming the ``(P, P)`` matrix.

    ``J_thth v`` by forward-over-reverse at fixed ``z``; the correction
    ``-mean_t (J_thz)_F (J_zz)_FF^{-1} (J_zth v)_F`` by one batched jvp of ``J_z``, one batched
    Cholesky solve with the masked ``M_t`` and one vjp. Cost: a few evaluations of ``J``.

    Args:
        model, x, u, x_next, gamma, eps: as :func:`violation_hessian`.
        v: ``(P,)`` direction, ordered as :func:`parameter_slices`.

    Returns:
        ``(P,)`` tensor, no autograd graph.
    """
    P = sum(getattr(model, k).numel() for k in PARAMETER_NAMES) if isinstance(model, LCS) else 0
    op = hvp_operator(model, x, u, x_next, gamma, eps)
    v = as_matrix("v", v, (P,), dtype=model.dtype, device=model.device)
    return op(v)
