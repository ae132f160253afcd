"""The QP step of C3: the horizon cost plus the consensus term, subject to the dynamics.

For targets ``t_k`` (``delta_k - w_k``) and a consensus scale ``rho`` it solves

$$
\\min_{z, x_N}\\ \\text{cost}(x, u) + \\sum_{k<N} (z_k - t_k)^\\top \\rho G_k (z_k - t_k)
\\quad\\text{s.t.}\\quad x_0 = x^0,\\ x_{k+1} = A_k x_k + B_k u_k + C_k \\lambda_k + d_k
$$

(plus ``eta_k = D_k x_k + E_k u_k + F_k lam_k + c_k`` for ``"c3+"``, ``lam_0`` fixed to the LCP
solution at ``x0`` when ``E = 0``, and optional box bounds on ``x``, ``u``, ``lam``).

Two paths solve it:

- ``"cvxpy"``: the problem declared **once** as a parameterised (DPP) CVXPY problem
  (:func:`qp_problem`; parameters ``x0``, the fixed ``lam_0``, the scaled targets, ``sqrt(rho)``
  and the scaled ``x^d``), re-solved by Clarabel or OSQP (warm-started). It takes box bounds.
- ``"fast"``: without bounds, an equality-constrained QP whose solution is affine in its data,
  ``y = Y_rho p + y_rho`` with ``p = (x0, lam_0, t, x^d)``. The KKT system is factorised once per
  consensus scale (``rho_scale**i``, ``i = 0..K``) when the controller is built; a QP step is then
  one matrix product, batched over initial states (torch, any device). With box bounds, the
  bounded coordinates ``s = y_S`` are the only unknowns left: the same factorisation gives the
  QP's inverse reduced Hessian ``P`` on them, and the step solves the small box QP
  ``min 1/2 (s - s*)^T P_SS^{-1} (s - s*)``, ``lo <= s <= hi`` per initial state by an exact
  active-set method (:mod:`lcs_cvx._kernels.box_qp`; NumPy arrays, compiled).

Shapes: ``x0 (B, n_x)``, ``t (B, N, n_z)``, ``x^d (B, N + 1, n_x)``; a step returns
``z (B, N, n_z)`` and ``x_N (B, n_x)``.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from typing import Any

import cvxpy as cp
import numpy as np
import scipy.linalg
import torch
from threadpoolctl import threadpool_limits

from .._checks import LCSInputError
from .._kernels.c3 import affine_qp, bounded_affine_qp
from .costs import Horizon, Layout, OnDevice, psd_factor

__all__ = ["Bounds", "QPStep", "qp_problem", "QP_SOLVERS"]

QP_SOLVERS = ("CLARABEL", "OSQP")
#: tolerances that make both solvers agree with the fast path to about 1e-9 (OSQP warm-started
#: and polished)
SOLVER_OPTIONS: dict[str, dict[str, Any]] = {
    "CLARABEL": {"tol_gap_abs": 1e-12, "tol_gap_rel": 1e-12, "tol_feas": 1e-12, "tol_ktratio": 1e-10},
    "OSQP": {"warm_start": True, "eps_abs": 1e-11, "eps_rel": 1e-11, "max_iter": 50000, "polishing": True},
}


@dataclasses.dataclass(frozen=True)
class Bounds:
    """Box bounds ``lo <= v <= hi`` on ``x`` (steps 1..N), ``u`` and ``lam`` (steps 0..N-1); each
    a pair of ``(n,)`` arrays with ``-inf``/``inf`` for no bound, or None."""

    x: tuple[np.ndarray, np.ndarray] | None = None
    u: tuple[np.ndarray, np.ndarray] | None = None
    lam: tuple[np.ndarray, np.ndarray] | None = None

    @classmethod
    def of(cls, layout: Layout, **given: Any) -> Bounds:
        sizes = {"x": layout.n_x, "u": layout.n_u, "lam": layout.n_lam}
        out = {}
        for key, value in given.items():
            name = f"{key}_bounds"
            if value is None:
                continue
            try:
                lo, hi = (np.broadcast_to(np.asarray(v, dtype=np.float64), (sizes[key],)).copy() for v in value)
            except (TypeError, ValueError) as exc:
                raise LCSInputError(
                    f"{name}: expected a pair (lo, hi) of scalars or ({sizes[key]},) arrays, received {value!r}"
                ) from exc
            if np.isnan(lo).any() or np.isnan(hi).any():
                raise LCSInputError(f"{name}: expected numbers or +-inf, received NaN")
            bad = np.flatnonzero(lo > hi)
            if bad.size:
                i = int(bad[0])
                raise LCSInputError(f"{name}: infeasible bounds, lo[{i}] = {lo[i]:g} > hi[{i}] = {hi[i]:g}")
            out[key] = (lo, hi)
        return cls(**out)

    def any(self) -> bool:
        return any(v is not None for v in (self.x, self.u, self.lam))


def _bounded_coordinates(horizon: Horizon, layout: Layout, bounds: Bounds, fix_lam0: bool
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(S, lo, hi)``: the coordinates of ``y = (z_0, ..., z_{N-1}, x_N)`` with a finite bound
    (``x`` at steps 1..N, ``u`` and ``lam`` at steps 0..N-1; not ``lam_0`` when ``fix_lam0``)
    and their bounds."""
    N, nz = horizon.N, layout.n_z
    S, lo, hi = [], [], []

    def add(offset: int, box: tuple[np.ndarray, np.ndarray] | None) -> None:
        if box is None:
            return
        for i in np.flatnonzero(np.isfinite(box[0]) | np.isfinite(box[1])):
            S.append(offset + int(i))
            lo.append(box[0][i])
            hi.append(box[1][i])

    for k in range(N + 1):
        base = k * nz
        if k >= 1:
            add(base + layout.x.start, bounds.x)
        if k == N:
            break
        if not (fix_lam0 and k == 0):
            add(base + layout.lam.start, bounds.lam)
        add(base + layout.u.start, bounds.u)
    return np.array(S, dtype=np.int64), np.array(lo, dtype=np.float64), np.array(hi, dtype=np.float64)


