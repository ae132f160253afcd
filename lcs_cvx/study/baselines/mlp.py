r"""The MLP baseline: a smooth regressor of the transition, tuned on held-out data.

On the normalised coordinates of :class:`lcs_cvx.scaling.Scaling` (``z``, ``v`` at the paper's
spread, the increment ``y = S_y^{-1} (x' - x - m_y)`` at unit scale)

    x' = x + m_y + S_y f(z, v),     f = a tanh MLP (hidden layer sizes ``h``),

trained with Adam on the mean squared error of ``y`` (minibatches, cosine learning rate from
``lr`` to ``lr / 100``). A fraction ``val_fraction`` of the training samples (a seeded random
subset) is held out: every ``(h, lr)`` of the grid ``hidden x lr`` is trained on the rest, its
best iterate on the held-out samples (checked every ``eval_every`` iterations) is kept, and the
grid point with the lowest held-out error is the model. The whole grid counts as training time.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from threadpoolctl import threadpool_limits

from ...data import Dataset
from ...scaling import Scaling

__all__ = ["MLPModel", "fit"]


class MLPModel:
    """``x' = x + m_y + S_y f(z, v)`` (module docstring); ``net`` maps ``(N, n_x + n_u)`` to
    ``(N, n_x)``."""

    dtype = torch.float64

    def __init__(self, net: torch.nn.Module, scaling: Scaling) -> None:
        self.net, self.scaling = net, scaling

    def step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Next states ``(N, n_x)`` of states ``x`` ``(N, n_x)`` and inputs ``u`` ``(N, n_u)``."""
        x, u = x.to(self.dtype), u.to(self.dtype)
        d = self.scaling.encode(Dataset(x, u, x))
        s = self.scaling
        with torch.no_grad():
            return s.k * x + s.my + s.sy * self.net(torch.cat([d.x, d.u], dim=1))


def _net(n_in: int, n_out: int, hidden: list[int], gen: torch.Generator) -> torch.nn.Module:
    layers: list[torch.nn.Module] = []
    for h in hidden:
        layers += [torch.nn.Linear(n_in, h, dtype=torch.float64), torch.nn.Tanh()]
        n_in = h
    layers.append(torch.nn.Linear(n_in, n_out, dtype=torch.float64))
    net = torch.nn.Sequential(*layers)
    with torch.no_grad():  # PyTorch's default initialisation, from this generator
        for layer in net:
            if isinstance(layer, torch.nn.Linear):
                bound = 1.0 / math.sqrt(layer.in_features)
                layer.weight.uniform_(-bound, bound, generator=gen)
                layer.bias.uniform_(-bound, bound, generator=gen)
    return net


def _train(X: torch.Tensor, Y: torch.Tensor, Xv: torch.Tensor, Yv: torch.Tensor,
           hidden: list[int], lr: float, opts: dict[str, Any], seed: int
           ) -> tuple[torch.nn.Module, float]:
    """One grid point: the net's best iterate on the held-out data and its mean squared error."""
    gen = torch.Generator().manual_seed(seed)
    net = _net(X.shape[1], Y.shape[1], hidden, gen)
    adam = torch.optim.Adam(net.parameters(), lr=lr, weight_decay=opts["weight_decay"])
    iters, batch = opts["iterations"], min(opts["batch_size"], X.shape[0])
    best, state = math.inf, None
    for it in range(iters):
        for g in adam.param_groups:
            g["lr"] = lr * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * it / iters)))
        idx = torch.randint(0, X.shape[0], (batch,), generator=gen)
        loss = ((net(X[idx]) - Y[idx]) ** 2).sum(-1).mean()
        adam.zero_grad()
        loss.backward()
        adam.step()
        if (it + 1) % opts["eval_every"] == 0 or it + 1 == iters:
            with torch.no_grad():
                err = float(((net(Xv) - Yv) ** 2).sum(-1).mean())
            if err < best:
                best, state = err, {k: v.clone() for k, v in net.state_dict().items()}
    if state is not None:  # None only if every held-out error was NaN
        net.load_state_dict(state)
    return net, best


def fit(train: Dataset, options: dict[str, Any], *, seed: int, modes: int
        ) -> tuple[MLPModel, dict[str, Any]]:
    """The grid of the module docstring on ``train``; ``options``: ``hidden`` (list of layer-size
    lists), ``lr`` (list), ``iterations``, ``batch_size``, ``weight_decay``, ``val_fraction``,
    ``eval_every``. ``modes`` is unused.

    Returns the chosen model and ``{"hidden", "lr", "val_mse", "grid": [{hidden, lr,
    val_mse}, ...]}`` (held-out mean squared error of the normalised increment).
    """
    with threadpool_limits(1):
        scaling = Scaling.fit(train)
        d = scaling.encode(Dataset(*(t.detach().to(torch.float64)
                                     for t in (train.x, train.u, train.x_next))))
        X, Y = torch.cat([d.x, d.u], dim=1), d.x_next
        perm = torch.randperm(X.shape[0], generator=torch.Generator().manual_seed(seed))
        n_val = max(1, round(options["val_fraction"] * X.shape[0]))
        val, fit_idx = perm[:n_val], perm[n_val:]
        grid, best = [], None
        for k, hidden in enumerate(options["hidden"]):
            for j, lr in enumerate(options["lr"]):
                net, err = _train(X[fit_idx], Y[fit_idx], X[val], Y[val], list(hidden), float(lr),
                                  options, seed + 1000 * k + j)
                grid.append({"hidden": list(hidden), "lr": float(lr), "val_mse": err})
                if best is None or err < best[1]:
                    best = (net, err, grid[-1])
    assert best is not None  # the grid is non-empty (baseline_options)
    net, _, chosen = best
    return MLPModel(net, scaling), {**chosen, "grid": grid}
