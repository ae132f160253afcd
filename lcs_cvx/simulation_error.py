r"""The simulation error of an LCS on recorded trajectories: the multi-step (output-error)
criterion that training can refine on, and the checks of a learned model's rollouts.

A window is ``H`` recorded steps ``x_s, u_s, ..., u_{s+H-1}, x_{s+H}`` of one trajectory. The
model rolls out from the recorded ``x_s`` under the recorded inputs,

$$
\hat x_{h+1} = A \hat x_h + B u_{s+h} + C \lambda(\hat x_h, u_{s+h}) + d,\quad \hat x_0 = x_s,
$$

with ``lambda`` the exact LCP solution (its gradient the implicit function's, Lemma 1, through
:meth:`lcs_cvx.LCS.step`), and the loss is the mean over windows, steps and coordinates of
``((x_hat_h - x_{s+h}) / sigma)^2``, ``sigma`` the spread of the one-step change of each
coordinate. One-step losses (eqs. (6), (9)) start every step from a measured, noisy state and
are biased when the states are noisy (errors in variables); the simulation error is not, and it
trains what a user of the model measures: rollouts.

- :class:`Windows`: every window of ``H`` steps of a :class:`~lcs_cvx.Trajectories`, sampled in
  batches.
- :func:`simulation_error`: the loss of a batch of windows, differentiable in the parameters;
  in normalised coordinates (:class:`lcs_cvx.scaling.Scaling`) when a scaling is given.
- :func:`affine_rollout_error`: :func:`lcs_cvx.rollout_error` of an affine map, the baseline.
- :func:`change_error`: the rollout error relative to the recorded change, each coordinate
  scaled by the spread of its one-step change: ``fit``'s held-out score on trajectories.
- :func:`rollout_growth`: how far the rollouts of a model over whole trajectories grow.
"""

from __future__ import annotations

from typing import Any

import torch

from ._checks import LCSInputError
from .metrics import AffineMap
from .scaling import Scaling
from .trajectories import Trajectories

__all__ = ["Windows", "simulation_error", "affine_rollout_error", "change_error", "rollout_growth"]


class Windows:
    """Every window of ``horizon`` steps of ``trajectories`` (starts ``s = 0 .. T_i - H`` of each
    trajectory ``i``), as row indices into the stacked states ``X (sum_i (T_i + 1), n_x)`` and
    inputs ``U (sum_i T_i, n_u)``.

    A trajectory shorter than ``horizon`` has no window (a ``UserWarning`` counts them and
    names the first); if none has one, an :class:`LCSInputError` names the horizon and the
    longest trajectory.
    """

    def __init__(self, trajectories: Trajectories, horizon: int) -> None:
        if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
            raise LCSInputError(f"rollout_horizon: expected an integer >= 1, received {horizon!r}")
        longest = max(trajectories.lengths)
        if horizon > longest:
            raise LCSInputError(
                f"rollout_horizon: expected at most {longest} steps (the longest trajectory's), "
                f"received {horizon}: no trajectory has a window of that length")
        short = [i for i, T in enumerate(trajectories.lengths) if T < horizon]
        if short:
            import warnings

            warnings.warn(f"rollout_horizon: {len(short)} of {len(trajectories)} trajectories are shorter than "
                          f"{horizon} steps (the first: index {short[0]}, {trajectories.lengths[short[0]]} steps) "
                          "and have no window", UserWarning, stacklevel=3)
        self.horizon = horizon
        self.X = torch.cat(trajectories.xs)
        self.U = torch.cat(trajectories.us)
        xr, ur, x0, u0 = [], [], 0, 0
        for T in trajectories.lengths:
            n = T - horizon + 1
            if n > 0:
                xr.append(torch.arange(x0, x0 + n))
                ur.append(torch.arange(u0, u0 + n))
            x0, u0 = x0 + T + 1, u0 + T
        self.x_rows, self.u_rows = torch.cat(xr), torch.cat(ur)

    def __len__(self) -> int:
        return int(self.x_rows.numel())

    def batch(self, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Windows ``idx``: start states ``(B, n_x)``, inputs ``(B, H, n_u)`` and the recorded
        states ``x_{s+1} .. x_{s+H}`` ``(B, H, n_x)``."""
        steps = torch.arange(self.horizon)
        xs = self.X[self.x_rows[idx, None] + steps + 1]
        return self.X[self.x_rows[idx]], self.U[self.u_rows[idx, None] + steps], xs


def simulation_error(model: Any, x0: torch.Tensor, us: torch.Tensor, xs: torch.Tensor,
                     scaling: Scaling | None = None, kinematics: Any = None,
                     sigma: torch.Tensor | None = None) -> torch.Tensor:
    """The mean of ``((x_hat_h - x_h) / sigma)^2`` over the windows ``(x0 (B, n_x), us (B, H,
    n_u), xs (B, H, n_x))``, ``x_hat`` the rollout of ``model``; differentiable in its parameters.

    With ``scaling``, ``model`` is in its normalised coordinates (it maps ``z, v`` to the scaled
    change ``y``): each step encodes ``x_hat``, steps, and decodes ``x' = K x + m_y + S_y y``;
    ``sigma = S_y``, and ``kinematics`` (the user's model's :class:`lcs_cvx.Kinematics`) then
    integrates the configuration. Without, ``model`` is in the data's units (its own kinematics
    in its step) and ``sigma`` is the given ``(n_x,)`` (default 1).
    """
    s = scaling._on(x0) if scaling is not None else None
    x, total = x0, x0.new_zeros(())
    for h in range(us.shape[1]):
        u = us[:, h]
        if s is None:
            x = model.step(x, u)
            err = x - xs[:, h] if sigma is None else (x - xs[:, h]) / sigma
        else:
            x_next = s.k * x + s.my + s.sy * model.step((x - s.mx) / s.sx, (u - s.mu) / s.su)
            x = x_next if kinematics is None else kinematics.integrate(x, x_next)
            err = (x - xs[:, h]) / s.sy
        total = total + err.pow(2).mean()
    return total / us.shape[1]


def _window_rollouts(step: Any, trajectories: Trajectories, horizon: int,
                     like: Any = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(predicted, recorded, start)`` states of every window of ``horizon`` steps, the first two
    stacked by step ``h = 1 .. H``: ``(H, W, n_x)`` each, the starts ``(W, n_x)``, on the device
    ``step`` returns; ``like``: a model whose dtype and device the windows are moved to first
    (None: as recorded)."""
    w = Windows(trajectories, horizon)
    x0, us, xs = w.batch(torch.arange(len(w)))
    if like is not None:
        x0, us = (t.to(dtype=like.dtype, device=like.device) for t in (x0, us))
    xh, pred = x0, []
    for h in range(horizon):
        xh = step(xh, us[:, h])
        pred.append(xh)
    pred_t = torch.stack(pred)
    kw = {"dtype": pred_t.dtype, "device": pred_t.device}
    return pred_t, xs.transpose(0, 1).to(**kw), x0.to(**kw)


