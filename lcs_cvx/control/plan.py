"""A C3 plan and what its model says of it: :class:`Plan`; the model's own forces
``lam = LCP(F, D x + E u + c)`` (eq. (2)) on a solve's arrays (:func:`model_lcp`, and
:func:`lcp_at` for the fixed ``lam_0``); the plan per initial state whose model rollout costs
least (:func:`cheapest`); and the polish (:func:`polish_plan`): the inputs re-planned in the
contact modes the model visits under them (:mod:`lcs_cvx._kernels.polish`), kept where the
model's rollout costs less still.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from .._kernels import compiled
from .._kernels.c3 import violation
from .._kernels.lcp import PIVOT_TOL
from .._kernels.pivoting import STALL
from .._kernels.polish import polish
from ..lcp import solve_lcp_fast
from .qp import Bounds

__all__ = ["Plan", "cheapest", "lcp_at", "model_lcp", "polish_plan"]

#: pivoting sweeps of the model's LCPs before a sample is solved by a reference (with a warning):
#: :func:`lcs_cvx.solve_lcp_fast`'s
MAX_SWEEPS = 1000


@dataclasses.dataclass
class Plan:
    """A C3 plan from ``x0``. With one initial state ``(n_x,)`` the shapes are as listed; with a
    batch ``(B, n_x)`` every array gains a leading ``B``.

    Attributes:
        x: ``(N + 1, n_x)`` planned states (``x[0] = x0``; the planned ``u`` and ``lam`` rolled
            through the dynamics; a polished plan's are the model's own rollout).
        u: ``(N, n_u)`` planned inputs (``u[0]`` is the control to apply).
        lam: ``(N, n_lam)`` planned contact forces, from the last QP step (so slightly negative
            where the plan's complementarity is not met; ``delta`` holds the projected ones); a
            polished plan's are the model's own.
        delta: ``(N, n_z)`` the last projection (the warm start of the next solve).
        primal_residual: ``(K,)`` ``max_k |z_k - delta_k|`` after each ADMM iteration.
        dual_residual: ``(K,)`` ``max_k |delta_k - delta_k^{prev}|`` of each iteration.
        complementarity: the plan's violation ``max_k max_i |min(lam_i, D x_k + E u_k + F lam_k + c)_i|``.
        times: seconds spent in each phase: ``"qp"``, ``"projection"``, ``"lcp"`` (the fixed
            ``lam_0``), ``"model"`` (the plans' model rollouts), ``"polish"``, ``"total"`` (a
            CVXPY path's first solve includes its compilation). On the compiled path
            (:mod:`lcs_cvx.control.compiled_path`) the compiled call, every phase in one, is
            under ``"qp"`` and the others are 0 (``"total"`` as ever).
        qp_failures: QP steps that failed (``"cvxpy"`` path; counted over the whole batch) and fell
            back to C3's plan ``x_k = x0``, ``lam = u = 0`` (a :class:`lcs_cvx.FallbackWarning`
            says so).
        x_model: ``(N + 1, n_x)`` the model's own rollout under ``u``: ``lam_k`` the LCP
            solution at ``(x_k, u_k)``, not the plan's ``lam`` (what the model predicts the plan
            does).
        lam_model: ``(N, n_lam)`` the model's own forces along ``x_model``.
        gap: ``max_k |x_model_k - x_k|_inf``, the plan's disagreement with its model (a scalar;
            ``(B,)`` for a batch).
        cost: the horizon cost of ``x_model`` and ``u`` (the cost ``"auto"`` compares).
        projection: the projection whose plan this is (``"c3+"`` or ``"lcp"`` under ``"auto"``;
            a list for a batch).
        polished: whether the polish replaced the ADMM's plan (a bool tensor, ``(B,)`` for a
            batch): then ``x = x_model`` and the gap is 0.
    """

    x: torch.Tensor
    u: torch.Tensor
    lam: torch.Tensor
    delta: torch.Tensor
    primal_residual: torch.Tensor
    dual_residual: torch.Tensor
    complementarity: torch.Tensor
    times: dict[str, float]
    qp_failures: int = 0
    x_model: torch.Tensor | None = None
    lam_model: torch.Tensor | None = None
    gap: torch.Tensor | None = None
    cost: torch.Tensor | None = None
    projection: str | list[str] | None = None
    polished: torch.Tensor | None = None


def model_lcp(xp: Any, mats: dict[str, Any]) -> Callable[[int, Any], Any]:
    """``lcp(k, q) -> lam``: the exact LCP of step ``k``'s ``F`` on ``q (M, n_lam)``, on ``xp``'s
    arrays: the compiled pivoting kernel on float64 NumPy arrays themselves, else (and for
    samples it leaves unconverged, which it reports and solves by a reference)
    :func:`lcs_cvx.solve_lcp_fast`."""
    def lcp(k: int, q: Any) -> Any:
        if q.shape[-1] == 0:
            return q
        if xp.np and q.dtype == np.float64:
            lam, _, _, bad, _ = compiled.lcp(np.ascontiguousarray(mats["F"][k]), np.ascontiguousarray(q),
                                             PIVOT_TOL, MAX_SWEEPS, STALL, compiled.COLD)
            if not len(bad):
                return lam
        return xp.wrap(solve_lcp_fast(xp.unwrap(mats["F"][k]), xp.unwrap(xp.contiguous(q)), residual=False).lam)
    return lcp


def lcp_at(xp: Any, x0: Any, mats: dict[str, Any]) -> Any:
    """``lam_0 = LCP(F_0, D_0 x0 + c_0)`` ``(B, n_lam)`` (``E = 0``, or ``u = 0`` where
    ``fix_lam0`` is forced) on ``xp``'s arrays: zero where ``q >= 0``, else :func:`model_lcp`'s."""
    q = x0 @ mats["D"][0].T + mats["c"][0]
    if bool((q >= 0).all()):
        return q * 0.0
    return model_lcp(xp, mats)(0, q)


def cheapest(plans: list[dict[str, torch.Tensor]]) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Per initial state, the plan of ``plans`` (each a dict of ``(B, ...)`` tensors with a
    ``"cost"``) whose model rollout costs least: the first's unless another costs less by more
    than round-off (with bounds met, two plans may apply the same inputs: a tie, and the first,
    ``"lcp"``'s, is the one the model agrees with). Returns the picked dict and ``chosen (B,)``."""
    best = plans[0]["cost"]
    chosen = torch.zeros(best.shape[0], dtype=torch.long, device=best.device)
    for i in range(1, len(plans)):
        cheaper = plans[i]["cost"] < best - 1e-9 * (1.0 + best.abs())
        chosen = torch.where(cheaper, i, chosen)
        best = torch.where(cheaper, plans[i]["cost"], best)
    return {key: _pick([p[key] for p in plans], chosen) for key in plans[0]}, chosen


