"""The projection step of C3: per step of the horizon, the point ``c_k = z_k + w_k`` projected
onto the complementarity set of the LCS in the ``U_k``-metric,

$$
\\delta_k = \\arg\\min_\\delta\\ (\\delta - c_k)^\\top U_k (\\delta - c_k)
\\quad\\text{s.t.}\\quad 0 \\le \\lambda \\perp D_k x + E_k u + F_k \\lambda + c_k \\ge 0 .
$$

The steps are independent, so every method projects all of them (and all initial states) at once:

- ``"lcp"`` (no solver but the model's own LCP): ``x_k`` and ``u_k`` kept, and
  ``lam_k = LCP(F_k, D_k x_k + E_k u_k + c_k)``, ``eta_k = D_k x_k + E_k u_k + F_k lam_k + c_k``
  (C3+'s layout): the point of the complementarity set that the model itself reaches from
  ``(x_k, u_k)``, the exact projection in the limit of an infinite weight on ``x`` and ``u``, and
  unique under Assumption 1. All steps and plans in one batched :func:`lcs_cvx.solve_lcp` when
  the model is the same at every step. Its plans use forces the model produces.
- ``"c3+"`` (closed form, no solver): ``z`` carries ``eta = D x + E u + F lam + c`` as its own
  coordinates; per coordinate the one of ``lam_i``, ``eta_i`` that costs less to zero in the
  ``U``-metric is zeroed and the other clipped at 0 (``U`` diagonal on ``lam`` and ``eta``).
- ``"qp"``: C3's convex relaxation, the ``lam`` block of ``U`` replaced by ``alpha F`` and
  ``(1 - alpha) lam^T F lam`` added, subject to ``lam >= 0`` and ``D x + E u + F lam + c >= 0``
  (all steps in one problem, declared once in CVXPY; solved by Clarabel with the QP set up
  once and only its linear term updated per plan, or through CVXPY when a solver is named).
- ``"miqp"``: exact, with big-M binaries ``b``: ``0 <= lam <= M (1 - b)``,
  ``0 <= D x + E u + F lam + c <= M b`` (declared once in CVXPY, solved by a mixed-integer solver:
  SCIP from the ``control`` extra, or a commercial one CVXPY reaches); or, with
  ``solver="enumerate"`` and ``n_lam <= 6``, by its ``3^n_lam`` active sets (per coordinate
  ``lam_i = 0``, ``eta_i = 0`` or both), each an equality-constrained least-squares problem in
  closed form, batched: no solver, the same projection.
- :func:`project_enumerate`: exact, by the ``2^n_lam`` sign patterns, each a convex QP (the test
  oracle of ``"miqp"``; small ``n_lam`` only).

Shapes: ``c (B, N, n_z)`` in, ``delta (B, N, n_z)`` out.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import Any

import cvxpy as cp
import numpy as np

from .._checks import LCSInputError, SolverError
from .._kernels.c3 import active_set_maps, project_active_sets, project_c3plus, project_lcp
from .._optional import require
from .costs import Horizon, Layout, OnDevice, psd_factor

__all__ = ["Projection", "project_enumerate", "MIQP_SOLVERS"]

# mixed-integer solvers CVXPY can hand a mixed-integer QP to (HiGHS and GLPK_MI take MILPs only)
MIQP_SOLVERS = ("SCIP", "GUROBI", "MOSEK", "XPRESS", "COPT", "CPLEX")
#: the convex QP of a fixed sign pattern, solved after the mixed-integer solver to make its
#: answer exact: SCIP's feasibility tolerance (1e-6) leaves it ~1e-4 from the exact projection,
#: and tighter tolerances make SCIP's LP solver fail on some problems
POLISH_OPTIONS: dict[str, Any] = {"tol_gap_abs": 1e-10, "tol_gap_rel": 1e-10, "tol_feas": 1e-10}


def _declare(horizon: Horizon, layout: Layout, U: np.ndarray, kind: str, *, alpha: float, scaling: float,
             big_m: float) -> tuple[cp.Problem, cp.Parameter, cp.Variable, Any]:
    """The ``"qp"`` or ``"miqp"`` projection of all ``N`` steps as one problem, declared once
    (``kind="pattern"``: the ``"miqp"`` one with its binaries a parameter, a convex QP).
    Parameter ``target (N, n)`` holds ``L_k c_k`` (``L_k^T L_k`` the metric); variable
    ``delta (N, n)``, ``n = n_x + n_lam + n_u``; the binaries ``(N, n_lam)`` (variable or
    parameter; None for ``"qp"``)."""
    N, nx, nl, nu = horizon.N, layout.n_x, layout.n_lam, layout.n_u
    n = nx + nl + nu
    delta = cp.Variable((N, n), name="delta")
    target = cp.Parameter((N, n), name="target")
    metric = U[:, :n, :n].copy()
    Fs = 0.5 * (horizon.F + np.swapaxes(horizon.F, 1, 2))
    if kind == "qp":
        metric[:, nx:nx + nl, nx:nx + nl] = alpha * Fs
    L = psd_factor(metric)
    LF = psd_factor((1 - alpha) * Fs) if kind == "qp" else None
    cost, cons = 0, []
    b = {"miqp": cp.Variable((N, nl), boolean=True, name="b"), "pattern": cp.Parameter((N, nl), name="b")}.get(kind)
    for k in range(N):
        x, lam, u = delta[k, :nx], delta[k, nx:nx + nl], delta[k, nx + nl:]
        eta = horizon.D[k] @ x + horizon.E[k] @ u + horizon.F[k] @ lam + horizon.c[k]
        cost += cp.sum_squares(L[k] @ delta[k] - target[k])
        if kind == "qp":
            cost += cp.sum_squares(LF[k] @ lam)
            cons += [lam >= 0, eta / scaling >= 0]
        elif kind == "miqp":
            cons += [lam >= 0, lam <= big_m * (1 - b[k]), eta >= 0, eta <= big_m * b[k]]
        else:  # the pattern as equalities: the inequality pairs would leave no interior to Clarabel
            cons += [lam >= 0, eta >= 0, cp.multiply(b[k], lam) == 0, cp.multiply(1 - b[k], eta) == 0]
    return cp.Problem(cp.Minimize(cost), cons), target, delta, b


def _relaxation_qp(horizon: Horizon, layout: Layout, metric: np.ndarray, *, alpha: float,
                   scaling: float) -> tuple[Any, np.ndarray]:
    """The ``"qp"`` projection of all ``N`` steps as a Clarabel QP (with ``A`` and ``b``),
    ``min 1/2 d^T P d + q^T d``
    s.t. ``A d + s = b``, ``s >= 0``: ``P`` block diagonal with ``2 (U'_k + (1 - alpha) F_k)``
    (``F`` symmetrised, in the ``lam`` block), ``q = -2 U'_k c_k`` per plan (returned: the
    ``(N, n, n)`` stack ``-2 U'_k``), rows ``-lam <= 0`` and ``-(D x + E u + F lam) / scaling <=
    c / scaling`` per step. The same problem as the declared one (tested to agree), but for a
    weight of 1e-9 (relative) on the coordinates ``U'`` leaves unweighted, which picks among
    their equally good values the one nearest the point."""
    import clarabel
    import scipy.sparse as sp

    N, nx, nl = horizon.N, layout.n_x, layout.n_lam
    n = metric.shape[1]
    lam = slice(nx, nx + nl)
    metric = metric.copy()
    Ps, As, bs = [], [], []
    for k in range(N):
        Pk = metric[k].copy()
        Pk[lam, lam] += (1 - alpha) * 0.5 * (horizon.F[k] + horizon.F[k].T)
        # a coordinate the metric does not weigh (u in C3's published U) may take any value:
        # a tiny weight keeps it at the point projected, and the QP strictly convex
        free = np.flatnonzero(np.diagonal(Pk) <= 0)
        tie = 1e-9 * max(1.0, float(np.abs(Pk).max()))
        metric[k, free, free] += tie
        Pk[free, free] += tie
        Ps.append(2 * Pk)
        Ak = np.zeros((2 * nl, n))
        Ak[:nl, lam] = -np.eye(nl)
        Ak[nl:] = -np.concatenate([horizon.D[k], horizon.F[k], horizon.E[k]], axis=1) / scaling
        As.append(Ak)
        bs.append(np.concatenate([np.zeros(nl), horizon.c[k] / scaling]))
    P = sp.triu(sp.block_diag(Ps)).tocsc()
    A = sp.block_diag(As).tocsc()
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    settings.tol_gap_abs = settings.tol_gap_rel = settings.tol_feas = 1e-11
    settings.tol_ktratio = 1e-10
    b = np.concatenate(bs)
    solver = clarabel.DefaultSolver(P, np.zeros(N * n), A, b, [clarabel.NonnegativeConeT(2 * N * nl)], settings)
    return solver, -2 * metric, A, b


class Projection:
    """The projection step ``projection`` (``"c3+"``, ``"qp"`` or ``"miqp"``) with metric ``U``
    ``(N, n_z, n_z)``.

    ``solver``: the CVXPY solver of ``"qp"`` or ``"miqp"`` (default SCIP); ``options``: keyword
    arguments of its ``Problem.solve`` (e.g. ``{"scip_params": {"limits/time": 1.0}}``). Without
    either, ``"qp"`` is solved by Clarabel directly, its QP set up once (the declared problem,
    re-solved through CVXPY, costs ~1.5 ms more per projection).
    ``alpha``, ``scaling``: C3's ``qp_projection_alpha`` (0.01) and ``qp_projection_scaling``
    (1000); ``big_m``: C3's ``M`` (1000).
    """

    def __init__(self, horizon: Horizon, layout: Layout, U: np.ndarray, projection: str, *,
                 solver: str | None = None, alpha: float = 0.01, scaling: float = 1000.0, big_m: float = 1000.0,
                 options: dict[str, Any] | None = None):
        self.horizon, self.layout, self.kind = horizon, layout, projection
        self.options = dict(options or {})
        nx, nl, nu = layout.n_x, layout.n_lam, layout.n_u
        if projection == "lcp":
            self._lcp = OnDevice({k: getattr(horizon, k) for k in "DEFc"})
            self.time_invariant = all(bool(np.all(getattr(horizon, k) == getattr(horizon, k)[:1])) for k in "DEFc")
            return
        if projection == "c3+":
            idx = np.r_[np.arange(layout.n_x, layout.n_x + nl), np.arange(layout.eta.start, layout.eta.stop)]
            block = U[:, idx][:, :, idx]
            if np.any(block - np.einsum("kii->ki", block)[:, :, None] * np.eye(2 * nl) != 0):
                raise LCSInputError("U: the 'c3+' projection is closed-form for a U diagonal on (lam, eta); "
                                    "received off-diagonal entries there")
            d_lam = np.diagonal(U[:, layout.lam, layout.lam], axis1=1, axis2=2)
            d_eta = np.diagonal(U[:, layout.eta, layout.eta], axis1=1, axis2=2)
            self._sqrt_w = OnDevice({"lam": np.sqrt(d_lam), "eta": np.sqrt(d_eta)})
            return
        if projection == "miqp" and solver == "enumerate":
            self._setup_active_sets(U)
            return
        if projection == "miqp":
            solver = solver or "SCIP"
            if solver not in MIQP_SOLVERS:
                raise LCSInputError("projection_solver: expected 'enumerate' or a mixed-integer QP solver, one of "
                                    f"{MIQP_SOLVERS}, received {solver!r}")
            if solver not in cp.installed_solvers():
                if solver == "SCIP":
                    require("pyscipopt", "control", "the 'miqp' projection (SCIP)")
                raise ModuleNotFoundError(
                    f"the 'miqp' projection asked for {solver}, which CVXPY does not find installed; "
                    "pip install 'lcs_cvx[control]' brings SCIP"
                )
        self.direct = projection == "qp" and solver is None and not self.options
        if projection == "qp":
            solver = solver or "CLARABEL"
        self.solver = solver
        self.problem, self.target, self.delta, self.binaries = _declare(
            horizon, layout, U, projection, alpha=alpha, scaling=scaling, big_m=big_m)
        if projection == "miqp":
            self.polish, self.polish_target, self.polish_delta, self.polish_pattern = _declare(
                horizon, layout, U, "pattern", alpha=alpha, scaling=scaling, big_m=big_m)
        metric = U[:, : nx + nl + nu, : nx + nl + nu].copy()
        if projection == "qp":
            metric[:, nx:nx + nl, nx:nx + nl] = alpha * 0.5 * (horizon.F + np.swapaxes(horizon.F, 1, 2))
        self._L = psd_factor(metric)
        if self.direct:
            self._clarabel = _relaxation_qp(horizon, layout, metric, alpha=alpha, scaling=scaling)

    def _setup_active_sets(self, U: np.ndarray) -> None:
        """The ``"miqp"`` projection by enumeration of active sets: the metric (a 1e-9 relative
        weight on the coordinates ``U`` leaves unweighted, which keeps them at the point, as the
        ``"qp"`` projection does), the constraint rows and the ``3^n_lam`` affine maps."""
        hz, lay = self.horizon, self.layout
        nx, nl, n = lay.n_x, lay.n_lam, lay.n_x + lay.n_lam + lay.n_u
        if nl > 6:
            raise LCSInputError(f"projection_solver='enumerate': 3^n_lam active sets; expected n_lam <= 6, received {nl}")
        metric = U[:, :n, :n].copy()
        for k in range(hz.N):
            free = np.flatnonzero(np.diagonal(metric[k]) <= 0)
            metric[k, free, free] += 1e-9 * max(1.0, float(np.abs(metric[k]).max()))
        if np.any(np.linalg.eigvalsh(metric).min(axis=1) <= 0):
            raise LCSInputError("U: projection_solver='enumerate' needs U positive definite on (x, lam, u) "
                                "once its unweighted coordinates get a tie-break weight; received a singular U")
        rows = np.zeros((hz.N, 2 * nl, n))
        rows[:, :nl, nx:nx + nl] = np.eye(nl)
        rows[:, nl:] = np.concatenate([hz.D, hz.F, hz.E], axis=2)
        offset = np.concatenate([np.zeros((hz.N, nl)), hz.c], axis=1)
        self.solver, self.direct = "enumerate", False
        self._active = (metric, rows, offset, active_set_maps(metric, rows))

    def _solve_active_sets(self, c: np.ndarray) -> np.ndarray:
        """The exact projection by :func:`~lcs_cvx._kernels.c3.project_active_sets`."""
        n = self.layout.n_x + self.layout.n_lam + self.layout.n_u
        out = c.copy()
        out[..., :n], found = project_active_sets(c[..., :n], *self._active)
        if not found.all():
            raise SolverError("the 'miqp' projection: no active set of the complementarity set is feasible "
                              f"for {int((~found).sum())} step(s)")
        return out

    def bind(self, xp: Any, like: Any, lcp: Callable[[int, Any], Any] | None = None) -> Callable[[Any], Any]:
        """The projection of one solve, ``project(c) -> delta`` for ``c (B, N, n_z)`` on the arrays
        of ``xp`` (``"qp"`` and ``"miqp"``: NumPy arrays); ``like``: an array of the solve;
        ``lcp(k, q) -> lam``: the LCP of step ``k``'s ``F`` on ``q (M, n_lam)`` (``"lcp"``)."""
        if self.kind == "lcp":
            mats = self._lcp.on(xp, like)
            return lambda c: project_lcp(xp, c, self.layout, mats["D"], mats["E"], mats["F"], mats["c"], lcp,
                                         self.time_invariant)
        if self.kind == "c3+":
            lam, eta = self.layout.lam, self.layout.eta
            w_lam, w_eta = self._sqrt_w.on(xp, like).values()
            return lambda c: project_c3plus(xp, c, lam, eta, w_lam, w_eta)
        if self.solver == "enumerate":
            return self._solve_active_sets
        return self._solve_direct if self.direct else self._solve_cvxpy

    def _solve_direct(self, c: np.ndarray) -> np.ndarray:
        """The ``"qp"`` projection with its QP set up in Clarabel once: per plan only the linear
        term changes (``solver.update(q=...)``), without CVXPY's per-solve work."""
        solver, metric2, A, rhs = self._clarabel
        n = self.layout.n_x + self.layout.n_lam + self.layout.n_u
        out = c.copy()
        for b in range(c.shape[0]):
            solver.update(q=np.einsum("kij,kj->ki", metric2, c[b, :, :n]).reshape(-1))
            sol = solver.solve()
            x = np.asarray(sol.x)
            status = str(sol.status)
            # as CVXPY's "optimal_inaccurate": stalled near the optimum, the constraints held
            feasible = status == "InsufficientProgress" and float((A @ x - rhs).max()) <= 1e-9
            if status not in ("Solved", "AlmostSolved") and not feasible:
                raise SolverError(f"the 'qp' projection: Clarabel returned status {status}")
            out[b, :, :n] = x.reshape(c.shape[1], n)
        return out

    def _solve_cvxpy(self, c: np.ndarray) -> np.ndarray:
        """The ``"qp"`` or ``"miqp"`` projection, the declared problem re-solved per plan."""
        n = self.layout.n_x + self.layout.n_lam + self.layout.n_u
        out = c.copy()
        for b in range(c.shape[0]):
            self.target.value = np.einsum("kij,kj->ki", self._L, c[b, :, :n])
            try:
                self.problem.solve(solver=self.solver, **self.options)
            except cp.error.SolverError as exc:
                raise SolverError(f"the '{self.kind}' projection failed in {self.solver}: {exc}") from exc
            if self.problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
                raise SolverError(f"the '{self.kind}' projection: {self.solver} returned status {self.problem.status}")
            if self.kind == "miqp":
                self._polish(b)
            out[b, :, :n] = self.delta.value
        return out

    def _polish(self, b: int) -> None:
        """Re-solve the projection on the sign pattern the mixed-integer solver chose (a convex
        QP, Clarabel at tight tolerances); ``self.delta`` then holds the exact projection."""
        self.polish_pattern.value = np.round(self.binaries.value)
        self.polish_target.value = self.target.value
        try:
            self.polish.solve(solver="CLARABEL", **POLISH_OPTIONS)
        except cp.error.SolverError as exc:
            raise SolverError(f"the 'miqp' projection: the QP of {self.solver}'s sign pattern failed in Clarabel: {exc}") from exc
        if self.polish.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
            raise SolverError(f"the 'miqp' projection: the QP of {self.solver}'s sign pattern returned {self.polish.status}")
        self.delta.value = self.polish_delta.value


def project_enumerate(c: Any, U: Any, D: Any, E: Any, F: Any, lcp_c: Any, n_x: int, n_u: int) -> np.ndarray:
    """The exact projection of one point ``c (n_x + n_lam + n_u,)`` onto
    ``{0 <= lam _|_ D x + E u + F lam + lcp_c >= 0}`` in the ``U``-metric, by enumerating the
    ``2^n_lam`` patterns (on ``S``: ``eta_S = 0, lam_S >= 0``; off ``S``: ``lam = 0, eta >= 0``),
    each a convex QP solved by Clarabel at tight tolerances. The oracle of ``"miqp"``; ``n_lam <= 10``."""
    c, U = np.asarray(c, dtype=np.float64), np.asarray(U, dtype=np.float64)
    D, E, F, lcp_c = (np.atleast_1d(np.asarray(a, dtype=np.float64)) for a in (D, E, F, lcp_c))
    nl = F.shape[0]
    if nl > 10:
        raise LCSInputError(f"project_enumerate: 2^n_lam patterns; expected n_lam <= 10, received {nl}")
    n = n_x + nl + n_u
    L = psd_factor(U[:n, :n])
    best, best_cost = None, np.inf
    for pattern in itertools.product((False, True), repeat=nl):
        on = np.array(pattern, dtype=bool)
        d = cp.Variable(n)
        x, lam, u = d[:n_x], d[n_x:n_x + nl], d[n_x + nl:]
        eta = D @ x + E @ u + F @ lam + lcp_c
        cons = []
        if on.any():
            cons += [lam[on] >= 0, eta[on] == 0]
        if (~on).any():
            cons += [lam[~on] == 0, eta[~on] >= 0]
        prob = cp.Problem(cp.Minimize(cp.sum_squares(L @ (d - c))), cons)
        prob.solve(solver="CLARABEL", **POLISH_OPTIONS)
        if prob.status == cp.OPTIMAL and prob.value < best_cost:
            best, best_cost = d.value.copy(), prob.value
    if best is None:
        raise SolverError("project_enumerate: no sign pattern is feasible")
    return best
