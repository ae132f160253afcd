r"""The arithmetic of the two fast losses, forward and backward, in the kernels' arrays.

Both losses start from the same per-batch quantities (:func:`batch`): ``q = D x + E u + c``,
``r = A x + B u + d - x'`` and ``F = G G^T + H - H^T + s I`` (:func:`F_matrix`), computed from
the model's parameters without an autograd graph. Their gradients are written out in closed
form (:func:`envelope_backward`: Lemma 3; :func:`implicit_backward`: Lemma 1), each a few small
products, and taken from ``F`` to ``(G, H)`` by :func:`F_adjoint`. :mod:`lcs_cvx.losses` wraps
them in ``torch.autograd.Function`` adapters.

Every function also takes a stack of ``K`` models (:mod:`lcs_cvx.stacked`): parameters with a
leading model axis (``(K, n, n)``, ``(K, n)``), per-sample arrays ``(K, B, .)`` (model ``k``'s
samples in row ``k``), a stiffness ``(K, 1, 1)``; the loss values are then ``(K,)``, one per
model, and their gradients stacked. Each model's numbers are those of its own call.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import torch

from .arrays import ArrayOps
from .stacks import matrices

__all__ = [
    "Batch",
    "F_adjoint",
    "F_matrix",
    "batch",
    "degenerate_count",
    "envelope_backward",
    "envelope_forward",
    "implicit_backward",
    "implicit_forward",
    "parameter_gradients",
]


def F_matrix(xp: ArrayOps, G: Any, H: Any, stiffness: Any) -> Any:
    """``F = G G^T + H - H^T + s I`` (paper Sec. 5) from ``G``, ``H`` ``(n, n)`` (or stacks
    ``(K, n, n)`` with ``s`` ``(K, 1, 1)``)."""
    HT = H.swapaxes(-1, -2)
    return G @ G.swapaxes(-1, -2) + H - HT + stiffness * xp.eye(G.shape[-1], G)


def F_adjoint(T_F: Any, G: Any) -> tuple[Any, Any]:
    """The chain rule of ``F = G G^T + H - H^T + s I``: given ``T_F[..., j, m] = d(.)/dF_jm``
    ``(..., n, n)``, ``d(.)/dG = (T_F + T_F^T) G`` and ``d(.)/dH = T_F - T_F^T``."""
    T = T_F.swapaxes(-1, -2)
    return (T_F + T) @ G, T_F - T


class Batch(NamedTuple):
    """What both fast losses start from, in the kernel's arrays (``xp``): the inputs ``x``
    ``(B, n_x)``, ``u`` ``(B, n_u)``, ``q = D x + E u + c`` ``(B, n)``, ``r = A x + B u + d - x'``
    ``(B, n_x)``, ``F`` ``(n, n)`` and the parameters ``C`` ``(n_x, n)``, ``G`` ``(n, n)``."""

    xp: ArrayOps
    x: Any
    u: Any
    q: Any
    r: Any
    F: Any
    C: Any
    G: Any


def batch(xp: ArrayOps, params: Sequence[torch.Tensor], x: torch.Tensor, u: torch.Tensor,
          x_next: torch.Tensor, stiffness: float) -> Batch:
    """:class:`Batch` from the nine parameter tensors ``A, B, C, d, D, E, G, H, c`` (in
    :data:`lcs_cvx.system.PARAMETER_NAMES` order) and the data tensors (detached, no copy on
    CPU). The caller holds :meth:`ArrayOps.threads`."""
    A, B, C, d, D, E, G, H, c = (xp.wrap(t) for t in params)
    x, u, x_next = xp.wrap(x), xp.wrap(u), xp.wrap(x_next)
    # the association of the closed form (Lemma 3's w = F lam + q - phi cancels: keep it)
    q = x @ D.swapaxes(-1, -2) + u @ E.swapaxes(-1, -2) + c[..., None, :]
    r = x @ A.swapaxes(-1, -2) + u @ B.swapaxes(-1, -2) + d[..., None, :] - x_next
    return Batch(xp, x, u, q, r, F_matrix(xp, G, H, stiffness), C, G)


def parameter_gradients(xp: ArrayOps, need: Sequence[bool], x: Any, u: Any, lam: Any, G: Any,
                        g_r: Any, g_q: Any) -> tuple[Any, ...]:
    """The gradients of ``A, B, C, d, D, E, G, H, c`` (None where ``need`` is False) of a loss
    whose sensitivities to ``r = A x + B u + d - x' + C lam`` and to ``q = D x + E u + c + F lam``
    (``lam`` held fixed) are ``g_r`` ``(B, n_x)`` and ``g_q`` ``(B, n)``: ``dA = g_r^T x``,
    ``dC = g_r^T lam``, ``dd = sum_t g_r``, ``dD = g_q^T x``, ``dF = g_q^T lam``, ..., and
    ``dG, dH`` from ``dF`` (:func:`F_adjoint`). One small product per gradient, each contiguous
    as the parameters are laid out."""
    grT, gqT = g_r.swapaxes(-1, -2), g_q.swapaxes(-1, -2)
    dG, dH = F_adjoint(gqT @ lam, G) if need[6] or need[7] else (None, None)
    return (grT @ x if need[0] else None, grT @ u if need[1] else None,
            grT @ lam if need[2] else None, xp.colsum(g_r) if need[3] else None,
            gqT @ x if need[4] else None, gqT @ u if need[5] else None,
            dG, dH, xp.colsum(g_q) if need[8] else None)


def _factor(xp: ArrayOps, grad: torch.Tensor) -> Any:
    """The incoming gradient as a factor of the residuals: a number (one model), or ``(K, 1, 1)``
    for a stack's ``(K,)`` values."""
    return xp.scalar(grad) if grad.dim() == 0 else xp.wrap(grad)[:, None, None]


