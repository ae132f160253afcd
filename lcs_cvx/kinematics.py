r"""Known kinematics: the configuration integrated exactly from the velocities eq. (1) predicts.

A state ``x = (q, v)`` of configuration and velocity coordinates; the LCS of eq. (1) predicts
the velocities (and ``lam``), and the configuration follows from them, known, not learned:

$$
v' = A_v x + B_v u + C_v \lambda + d_v, \qquad q'_i = q_i + \Delta t\, v'_{j(i)},
$$

for positions and angles, and for a unit quaternion with a body angular velocity

$$
\mathbf q' = \mathbf q \otimes \exp(\Delta t\, \omega' / 2) \,/\, \|\cdot\|,
$$

``exp(dt w / 2) ⊗ q`` for an angular velocity in the world frame; quaternions are scalar
first ``(w, x, y, z)``, body to world. A body's *up* coordinates ``g = R(q)^T e_z`` (the world's
vertical in the body frame) follow its integrated quaternion: with them in the state, the height
``p_z + r · g`` of a point ``r`` of the body is linear in the state, so an LCS's gap ``D x + c``
can be a contact's. Attached to a model (:meth:`lcs_cvx.LCS.with_kinematics`), the model's
configuration rows of ``A, B, C, d`` are held at ``x'_q = x_q`` (:meth:`Kinematics.holds`) and
its :meth:`~lcs_cvx.LCS.step` integrates them (:meth:`Kinematics.integrate`), so every rollout,
score and the simulation-error loss see the exact integration; the one-step losses train the
velocity rows (:meth:`Kinematics.one_step`: the configuration rows' targets are the held rows'
own prediction, so they add nothing). Positions integrate linearly: such a model is itself an
LCS (:meth:`Kinematics.to_lcs`: ``row_q += dt row_v``); a quaternion block is linearised about a
given state there.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ._checks import LCSInputError

__all__ = ["Kinematics", "quaternion_product", "quaternion_exp", "up_in_body", "rotation_matrix", "cross_matrix",
           "unit_quaternions", "UNIT_TOL"]

#: How far from unit norm a data quaternion may be before it is an error, not round-off.
UNIT_TOL = 1e-6

FRAMES = ("body", "world")


def _index(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise LCSInputError(f"{name}: expected a state index (an integer >= 0), received {value!r}")
    return int(value)


@dataclass(frozen=True, init=False)
class Kinematics:
    """Which coordinates of the state are integrated, and how (module docstring).

    Args:
        dt: the integration step ``> 0`` (the data's effective period: check it, e.g. as the
            ratio of the finite difference of a position to its logged velocity).
        positions: ``{configuration index: velocity index}`` (or pairs): ``x'_i = x_i + dt x'_j``.
        quaternions: ``(q0, w0)`` pairs: the unit quaternion ``x[q0:q0 + 4]`` (scalar first)
            integrated with the angular velocity ``x'[w0:w0 + 3]``.
        frame: ``"body"`` (``q ⊗ exp(dt w / 2)``) or ``"world"`` (``exp(dt w / 2) ⊗ q``).
        up: ``(g0, q0)`` pairs: ``x[g0:g0 + 3] = R(q)^T e_z`` of the declared quaternion
            ``x[q0:q0 + 4]``, computed from it (a coordinate the complementarity rows can see).

    Example:
        >>> k = Kinematics(0.5, positions={0: 1})
        >>> x, x_next = torch.tensor([[1.0, 2.0]]), torch.tensor([[1.0, 3.0]])  # x_next: eq. (1)'s
        >>> k.integrate(x, x_next).tolist()  # x'_0 = x_0 + dt x'_1
        [[2.5, 3.0]]
    """

    dt: float
    positions: tuple[tuple[int, int], ...]
    quaternions: tuple[tuple[int, int], ...]
    frame: str
    up: tuple[tuple[int, int], ...]

    def __init__(self, dt: float, positions: Mapping[int, int] | Iterable[tuple[int, int]] = (),
                 quaternions: Iterable[tuple[int, int]] = (), frame: str = "body",
                 up: Iterable[tuple[int, int]] = ()) -> None:
        if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not math.isfinite(dt) or dt <= 0:
            raise LCSInputError(f"dt: expected a finite number > 0, received {dt!r}")
        pairs = list(positions.items()) if isinstance(positions, Mapping) else list(positions)
        pos = tuple((_index("positions", p[0]), _index("positions", p[1])) for p in pairs)
        quats = tuple((_index("quaternions", p[0]), _index("quaternions", p[1])) for p in quaternions)
        ups = tuple((_index("up", p[0]), _index("up", p[1])) for p in up)
        if any(q0 not in [q for q, _ in quats] for _, q0 in ups):
            raise LCSInputError(f"up: expected (g0, q0) pairs whose q0 starts a declared quaternion "
                                f"{[q for q, _ in quats]}, received {list(ups)}")
        if frame not in FRAMES:
            raise LCSInputError(f"frame: expected one of {FRAMES}, received {frame!r}")
        if not pos and not quats:
            raise LCSInputError("positions, quaternions: expected at least one coordinate to integrate, "
                                "received none")
        object.__setattr__(self, "dt", float(dt))
        object.__setattr__(self, "positions", pos)
        object.__setattr__(self, "quaternions", quats)
        object.__setattr__(self, "frame", frame)
        object.__setattr__(self, "up", ups)
        # the positions' index tensors, built once (integrate runs at every step of a rollout)
        object.__setattr__(self, "_q_index", torch.tensor([i for i, _ in pos], dtype=torch.long))
        object.__setattr__(self, "_v_index", torch.tensor([j for _, j in pos], dtype=torch.long))
        rows = self.rows
        if len(set(rows)) != len(rows):
            raise LCSInputError(f"positions, quaternions: expected each configuration index once, received "
                                f"{sorted(rows)}")
        both = sorted(set(rows) & set(self.velocities))
        if both:
            raise LCSInputError(f"positions, quaternions: expected velocity indices that are not configuration "
                                f"indices, received {both} as both")

    @property
    def rows(self) -> tuple[int, ...]:
        """The configuration indices (integrated, not learned), in declaration order."""
        return (tuple(i for i, _ in self.positions) + tuple(q + k for q, _ in self.quaternions for k in range(4))
                + tuple(g + k for g, _ in self.up for k in range(3)))

    @property
    def velocities(self) -> tuple[int, ...]:
        """The velocity indices the configuration is integrated from."""
        return tuple(j for _, j in self.positions) + tuple(w + k for _, w in self.quaternions for k in range(3))

    def check(self, n_x: int) -> Kinematics:
        """``self``, or :class:`LCSInputError` when an index is not below ``n_x``."""
        out = [i for i in self.rows + self.velocities if i >= n_x]
        if out:
            raise LCSInputError(f"kinematics: expected state indices below n_x = {n_x}, received {out[0]}")
        return self

    def to_dict(self) -> dict[str, Any]:
        """A JSON-serialisable dict; :meth:`from_dict` is its inverse (model files)."""
        return {"dt": self.dt, "positions": [list(p) for p in self.positions],
                "quaternions": [list(p) for p in self.quaternions], "frame": self.frame,
                "up": [list(p) for p in self.up]}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Kinematics:
        """The :class:`Kinematics` of :meth:`to_dict`'s dict."""
        if not isinstance(d, Mapping):
            raise LCSInputError(f"kinematics: expected a dict, received {type(d).__name__}")
        return cls(d.get("dt"), [tuple(p) for p in d.get("positions", [])],
                   [tuple(p) for p in d.get("quaternions", [])], d.get("frame", "body"),
                   [tuple(p) for p in d.get("up", [])])

    @classmethod
    def parse(cls, spec: str) -> Kinematics:
        """From ``"dt=0.01 positions=0:2,1:3 quaternions=3:10 frame=body up=13:3"`` (the CLI's
        ``--kinematics``): ``positions`` as ``configuration:velocity`` pairs, ``quaternions`` as
        ``q0:w0`` pairs, ``up`` as ``g0:q0`` pairs, comma separated; ``dt`` required."""
        fields: dict[str, str] = {}
        for part in str(spec).split():
            key, eq, value = part.partition("=")
            if not eq or key not in ("dt", "positions", "quaternions", "frame", "up") or key in fields:
                raise LCSInputError(f"kinematics: expected 'dt=... positions=i:j,... quaternions=q0:w0,... "
                                    f"frame=body|world up=g0:q0,...' (each key once), received {spec!r}")
            fields[key] = value

        def pairs(key: str) -> list[tuple[int, int]]:
            out = []
            for item in filter(None, fields.get(key, "").split(",")):
                a, colon, b = item.partition(":")
                if not colon or not a.strip().isdigit() or not b.strip().isdigit():
                    raise LCSInputError(f"kinematics: expected {key} as index:index pairs, received {item!r}")
                out.append((int(a), int(b)))
            return out

        try:
            dt = float(fields["dt"])
        except (KeyError, ValueError):
            raise LCSInputError(f"kinematics: expected dt=<step in seconds>, received {spec!r}") from None
        return cls(dt, pairs("positions"), pairs("quaternions"), fields.get("frame", "body"), pairs("up"))

    def __str__(self) -> str:
        out = f"dt={self.dt!r}"
        for key in ("positions", "quaternions", "up"):
            if getattr(self, key):
                out += f" {key}=" + ",".join(f"{a}:{b}" for a, b in getattr(self, key))
                out += f" frame={self.frame}" if key == "quaternions" else ""
        return out

    # -- the model's rows --------------------------------------------------------------------
    def holds(self, n_x: int, n_u: int, n_lam: int) -> dict[str, torch.Tensor]:
        """``{name: values}`` for :meth:`lcs_cvx.LCS.hold`: the configuration rows of ``A``
        ``(n_x, n_x)``, ``B``, ``C``, ``d`` held at ``x'_q = x_q`` (NaN elsewhere: learned)."""
        nan = float("nan")
        out = {"A": torch.full((n_x, n_x), nan, dtype=torch.float64), "B": torch.full((n_x, n_u), nan, dtype=torch.float64),
               "C": torch.full((n_x, n_lam), nan, dtype=torch.float64), "d": torch.full((n_x,), nan, dtype=torch.float64)}
        rows = list(self.check(n_x).rows)
        for t in out.values():
            t[rows] = 0.0
        out["A"][rows, rows] = 1.0
        return out

    def one_step(self, data: Any) -> Any:
        """``data`` (an :class:`lcs_cvx.Dataset`) with the configuration rows of ``x'`` replaced
        by ``x``'s: the held rows' prediction, so that a one-step loss trains the velocity rows
        alone."""
        rows = torch.tensor(self.check(data.n_x).rows, device=data.x.device)
        x_next = data.x_next.index_copy(1, rows, data.x.index_select(1, rows))
        return type(data)(data.x, data.u, x_next, data.lam)

    # -- the integration ---------------------------------------------------------------------
    def integrate(self, x: torch.Tensor, x_next: torch.Tensor) -> torch.Tensor:
        """``x_next`` ``(N, n_x)`` (eq. (1)'s step from ``x`` ``(N, n_x)``) with its configuration
        rows integrated from its velocities (module docstring); differentiable in both."""
        last = x_next.dim() - 1
        out = x_next
        if self.positions:
            qi, vi = self._q_index.to(x.device), self._v_index.to(x.device)
            out = out.index_copy(last, qi, x.index_select(last, qi) + self.dt * x_next.index_select(last, vi))
        for q0, w0 in self.quaternions:
            new = _step(x[..., q0:q0 + 4], x_next[..., w0:w0 + 3], self.dt, self.frame)
            out = out.index_copy(last, torch.arange(q0, q0 + 4, device=x.device), new)
        for g0, q0 in self.up:
            out = out.index_copy(last, torch.arange(g0, g0 + 3, device=x.device), up_in_body(out[..., q0:q0 + 4]))
        return out

    # -- the model as one LCS ----------------------------------------------------------------
    def to_lcs(self, model: Any, about: Any = None, u: Any = None) -> Any:
        """A plain :class:`lcs_cvx.LCS` (no kinematics, no masks) whose step is ``model``'s:
        exact for positions (``row_q += dt row_v`` of ``A, B, C, d``); a quaternion block
        linearised about the state ``about`` ``(n_x,)`` and input ``u`` (default 0):
        ``q' ~ f(q_a, w_a) + J_q (q - q_a) + J_w (w' - w_a)``, ``w'`` the model's angular velocity
        rows and ``w_a`` their value at ``(about, u)``: exact there, second order around it."""
        if self.quaternions and about is None:
            raise LCSInputError("about: expected a state (n_x,) to linearise the quaternion integration about, "
                                "received None (only positions integrate linearly)")
        out = copy.deepcopy(model)
        out._kinematics = None
        out.replace_masks({})
        with torch.no_grad():
            rows = {k: getattr(model, k).detach().clone() for k in ("A", "B", "C", "d")}
            new = {k: v.clone() for k, v in rows.items()}
            for i, j in self.positions:
                for k in new:
                    new[k][i] = rows[k][i] + self.dt * rows[k][j]
            if self.quaternions:
                xa = torch.as_tensor(about, dtype=torch.float64).reshape(-1)
                if xa.numel() != model.n_x or not bool(torch.isfinite(xa).all()):
                    raise LCSInputError(f"about: expected a finite state of shape ({model.n_x},), received "
                                        f"{tuple(torch.as_tensor(about).shape)}")
                xa = xa.to(rows["A"])
                # the model's step there: its velocity rows are eq. (1)'s (only configuration rows are integrated)
                x_next = model.step(xa, torch.zeros(model.n_u, dtype=model.dtype, device=model.device) if u is None else u)
                for q0, w0 in self.quaternions:
                    self._linearise(rows, new, xa, x_next, q0, w0)
            for k, v in new.items():
                getattr(out, k).copy_(v)
        return out

    def _linearise(self, rows: dict, new: dict, xa: torch.Tensor, raw: torch.Tensor, q0: int, w0: int) -> None:
        """The quaternion ``x[q0:q0+4]``'s rows, and those of its up coordinates, linearised."""
        qs, ws = slice(q0, q0 + 4), slice(w0, w0 + 3)
        out = torch.tensor([q0 + k for k in range(4)] + [g + k for g, q in self.up if q == q0 for k in range(3)])

        def f(q: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
            turned = _step(q, w, self.dt, self.frame)
            return torch.cat([turned] + [up_in_body(turned) for _, q in self.up if q == q0])

        qa, wa = xa[qs], raw[ws]
        Jq, Jw = torch.autograd.functional.jacobian(f, (qa, wa))
        fa = f(qa, wa)
        for k in ("A", "B", "C"):
            new[k][out] = Jq @ rows[k][qs] + Jw @ rows[k][ws]
        new["d"][out] = fa - Jq @ qa - Jw @ wa + Jq @ rows["d"][qs] + Jw @ rows["d"][ws]


def attach(model: Any, kinematics: Any) -> Any:
    """:meth:`lcs_cvx.LCS.with_kinematics`: hold ``model``'s configuration rows
    (:meth:`Kinematics.holds`; entries held before stay held at their values) and attach."""
    if not isinstance(kinematics, Kinematics):
        raise LCSInputError(f"kinematics: expected an lcs_cvx.Kinematics, received {type(kinematics).__name__}")
    model.hold(**kinematics.holds(model.n_x, model.n_u, model.n_lam))
    model._kinematics = kinematics
    return model


def _step(q: torch.Tensor, w: torch.Tensor, dt: float, frame: str) -> torch.Tensor:
    """The unit quaternion ``q`` ``(..., 4)`` turned by ``dt w`` ``(..., 3)``, renormalised."""
    delta = quaternion_exp(dt * w)
    new = quaternion_product(q, delta) if frame == "body" else quaternion_product(delta, q)
    return new / new.norm(dim=-1, keepdim=True)


def up_in_body(q: torch.Tensor) -> torch.Tensor:
    """``R(q)^T e_z`` ``(..., 3)``: the world's vertical in the body frame of the unit quaternion
    ``q`` ``(..., 4)`` (scalar first, body to world)."""
    w, x, y, z = q.unbind(-1)
    return torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=-1)


