"""C3's cart-pole with soft walls (the end-to-end test problem of DAIRLab/c3), as an LCS, eq. (1),
with C3's published weights.

A pole on a cart between two soft walls at ``+-0.35`` m (stiffness ``k_s = 100``); the state is
``(cart position, pole angle, cart velocity, pole angular velocity)``, the input the cart force,
``lam`` the two wall forces. Linearised about the upright pole and discretised by forward Euler
with ``dt``: ``A = I + dt A_c``, ``B = dt B_c``, ``C = dt C_c``; the complementarity is
``0 <= lam _|_ D x + F lam + c >= 0`` with ``F = I / k_s`` (the input does not enter it, ``E = 0``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..system import LCS

__all__ = ["CartpoleProblem", "c3_cartpole"]


@dataclasses.dataclass(frozen=True)
class CartpoleProblem:
    """The model and C3's published settings: ``x0 (4,)``, ``horizon``, ``Q (4,)``, ``R (1,)``
    diagonals, and ``G``, ``U`` diagonals for each projection (``weights[projection]``)."""

    model: LCS
    x0: np.ndarray
    horizon: int
    dt: float
    Q: np.ndarray
    R: np.ndarray
    weights: dict[str, tuple[np.ndarray, np.ndarray]]


def c3_cartpole(mp: float = 0.411, mc: float = 0.978, len_p: float = 0.6, len_com: float = 0.4267,
                wall: float = 0.35, ks: float = 100.0, g: float = 9.81, horizon: int = 5,
                dt: float = 0.01) -> CartpoleProblem:
    """C3's cart-pole (its published parameters as defaults) and its C3 settings."""
    Ac = np.array([[0, 0, 1, 0], [0, 0, 0, 1], [0, g * mp / mc, 0, 0],
                   [0, g * (mc + mp) / (len_com * mc), 0, 0]])
    Bc = np.array([[0], [0], [1 / mc], [1 / (len_com * mc)]])
    a = -1 / mc + len_p / (mc * len_com)
    b = -1 / (mc * len_com) + len_p * (mc + mp) / (mc * mp * len_com**2)
    Cc = np.array([[0, 0], [0, 0], [a, -a], [b, -b]])
    D = np.array([[-1, len_p, 0, 0], [1, -len_p, 0, 0]], dtype=float)
    model = LCS.from_matrices(A=np.eye(4) + dt * Ac, B=dt * Bc, C=dt * Cc, d=np.zeros(4), D=D,
                              E=np.zeros((2, 1)), F=np.eye(2) / ks, c=np.array([wall, wall]))
    z = np.zeros(7)
    G, U = z.copy(), z.copy()
    G[:6] = 0.1  # x and lam
    U[:4], U[4:6] = 1000.0, 1.0
    Gp, Up = np.zeros(9), np.zeros(9)  # (x, lam, u, eta)
    Gp[4:6], Gp[7:9] = 1.0, 1.0
    Up[4:6], Up[7:9] = 1.0, 1e4
    return CartpoleProblem(
        model=model, x0=np.array([0.1, -0.5, 0.5, -0.4]), horizon=horizon, dt=dt,
        Q=np.array([10.0, 2.0, 1.0, 1.0]), R=np.array([1.0]),
        weights={"qp": (G, U), "miqp": (G.copy(), U.copy()), "c3+": (Gp, Up)},
    )
