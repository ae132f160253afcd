r"""C3's polish (:mod:`lcs_cvx.control.c3`): the plan's inputs re-planned in the contact modes
the model itself visits under them, on the arrays of an :class:`~.arrays.ArrayOps` back-end.

The model's rollout of the inputs ``u`` (``lam_k = LCP(F_k, D_k x_k + E_k u_k + c_k)``, eq.
(1)) visits at each step the mode ``a_k = {i : lam_{k,i} > 0}``. In that mode the LCS is affine:
``lam_{k,a} = -F_{aa}^{-1} (D_a x_k + E_a u_k + c_a)``, the other units 0, so

$$
x_{k+1} = \tilde A_k x_k + \tilde B_k u_k + \tilde d_k, \qquad
[\tilde A_k\ \tilde B_k\ \tilde d_k] = [A_k\ B_k\ d_k] - C_{k,a} F_{k,aa}^{-1} [D_{k,a}\ E_{k,a}\ c_{k,a}],
$$

and the horizon cost is a quadratic in the stacked inputs ``U = (u_0, ..., u_{N-1})``
(``x_k = \bar x_k + \Gamma_k U``; ``H = \sum_k \Gamma_k^T Q_k \Gamma_k + \mathrm{blkdiag}(R_k)``)
whose minimiser, within the input bounds, is one small QP per initial state: a linear solve
without bounds, the exact active-set method of :mod:`.box_qp` with them (``P = H^{-1}``). The
model's rollout of the new inputs may visit other modes; the step repeats in those (at most
``iterations`` times, stopping when the modes repeat), and each initial state keeps the inputs
whose model rollout costs least (those it started from included), so polishing never raises the
cost of the plan applied.

Shapes: ``x0 (B, n_x)``, ``u, u_ref (B, N, n_u)``, ``x_des (B, N + 1, n_x)``; matrices stacked
over the steps, ``A (N, n_x, n_x)`` and so on.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from .box_qp import box_qp
from .c3 import model_rollout, plan_cost

__all__ = ["mode_dynamics", "polish", "stack"]


def mode_dynamics(xp: Any, mats: dict[str, Any], active: Any) -> tuple[Any, Any, Any, Any]:
    """``(A~, B~, d~, failed)`` of the module docstring for the modes ``active (B, N, n_lam)``
    (bool): ``(B, N, n_x, n_x)``, ``(B, N, n_x, n_u)``, ``(B, N, n_x)`` and ``(B,)``, the
    initial states with a singular ``F_aa`` at some step (their maps are not used)."""
    A, Bm, C, d, D, E, F, c = (mats[k] for k in "ABCdDEFc")
    Bt, N, nl = active.shape
    n_x = A.shape[-1]
    a = xp.to_float(active, A)
    eye = xp.eye(nl, A)
    # F on the active rows and columns, the identity on the others: its inverse is F_aa^{-1} there
    Fm = a[..., :, None] * a[..., None, :] * F + (1.0 - a)[..., :, None] * eye
    rhs = a[..., None] * xp.concat([D, E, c[..., None]])  # (B, N, n_lam, n_x + n_u + 1)
    sol, info = xp.via_torch(torch.linalg.solve_ex, Fm, rhs)
    K = C @ (a[..., None] * sol)  # (B, N, n_x, n_x + n_u + 1)
    failed = (info != 0).reshape(Bt, N).any(1)
    return A - K[..., :n_x], Bm - K[..., n_x:-1], d - K[..., -1], failed


def _condensed(xp: Any, x0: Any, At: Any, Bt: Any, dt: Any, x_des: Any, u_ref: Any, Q: Any, R: Any, QN: Any
               ) -> tuple[Any, Any]:
    """``(H (B, M, M), f (B, M))`` of the cost ``1/2 U^T H U + f^T U + const`` (``M = N n_u``)
    on the modes' affine dynamics ``At, Bt, dt`` (factor 2 dropped: ``H U = -f`` at the
    minimum)."""
    B, N, n_x, n_u = Bt.shape
    M = N * n_u
    H = xp.zeros((B, M, M), x0)
    f = xp.zeros((B, M), x0)
    xbar = x0  # the state with U = 0
    Gam = xp.zeros((B, n_x, M), x0)  # d x_k / d U
    for k in range(N + 1):
        Wk = Q[k] if k < N else QN
        if k > 0:
            GW = Gam.mT @ Wk
            H = H + GW @ Gam
            f = f + (GW @ (xbar - x_des[:, k])[..., None])[..., 0]
        if k == N:
            break
        s = slice(k * n_u, (k + 1) * n_u)
        H[:, s, s] = H[:, s, s] + R[k]
        f[:, s] = f[:, s] - u_ref[:, k] @ R[k]
        xbar = (At[:, k] @ xbar[..., None])[..., 0] + dt[:, k]
        Gam = At[:, k] @ Gam
        Gam[..., s] = Gam[..., s] + Bt[:, k]
    return H, f


def _minimise(xp: Any, H: Any, f: Any, lo: np.ndarray | None, hi: np.ndarray | None) -> tuple[Any, Any]:
    """The minimiser ``U (B, M)`` of ``1/2 U^T H U + f^T U`` within ``lo <= U <= hi`` (``(M,)``,
    NumPy back-end only; None: no bounds), and ``failed (B,)``."""
    U, failed = xp.solve(H, -f)  # H = Gamma^T Q Gamma + R: positive definite where R is
    if failed is None:
        failed = xp.zeros_bool(U.shape[0], U)
    if lo is None:
        return U, failed
    P_all = np.linalg.inv(np.where(failed[:, None, None], np.eye(H.shape[-1]), H))
    for b in range(U.shape[0]):
        if failed[b]:
            continue
        mu, status = box_qp(P_all[b], np.ascontiguousarray(U[b:b + 1]), lo, hi, 20 * lo.size + 100)
        if status[0] < 0:
            failed[b] = True
        else:
            U[b] = U[b] + P_all[b] @ mu[0]
    return U, failed


def polish(xp: Any, x0: Any, start: dict[str, Any], mats: dict[str, Any], lcp: Callable[[int, Any], Any],
           weights: dict[str, Any], x_des: Any, u_ref: Any, u_box: tuple[np.ndarray, np.ndarray] | None,
           iterations: int, accept: Callable[[list[Any], list[Any]], Any] | None = None) -> dict[str, Any]:
    """The polish of the module docstring from the plan ``start``: its inputs ``"u"``, the
    model's rollout of them ``"x"`` ``(B, N + 1, n_x)`` and ``"lam"`` ``(B, N, n_lam)``, and its
    ``"cost"`` ``(B,)``. ``u_box``: the bounds ``(lo, hi)`` of one step's ``u`` (NumPy
    back-end); ``accept(xs, lams) -> (B,) bool``: a polished plan also has to pass it (state and
    force bounds). Returns the cheapest plan per initial state in the same keys, and
    ``"polished"`` ``(B,)``: whether it is a polished one."""
    N = start["u"].shape[1]
    lo = hi = None
    if u_box is not None:
        lo, hi = np.tile(u_box[0], N), np.tile(u_box[1], N)
    Q, R, QN = weights["Q"], weights["R"], weights["QN"]
    best = dict(start)
    polished = xp.zeros_bool(x0.shape[0], x0)
    active = best["lam"] > 0
    for _ in range(iterations):
        At, Bt, dt, singular = mode_dynamics(xp, mats, active)
        H, f = _condensed(xp, x0, At, Bt, dt, x_des, u_ref, Q, R, QN)
        U, failed = _minimise(xp, H, f, lo, hi)
        U = U.reshape(start["u"].shape)
        lams: list[Any] = []
        xs = model_rollout(x0, U, mats, lcp, lams)
        c = plan_cost(xs, U - u_ref, x_des, Q, R, QN)
        ok = ~(singular | failed) & (c < best["cost"] - 1e-12 * (1.0 + abs(best["cost"])))
        if accept is not None:
            ok = ok & accept(xs, lams)
        lam = stack(xp, lams)
        keep = ok[:, None, None]
        best = {"u": xp.where(keep, U, best["u"]), "x": xp.where(keep, stack(xp, xs), best["x"]),
                "lam": xp.where(keep, lam, best["lam"]), "cost": xp.where(ok, c, best["cost"])}
        polished = polished | ok
        new = lam > 0
        if bool((new == active).all()):
            break
        active = new
    best["polished"] = polished
    return best


def stack(xp: Any, arrays: list[Any]) -> Any:
    """``N`` arrays ``(B, m)`` as one ``(B, N, m)``."""
    B, m = arrays[0].shape
    if not m:
        return xp.empty((B, len(arrays), 0), arrays[0])
    return xp.concat(arrays).reshape(B, len(arrays), m)
