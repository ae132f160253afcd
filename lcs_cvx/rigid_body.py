r"""A free rigid body on a ground plane as an LCS of its state: the time-stepping LCS of its
configuration, built at every state from learnable geometry, friction and inertia.

State (:data:`lcs_cvx.datasets.CUBE_COLUMNS`): ``x = (q, p, omega, v)``, a unit quaternion
``q = (w, x, y, z)`` (body to world), the position ``p`` of the body frame's origin (world),
the angular velocity ``omega`` (body frame) and the linear velocity ``v`` of the origin (world);
``nu = (omega, v)``. Optional input: a wrench ``u = (torque (body), force (world))``.

Contact point ``k`` is a sphere of radius ``rho >= 0`` (a rounded corner; ``rho = 0``: a point)
centred at ``r_k`` (body frame): its gap to the floor at height ``h`` is
``phi_k = e_z^T (p + R(q) r_k) - rho - h`` and the world velocity of its lowest point is
``J_k nu``, ``J_k = [-R [r_k - rho g]_x, I]`` (``3 x 6``; ``g = R^T e_z``, the up direction in the
body frame). The friction cone is a polyhedron of ``m``
directions ``d_j`` in the floor's plane. One step of length ``dt`` of Anitescu's
time-stepping (one ``lambda`` per cone edge, the impulse along ``n + mu d_j``):

$$
\begin{aligned}
M(q)\,(\nu' - \nu) &= \Delta t\, f(x) + \Delta t\, u + \tilde J(q)^\top \lambda, \\
0 \le \lambda_{kj} &\perp \phi_k / \Delta t + \tilde J_{kj}(q)\, \nu' + \kappa_k \lambda_{kj} \ge 0,
\qquad \tilde J_{kj} = (n + \mu d_j)^\top J_k,
\end{aligned}
$$

with ``M = diag(I_c, 0) + m J_c^T J_c`` (``J_c = [-R [c]_x, I]``, ``c`` the centre of mass in
the body frame), ``f`` gravity at the centre of mass, the gyroscopic torque ``-omega x I_c
omega`` and the centre of mass's centripetal term, all at ``x`` (explicit). Substituting
``nu'`` gives, at each state, the velocity rows of eq. (1) with per-sample matrices:

$$
\begin{aligned}
\nu' &= \nu_\text{free}(x, u) + C(x)\,\lambda, & w &= F(x)\,\lambda + q(x, u), \\
C &= M^{-1}\tilde J^\top, & F &= \tilde J M^{-1} \tilde J^\top + \operatorname{diag}(\kappa),
\quad q = \phi/\Delta t + \tilde J \nu_\text{free},
\end{aligned}
$$

``nu_free = nu + dt M^{-1} (f + u)``. ``F`` is symmetric positive definite (``kappa > 0``: the
contact compliance, the role of the paper's stiffness ``s``), so Assumption 1 holds at every
state and the LCP is a strongly convex QP, solved exactly by the package's pivoting. The
configuration is integrated exactly from ``nu'`` (:class:`lcs_cvx.Kinematics`:
``q' = q ⊗ exp(dt omega' / 2)``, ``p' = p + dt v'``). :meth:`RigidBodyContact.sample_lcs` gives
the per-sample matrices the losses consume (:mod:`lcs_cvx.per_sample`);
:meth:`RigidBodyContact.lcs_at` the plain :class:`lcs_cvx.LCS` of one state.
Learnable (:data:`LEARNABLE`), each constrained by its parameterisation (positive sizes, ``mu``,
compliance; a positive definite inertia); the mass is known: only impulse over mass is identifiable.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable
from typing import Any

import numpy as np
import torch
from torch import nn

from ._checks import LCSInputError, as_batch, check_number, check_positive
from .kinematics import UNIT_TOL, Kinematics, cross_matrix, rotation_matrix, unit_quaternions
from .losses import LossInfo
from .per_sample import SampleLCS, model_loss_info, solve_sample_lcp
from .rollout import rollout
from .state_lcs import lcs_of_state

__all__ = ["RigidBodyContact", "FORMULATIONS", "LEARNABLE", "box_vertices"]

#: The time-stepping formulations. Stewart--Trinkle's (C3's other) is not offered: its ``F`` is not
#: a P-matrix (C3 uses Lemke) and ``F + F^T`` is indefinite, so no ``gamma`` meets Lemma 2.
FORMULATIONS = ("anitescu",)
#: The physical quantities :class:`RigidBodyContact` can learn (its ``learn`` argument).
LEARNABLE = ("vertices", "radius", "mu", "inertia", "com", "ground", "compliance", "residual")
#: Quaternion rows, position rows, angular velocity rows, linear velocity rows of the state.
Q, P, W, V = slice(0, 4), slice(4, 7), slice(7, 10), slice(10, 13)
N_X = 13


def box_vertices(half_sizes: torch.Tensor) -> torch.Tensor:
    """The 8 corners ``(8, 3)`` of the box ``|r_i| <= half_sizes_i`` centred at the origin."""
    signs = torch.tensor([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)],
                         dtype=half_sizes.dtype, device=half_sizes.device)
    return signs * half_sizes


def _inv_softplus(y: float) -> float:
    return y + math.log(-math.expm1(-y))


class RigidBodyContact(nn.Module):
    r"""A free rigid body on a ground plane as the time-stepping LCS of its state (module
    docstring): eq. (1) with matrices built at each state from learnable geometry, friction and
    inertia.

    Args:
        vertices: the contact points ``(K, 3)`` in the body frame (learned freely; the centres of
            the rounded corners); or
        half_sizes: a box's half sizes ``(3,)`` (its 8 corners; learned as three positive
            numbers; the corners' centres at ``half_sizes - corner_radius``). Exactly one of the two.
        corner_radius: the initial radius ``rho`` of the rounded corners (m) ``>= 0``; 0 (the
            default): point contacts, the radius neither used nor learned; ``> 0``: learned
            (``log rho``) where ``learn`` names ``"radius"``.
        mass: the known mass (kg) ``> 0``.
        dt: the time step (s) ``> 0``; gravity: ``g`` (m/s², along ``-z``), ``>= 0``.
        mu: the initial friction coefficient ``>= 0``.
        inertia: the initial inertia about the centre of mass, a number (``I 1``), ``(3,)`` (a
            diagonal) or ``(3, 3)`` symmetric positive definite (kg m²); default that of a solid
            box of the half sizes (of the vertices' bounding box).
        com: the initial centre of mass in the body frame ``(3,)`` (default the origin).
        ground: the initial floor height (m).
        compliance: the initial contact compliance ``kappa`` (1/kg) ``> 0``; it is learned as
            ``kappa_min + softplus(.)`` with ``kappa_min = compliance / 2`` fixed, so
            ``sigma_min(F + F^T) >= compliance`` at every state (Lemma 2 then holds for every
            ``gamma < compliance``).
        friction_directions: the polyhedral cone's edges ``m >= 3`` (default 4).
        formulation: ``"anitescu"``.
        n_u: 0 (no input) or 6 (a wrench: body torque, world force).
        residual: add a learned affine map of ``(x, u)`` to ``nu_free`` (dair_pll's "+ residual":
            what the rigid-body model leaves out, as an impulse per step that contact then
            answers), started at 0; ``residual_map`` ``(6, 14 + n_u)`` acts on ``[x; u; 1]``.
        learn: the quantities learned (names of :data:`LEARNABLE`); the others are fixed.
        dtype: torch.float64 (recommended) or torch.float32.

    Example:
        >>> import torch, lcs_cvx
        >>> cube = lcs_cvx.RigidBodyContact(half_sizes=[0.05, 0.05, 0.05], mass=0.37, dt=0.01)
        >>> x = torch.tensor([[1.0, 0, 0, 0, 0, 0, 0.2, 0, 0, 0, 0, 0, 0]], dtype=torch.float64)
        >>> cube.step(x, torch.zeros(1, 0, dtype=torch.float64))[0, 12].item()  # falling freely
        -0.0981
    """

    def __init__(self, vertices: Any = None, *, half_sizes: Any = None, corner_radius: float = 0.0,
                 mass: float, dt: float,
                 gravity: float = 9.81, mu: float = 0.15, inertia: Any = None, com: Any = (0.0, 0.0, 0.0),
                 ground: float = 0.0, compliance: float = 0.02, friction_directions: int = 4,
                 formulation: str = "anitescu", n_u: int = 0, residual: bool = False,
                 learn: Iterable[str] = LEARNABLE, dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        if dtype not in (torch.float32, torch.float64):
            raise LCSInputError(f"dtype: expected torch.float32 or torch.float64, received {dtype}")
        if (vertices is None) == (half_sizes is None):
            raise LCSInputError("vertices, half_sizes: expected exactly one of them, received "
                                f"{'both' if vertices is not None else 'neither'}")
        if formulation not in FORMULATIONS:
            raise LCSInputError(f"formulation: expected one of {FORMULATIONS}, received {formulation!r}")
        learn = tuple(learn)
        unknown = [k for k in learn if k not in LEARNABLE]
        if unknown:
            raise LCSInputError(f"learn: expected names among {LEARNABLE}, received {unknown[0]!r}")
        self.mass = float(check_positive("mass", mass))
        self.dt = float(check_positive("dt", dt))
        self.gravity = check_number("gravity", gravity, 0.0)
        if isinstance(friction_directions, bool) or not isinstance(friction_directions, int) or friction_directions < 3:
            raise LCSInputError(f"friction_directions: expected an integer >= 3, received {friction_directions!r}")
        self.friction_directions = friction_directions
        self.formulation = formulation
        if n_u not in (0, 6):
            raise LCSInputError(f"n_u: expected 0 (no input) or 6 (a wrench), received {n_u!r}")
        self.n_x, self.n_u = N_X, int(n_u)
        mu, corner_radius = check_number("mu", mu, 0.0), check_number("corner_radius", corner_radius, 0.0)
        check_positive("compliance", compliance)
        kw = {"dtype": torch.float64}
        if half_sizes is not None:
            hs = torch.as_tensor(np.asarray(half_sizes, dtype=np.float64))
            if hs.shape != (3,) or not bool(torch.isfinite(hs).all()) or not bool((hs > corner_radius).all()):
                raise LCSInputError(f"half_sizes: expected 3 finite numbers > {corner_radius:g} (the corner radius), "
                                    f"received {np.asarray(half_sizes).tolist()!r}")
            self.box = True
            self.log_half_sizes = nn.Parameter(hs.log())
            extent = hs
        else:
            vs = torch.as_tensor(np.asarray(vertices, dtype=np.float64))
            if vs.dim() != 2 or vs.shape[1] != 3 or vs.shape[0] < 1 or not bool(torch.isfinite(vs).all()):
                raise LCSInputError(f"vertices: expected a finite (K, 3) array of contact points (K >= 1), "
                                    f"received shape {tuple(vs.shape)}")
            self.box = False
            extent = (vs.amax(0) - vs.amin(0)).clamp_min(1e-3) / 2
            self.vertex_positions = nn.Parameter(vs / float(extent.mean()))
        if inertia is None:
            a2 = (2 * extent) ** 2
            inertia = torch.stack([a2[1] + a2[2], a2[0] + a2[2], a2[0] + a2[1]]) * self.mass / 12
        I = torch.as_tensor(np.asarray(inertia, dtype=np.float64))
        I = I * torch.eye(3, **kw) if I.dim() == 0 else (torch.diag(I) if I.dim() == 1 else I)
        if I.shape != (3, 3) or not bool(torch.isfinite(I).all()) or not bool(torch.allclose(I, I.mT)) \
                or float(torch.linalg.eigvalsh(I).min()) <= 0:
            raise LCSInputError(f"inertia: expected a number > 0, (3,) positive numbers or a (3, 3) symmetric "
                                f"positive definite matrix, received {np.asarray(inertia).tolist()!r}")
        # every parameter in the body's own units, so that one learning rate suits them all: lengths
        # in l (the mean half extent), the inertia factor's off-diagonal in sqrt(mean I)
        ell = float(extent.mean())
        self.register_buffer("length_scale", torch.tensor(ell, **kw))
        self.register_buffer("inertia_scale", torch.tensor(float(I.diagonal().mean()) ** 0.5, **kw))
        Lc = torch.linalg.cholesky(I)
        self.inertia_factor = nn.Parameter(torch.tril(Lc, -1) / self.inertia_scale + torch.diag(Lc.diagonal().log()))
        c = torch.as_tensor(np.asarray(com, dtype=np.float64))
        if c.shape != (3,) or not bool(torch.isfinite(c).all()):
            raise LCSInputError(f"com: expected 3 finite numbers, received {np.asarray(com).tolist()!r}")
        ground = check_number("ground", ground)
        self.com_scaled = nn.Parameter(c / ell)
        self.ground_scaled = nn.Parameter(torch.tensor(float(ground) / ell, **kw))
        self.register_buffer("compliance_min", torch.tensor(compliance / 2, **kw))
        self.log_radius = nn.Parameter(torch.tensor(math.log(corner_radius), **kw)) if corner_radius > 0 else None
        self.mu_raw = nn.Parameter(torch.tensor(_inv_softplus(max(float(mu), 1e-12)), **kw))
        K = self.n_contacts
        self.compliance_raw = nn.Parameter(torch.full((K,), _inv_softplus(compliance / 2), **kw))
        theta = torch.arange(friction_directions, dtype=torch.float64) * (2 * math.pi / friction_directions)
        self.register_buffer("directions", torch.stack([theta.cos(), theta.sin(), torch.zeros_like(theta)], -1))
        # the fixed metric of the velocity residuals: m (l^2 |d omega|^2 + |d v|^2), l the start's
        # mean half extent (the speed of a point at l from the origin)
        self.register_buffer("residual_weight", torch.tensor([self.mass * ell**2] * 3 + [self.mass] * 3, **kw))
        self.kinematics = Kinematics(self.dt, positions={4: 10, 5: 11, 6: 12}, quaternions=[(0, 7)], frame="body")
        if not isinstance(residual, bool):
            raise LCSInputError(f"residual: expected True or False, received {residual!r}")
        self.residual_map = nn.Parameter(torch.zeros(6, N_X + self.n_u + 1, **kw)) if residual else None
        self._config = {"box": self.box, "n_contacts": self.n_contacts, "mass": self.mass, "dt": self.dt,
                        "gravity": self.gravity, "compliance": float(compliance),
                        "friction_directions": friction_directions, "formulation": formulation, "n_u": self.n_u,
                        "residual": residual, "learn": list(learn), "dtype": str(dtype).removeprefix("torch."),
                        "corner_radius": float(corner_radius)}
        self.to(dtype)
        names = {"vertices": "log_half_sizes" if self.box else "vertex_positions", "mu": "mu_raw",
                 "inertia": "inertia_factor", "com": "com_scaled", "ground": "ground_scaled", "compliance": "compliance_raw"}
        if residual:
            names["residual"] = "residual_map"
        if corner_radius > 0:
            names["radius"] = "log_radius"
        for quantity, pname in names.items():
            getattr(self, pname).requires_grad_(quantity in learn)
        self._quaternion_note = False

    # -- the physical quantities ---------------------------------------------------------------
    @property
    def n_contacts(self) -> int:
        return 8 if self.box else self.vertex_positions.shape[0]

    @property
    def n_lam(self) -> int:
        """``K m``: one ``lambda`` per contact point and cone edge."""
        return self.n_contacts * self.friction_directions

    @property
    def corner_radius(self) -> torch.Tensor:
        """The radius ``rho`` of the rounded corners (m; 0: point contacts)."""
        if self.log_radius is None:
            return torch.zeros((), dtype=self.dtype, device=self.device)
        return self.log_radius.exp()

    @property
    def vertices(self) -> torch.Tensor:
        """The contact points ``(K, 3)`` in the body frame (m): the rounded corners' centres."""
        if self.box:
            return box_vertices(self.log_half_sizes.exp() - self.corner_radius)
        return self.vertex_positions * self.length_scale

    @property
    def com(self) -> torch.Tensor:
        """The centre of mass ``(3,)`` in the body frame (m)."""
        return self.com_scaled * self.length_scale

    @property
    def ground(self) -> torch.Tensor:
        """The floor's height (m)."""
        return self.ground_scaled * self.length_scale

    @property
    def half_sizes(self) -> torch.Tensor:
        """Half the extent of the body along each body axis ``(3,)`` (m): a box's half sizes (the
        contact points' half extent plus the corners' radius)."""
        v = self.vertices
        return (v.amax(0) - v.amin(0)) / 2 + self.corner_radius

    @property
    def mu(self) -> torch.Tensor:
        """The friction coefficient ``mu >= 0``."""
        return nn.functional.softplus(self.mu_raw)

    @property
    def inertia(self) -> torch.Tensor:
        """The inertia about the centre of mass ``(3, 3)`` (kg m²), ``L L^T`` (positive definite)."""
        L = torch.tril(self.inertia_factor, -1) * self.inertia_scale + torch.diag(self.inertia_factor.diagonal().exp())
        return L @ L.mT

    @property
    def compliance(self) -> torch.Tensor:
        """The contact compliance ``kappa`` ``(K,)`` (1/kg), ``kappa_min + softplus(.)``."""
        return self.compliance_min + nn.functional.softplus(self.compliance_raw)

    @property
    def dtype(self) -> torch.dtype:
        return self.com_scaled.dtype

    @property
    def device(self) -> torch.device:
        return self.com_scaled.device

    def physical(self) -> dict[str, Any]:
        """The learned quantities in units, as plain numbers (half sizes in m, ``mu``, inertia
        in kg m², centre of mass in m, floor height in m, compliance in 1/kg)."""
        with torch.no_grad():
            return {"half_sizes": self.half_sizes.tolist(), "side": float(2 * self.half_sizes.mean()),
                    "vertices": self.vertices.tolist(), "corner_radius": float(self.corner_radius),
                    "mu": float(self.mu),
                    "inertia": self.inertia.tolist(), "com": self.com.tolist(), "ground": float(self.ground),
                    "compliance": self.compliance.tolist(), "mass": self.mass,
                    "residual": None if self.residual_map is None else self.residual_map.tolist()}

    def extra_repr(self) -> str:
        p = self.physical()
        hs = ", ".join(f"{1e3 * h:.1f}" for h in p["half_sizes"])
        I = np.diag(np.asarray(p["inertia"]))
        return (f"contacts={self.n_contacts}, half sizes=({hs}) mm, mu={p['mu']:.3g}, "
                f"inertia diag=({', '.join(f'{i:.3g}' for i in I)}) kg m², mass={self.mass:g} kg, "
                f"dt={self.dt:g} s, friction_directions={self.friction_directions}, formulation={self.formulation}")

    # -- files -------------------------------------------------------------------------------
    def config(self) -> dict[str, Any]:
        """The constructor's settings as a JSON-serialisable dict (:func:`lcs_cvx.save_model`);
        :meth:`from_config` and the stored parameters rebuild the model."""
        return dict(self._config)

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> RigidBodyContact:
        """A model of :meth:`config`'s settings (its parameters at a placeholder start, to be
        loaded with ``load_state_dict``)."""
        c = dict(config)
        big = max(1.0, 2 * c.get("corner_radius", 0.0))
        shape = {"half_sizes": [big] * 3} if c.pop("box") else {"vertices": np.ones((c["n_contacts"], 3))}
        c.pop("n_contacts")
        dtype = {"float32": torch.float32, "float64": torch.float64}[c.pop("dtype")]
        return cls(**shape, **c, dtype=dtype)

    # -- inputs ------------------------------------------------------------------------------
    def _xu(self, x: Any, u: Any) -> tuple[torch.Tensor, torch.Tensor]:
        kw = {"dtype": self.dtype, "device": self.device}
        x = self.check_states("x", as_batch("x", x, N_X, **kw))
        u = as_batch("u", u, self.n_u, batch=x.shape[0], **kw)
        return x, u

    def check_states(self, name: str, x: torch.Tensor) -> torch.Tensor:
        """``x`` ``(N, 13)`` with its quaternions (columns 0-3) normalised: within
        :data:`UNIT_TOL` of unit norm silently, within 1e-2 with a warning (once per model);
        farther is an :class:`lcs_cvx.LCSInputError` naming ``name``."""
        q, off = unit_quaternions(name, x[:, Q])
        if off > UNIT_TOL and not self._quaternion_note:
            warnings.warn(f"{name}: quaternions up to {off:.2e} from unit norm were normalised", stacklevel=3)
            self._quaternion_note = True
        return torch.cat([q, x[:, 4:]], dim=1)

    # -- the LCS of each state -----------------------------------------------------------------
    def dynamics(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(M (N, 6, 6), f (N, 6), J~ (N, K m, 6), phi (N, K))`` at the states ``x`` (module
        docstring): the mass matrix, the forces (no input), the cone edges' Jacobians (contact-major)
        and the gaps."""
        N = x.shape[0]
        kw = {"dtype": x.dtype, "device": x.device}
        R = rotation_matrix(x[:, Q])                                    # (N, 3, 3)
        p, omega = x[:, P], x[:, W]
        m, Ic, c = self.mass, self.inertia, self.com
        ez = torch.tensor([0.0, 0.0, 1.0], **kw)
        # M = diag(I_c, 0) + m J_c^T J_c, J_c = [-R [c]_x, I] (the centre of mass's velocity)
        Jc = torch.cat([-R @ cross_matrix(c), torch.eye(3, **kw).expand(N, 3, 3)], dim=2)
        M = m * Jc.mT @ Jc + torch.block_diag(Ic, torch.zeros(3, 3, **kw))
        # gravity at the centre of mass, less its centripetal acceleration R (omega x (omega x c)),
        # through J_c^T; the gyroscopic torque -omega x I_c omega
        cc = c.expand(N, 3)
        centripetal = (R @ torch.linalg.cross(omega, torch.linalg.cross(omega, cc))[..., None])[..., 0]
        f = (Jc.mT @ (-m * self.gravity * ez - m * centripetal)[..., None])[..., 0]
        f = f - torch.cat([torch.linalg.cross(omega, omega @ Ic.mT), torch.zeros_like(omega)], dim=1)
        # the cone edges' Jacobians J~_kj = (n + mu d_j)^T [-R [a_k]_x, I] = [(a_k x R^T e_j)^T, e_j^T],
        # a_k = r_k - rho g the lowest point of corner k (g = R^T e_z, row 2 of R)
        r, rho, g = self.vertices, self.corner_radius, R[:, 2, :]       # (K, 3), (), (N, 3)
        edges = ez + self.mu * self.directions                          # (m, 3), world
        K, n_dir = r.shape[0], edges.shape[0]
        body = edges @ R                                                # (N, m, 3): R^T e_j
        lever = r[None] - rho * g[:, None, :]                           # (N, K, 3)
        ang = torch.linalg.cross(lever[:, :, None, :].expand(N, K, n_dir, 3), body[:, None].expand(N, K, n_dir, 3))
        J = torch.cat([ang, edges.expand(N, K, n_dir, 3)], dim=-1).reshape(N, K * n_dir, 6)
        phi = p[:, 2:3] + g @ r.mT - rho - self.ground                  # (N, K): e_z^T (p + R r_k) - rho - h
        return M, f, J, phi

    def sample_lcs(self, x: torch.Tensor, u: torch.Tensor) -> SampleLCS:
        """The velocity rows of eq. (1) at every state ``x`` ``(N, 13)`` under ``u`` ``(N, n_u)``
        (module docstring): ``nu' = nu_free + C lam``, ``0 <= lam _|_ F lam + q >= 0``;
        differentiable in the parameters."""
        M, f, J, phi = self.dynamics(x)
        if self.n_u:
            f = f + u
        Minv = torch.linalg.inv(M)
        nu_free = x[:, 7:] + self.dt * (Minv @ f[..., None])[..., 0]
        if self.residual_map is not None:
            W = self.residual_map  # on [x; u; 1]
            nu_free = nu_free + x @ W[:, :N_X].mT + u @ W[:, N_X:-1].mT + W[:, -1]
        C = Minv @ J.mT                                                 # (N, 6, n)
        kappa = self.compliance.repeat_interleave(self.friction_directions)
        F = J @ C + torch.diag_embed(kappa.expand(x.shape[0], -1))
        q = phi.repeat_interleave(self.friction_directions, dim=1) / self.dt + (J @ nu_free[..., None])[..., 0]
        return SampleLCS(rows=tuple(range(7, 13)), r0=nu_free, C=C, F=F, q=q, weight=self.residual_weight,
                         sigma_min_bound=2.0 * float(self.compliance_min))

    def loss_info(self, kind: str, x: Any, u: Any, x_next: Any, *, gamma: float = 1e-2, eps: float = 1e-4,
                  solver: str = "fast", warm_start: torch.Tensor | None = None) -> LossInfo:
        """The violation loss (``kind="violation"``, eq. (9)) or the prediction loss (eq. (6))
        of the transitions ``(x, u, x_next)`` with each state's own LCS (:mod:`lcs_cvx.per_sample`);
        the data checked first (widths, quaternions). :func:`lcs_cvx.violation_loss` and
        :func:`lcs_cvx.prediction_loss` call this for a rigid body."""
        x, u, x_next = self.transitions(x, u, x_next)
        return model_loss_info(kind, self, x, u, x_next, gamma=gamma, eps=eps, solver=solver, warm_start=warm_start)

    def transitions(self, x: Any, u: Any, x_next: Any) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(x, u, x_next)`` checked (widths, quaternions) as tensors of the model's dtype."""
        x, u = self._xu(x, u)
        x_next = self.check_states("x_next", as_batch("x_next", x_next, N_X, batch=x.shape[0], dtype=self.dtype,
                                                      device=self.device))
        return x, u, x_next

    def solve_lcp(self, x: Any, u: Any) -> torch.Tensor:
        """The impulses ``lam`` ``(N, K m)`` of every state (the exact LCP of its LCS);
        differentiable in the parameters (Lemma 1 on the solution's free set)."""
        x, u = self._xu(x, u)
        return solve_sample_lcp(self.sample_lcs(x, u))

    def step(self, x: Any, u: Any) -> torch.Tensor:
        """``x'`` ``(N, 13)`` (``(13,)`` for one state): the velocities of eq. (1) at each state
        with ``lam`` from its exact LCP, the configuration integrated from them
        (:class:`lcs_cvx.Kinematics`)."""
        single = np.ndim(x) == 1
        x, u = self._xu(x, u)
        lcs = self.sample_lcs(x, u)
        nu = lcs.r0 + (lcs.C @ solve_sample_lcp(lcs)[..., None])[..., 0]
        out = self.kinematics.integrate(x, torch.cat([x[:, :7], nu], dim=1))
        return out[0] if single else out

    def forward(self, x: Any, u: Any) -> torch.Tensor:
        """Same as :meth:`step`."""
        return self.step(x, u)

    def rollout(self, x0: Any, us: Any) -> torch.Tensor:
        """Simulate from ``x0`` ``(N, 13)`` under ``us`` ``(N, T, n_u)`` (a single run: ``(13,)``
        and ``(T, n_u)``); returns ``(N, T + 1, 13)`` (:func:`lcs_cvx.rollout.rollout`)."""
        return rollout(self, x0, us)

    def lcs_at(self, x: Any, u: Any = None) -> Any:
        """The plain :class:`lcs_cvx.LCS` (13 states, ``n_u`` inputs, ``K m`` units) of the state
        ``x`` ``(13,)`` under ``u`` (default 0), detached: a model to simulate or control
        (``to_c3()``, :class:`lcs_cvx.control.C3`; :func:`lcs_cvx.state_lcs.lcs_of_state`)."""
        xa, ua = self._xu(x, torch.zeros(self.n_u, dtype=self.dtype) if u is None else u)
        if xa.shape[0] != 1:
            raise LCSInputError(f"x: expected one state (13,), received {xa.shape[0]} states")
        return lcs_of_state(self, xa, ua)
