r"""Recorded transitions of a simulated plant: samples ``(x_t, u_t, x_{t+1})`` one control
period apart, with their trajectory structure and, for evaluation only, the true contact state.

Both physics studies record their data in this form: the cart-pole with walls
(:mod:`studies.physics.plant`, ``contact`` a bool per wall) and the pusher-slider
(:mod:`studies.physics.pusher_plant`, ``contact`` an integer contact mode per sample).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from lcs_cvx import Dataset, Trajectories

__all__ = ["Transitions"]


@dataclass(frozen=True)
class Transitions:
    """Samples ``(x, u, x')`` with their trajectory structure and the true contact state.

    Attributes:
        x, x_next: ``(N, n_x)``; u: ``(N, n_u)``; force: ``(N, k)`` mean contact forces over the
        period (N); contact: ``(N, k)`` bool (which contacts pushed during the period) or ``(N,)``
        int (a contact mode label, ``0`` = no contact); traj: ``(N,)`` trajectory index;
        step: ``(N,)`` index in it. Samples of one trajectory are consecutive.
    """

    x: np.ndarray
    u: np.ndarray
    x_next: np.ndarray
    force: np.ndarray
    contact: np.ndarray
    traj: np.ndarray
    step: np.ndarray

    @classmethod
    def from_lists(cls, columns: dict[str, list[Any]]) -> Transitions:
        """Stack per-sample lists (one list per field) into arrays; floating-point fields as
        float64."""
        out = {k: np.asarray(v) for k, v in columns.items()}
        for k, v in out.items():
            if np.issubdtype(v.dtype, np.floating):
                out[k] = v.astype(np.float64)
        return cls(**out)

    def __len__(self) -> int:
        return self.x.shape[0]

    @property
    def in_contact(self) -> np.ndarray:
        """``(N,)`` bool: some contact pushed during the sample's control period."""
        c = np.asarray(self.contact)
        return c != 0 if c.ndim == 1 else c.any(axis=1)

    def select(self, mask: np.ndarray) -> Transitions:
        """The samples where ``mask`` is true (select whole trajectories to keep windows intact)."""
        return type(self)(*(getattr(self, f.name)[mask] for f in dataclasses.fields(self)))

    def dataset(self) -> Dataset:
        """The transitions as an :class:`lcs_cvx.Dataset` (``lam`` = the contact forces)."""
        return Dataset.from_arrays(self.x, self.u, self.x_next, lam=self.force)

    def to_trajectories(self) -> Trajectories:
        """The samples as :class:`lcs_cvx.Trajectories`: per trajectory the states
        ``x_0, ..., x_T`` (its first ``x`` and every ``x_next``) and the inputs ``u_0 .. u_{T-1}``."""
        starts = np.flatnonzero(np.r_[True, self.traj[1:] != self.traj[:-1]])
        ends = np.r_[starts[1:], len(self)]
        return Trajectories([np.vstack([self.x[a : a + 1], self.x_next[a:b]]) for a, b in zip(starts, ends, strict=True)],
                            [self.u[a:b] for a, b in zip(starts, ends, strict=True)])

    def windows(self, horizon: int) -> np.ndarray:
        """Start indices ``i`` of every ``horizon``-step window inside one trajectory."""
        n = len(self)
        if horizon < 1 or n < horizon:
            return np.zeros(0, dtype=np.int64)
        i = np.arange(n - horizon + 1)
        same = self.traj[i + horizon - 1] == self.traj[i]
        return i[same]