def quaternion_product(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a ⊗ b`` of quaternions ``(..., 4)``, scalar first."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], dim=-1)


def quaternion_exp(phi: torch.Tensor) -> torch.Tensor:
    """``exp(phi / 2)`` ``(..., 4)``: the unit quaternion of the rotation vector ``phi``
    ``(..., 3)`` (angle ``|phi|``), ``(cos(|phi|/2), sin(|phi|/2) phi / |phi|)``; smooth at 0."""
    t2 = phi.pow(2).sum(-1, keepdim=True)
    small = t2 < 1e-10
    t = torch.where(small, torch.ones_like(t2), t2).sqrt()
    w = torch.where(small, 1.0 - t2 / 8.0, torch.cos(0.5 * t))
    s = torch.where(small, 0.5 - t2 / 48.0, torch.sin(0.5 * t) / t)
    return torch.cat([w, s * phi], dim=-1)


def unit_quaternions(name: str, q: torch.Tensor) -> tuple[torch.Tensor, float]:
    """``(q / |q|, off)`` for quaternions ``q`` ``(N, 4)``, ``off`` the largest distance of a norm
    from 1; past 1e-2 (or not finite) an :class:`LCSInputError` naming ``name``: recorded data, not
    round-off."""
    norm = q.norm(dim=-1)
    off = float((norm.detach() - 1).abs().max()) if len(norm) else 0.0
    if off > 1e-2 or not math.isfinite(off):
        raise LCSInputError(f"{name}: expected unit quaternions (w, x, y, z), received "
                            f"norms off by up to {off:.3g}")
    return q / norm[:, None], off


def rotation_matrix(q: torch.Tensor) -> torch.Tensor:
    """``R(q)`` ``(..., 3, 3)`` of unit quaternions ``q`` ``(..., 4)`` (scalar first, body to world)."""
    w, x, y, z = q.unbind(-1)
    rows = [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]
    return torch.stack(rows, dim=-1).reshape(q.shape[:-1] + (3, 3))


def cross_matrix(r: torch.Tensor) -> torch.Tensor:
    """``[r]_x`` ``(..., 3, 3)`` of ``r`` ``(..., 3)``: ``[r]_x a = r x a``."""
    zero = torch.zeros_like(r[..., 0])
    x, y, z = r.unbind(-1)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(r.shape[:-1] + (3, 3))
