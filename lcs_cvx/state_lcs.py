"""The plain LCS of one state of a rigid body (:meth:`lcs_cvx.RigidBodyContact.lcs_at`): the
time-stepping LCS of that configuration (eq. (1) with the rigid body's matrices at ``x``, ``f`` held
at its value there) as an :class:`lcs_cvx.LCS` with constant matrices, its configuration rows
``p' = p + dt v'`` exact and ``q'`` linearised about ``x`` (:meth:`lcs_cvx.Kinematics.to_lcs`): a
model to simulate or control (``to_c3()``, :class:`lcs_cvx.control.C3`)."""

from __future__ import annotations

from typing import Any

import torch

from .system import LCS

__all__ = ["lcs_of_state"]

N_X = 13


def lcs_of_state(body: Any, xa: torch.Tensor, ua: torch.Tensor) -> LCS:
    """The plain :class:`lcs_cvx.LCS` of ``body`` (a :class:`lcs_cvx.RigidBodyContact`) at the
    checked state ``xa`` ``(1, 13)`` under the input ``ua`` ``(1, n_u)``, detached."""
    with torch.no_grad():
        # the velocity rows of sample_lcs at x, split as nu_free = A_v x + B_v u + d_v (f held at x)
        lcs = body.sample_lcs(xa, ua)
        M, _, J, _ = (t[0].double() for t in body.dynamics(xa))
        A = torch.zeros(N_X, N_X, dtype=torch.float64)
        A[7:, 7:] = torch.eye(6, dtype=torch.float64)
        B = torch.zeros(N_X, body.n_u, dtype=torch.float64)
        B[7:] = (body.dt * torch.linalg.inv(M))[:, : body.n_u]
        if body.residual_map is not None:
            W = body.residual_map.double()
            A[7:] += W[:, :N_X]
            B[7:] += W[:, N_X:N_X + body.n_u]
        x0, u0 = xa[0].double(), ua[0].double()
        d = torch.zeros(N_X, dtype=torch.float64)
        d[7:] = lcs.r0[0].double() - A[7:] @ x0 - B[7:] @ u0
        C = torch.zeros(N_X, body.n_lam, dtype=torch.float64)
        C[7:] = lcs.C[0].double()
        # w = F lam + q with q = phi / dt + J nu_free = (J A_v) x + (J B_v) u + c
        D, E = J @ A[7:], J @ B[7:]
        c = lcs.q[0].double() - D @ x0 - E @ u0
        plain = LCS.from_matrices(A=A, B=B, C=C, d=d, D=D, E=E, F=lcs.F[0].double(), c=c, dtype=body.dtype)
        plain.with_kinematics(body.kinematics)
        return body.kinematics.to_lcs(plain, about=xa[0], u=ua[0])