def affine_rollout_error(affine: AffineMap, trajectories: Trajectories, horizon: int) -> float:
    """:func:`lcs_cvx.rollout_error` at ``horizon`` of the affine map ``x' = W [x; u; 1]``
    (:func:`lcs_cvx.metrics.affine_lstsq`): ``sum ||x_hat_{s+H} - x_{s+H}||^2 / sum
    ||x_{s+H}||^2`` over the windows."""
    with torch.no_grad():
        pred, rec, _ = _window_rollouts(affine.step, trajectories, horizon)
    return float((pred[-1] - rec[-1]).pow(2).sum() / rec[-1].pow(2).sum())


def change_error(model: Any, trajectories: Trajectories, horizon: int, scale: torch.Tensor) -> float:
    r"""The ``horizon``-step rollout error relative to the recorded change, each coordinate
    scaled by ``scale`` ``(n_x,)`` (the spread of its one-step change, as in the simulation-error
    loss):

    $$
    e_H = \frac{\sum_{\text{windows}} \|(\hat x_{s+H} - x_{s+H}) / \sigma\|^2}
               {\sum_{\text{windows}} \|(x_{s+H} - x_s) / \sigma\|^2},
    $$

    over every window of ``horizon`` steps of ``trajectories`` (:class:`Windows`), ``x_hat``
    the open-loop rollout from the recorded ``x_s`` under the recorded inputs. Predicting no
    motion scores 1, and every coordinate counts by its own motion: a held-out score that
    positions and velocities both move (the relative error of :func:`lcs_cvx.rollout_error` is
    dominated by the coordinates of largest magnitude). ``model``: an :class:`lcs_cvx.LCS` or an
    affine map (:class:`lcs_cvx.metrics.AffineMap`)."""
    with torch.no_grad():
        like = model if isinstance(model, torch.nn.Module) else None
        pred, rec, x0 = _window_rollouts(model.step, trajectories, horizon, like)
        sigma = scale.to(dtype=pred.dtype, device=pred.device)
        moved = ((rec[-1] - x0) / sigma).pow(2).sum()
        return float(((pred[-1] - rec[-1]) / sigma).pow(2).sum() / moved.clamp_min(torch.finfo(pred.dtype).tiny))


def rollout_growth(model: Any, trajectories: Trajectories) -> float:
    """The largest ``max_t ||x_hat_t|| / max_t ||x_t||`` over ``trajectories``, each rolled out
    open loop from its first state to its end (inf when a rollout leaves the finite numbers): a
    stable model stays near 1, a diverging one grows without bound. All trajectories are stepped
    together, the longest first (those still running at step ``t`` are a prefix). ``model``: an
    LCS, or anything with ``step(x, u)`` and ``dtype`` (the affine map,
    :class:`lcs_cvx.metrics.AffineMap`: then on the trajectories' device)."""
    kw = {"dtype": model.dtype, "device": getattr(model, "device", trajectories.xs[0].device)}
    order = sorted(range(len(trajectories)), key=lambda i: -trajectories.lengths[i])
    lengths = torch.tensor([trajectories.lengths[i] for i in order])
    top = torch.stack([trajectories.xs[i].norm(dim=-1).max() for i in order]).to(**kw)
    x = torch.stack([trajectories.xs[i][0] for i in order]).to(**kw)
    U = torch.zeros(len(order), int(lengths[0]), trajectories.n_u, **kw)  # inputs, padded
    for row, i in enumerate(order):
        U[row, : lengths[row]] = trajectories.us[i]
    reached = x.norm(dim=-1)
    with torch.no_grad():
        for t in range(int(lengths[0])):
            n = int((lengths > t).sum())
            x = model.step(x[:n], U[:n, t])
            if not bool(torch.isfinite(x).all()):
                return float("inf")
            reached[:n] = torch.maximum(reached[:n], x.norm(dim=-1))
    return float((reached / top.clamp_min(1e-300)).max())
