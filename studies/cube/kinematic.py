r"""The cube study's LCSs with known kinematics (:class:`lcs_cvx.Kinematics`): the configuration
integrated exactly from the velocities the LCS predicts, gravity held in ``d``.

State ``x = (q, p, w, v)`` (13): unit quaternion (scalar first, body to world), position, body
angular velocity, linear velocity; the recorded tosses follow ``p' = p + dt v'`` and
``q' = q ⊗ exp(dt w' / 2)`` (body frame), with ``dt = 1/148 s``.

- :func:`kinematic_lcs`: ``p`` and ``q`` integrated, ``v_z' = ... - g dt`` held (``d``), the
  rest of the velocity rows and the complementarity rows learned;
- :func:`contact_lcs`: the same on the state with the body's up coordinates appended,
  ``g = R(q)^T e_z`` (16; :func:`augment`), in which the height of each of the cube's 8 corners
  ``r_c`` is linear, ``p_z + r_c · g``; free flight held as well, ``v' = v - g dt e_z`` and
  ``w' = w`` (a cube's inertia is isotropic: no torque, no change of the body angular velocity)
  plus ``C lam``, so that only the contacts change the velocities; the first 8 units start at
  the corner heights (``D``, ``c``: the complementarity of a corner's force with its height),
  further units at random.

The steppers keep the study's 13-state: the contact model appends ``g`` before a step and drops it
after (:func:`stepper`).
"""

from __future__ import annotations

import itertools
import math

import torch

import lcs_cvx
from lcs_cvx.datasets import CUBE_DT
from lcs_cvx.kinematics import up_in_body

__all__ = ["KINEMATICS", "CONTACT_KINEMATICS", "HALF_SIDE", "kinematic_lcs", "contact_lcs", "augment",
           "stepper", "CONTACT_N_LAMS"]

#: Standard gravity (m/s^2), held in ``d`` of the vertical velocity row.
GRAVITY = 9.81
#: Half the cube's side (m): the corners are at ``(±a, ±a, ±a)`` in the body frame.
HALF_SIDE = 0.1048 / 2
#: p integrated from v, q from the body angular velocity w.
KINEMATICS = lcs_cvx.Kinematics(CUBE_DT, positions={4: 10, 5: 11, 6: 12}, quaternions=[(0, 7)], frame="body")
#: The same with the up coordinates g = R(q)^T e_z at 13:16.
CONTACT_KINEMATICS = lcs_cvx.Kinematics(CUBE_DT, positions={4: 10, 5: 11, 6: 12}, quaternions=[(0, 7)],
                                        frame="body", up=[(13, 0)])
#: Candidate n_lam of the contact model: the 8 corners, and 8 more units for friction.
CONTACT_N_LAMS = (8, 16)
EMPTY_U = torch.zeros(0, 0, dtype=torch.float64)


def _gravity(n_x: int) -> list[float]:
    d = [math.nan] * n_x
    d[12] = -GRAVITY * CUBE_DT
    return d


def kinematic_lcs(n_lam: int, seed: int = 0) -> lcs_cvx.LCS:
    """``LCS(13, 0, n_lam)`` with :data:`KINEMATICS` and gravity held."""
    return lcs_cvx.LCS(13, 0, n_lam, seed=seed, kinematics=KINEMATICS).hold(d=_gravity(13))


def contact_lcs(n_lam: int, seed: int = 0) -> lcs_cvx.LCS:
    """``LCS(16, 0, n_lam)`` with :data:`CONTACT_KINEMATICS`, free flight held (the velocity
    rows of ``A`` at the identity, of ``d`` at gravity), and units ``0..7`` starting at the corner
    heights: ``D[c] x + c_c = p_z + r_c · g``."""
    A = torch.full((16, 16), math.nan, dtype=torch.float64)
    A[7:13] = torch.eye(16, dtype=torch.float64)[7:13]
    d = torch.tensor(_gravity(16), dtype=torch.float64)
    d[7:12] = 0.0
    model = lcs_cvx.LCS(16, 0, n_lam, seed=seed, kinematics=CONTACT_KINEMATICS).hold(A=A, d=d)
    corners = list(itertools.product((-HALF_SIDE, HALF_SIDE), repeat=3))
    with torch.no_grad():
        for c, r in enumerate(corners[:n_lam]):
            model.D[c].zero_()
            model.D[c, 6] = 1.0
            model.D[c, 13:16] = torch.tensor(r, dtype=model.dtype)
            model.c[c] = 0.0
    return model


def augment(tosses: lcs_cvx.Trajectories) -> lcs_cvx.Trajectories:
    """The tosses with ``g = R(q)^T e_z`` appended to every state (16 columns)."""
    return lcs_cvx.Trajectories([torch.cat([x, up_in_body(x[:, :4])], dim=1) for x in tosses.xs], tosses.us)


def stepper(model: lcs_cvx.LCS):  # noqa: ANN201 - a studies.cube.metrics.Stepper
    """``x (N, 13) -> x'``: ``model``'s step, on the augmented state when ``model`` has 16."""
    def step(x: torch.Tensor) -> torch.Tensor:
        u = EMPTY_U.new_zeros(x.shape[0], 0)
        if model.n_x == 13:
            return model.step(x, u)
        return model.step(torch.cat([x, up_in_body(x[:, :4])], dim=1), u)[:, :13]
    return step
