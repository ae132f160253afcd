r"""The exact optimum of C3's horizon problem, one mixed-integer QP over the whole horizon.

For an LCS ``x' = A x + B u + C lam + d``, ``0 <= lam _|_ D x + E u + F lam + c >= 0`` and
weights ``Q``, ``R``, ``Q_N`` it solves, from ``x_0``,

.. math::

    \min_{x, u, \lambda, b}\ \sum_{k<N} x_k^\top Q x_k + u_k^\top R u_k + x_N^\top Q_N x_N
    \quad\text{s.t.}\quad x_{k+1} = A x_k + B u_k + C \lambda_k + d,\
    0 \le \lambda_k \le M (1 - b_k),\ 0 \le D x_k + E u_k + F \lambda_k + c \le M b_k,\
    b_k \in \{0, 1\}^{n_\lambda}

(big-M binaries: ``b_{k,i} = 0`` lets ``lam_{k,i}`` be positive, ``b_{k,i} = 1`` lets the gap
be positive; ``1 - b`` are the contact modes), declared once in CVXPY with ``x_0`` as a Parameter and solved by SCIP.

SCIP satisfies the big-M rows to its feasibility tolerance (about ``1e-6``), which with
``M = 1000`` could leave a complementarity violation of about ``1e-3``. So the optimum is
*polished*: the contact modes SCIP chose are fixed (rounded binaries) and the convex QP of that
mode sequence, declared once with the modes as Parameters, is re-solved by Clarabel to
``1e-12``. Its inputs are then rolled out through the exact LCS and the cost of that rollout is
the optimum reported (the same evaluation as for C3's plans, so both are costs of feasible
trajectories). SCIP stops at a relative gap of 1e-4 (:data:`DEFAULT_SCIP_PARAMS`), so its mode
sequence is certified by :func:`enumerate_optimum`, which tries every mode sequence
(``2^{N n_lam}`` convex QPs, the first step's fixed by ``x_0`` when ``E = 0``; small problems only).
"""

from __future__ import annotations

import dataclasses
import itertools
import time
import warnings
from typing import Any

import cvxpy as cp
import numpy as np
import torch

__all__ = ["ExactResult", "HorizonMIQP", "rollout_cost", "enumerate_optimum", "DEFAULT_SCIP_PARAMS"]

#: SCIP stops at a relative gap of 1e-4. CVXPY hands SCIP the quadratic cost as second-order
#: cones, and at smaller gaps (1e-6, or its default 0) SCIP keeps refining them without closing
#: the last ~1e-5 of the gap, for minutes on some initial states. Only the modes SCIP picks are
#: kept (the QP of those modes is then solved exactly), and :func:`enumerate_optimum` certifies them.
DEFAULT_SCIP_PARAMS: dict[str, Any] = {"limits/gap": 1e-4, "limits/time": 60.0}


def _factor(M: np.ndarray) -> np.ndarray:
    """``L`` with ``L^T L = M`` (symmetric positive semidefinite ``M``)."""
    w, V = np.linalg.eigh(0.5 * (M + M.T))
    return np.sqrt(np.clip(w, 0.0, None))[:, None] * V.T


def rollout_cost(model: Any, x0: Any, u: Any, Q: np.ndarray, R: np.ndarray, QN: np.ndarray
                 ) -> tuple[float, np.ndarray]:
    """The horizon cost of the inputs ``u (N, n_u)`` rolled out from ``x0`` through the exact
    LCS ``model`` (``lcs_cvx.LCS.rollout``); returns ``(cost, x (N + 1, n_x))``."""
    u = np.asarray(u, dtype=np.float64).reshape(-1, model.n_u)
    with torch.no_grad():
        x = model.rollout(torch.as_tensor(np.asarray(x0, dtype=np.float64)), torch.as_tensor(u)).numpy()
    N = u.shape[0]
    cost = sum(float(x[k] @ Q @ x[k] + u[k] @ R @ u[k]) for k in range(N)) + float(x[N] @ QN @ x[N])
    return cost, x