def _tensors(xp: ArrayOps, arrays: tuple[Any, ...]) -> tuple[torch.Tensor | None, ...]:
    """The kernel arrays as tensors (None kept)."""
    return tuple(None if a is None else xp.unwrap(a) for a in arrays)


def envelope_forward(b: Batch, lam: Any, phi: Any, gamma: float, eps: float) -> tuple[torch.Tensor, tuple]:
    r"""Batch mean of (V)'s objective at the optimum ``(lam, phi)`` ``(B, n)`` (arrays):
    ``mean_t 1/2 ||e_t||^2 + (lam_t^T phi_t + ||w_t||^2 / (2 gamma)) / eps`` with
    ``e = C lam + r`` and ``w = F lam + q - phi``. Returns the value (a 0-dim tensor) and what
    :func:`envelope_backward` needs."""
    xp = b.xp
    e = b.r + lam @ b.C.swapaxes(-1, -2)
    w = b.q + lam @ b.F.swapaxes(-1, -2) - phi  # the association of the closed form
    n = lam.shape[-2]
    total = 0.5 * xp.inner(e, e) + (xp.inner(lam, phi) + 0.5 / gamma * xp.inner(w, w)) / eps
    # the residuals, already scaled by the gradient's 1/B and 1/(gamma eps B)
    saved = (xp, b.x, b.u, lam, b.G, e * (1.0 / n), w * (1.0 / (gamma * eps * n)))
    return xp.unwrap(total / n), saved


def envelope_backward(saved: tuple, grad: torch.Tensor, need: Sequence[bool]) -> tuple[torch.Tensor | None, ...]:
    r"""Lemma 3's gradients of :func:`envelope_forward`'s value times ``grad`` (the envelope
    theorem: ``lam`` and ``phi`` are optimal, so their variation does not contribute). With
    ``g_e = e / B`` and ``g_w = w / (gamma eps B)``::

        dA = g_e^T x,  dB = g_e^T u,  dC = g_e^T lam,  dd = sum_t g_e,
        dD = g_w^T x,  dE = g_w^T u,  dF = g_w^T lam,  dc = sum_t g_w,

    and ``dG, dH`` from ``dF`` -- tensors in ``A, B, C, d, D, E, G, H, c`` order (None where
    ``need`` is False)."""
    xp, x, u, lam, G, ge, gw = saved
    s = _factor(xp, grad)
    with xp.threads():
        return _tensors(xp, parameter_gradients(xp, need, x, u, lam, G, ge * s, gw * s))


def implicit_forward(b: Batch, lam: Any, free: Any) -> tuple[torch.Tensor, tuple]:
    r"""Batch mean of ``1/2 ||e_t||^2``, ``e = C lam + r``, at the exact LCP solution ``lam``
    ``(B, n)`` with its free sets ``free`` (arrays; a degenerate index is not free: held at
    zero, the one-sided derivative). Returns the value and what :func:`implicit_backward`
    needs."""
    xp = b.xp
    e = b.r + lam @ b.C.swapaxes(-1, -2)
    n = lam.shape[-2]
    total = 0.5 * xp.inner(e, e)
    return xp.unwrap(total / n), (xp, b.x, b.u, lam, free, b.F, b.C, b.G, e * (1.0 / n))


def implicit_backward(saved: tuple, grad: torch.Tensor, need: Sequence[bool]) -> tuple[torch.Tensor | None, ...]:
    r"""Lemma 1's gradients of :func:`implicit_forward`'s value times ``grad``. On the free set
    ``I`` of a sample, ``F_II lam_I = -q_I`` and ``lam_J = 0``; with ``g_e = e / B``,
    ``g_lam = C^T g_e`` and the adjoint ``mu`` (``F_II^T mu_I = (g_lam)_I``, ``mu_J = 0``: one
    batched solve)::

        dA = g_e^T x,  dB = g_e^T u,  dC = g_e^T lam,  dd = sum_t g_e,
        dq = -mu:  dD = dq^T x,  dE = dq^T u,  dc = sum_t dq,  dF = dq^T lam,

    and ``dG, dH`` from ``dF`` -- tensors in ``A, B, C, d, D, E, G, H, c`` order."""
    xp, x, u, lam, free, F, C, G, ge = saved
    n = F.shape[-1]
    with xp.threads():
        ge = ge * _factor(xp, grad)
        rows = free.reshape(-1, n)  # a stack's samples, model-major
        on = matrices(xp, F, rows.shape[0]).select(None)
        F_II = xp.free_block(on.rows(F.reshape(-1, n * n)), rows)
        rhs = xp.where(rows, (ge @ C).reshape(rows.shape), 0.0)
        mu, _ = on.solve(F_II.swapaxes(-1, -2), rhs, False)
        mu = mu.reshape(free.shape)
        return _tensors(xp, parameter_gradients(xp, need, x, u, lam, G, ge, -mu))


def degenerate_count(xp: ArrayOps, lam: Any, w: Any, q: Any, tol: float) -> int:
    """The number of samples with some ``lam_i = w_i = 0`` (strict complementarity fails):
    both below ``tol * (1 + |q|_inf)``, per sample, for ``lam``, ``w = F lam + q``, ``q``
    ``(B, n)``."""
    at = tol * (1.0 + xp.amax_abs(q))
    return xp.count(((abs(lam) <= at) & (abs(w) <= at)).any(1))
