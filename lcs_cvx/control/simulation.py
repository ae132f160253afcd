"""Closed-loop simulation: a controller ``u = ctrl(x)`` applied to a plant ``x' = plant.step(x, u)``
(an :class:`lcs_cvx.LCS`, eq. (1), or anything with that ``step``), batched over initial states."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from .._checks import as_batch, check_positive

__all__ = ["ClosedLoop", "closed_loop"]


@dataclasses.dataclass
class ClosedLoop:
    """Closed-loop trajectories: ``x (B, T + 1, n_x)``, ``u (B, T, n_u)``; ``settled (B,)`` the
    first step from which ``|x - x_des|_inf <= tol`` held for ``hold`` steps (``-1`` if never);
    ``solve_times (T,)`` seconds per controller call."""

    x: torch.Tensor
    u: torch.Tensor
    settled: torch.Tensor
    solve_times: np.ndarray


@torch.no_grad()
def closed_loop(controller: Callable[[torch.Tensor], torch.Tensor], plant: Any, x0: Any, steps: int, *,
                tol: float = 0.1, hold: int = 30, x_des: Any = None, stop_when_settled: bool = False) -> ClosedLoop:
    """Run ``steps`` steps of ``x_{t+1} = plant.step(x_t, controller(x_t))`` from ``x0``
    ``(n_x,)`` or ``(B, n_x)``; the controller gets the whole batch at once. ``settled`` counts
    ``|x - x_des|_inf <= tol`` for ``hold`` consecutive steps (C3's end-to-end criterion)."""
    steps = check_positive("steps", steps, integer=True)
    x = as_batch("x0", x0, plant.n_x)
    target = torch.zeros(plant.n_x, dtype=x.dtype) if x_des is None else torch.as_tensor(np.asarray(x_des, dtype=np.float64))
    xs, us, times = [x], [], []
    run = torch.zeros(x.shape[0], dtype=torch.long)
    settled = torch.full((x.shape[0],), -1, dtype=torch.long)
    for t in range(steps):
        t0 = time.perf_counter()
        u = controller(x)
        times.append(time.perf_counter() - t0)
        u = as_batch("u", u, plant.n_u, batch=x.shape[0])
        x = plant.step(x, u)
        xs.append(x)
        us.append(u)
        near = (x - target).abs().amax(dim=1) <= tol
        run = torch.where(near, run + 1, torch.zeros_like(run))
        settled = torch.where((settled < 0) & (run >= hold), torch.full_like(settled, t + 2 - hold), settled)
        if stop_when_settled and bool((settled >= 0).all()):
            break
    return ClosedLoop(x=torch.stack(xs, 1), u=torch.stack(us, 1), settled=settled, solve_times=np.array(times))
