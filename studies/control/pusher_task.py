"""The pusher-slider task of :mod:`studies.control.pusher_closed_loop`: its constants and random
starts, the slider's pose and its kinematics over a control period (:func:`displacement`,
:func:`compose`, :func:`to_local`), the pose-augmented LCS a controller plans with
(:func:`augment`), and the hand-written quasi-static LCS (:func:`handwritten_lcs`)."""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np

from lcs_cvx import LCS

__all__ = ["starts", "displacement", "compose", "to_local", "wrap_angle", "augment", "as_lcs", "handwritten_lcs",
           "affine_matrices"]

MODELS = os.path.join("studies", "results", "pusher_slider", "models")
DT = 0.05
TOUCH = -6.0  # p_x (cm) of the pusher touching the back face
#: stage weights on (p_x, p_y, v_x, v_y, omega, X, Y, Theta)
Q_STAGE = (0.1, 1.0, 0.01, 0.01, 0.1, 10.0, 10.0, 300.0)
R_STAGE = (0.1, 0.1)
QN_FACTOR = 5.0
#: C3 on the learned LCSs: R on u (chosen on starts 0-7, see the report)
C3_LEARNED_R = (1.0, 1.0)
HORIZON = 10
U_MAX = 10.0
POS_TOL, HEADING_TOL = 2.0, 0.2
MACHINE = "2-core x86-64 VM, 1 torch thread"
DATE = "2026-11-25 (the C3 rows 2026-11-27, the C3 (defaults) rows 2026-11-28)"


def starts(n: int, seed: int = 0) -> np.ndarray:
    """``n`` starts ``(n, 6)``: ``(gap, p_y, Theta_0, X_g, Y_g, Theta_g)`` (cm, cm, rad, cm, cm,
    rad), the box of the module docstring."""
    rng = np.random.default_rng(seed)
    out = np.empty((n, 6))
    for i in range(n):
        out[i] = (rng.uniform(0.0, 1.0), rng.uniform(-2.0, 2.0), rng.uniform(-0.2, 0.2),
                  rng.uniform(12.0, 18.0), rng.uniform(-4.0, 4.0), 0.0)
    return out


# ----------------------------------------------------------------------------- pose

def _rot(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s], [s, c]])


def displacement(x: np.ndarray, u: np.ndarray, x_next: np.ndarray, dt: float = DT) -> np.ndarray:
    """The slider's displacement ``(dX, dY, dTheta)`` over one period in its frame at the period's
    start, from the pusher's kinematics: ``dt u - (p' - p)`` and ``dt omega'`` (``(..., 3)``)."""
    x, u, x_next = (np.asarray(a, dtype=np.float64) for a in (x, u, x_next))
    return np.concatenate([dt * u - (x_next[..., 0:2] - x[..., 0:2]), dt * x_next[..., 4:5]], -1)


def compose(pose: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """The pose after a displacement ``delta`` given in the frame of ``pose`` (exact)."""
    pose = np.asarray(pose, dtype=np.float64)
    return np.concatenate([pose[:2] + _rot(pose[2]) @ delta[:2], [pose[2] + delta[2]]])


def to_local(pose: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``target`` (a world pose) in the frame of ``pose``."""
    d = _rot(-pose[2]) @ (np.asarray(target[:2]) - pose[:2])
    return np.array([d[0], d[1], wrap_angle(target[2] - pose[2])])


def wrap_angle(a: float) -> float:
    return float((a + math.pi) % (2 * math.pi) - math.pi)


def augment(m: dict[str, Any], dt: float = DT, theta: float = 0.0) -> dict[str, np.ndarray]:
    """The LCS ``m`` (slider-frame state ``(p_x, p_y, v_x, v_y, omega)``, input ``u``) with the
    world pose ``(X, Y, Theta)`` appended, the rotation frozen at the heading ``theta``:
    ``(X, Y)' = (X, Y) + R(theta) (dt u - (p' - p))``, ``Theta' = Theta + dt omega'`` with
    ``p'``, ``omega'`` the LCS's own next state. Returns the 8-state matrices."""
    m = {k: np.asarray(v, dtype=np.float64) for k, v in m.items()}
    n_x, n_u, n_lam = m["A"].shape[0], m["B"].shape[1], m["C"].shape[1]
    if n_x != 5 or n_u != 2:
        raise ValueError(f"augment: expected the pusher's 5 states and 2 inputs, received {n_x}, {n_u}")
    Rm = _rot(theta)
    A, B, C, d = np.zeros((8, 8)), np.zeros((8, 2)), np.zeros((8, n_lam)), np.zeros(8)
    A[:5, :5], B[:5], C[:5], d[:5] = m["A"], m["B"], m["C"], m["d"]
    # slider-frame displacement rows: delta = dt u - (p' - p), dTheta = dt omega'
    dA = np.zeros((3, 5))
    dA[:2] = -m["A"][0:2]
    dA[0, 0] += 1.0
    dA[1, 1] += 1.0
    dB = np.zeros((3, 2))
    dB[:2] = dt * np.eye(2) - m["B"][0:2]
    dC = np.zeros((3, n_lam))
    dC[:2] = -m["C"][0:2]
    dd = np.zeros(3)
    dd[:2] = -m["d"][0:2]
    dA[2], dB[2], dC[2], dd[2] = dt * m["A"][4], dt * m["B"][4], dt * m["C"][4], dt * m["d"][4]
    P = np.eye(3)
    P[:2, :2] = Rm
    A[5:, :5], B[5:], C[5:], d[5:] = P @ dA, P @ dB, P @ dC, P @ dd
    A[5:, 5:] = np.eye(3)
    D = np.zeros((n_lam, 8))
    D[:, :5] = m["D"]
    return {"A": A, "B": B, "C": C, "d": d, "D": D, "E": m["E"], "F": m["F"], "c": m["c"]}


