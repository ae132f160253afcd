"""The horizon problem of C3: the LCS at every step of the horizon, the cost weights, and the
layout of the per-step decision vector.

Over a horizon of ``N`` steps C3 plans ``z_k = (x_k, lam_k, u_k)`` (``k = 0 .. N-1``; with
``eta_k = D x_k + E u_k + F lam_k + c`` appended for the ``"c3+"`` projection) and ``x_N``, and
minimises

$$
\\sum_{k<N} (x_k - x_k^d)^\\top Q_k (x_k - x_k^d) + u_k^\\top R_k u_k
+ (x_N - x_N^d)^\\top Q_N (x_N - x_N^d)
$$

subject to the dynamics of eq. (1), ``x_{k+1} = A_k x_k + B_k u_k + C_k lam_k + d_k``. The
consensus weights ``G_k`` (QP step) and ``U_k`` (projection step) act on ``z_k``.
``Q_N = "dare"`` is the solution of the discrete algebraic Riccati equation of ``(A_0, B_0, Q, R)``.
Everything here is NumPy float64: the horizon problem is set up once, when a controller is built
(:class:`OnDevice` keeps torch copies for solves on another device).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np
import scipy.linalg
import torch

from .._checks import LCSInputError
from ..lcp import solve_lcp
from ..system import ACTIVE_TOL, LCS

__all__ = ["PROJECTIONS", "WITH_ETA", "Horizon", "Layout", "OnDevice", "dare", "mode_dynamics", "weight_matrix", "default_consensus_weights",
           "psd_factor"]

PROJECTIONS = ("auto", "lcp", "c3+", "qp", "miqp")
#: the projections whose decision vector carries ``eta`` (C3+'s layout)
WITH_ETA = ("auto", "lcp", "c3+")


class OnDevice:
    """NumPy arrays set up once (a name -> array dict), and their copies as torch tensors of the
    device and dtype a solve runs on, made at first use: ``cache.on(xp, like)``."""

    def __init__(self, arrays: dict[str, np.ndarray]):
        self._copies: dict[str, dict[str, Any]] = {"numpy": arrays}

    def on(self, xp: Any, like: Any) -> dict[str, Any]:
        """The arrays for the back-end ``xp`` (an ``ArrayOps``): NumPy's, or tensors like ``like``."""
        if xp.np:
            return self._copies["numpy"]
        key = f"{like.device}:{like.dtype}"
        if key not in self._copies:
            self._copies[key] = {k: torch.as_tensor(a).to(device=like.device, dtype=like.dtype)
                                 for k, a in self._copies["numpy"].items()}
        return self._copies[key]


@dataclasses.dataclass(frozen=True)
class Layout:
    """Where ``x``, ``lam``, ``u`` (and ``eta`` for ``"c3+"``) sit in ``z_k``."""

    n_x: int
    n_lam: int
    n_u: int
    with_eta: bool

    @property
    def n_z(self) -> int:
        return self.n_x + self.n_lam + self.n_u + (self.n_lam if self.with_eta else 0)

    @property
    def x(self) -> slice:
        return slice(0, self.n_x)

    @property
    def lam(self) -> slice:
        return slice(self.n_x, self.n_x + self.n_lam)

    @property
    def u(self) -> slice:
        return slice(self.n_x + self.n_lam, self.n_x + self.n_lam + self.n_u)

    @property
    def eta(self) -> slice:
        start = self.n_x + self.n_lam + self.n_u
        return slice(start, start + self.n_lam)


