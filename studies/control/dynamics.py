"""The learned dynamics the MuJoCo control studies give their sampling controller (MPPI,
:class:`studies.control.harness.MPPI`): a residual tanh MLP of the state increment, fitted by
Adam on normalised increments with 10 % of the transitions held out."""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = ["MLPDynamics", "fit_mlp_dynamics"]


class MLPDynamics(torch.nn.Module):
    """``x' = x + s_y f((x - m_x) / s_x, u / s_u) + m_y`` with ``f`` a tanh MLP (float32); the
    sizes ``n_x``, ``n_u`` are those of ``stats`` (``mx``, ``su``)."""

    def __init__(self, stats: dict[str, np.ndarray], hidden: int = 64) -> None:
        super().__init__()
        n_x, n_u = len(stats["mx"]), len(stats["su"])
        self.net = torch.nn.Sequential(torch.nn.Linear(n_x + n_u, hidden), torch.nn.Tanh(),
                                       torch.nn.Linear(hidden, hidden), torch.nn.Tanh(), torch.nn.Linear(hidden, n_x))
        for k, v in stats.items():
            self.register_buffer(k, torch.as_tensor(np.asarray(v), dtype=torch.float32))

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        z = torch.cat([(x - self.mx) / self.sx, u / self.su], -1)
        return x + self.net(z) * self.sy + self.my


def fit_mlp_dynamics(x: np.ndarray, u: np.ndarray, x_next: np.ndarray, *, iterations: int = 4000,
                     batch: int = 256, lr: float = 3e-3, seed: int = 0) -> tuple[MLPDynamics, float]:
    """Adam on the mean squared error of the normalised state increment, 10 % held out; returns
    the model (the iterate with the lowest held-out error, checked every 200 iterations) and
    that error."""
    torch.manual_seed(seed)
    dx = x_next - x
    stats = {"mx": x.mean(0), "sx": x.std(0) + 1e-9, "su": u.std(0) + 1e-9, "my": dx.mean(0), "sy": dx.std(0) + 1e-9}
    model = MLPDynamics(stats)
    X, U_, Y = (torch.as_tensor(a, dtype=torch.float32) for a in (x, u, x_next))
    n_val = max(1, len(X) // 10)
    perm = torch.randperm(len(X))
    val, tr = perm[:n_val], perm[n_val:]
    sy = model.sy
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    best, best_state = math.inf, None
    for it in range(iterations):
        for gr in opt.param_groups:
            gr["lr"] = lr * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * it / iterations)))
        idx = tr[torch.randint(0, len(tr), (batch,))]
        loss = (((model(X[idx], U_[idx]) - Y[idx]) / sy) ** 2).sum(-1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if (it + 1) % 200 == 0 or it + 1 == iterations:
            with torch.no_grad():
                h = float((((model(X[val], U_[val]) - Y[val]) / sy) ** 2).sum(-1).mean())
            if h < best:
                best, best_state = h, {k: v.clone() for k, v in model.state_dict().items()}
    if best_state is not None:
        model.load_state_dict(best_state)
    return model, best