def as_lcs(m: dict[str, np.ndarray]) -> Any:
    return LCS.from_matrices(**m)


# ----------------------------------------------------------------------------- models

def handwritten_lcs(p_y: float = 0.0, dt: float = DT, mu: float = 0.3, c_ls: float | None = None,
                    k: float = 0.1, eps: float = 1e-3) -> dict[str, np.ndarray]:
    r"""The quasi-static pusher-slider with a point contact on the back face and Coulomb friction
    at the finger (Anitescu's linearised cone), as LCS matrices in the study's units, the contact
    offset frozen at ``p_y`` (cm).

    The slider's twist ``V = (v_x, v_y, omega)`` over the step follows the ellipsoidal limit
    surface, ``V = k H J^T f`` with ``H = diag(1, 1, 1 / c_ls^2)`` (``c_ls`` the ratio of the
    largest friction torque to the largest friction force; by default ``a sqrt(2)``, the slider
    resting on its four corners, ``a = 5`` cm) and ``J`` the contact point's Jacobian at
    ``(-5, p_y)``; ``k`` only scales the forces. The force ``f = G lam``, ``lam >= 0`` the
    weights of the two friction-cone edges ``(1, +-mu)``. With the pusher's velocity relative to
    the contact point ``g = u - J V``, ``0 <= lam _|_ (-6 - p_x) / dt - G^T g >= 0`` (in contact
    and sticking both ``lam`` can be positive; sliding leaves one edge; the relaxation lets the
    finger drift off the face by ``mu`` times the slip, Anitescu's artefact). The pusher's
    position ``p' = p + dt (u - J_p V)``, ``J_p`` the Jacobian at the pusher's centre. ``F`` is
    ``G^T J H J^T G k + eps I`` (positive definite)."""
    a = 5.0
    c_ls = a * math.sqrt(2.0) if c_ls is None else c_ls
    H = np.diag([1.0, 1.0, 1.0 / c_ls**2])
    Jc = np.array([[1.0, 0.0, -p_y], [0.0, 1.0, -a]])
    Jp = np.array([[1.0, 0.0, -p_y], [0.0, 1.0, TOUCH]])
    G = np.array([[1.0, 1.0], [mu, -mu]])
    Kv = k * H @ Jc.T @ G  # V' = Kv lam
    A = np.diag([1.0, 1.0, 0.0, 0.0, 0.0])
    B = np.zeros((5, 2))
    B[:2] = dt * np.eye(2)
    C = np.concatenate([-dt * Jp @ Kv, Kv])
    D = np.zeros((2, 5))
    D[:, 0] = -1.0 / dt
    E = -G.T
    F = G.T @ Jc @ Kv + eps * np.eye(2)
    c = np.full(2, TOUCH / dt)
    return {"A": A, "B": B, "C": C, "d": np.zeros(5), "D": D, "E": E, "F": F, "c": c}


def affine_matrices(W: np.ndarray) -> dict[str, np.ndarray]:
    """The affine fit ``x' = [x, u, 1] W`` as ``(A, B, d)``."""
    return {"A": W[:5].T, "B": W[5:7].T, "d": W[7]}