@dataclasses.dataclass
class ExactResult:
    """The optimum from one ``x0``: ``cost`` (the exact-LCS rollout of ``u``), ``objective``
    (the polished QP's value), ``scip_objective``; ``x``, ``u``, ``lam``; ``modes (N, n_lam)``
    (1: ``lam`` may be positive); ``complementarity`` ``max |min(lam, gap)|`` of the polished
    plan; ``max_lam``, ``max_gap`` and ``big_m_active`` (a big-M bound within 0.1 % of ``M``);
    ``times`` (``"scip"``, ``"polish"`` seconds); ``status`` (SCIP's: ``"optimal"``, ``"gaplimit"``,
    ``"timelimit"``, ...)."""

    cost: float
    objective: float
    scip_objective: float
    x: np.ndarray
    u: np.ndarray
    lam: np.ndarray
    modes: np.ndarray
    complementarity: float
    max_lam: float
    max_gap: float
    big_m_active: bool
    times: dict[str, float]
    status: str


class HorizonMIQP:
    """The horizon problem of ``model`` (an ``lcs_cvx.LCS``) over ``horizon`` steps with weights
    ``Q``, ``R`` (matrices or diagonals) and ``QN`` (a matrix), declared once.

    ``solve(x0)`` returns an :class:`ExactResult`. ``scip_params`` go to SCIP (through CVXPY).
    """

    def __init__(self, model: Any, horizon: int, Q: Any, R: Any, QN: Any, *, big_m: float = 1000.0,
                 solver: str = "SCIP", scip_params: dict[str, Any] | None = None):
        m = model.to_matrices()
        self.model, self.N, self.big_m, self.solver = model, int(horizon), float(big_m), solver
        self.scip_params = {**DEFAULT_SCIP_PARAMS, **(scip_params or {})}
        nx, nu, nl = m["B"].shape[0], m["B"].shape[1], m["C"].shape[1]
        self.n_x, self.n_u, self.n_lam = nx, nu, nl
        self.Q = np.diag(Q) if np.ndim(Q) == 1 else np.asarray(Q, dtype=np.float64)
        self.R = np.diag(R) if np.ndim(R) == 1 else np.asarray(R, dtype=np.float64)
        self.QN = np.asarray(QN, dtype=np.float64)
        self.m = m
        self.x0 = cp.Parameter(nx, name="x0")
        self.modes = cp.Parameter((self.N, nl), name="modes")  # the polish QP's fixed modes
        self._miqp, self._miqp_vars = self._declare(binary=True)
        self._qp, self._qp_vars = self._declare(binary=False)

    def _declare(self, *, binary: bool) -> tuple[cp.Problem, dict[str, Any]]:
        m, N, M = self.m, self.N, self.big_m
        x = cp.Variable((N + 1, self.n_x), name="x")
        u = cp.Variable((N, self.n_u), name="u")
        lam = cp.Variable((N, self.n_lam), name="lam")
        b = cp.Variable((N, self.n_lam), boolean=True, name="b") if binary else self.modes
        LQ, LR, LQN = _factor(self.Q), _factor(self.R), _factor(self.QN)
        cost = cp.sum_squares(LQN @ x[N])
        cons = [x[0] == self.x0]
        for k in range(N):
            cost += cp.sum_squares(LQ @ x[k]) + cp.sum_squares(LR @ u[k])
            gap = m["D"] @ x[k] + m["E"] @ u[k] + m["F"] @ lam[k] + m["c"]
            cons += [x[k + 1] == m["A"] @ x[k] + m["B"] @ u[k] + m["C"] @ lam[k] + m["d"],
                     lam[k] >= 0, gap >= 0]
            if binary:  # b = 1: lam = 0 and the gap may be positive; b = 0: the reverse
                cons += [lam[k] <= M * (1 - b[k]), gap <= M * b[k]]
            else:  # fixed modes (1: lam may be positive, the gap is 0), as two bounds (DPP)
                cons += [lam[k] <= M * b[k], gap <= M * (1 - b[k])]
        return cp.Problem(cp.Minimize(cost), cons), {"x": x, "u": u, "lam": lam, "b": b}

    def solve(self, x0: Any) -> ExactResult:
        self.x0.value = np.asarray(x0, dtype=np.float64)
        t = time.perf_counter()
        opts = {"scip_params": self.scip_params} if self.solver == "SCIP" else {}
        with warnings.catch_warnings():  # CVXPY calls a stop at the gap limit "inaccurate"
            warnings.simplefilter("ignore", UserWarning)
            self._miqp.solve(solver=self.solver, **opts)
        t_scip = time.perf_counter() - t
        if self._miqp.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
            raise RuntimeError(f"HorizonMIQP: {self.solver} returned status {self._miqp.status}")
        scip_obj = float(self._miqp.value)
        modes = 1.0 - np.rint(np.clip(self._miqp_vars["b"].value, 0, 1))
        t = time.perf_counter()
        res = self.solve_modes(modes)
        res.times = {"scip": t_scip, "polish": time.perf_counter() - t}
        res.scip_objective = scip_obj
        extra = self._miqp.solver_stats.extra_stats if self._miqp.solver_stats is not None else None
        res.status = str(extra.get("scip_status", self._miqp.status)) if isinstance(extra, dict) else self._miqp.status
        return res

    def solve_modes(self, modes: np.ndarray) -> ExactResult:
        """The convex QP of the mode sequence ``modes (N, n_lam)`` (1: ``lam`` free, gap 0; 0:
        ``lam`` 0), by Clarabel, at the current ``x0``; ``cost`` inf where infeasible."""
        self.modes.value = np.asarray(modes, dtype=np.float64)
        try:
            with warnings.catch_warnings():  # infeasible mode sequences end "inaccurate"
                warnings.simplefilter("ignore", UserWarning)
                self._qp.solve(solver="CLARABEL", tol_gap_abs=1e-12, tol_gap_rel=1e-12, tol_feas=1e-12,
                               tol_ktratio=1e-10)
            status = self._qp.status
        except cp.error.SolverError:
            status = "solver_error"
        nan = np.full(1, np.nan)
        if status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
            return ExactResult(cost=np.inf, objective=np.inf, scip_objective=np.nan, x=nan, u=nan, lam=nan,
                               modes=modes, complementarity=np.nan, max_lam=np.nan, max_gap=np.nan,
                               big_m_active=False, times={}, status=status)
        v = self._qp_vars
        x, u, lam = v["x"].value, v["u"].value, v["lam"].value
        m = self.m
        gap = x[:-1] @ m["D"].T + u @ m["E"].T + lam @ m["F"].T + m["c"]
        cost, _ = rollout_cost(self.model, self.x0.value, u, self.Q, self.R, self.QN)
        top = max(float(lam.max()), float(gap.max()))
        return ExactResult(
            cost=cost, objective=float(self._qp.value), scip_objective=np.nan, x=x, u=u, lam=lam, modes=modes,
            complementarity=float(np.abs(np.minimum(lam, gap)).max()), max_lam=float(lam.max()),
            max_gap=float(gap.max()), big_m_active=top >= 0.999 * self.big_m, times={}, status=status)