def _box_sensitivity(P_S: np.ndarray, S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(P_SS, P_S^T)`` of one consensus level: the data of the bounded step
    (:mod:`lcs_cvx._kernels.box_qp`)."""
    P_SS = P_S[S]
    return np.ascontiguousarray(0.5 * (P_SS + P_SS.T)), np.ascontiguousarray(P_S.T)


def _stage_matrices(horizon: Horizon, layout: Layout, Q, R, QN, G, rho: float, fix_lam0: bool):
    """The KKT data of the QP step at scale ``rho``: Hessian ``H (n_y, n_y)``, linear term
    ``f = Fp p``, equalities ``A_eq y = Bp p + b0``."""
    N, nz, nx, nl = horizon.N, layout.n_z, layout.n_x, layout.n_lam
    n_y = N * nz + nx
    nu = layout.n_u
    n_p = nx + (nl if fix_lam0 else 0) + N * nz + (N + 1) * nx + N * nu
    p_t = nx + (nl if fix_lam0 else 0)
    p_xd = p_t + N * nz
    p_ur = p_xd + (N + 1) * nx

    def xk(k: int) -> np.ndarray:
        return np.arange(nx) + (k * nz if k < N else N * nz)

    def part(k: int, s: slice) -> np.ndarray:
        return np.arange(s.start, s.stop) + k * nz

    H = np.zeros((n_y, n_y))
    Fp = np.zeros((n_y, n_p))
    for k in range(N + 1):
        Qk = Q[k] if k < N else QN
        H[np.ix_(xk(k), xk(k))] += 2 * Qk
        Fp[np.ix_(xk(k), p_xd + k * nx + np.arange(nx))] -= 2 * Qk
        if k == N:
            break
        z = np.arange(k * nz, (k + 1) * nz)
        H[np.ix_(part(k, layout.u), part(k, layout.u))] += 2 * R[k]
        Fp[np.ix_(part(k, layout.u), p_ur + k * nu + np.arange(nu))] -= 2 * R[k]  # (u - u_ref)^T R (u - u_ref)
        H[np.ix_(z, z)] += 2 * rho * G[k]
        Fp[np.ix_(z, p_t + k * nz + np.arange(nz))] -= 2 * rho * G[k]
    m_rows = nx + N * nx + (N * nl if layout.with_eta else 0) + (nl if fix_lam0 else 0)
    Aeq = np.zeros((m_rows, n_y))
    Bp = np.zeros((m_rows, n_p))
    b0 = np.zeros(m_rows)
    r = 0
    Aeq[r:r + nx, xk(0)] = np.eye(nx)
    Bp[r:r + nx, :nx] = np.eye(nx)
    r += nx
    for k in range(N):
        rr = slice(r, r + nx)
        Aeq[rr, xk(k + 1)] = np.eye(nx)
        Aeq[rr, xk(k)] -= horizon.A[k]
        Aeq[rr, part(k, layout.u)] -= horizon.B[k]
        Aeq[rr, part(k, layout.lam)] -= horizon.C[k]
        b0[rr] = horizon.d[k]
        r += nx
    if layout.with_eta:
        for k in range(N):
            rr = slice(r, r + nl)
            Aeq[rr, part(k, layout.eta)] = np.eye(nl)
            Aeq[rr, xk(k)] -= horizon.D[k]
            Aeq[rr, part(k, layout.u)] -= horizon.E[k]
            Aeq[rr, part(k, layout.lam)] -= horizon.F[k]
            b0[rr] = horizon.c[k]
            r += nl
    if fix_lam0:
        Aeq[r:r + nl, part(0, layout.lam)] = np.eye(nl)
        Bp[r:r + nl, nx:nx + nl] = np.eye(nl)
        r += nl
    return H, Fp, Aeq, Bp, b0


def qp_problem(horizon: Horizon, layout: Layout, Q: np.ndarray, R: np.ndarray, QN: np.ndarray,
               G: np.ndarray, *, fix_lam0: bool, bounds: Bounds | None = None
               ) -> tuple[cp.Problem, dict[str, cp.Parameter], dict[str, cp.Variable]]:
    """The QP step declared once (DPP). Parameters: ``x0 (n_x)``, ``lam0 (n_lam)`` (when
    ``fix_lam0``), ``sqrt_rho`` (scalar), ``target (N, n_z)`` holding ``sqrt(rho) L_k t_k`` with
    ``L_k^T L_k = G_k``, ``x_des (N + 1, n_x)`` holding ``M_k x^d_k`` with ``M_k^T M_k = Q_k``,
    ``u_ref (N, n_u)`` holding ``S_k u^ref_k`` with ``S_k^T S_k = R_k`` (the input cost is
    ``(u_k - u^ref_k)^T R_k (u_k - u^ref_k)``; ``u^ref = 0`` by default).
    Variables ``x (N + 1, n_x)``, ``lam``, ``u`` (and ``eta``) ``(N, .)``."""
    N, nx, nl, nu = horizon.N, layout.n_x, layout.n_lam, layout.n_u
    x = cp.Variable((N + 1, nx), name="x")
    lam = cp.Variable((N, nl), name="lam") if nl else None
    u = cp.Variable((N, nu), name="u")
    eta = cp.Variable((N, nl), name="eta") if layout.with_eta else None
    params = {
        "x0": cp.Parameter(nx, name="x0"),
        "sqrt_rho": cp.Parameter(nonneg=True, name="sqrt_rho"),
        "target": cp.Parameter((N, layout.n_z), name="target"),
        "x_des": cp.Parameter((N + 1, nx), name="x_des"),
        "u_ref": cp.Parameter((N, nu), name="u_ref"),
    }
    LG, LQ, LR, LQN = psd_factor(G), psd_factor(Q), psd_factor(R), psd_factor(QN)
    cost = 0
    cons = [x[0] == params["x0"]]
    for k in range(N):
        parts = [x[k], lam[k], u[k]] if nl else [x[k], u[k]]
        if eta is not None:
            parts.append(eta[k])
        z = cp.hstack(parts)
        cost += cp.sum_squares(LQ[k] @ x[k] - params["x_des"][k]) + cp.sum_squares(LR[k] @ u[k] - params["u_ref"][k])
        cost += cp.sum_squares(params["sqrt_rho"] * (LG[k] @ z) - params["target"][k])
        nxt = horizon.A[k] @ x[k] + horizon.B[k] @ u[k] + horizon.d[k]
        if nl:
            nxt = nxt + horizon.C[k] @ lam[k]
        cons.append(x[k + 1] == nxt)
        if eta is not None:
            cons.append(eta[k] == horizon.D[k] @ x[k] + horizon.E[k] @ u[k] + horizon.F[k] @ lam[k] + horizon.c[k])
    cost += cp.sum_squares(LQN @ x[N] - params["x_des"][N])
    if fix_lam0:
        params["lam0"] = cp.Parameter(nl, name="lam0")
        cons.append(lam[0] == params["lam0"])
    if bounds is not None:
        for var, box, steps in ((x, bounds.x, range(1, N + 1)), (u, bounds.u, range(N)), (lam, bounds.lam, range(N))):
            if box is None or var is None:
                continue
            lo, hi = box
            for i in np.flatnonzero(np.isfinite(lo)):
                cons.append(var[list(steps), int(i)] >= lo[i])
            for i in np.flatnonzero(np.isfinite(hi)):
                cons.append(var[list(steps), int(i)] <= hi[i])
    prob = cp.Problem(cp.Minimize(cost), cons)
    variables = {"x": x, "lam": lam, "u": u, "eta": eta}
    return prob, params, variables


class QPStep:
    """The QP step at the consensus scales ``rho_levels[i]`` (``i = 0..K``), on one path.

    Args:
        horizon, layout: the horizon problem (:mod:`lcs_cvx.control.costs`).
        Q ``(N, n_x, n_x)``, R ``(N, n_u, n_u)``, QN ``(n_x, n_x)``, G ``(N, n_z, n_z)``: weights.
        rho_levels: ``(K + 1,)`` the scale of ``G`` at each ADMM iteration and the last QP step.
        fix_lam0: constrain ``lam_0`` to a given value (the LCP solution at ``x0``).
        bounds: box bounds (``lam`` at step 0 is left unbounded on the ``"fast"`` path when
            ``fix_lam0``: the LCP fixes it).
        path: ``"fast"`` or ``"cvxpy"``; solver: ``"CLARABEL"`` or ``"OSQP"`` (``"cvxpy"`` path).
    """

    def __init__(self, horizon: Horizon, layout: Layout, Q: np.ndarray, R: np.ndarray, QN: np.ndarray,
                 G: np.ndarray, rho_levels: np.ndarray, *, fix_lam0: bool, bounds: Bounds, path: str,
                 solver: str):
        if path not in ("fast", "cvxpy"):
            raise LCSInputError(f"qp_path: expected 'fast' or 'cvxpy', received {path!r}")
        if solver not in QP_SOLVERS:
            raise LCSInputError(f"qp_solver: expected one of {QP_SOLVERS}, received {solver!r}")
        self.horizon, self.layout, self.path, self.solver = horizon, layout, path, solver
        self.fix_lam0 = fix_lam0
        self.rho_levels = np.asarray(rho_levels, dtype=np.float64)
        self._LG = psd_factor(G)
        self._LR = psd_factor(R)
        self._LQ = psd_factor(np.concatenate([Q, QN[None]]))
        if path == "fast":
            # BLAS threads as torch's: a dense solve per level, a few milliseconds each
            self._box = _bounded_coordinates(horizon, layout, bounds, fix_lam0)
            S = self._box[0]
            with threadpool_limits(limits=torch.get_num_threads()):
                maps = [self._affine_map(Q, R, QN, G, rho, S) for rho in self.rho_levels]
            if S.size:
                self._sensitivity = [_box_sensitivity(m[2], S) for m in maps]
            n_t = horizon.N * layout.n_z
            p_t = layout.n_x + (layout.n_lam if fix_lam0 else 0)
            Y = np.stack([m[0].T for m in maps])  # (levels, n_p, n_y)
            # rows of Y: x0 (and lam0), then the targets t, then x^d
            self._maps = OnDevice({
                "Yf": np.ascontiguousarray(np.concatenate([Y[:, :p_t], Y[:, p_t + n_t:]], axis=1)),
                "Yt": np.ascontiguousarray(Y[:, p_t:p_t + n_t]), "y0": np.stack([m[1] for m in maps])})
        else:
            self.problem, self.params, self.variables = qp_problem(
                horizon, layout, Q, R, QN, G, fix_lam0=fix_lam0, bounds=bounds
            )

    def _affine_map(self, Q, R, QN, G, rho, S):
        """``(Y, y0, P_S)``: the solution map ``y = p Y^T + y0`` and the columns ``S`` of the
        inverse KKT matrix's ``(n_y, n_y)`` block, ``P_S (n_y, |S|)``."""
        H, Fp, Aeq, Bp, b0 = _stage_matrices(self.horizon, self.layout, Q, R, QN, G, rho, self.fix_lam0)
        n_y, m = H.shape[0], Aeq.shape[0]
        K = np.block([[H, Aeq.T], [Aeq, np.zeros((m, m))]])
        unit = np.zeros((n_y + m, S.size))
        unit[S, np.arange(S.size)] = 1.0
        rhs = np.concatenate([np.concatenate([-Fp, Bp]), np.concatenate([np.zeros(n_y), b0])[:, None], unit],
                             axis=1)
        exc_ = None
        try:
            with warnings.catch_warnings():
                # ill-conditioned at a large rho (G scaled by rho_scale**K): the residual below decides
                warnings.simplefilter("ignore", scipy.linalg.LinAlgWarning)
                sol = scipy.linalg.solve(K, rhs, assume_a="sym")
        except np.linalg.LinAlgError as exc:
            sol, exc_ = None, exc
        if sol is None or not np.all(np.isfinite(sol)) or np.abs(K @ sol - rhs).max() > 1e-8 * max(1.0, np.abs(rhs).max()) * max(1.0, np.abs(K).max()):
            raise LCSInputError(
                "G, R: the QP step has no unique solution: its Hessian is singular on the dynamics "
                "(G must weight lam, and R or G must weight u)"
                + (f" ({exc_})" if exc_ is not None else "")
            )
        n_p = Fp.shape[1]
        return sol[:n_y, :n_p], sol[:n_y, n_p], sol[:n_y, n_p + 1:]

    def bind(self, xp: Any, x0: Any, lam0: Any, x_des: Any, u_ref: Any = None) -> Callable[[int, Any], tuple[Any, Any, int]]:
        """The QP step of one solve, ``step(level, target) -> (z (B, N, n_z), x_N (B, n_x),
        failures)`` at ``rho_levels[level]``, for ``x0 (B, n_x)``, the fixed ``lam0 (B, n_lam)`` (or
        None), ``x_des (B, N + 1, n_x)`` and the input reference ``u_ref (B, N, n_u)`` (None: 0),
        on the arrays of ``xp``. ``failures``: the initial states whose QP failed (they get C3's
        fallback plan, ``x_k = x0`` and ``lam = u = 0``)."""
        B = x0.shape[0]
        if u_ref is None:
            like = xp.unwrap(x0)
            u_ref = xp.wrap(torch.zeros(B, self.horizon.N, self.layout.n_u, dtype=like.dtype, device=like.device))
        if self.path == "cvxpy":
            return lambda level, target: self._solve_cvxpy(level, x0, lam0, target, x_des, u_ref)
        Yf, Yt, y0 = self._maps.on(xp, x0).values()
        p_fixed = xp.concat([x0] + ([lam0] if self.fix_lam0 else []) + [x_des.reshape(B, -1), u_ref.reshape(B, -1)])
        base = p_fixed @ Yf + y0[:, None, :]  # (levels, B, n_y): the fixed data of every level at once
        if not self._box[0].size:
            return lambda level, target: (*affine_qp(base[level], Yt[level], target), 0)
        S, lo, hi = self._box

        def bounded(level: int, target: Any) -> tuple[Any, Any, int]:
            z, xN, failed = bounded_affine_qp(base[level], Yt[level], target, S, lo, hi, *self._sensitivity[level])
            if failed.any():  # no input meets the bounds: C3's fallback plan, as on the "cvxpy" path
                z[failed] = 0.0
                z[failed, :, self.layout.x] = x0[failed, None, :]
                xN[failed] = x0[failed]
            return z, xN, int(failed.sum())

        return bounded

    def _solve_cvxpy(self, level: int, x0: np.ndarray, lam0: np.ndarray | None, target: np.ndarray,
                     x_des: np.ndarray, u_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """The ``"cvxpy"`` path, one declared problem re-solved per initial state (NumPy arrays)."""
        B, N, nz = target.shape
        s = float(np.sqrt(self.rho_levels[level]))
        z = np.zeros((B, N, nz))
        xN = np.zeros((B, self.layout.n_x))
        failed = 0
        t_np, x0_np, xd_np = target, x0, x_des
        lay, var = self.layout, self.variables
        for b in range(B):
            self.params["x0"].value = x0_np[b]
            self.params["sqrt_rho"].value = s
            self.params["target"].value = s * np.einsum("kij,kj->ki", self._LG, t_np[b])
            self.params["x_des"].value = np.einsum("kij,kj->ki", self._LQ, xd_np[b])
            self.params["u_ref"].value = np.einsum("kij,kj->ki", self._LR, np.asarray(u_ref[b]).reshape(N, -1))
            if self.fix_lam0:
                self.params["lam0"].value = lam0[b]
            try:
                self.problem.solve(solver=self.solver, **SOLVER_OPTIONS[self.solver])
                ok = self.problem.status == cp.OPTIMAL
            except cp.error.SolverError:
                ok = False
            if not ok:
                failed += 1
                z[b, :, lay.x] = x0_np[b]
                xN[b] = x0_np[b]
                continue
            z[b, :, lay.x] = var["x"].value[:N]
            if var["lam"] is not None:
                z[b, :, lay.lam] = var["lam"].value
            z[b, :, lay.u] = var["u"].value
            if var["eta"] is not None:
                z[b, :, lay.eta] = var["eta"].value
            xN[b] = var["x"].value[N]
        return z, xN, failed