def _pick(values: list[torch.Tensor], chosen: torch.Tensor) -> torch.Tensor:
    """Per initial state (the leading axis), ``values[chosen[b]][b]``."""
    out = values[0]
    for i, v in enumerate(values[1:], start=1):
        out = torch.where(chosen.reshape(-1, *[1] * (v.dim() - 1)) == i, v, out)
    return out


def polish_plan(xp: Any, pick: dict[str, torch.Tensor], x0: Any, x_des: Any, u_ref: Any, mats: dict[str, Any],
                weights: dict[str, Any], lcp: Callable[[int, Any], Any], iterations: int, bounds: Bounds
                ) -> torch.Tensor:
    """Replace, in ``pick`` (the chosen plans, tensors), the plans that at most ``iterations``
    mode-fixed QPs (:func:`lcs_cvx._kernels.polish.polish`, within ``bounds.u``) make cheaper in
    the model's own rollout, keeping the model's rollout within ``bounds.x`` and ``bounds.lam``;
    ``(B,)`` bool, which ones."""
    B = pick["u"].shape[0]
    if not iterations:
        return torch.zeros(B, dtype=torch.bool, device=pick["u"].device)
    start = {k: xp.wrap(pick[key].contiguous()) for k, key in
             (("u", "u"), ("x", "x_model"), ("lam", "lam_model"), ("cost", "cost"))}
    accept = (lambda xs, lams: _within(bounds, xs, lams)) if bounds.x or bounds.lam else None
    out = polish(xp, x0, start, mats, lcp, weights, x_des, u_ref, bounds.u, iterations, accept)
    done = xp.unwrap(out["polished"])
    if bool(done.any()):
        new = {k: xp.unwrap(out[k]) for k in ("u", "x", "lam", "cost")}
        xs = [out["x"][:, k] for k in range(new["u"].shape[1] + 1)]
        new["complementarity"] = xp.unwrap(violation(xp, xs, out["u"], out["lam"], *(mats[k] for k in "DEFc")))[:, 0]
        new["x_model"], new["lam_model"] = new["x"], new["lam"]
        for key, value in new.items():
            pick[key] = torch.where(done.reshape(-1, *[1] * (value.dim() - 1)), value, pick[key])
    return done


def _within(bounds: Bounds, xs: list[Any], lams: list[Any]) -> Any:
    """``(B,)``: the model rollouts (NumPy) whose states ``x_1..x_N`` and forces meet
    ``bounds.x`` and ``bounds.lam`` (to 1e-9 of their size)."""
    ok = np.ones(xs[0].shape[0], dtype=bool)
    for values, box in ((xs[1:], bounds.x), (lams, bounds.lam)):
        if box is None:
            continue
        v = np.stack(values, 1)
        tol = 1e-9 * (1.0 + np.abs(v))
        ok &= ((v >= box[0] - tol) & (v <= box[1] + tol)).all(axis=(1, 2))
    return ok