@dataclasses.dataclass(frozen=True)
class Horizon:
    """The LCS of every step, stacked: ``A (N, n_x, n_x)``, ``B (N, n_x, n_u)``,
    ``C (N, n_x, n_lam)``, ``d (N, n_x)``, ``D (N, n_lam, n_x)``, ``E (N, n_lam, n_u)``,
    ``F (N, n_lam, n_lam)``, ``c (N, n_lam)`` (letters of eq. (1))."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    d: np.ndarray
    D: np.ndarray
    E: np.ndarray
    F: np.ndarray
    c: np.ndarray

    @classmethod
    def of(cls, model: Any, horizon: int) -> Horizon:
        """The stack of ``model`` (one :class:`lcs_cvx.LCS`, or a list of ``horizon`` of them of one
        size, for a time-varying system). Every ``F`` satisfies Assumption 1 (``F + F^T``
        positive definite, a unique LCP solution): an ``LCS`` holds it by construction, and
        :meth:`lcs_cvx.LCS.from_matrices` refuses an ``F`` without it, naming ``F``. A model with
        known kinematics (:class:`lcs_cvx.Kinematics`) enters as :meth:`lcs_cvx.LCS.as_lcs`:
        exact for positions; a quaternion block asks for ``as_lcs(about=x)``."""
        if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or horizon < 1:
            raise LCSInputError(f"horizon: expected an integer >= 1, received {horizon!r}")
        models = list(model) if isinstance(model, Sequence) else [model] * int(horizon)
        if len(models) != horizon:
            raise LCSInputError(
                f"model: expected one LCS or a list of horizon = {horizon} of them, received a list of {len(models)}"
            )
        for k, m in enumerate(models):
            if not isinstance(m, LCS):
                raise LCSInputError(f"model: expected an lcs_cvx.LCS, received {type(m).__name__} (step {k})")
            if (m.n_x, m.n_u, m.n_lam) != (models[0].n_x, models[0].n_u, models[0].n_lam):
                raise LCSInputError(
                    f"model: every step's LCS must have (n_x, n_u, n_lam) = "
                    f"{(models[0].n_x, models[0].n_u, models[0].n_lam)}, step {k} has {(m.n_x, m.n_u, m.n_lam)}"
                )
            if m.kinematics is not None and m.kinematics.quaternions:
                raise LCSInputError(
                    f"model: expected an LCS, received one whose kinematics integrate a quaternion (step {k}), "
                    "which no LCS does; pass model.as_lcs(about=x) (linearised about the state x)")
        exported = {id(m): m.as_lcs().to_matrices() for m in models}  # positions integrate linearly: exact
        mats = [exported[id(m)] for m in models]
        stack = {key: np.stack([m[key] for m in mats]) for key in ("A", "B", "C", "d", "D", "E", "F", "c")}
        return cls(**stack)

    @property
    def N(self) -> int:
        return self.A.shape[0]

    @property
    def n_x(self) -> int:
        return self.A.shape[1]

    @property
    def n_u(self) -> int:
        return self.B.shape[2]

    @property
    def n_lam(self) -> int:
        return self.C.shape[2]

    def lam_scaled(self) -> tuple[Horizon, float]:
        """DAIRLab/c3's ``scale_lcs``: the same system with ``lam = s lam_s``,
        ``s = ||A_0||_F / ||C_0||_F`` (1 where ``C_0 = 0``): ``C s``, and the complementarity rows
        divided by ``s`` (``D / s``, ``E / s``, ``c / s``; ``F`` kept), so that
        ``0 <= lam_s _|_ (D x + E u + F lam + c) / s >= 0`` holds exactly when the original does.
        Returns the scaled stack and ``s``: the ADMM's weights on ``lam`` then act on forces of
        the dynamics' size."""
        norm_c = float(np.linalg.norm(self.C[0]))
        s = float(np.linalg.norm(self.A[0])) / norm_c if norm_c > 0 else 1.0
        return dataclasses.replace(self, C=self.C * s, D=self.D / s, E=self.E / s, c=self.c / s), s

    def input_in_complementarity(self) -> bool:
        """Whether ``u`` enters the complementarity (``E != 0``); if not, ``lam_0`` is fixed to the
        LCP solution at ``x0``, as in C3."""
        return bool(np.any(self.E != 0))