def enumerate_optimum(problem: HorizonMIQP, x0: Any) -> tuple[float, np.ndarray]:
    """The optimum from ``x0`` by trying every mode sequence (``2^{N n_lam}`` convex QPs; the
    first step's mode is fixed by ``x0`` when ``E = 0``, since the LCP at ``x0`` has one
    solution). Returns ``(cost, modes)``: the rolled-out cost of the best sequence."""
    problem.x0.value = np.asarray(x0, dtype=np.float64)
    N, nl = problem.N, problem.n_lam
    first = None
    if not np.any(problem.m["E"]):
        with torch.no_grad():
            lam0 = problem.model.solve_lcp(torch.as_tensor(problem.x0.value)[None],
                                           torch.zeros(1, problem.n_u, dtype=torch.float64)).lam[0].numpy()
        first = (lam0 > 0).astype(float)
    best, best_modes = np.inf, None
    steps = N - (first is not None)
    for bits in itertools.product((0.0, 1.0), repeat=steps * nl):
        modes = np.array(bits).reshape(steps, nl)
        if first is not None:
            modes = np.vstack([first, modes])
        res = problem.solve_modes(modes)
        if res.objective < best:
            best, best_modes = res.objective, modes
    res = problem.solve_modes(best_modes)
    return res.cost, best_modes