def weight_matrix(name: str, value: Any, n: int, count: int) -> np.ndarray:
    """``value`` as ``count`` symmetric positive semidefinite ``(n, n)`` matrices: a vector of
    ``n`` diagonal entries, an ``(n, n)`` matrix, or a stack ``(count, n, n)``."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0 and n == 1:
        arr = arr.reshape(1)
    if arr.ndim == 1 and arr.shape == (n,):
        arr = np.diag(arr)
    if arr.ndim == 2 and arr.shape == (n, n):
        arr = np.broadcast_to(arr, (count, n, n)).copy()
    if arr.shape != (count, n, n):
        raise LCSInputError(
            f"{name}: expected {n} diagonal entries, an ({n}, {n}) matrix or ({count}, {n}, {n}) per step, "
            f"received shape {np.shape(value)}"
        )
    if not np.all(np.isfinite(arr)):
        raise LCSInputError(f"{name}: expected finite entries, received a non-finite value")
    if not np.allclose(arr, np.swapaxes(arr, 1, 2), rtol=1e-12, atol=1e-12):
        raise LCSInputError(f"{name}: expected a symmetric matrix")
    arr = 0.5 * (arr + np.swapaxes(arr, 1, 2))
    low = min(float(np.linalg.eigvalsh(a).min()) for a in arr) if n else 0.0
    if low < -1e-12 * max(1.0, float(np.abs(arr).max())):
        raise LCSInputError(f"{name}: expected a positive semidefinite matrix, smallest eigenvalue {low:.3g}")
    return arr


def psd_factor(M: np.ndarray) -> np.ndarray:
    """``L`` with ``L^T L = M`` for a symmetric positive semidefinite ``M`` ``(..., n, n)``."""
    w, V = np.linalg.eigh(M)
    return np.sqrt(np.clip(w, 0.0, None))[..., :, None] * np.swapaxes(V, -1, -2)


def mode_dynamics(horizon: Horizon, x: np.ndarray, u: np.ndarray, k: int = 0) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """The affine dynamics of step ``k``'s LCS in the contact mode active at ``(x, u)``: with
    ``S`` the units with ``lam_i > 0`` there, ``lam_S = -F_SS^{-1} (D_S x + E_S u + c_S)``, so
    ``A_S = A - C_S F_SS^{-1} D_S`` and ``B_S = B - C_S F_SS^{-1} E_S``. Returns
    ``(A_S, B_S, S)``; with no unit active, ``(A, B, [])``."""
    A, B, C, D, E, F, c = (getattr(horizon, n)[k] for n in ("A", "B", "C", "D", "E", "F", "c"))
    if horizon.n_lam == 0:
        return A, B, []
    q = torch.as_tensor(D @ x + E @ u + c)[None]
    lam = solve_lcp(torch.as_tensor(F), q).lam[0].numpy()
    S = [int(i) for i in np.flatnonzero(lam > ACTIVE_TOL)]
    if not S:
        return A, B, []
    solve = np.linalg.solve(F[np.ix_(S, S)], np.concatenate([D[S], E[S]], axis=1))
    return A - C[:, S] @ solve[:, : horizon.n_x], B - C[:, S] @ solve[:, horizon.n_x:], S


def dare(A: Any, B: Any, Q: Any, R: Any) -> np.ndarray:
    """The stabilising solution ``P`` of ``P = A^T P A - A^T P B (R + B^T P B)^{-1} B^T P A + Q``."""
    A, B, Q, R = (np.atleast_2d(np.asarray(v, dtype=np.float64)) for v in (A, B, Q, R))
    try:
        P = scipy.linalg.solve_discrete_are(A, B, Q, R)
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise LCSInputError(f"QN='dare': the Riccati equation of (A, B, Q, R) has no stabilising solution ({exc})") from exc
    return 0.5 * (P + P.T)


def default_consensus_weights(layout: Layout, projection: str, input_in_complementarity: bool = False
                              ) -> tuple[np.ndarray, np.ndarray]:
    """``G`` and ``U`` diagonals when the user gives none: C3's published cart-pole weights.

    ``"qp"`` and ``"miqp"``: ``G`` 0.1 on ``x`` and ``lam``, ``U`` 1000 on ``x`` and 1 on
    ``lam``; 0 on ``u``, as published for a system whose input does not enter the
    complementarity (``E = 0``); where it does, ``U`` is 1000 on ``u`` as on ``x``, or the
    projection would reach any contact mode by moving ``u`` freely. ``"c3+"``: ``G`` 1 on
    ``lam`` and ``eta``; ``U`` 1 on ``lam`` and 10,000 on ``eta`` (its projection leaves ``x``
    and ``u`` as they are). ``"lcp"`` and ``"auto"``: as ``"c3+"`` (the same layout and QP
    step; ``"lcp"`` does not use ``U``: its projection is the model's own LCP).
    """
    G = np.zeros(layout.n_z)
    U = np.zeros(layout.n_z)
    if projection in WITH_ETA:
        G[layout.lam] = 1.0
        G[layout.eta] = 1.0
        U[layout.lam] = 1.0
        U[layout.eta] = 1e4
    else:
        G[layout.x] = 0.1
        G[layout.lam] = 0.1
        U[layout.x] = 1000.0
        U[layout.lam] = 1.0
        if input_in_complementarity:
            U[layout.u] = 1000.0
    return G, U
