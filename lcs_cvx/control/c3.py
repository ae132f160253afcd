"""C3, consensus complementarity control (Aydinoglu, Wei, Posa): model-predictive control of an
LCS, eq. (1), by ADMM between a QP over the horizon and a per-step projection onto the
complementarity set.

With ``delta^0`` (zero, or the previous plan shifted by one step) and ``w^0 = 0``, each of the
``K = admm_iterations`` iterations ``i`` does

$$
\\begin{aligned}
z^{i+1} &= \\arg\\min_z\\ \\text{cost}(z) + \\textstyle\\sum_k (z_k - \\delta^i_k + w^i_k)^\\top
    \\rho^i G_k (z_k - \\delta^i_k + w^i_k) \\quad\\text{s.t. the dynamics} \\\\
\\delta^{i+1}_k &= \\Pi_{U_k}(z^{i+1}_k + w^i_k) \\\\
w^{i+1} &= (w^i + z^{i+1} - \\delta^{i+1}) / \\rho_s, \\qquad \\rho^{i+1} = \\rho_s \\rho^i
\\end{aligned}
$$

(the QP step of :mod:`lcs_cvx.control.qp`, the projection of :mod:`lcs_cvx.control.projection`,
the loop in the kernel :mod:`lcs_cvx._kernels.c3`, or, for float64 states on the CPU with the
fast QP path and C3+'s layout, the whole solve in one compiled call,
:mod:`lcs_cvx.control.compiled_path`; the scaled dual of C3's code: ``G`` grows by
``rho_s = rho_scale`` and ``w`` shrinks by it), then
a last QP step at ``rho^K`` returns the plan (its target is ``delta - w``; ``delta`` for
C3+'s layout, as in C3+). When ``u`` does not enter the complementarity (``E = 0``), ``lam_0`` is
fixed to the LCP solution at ``x0``.

Every plan is checked against the model: its inputs ``u`` are rolled out through eq. (1) with
the model's own ``lam_k = LCP(F, D x_k + E u_k + c)`` (``Plan.x_model``), and the gap to the
planned states is reported (``Plan.gap``, a :class:`lcs_cvx.PlanGapWarning` above ``gap_tol``).
The default projection ``"auto"`` runs the ADMM with the ``"c3+"`` and the ``"lcp"`` projections
(one QP step, two projections) and applies, per initial state, the plan whose model rollout
costs less. Then the polish (``polish``, :mod:`lcs_cvx._kernels.polish`) re-plans the inputs in
the contact modes the model visits under them, one QP per mode sequence, and keeps the result
where its model rollout costs less still: the ADMM finds the modes, the polish the inputs that
are optimal in them.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from typing import Any

import numpy as np
import torch

from .._checks import FallbackWarning, LCSInputError, PlanGapWarning, as_batch, check_positive
from .._kernels.arrays import array_ops
from .._kernels.c3 import admm, model_rollout, plan_cost, rollout, violation
from ..system import LCS
from .compiled_path import CompiledSolve
from .costs import (
    PROJECTIONS,
    WITH_ETA,
    Horizon,
    Layout,
    OnDevice,
    dare,
    default_consensus_weights,
    mode_dynamics,
    weight_matrix,
)
from .plan import Plan, cheapest, lcp_at, model_lcp, polish_plan
from .projection import Projection
from .qp import Bounds, QPStep

__all__ = ["C3"]

class C3:
    """C3 for an LCS ``model`` over ``horizon`` steps.

    The weights act on the model's own units, of ``x``, ``u`` and of ``lam``: a learned model's
    ``lam`` has arbitrary units, so ``G`` and ``U`` on ``lam`` (and ``eta``) may need scaling to
    its forces' size.

    Args:
        model: an :class:`lcs_cvx.LCS` (as learned, physical units; :meth:`lcs_cvx.LCS.from_matrices`
            or :meth:`lcs_cvx.LCS.from_c3` for a written one), or a list of ``horizon`` of them
            (a time-varying system).
        horizon: ``N``, the number of steps planned.
        Q: stage weight on ``x - x_des``, ``(n_x, n_x)`` or its diagonal ``(n_x,)``.
        R: stage weight on ``u``, ``(n_u, n_u)`` or its diagonal.
        QN: terminal weight, a matrix, its diagonal, or ``"dare"``: the solution of the discrete
            algebraic Riccati equation of ``(Q, R)`` and the last step's dynamics in the contact
            mode active at the target (``x_des`` with ``u = 0``; with no unit active there, as
            for a physical model at rest away from contact, ``(A, B)`` itself); the mode is
            kept as ``ctrl.target_mode``. A learned model's ``lam`` may be active at the target.
        G: consensus weight of the QP step over ``z = (x, lam, u)`` (``(x, lam, u, eta)`` for
            ``"c3+"``), a matrix or its diagonal; None: C3's published cart-pole weights for the
            projection (``"qp"``, ``"miqp"``: 0.1 on ``x`` and ``lam``; ``"c3+"``: 1 on ``lam``
            and ``eta``).
        U: metric of the projection over ``z``; None: C3's published cart-pole weights
            (``"qp"``, ``"miqp"``: 1000 on ``x``, 1 on ``lam``, and 1000 on ``u`` where ``u``
            enters the complementarity; ``"c3+"``: 1 on ``lam``, 10,000 on ``eta``; diagonal on
            ``(lam, eta)`` for ``"c3+"``).
        projection: ``"auto"`` (default: the ADMM with ``"lcp"`` and with ``"c3+"``, the plan
            whose model rollout costs less; ``"lcp"``'s on a tie to round-off), ``"lcp"`` (the model's own forces at the plan's
            ``(x_k, u_k)``: works on learned models, whose dense ``F``, nonzero ``E`` and
            built-in drift defeat a per-unit projection), ``"c3+"`` (closed form, per unit),
            ``"qp"`` (C3's convex relaxation) or ``"miqp"`` (exact, big-M binaries; the
            ``control`` extra's SCIP).
        admm_iterations: ``K``, the ADMM iterations before the last QP step.
        rho_scale: the growth of ``G`` per iteration (and the shrinking of the scaled dual).
        x_des: the target, ``(n_x,)`` or ``(N + 1, n_x)``; default the origin.
        x_bounds: box bounds ``(lo, hi)`` on ``x_1 .. x_N`` (scalars or ``(n_x,)``, ``+-inf`` for
            none), inside the QP step on either path.
        u_bounds: box bounds on ``u_0 .. u_{N-1}``.
        lam_bounds: box bounds on ``lam_0 .. lam_{N-1}``.
        qp_path: ``"fast"`` (default: the QP as an affine map, batched; with bounds, plus a
            small box QP per initial state solved exactly by active sets) or ``"cvxpy"`` (the
            declared problem, re-solved per initial state).
        qp_solver: ``"CLARABEL"`` or ``"OSQP"`` (the ``"cvxpy"`` path).
        projection_solver: the CVXPY solver of ``"qp"`` (default Clarabel) or ``"miqp"``
            (default SCIP; Gurobi and other mixed-integer QP solvers CVXPY reaches are accepted;
            ``"enumerate"``: the same exact projection by its ``3^n_lam`` active sets in closed
            form, batched, for ``n_lam <= 6``; ~1,000x faster than SCIP at ``n_lam = 2``).
        projection_options: keyword arguments of that solver's ``Problem.solve`` (for SCIP, e.g.
            ``{"scip_params": {"limits/time": 1.0, "limits/gap": 1e-4}}``).
        warm_start: ``ctrl(x0)`` starts from the previous plan's ``delta`` shifted by one step.
        big_m: the big-M of the ``"miqp"`` projection (C3's ``M``).
        fix_lam0: fix ``lam_0`` to the LCP solution at ``x0`` (with ``u = 0``); None: when ``E = 0`` exactly (as
            C3 does), so a learned model whose ``E`` is merely small needs ``fix_lam0=True``.
        arrays: the array back-end of the solve (``"auto"`` or ``"compiled"``: with the fast QP
            path and C3+'s layout (``"auto"``, ``"lcp"``, ``"c3+"``), float64 states on the CPU
            are planned by one compiled call (:mod:`lcs_cvx.control.compiled_path`; the same
            plans to round-off), other CPU tensors on NumPy, other devices on torch;
            ``"numpy"`` and ``"torch"`` run the array kernels on that library, ``"torch"`` on
            the CPU too).
        penalize_input_change: the input cost ``(u_k - u^prev_k)^T R (u_k - u^prev_k)`` with
            ``u^prev`` the previous plan's inputs shifted by one step (``ctrl(x0)`` after a
            first call; ``solve(..., u_ref=plan)``), instead of ``u_k^T R u_k`` (DAIRLab/c3's
            option of that name): smoother inputs, and no pull towards ``u = 0`` where holding
            a force is needed.
        gap_tol: a :class:`lcs_cvx.PlanGapWarning` when a plan's ``gap`` passes
            ``gap_tol (1 + max_k |x_model_k|_inf)``; ``ctrl.gap_warnings`` counts those plans
            (None: no check; the gap is still in every plan).
        polish: after the ADMM, at most this many QPs in the contact modes the model visits
            under the plan's inputs (:mod:`lcs_cvx._kernels.polish`: in a fixed mode the LCS is
            affine, and the horizon cost one small QP in the inputs, within ``u_bounds``); each
            initial state applies whichever plan's model rollout costs least, so the polish
            never raises it (a polished plan must also keep the model's rollout within
            ``x_bounds`` and ``lam_bounds``). 0: the ADMM's plan as it is. On the learned
            pusher-slider it brings the box to a median 0.15 cm of the goal, 1.95 cm without
            it (``studies/results/control/pusher_closed_loop.md``).
        scale_lcs: DAIRLab/c3's option of that name: the ADMM runs on the same system with
            ``lam = s lam_s``, ``s = ||A_0||_F / ||C_0||_F`` (``C s``; ``D, E, c`` divided by
            ``s``, ``F`` kept: :meth:`~lcs_cvx.control.costs.Horizon.lam_scaled`), so that
            ``G`` and ``U`` on ``lam`` and ``eta`` weigh forces of the dynamics' size; the plan's
            ``lam`` is returned in the model's units (``delta`` stays in the scaled ones).
            ``ctrl.lam_scale`` is ``s`` (1.0 without). Off by default: with the default ``G``
            and ``U`` it lost most starts of the MuJoCo cart-pole study's learned models
            (``studies/results/control/mujoco_closed_loop.md``); weights tuned for the scaled
            forces are the user's.
    """

    def __init__(self, model: Any, horizon: int, *, Q: Any, R: Any, QN: Any = "dare", G: Any = None,
                 U: Any = None, projection: str = "auto", admm_iterations: int = 10, rho_scale: float = 2.0,
                 x_des: Any = None, x_bounds: Any = None, u_bounds: Any = None, lam_bounds: Any = None,
                 qp_path: str | None = None, qp_solver: str = "CLARABEL", projection_solver: str | None = None,
                 projection_options: dict[str, Any] | None = None, warm_start: bool = True,
                 big_m: float = 1000.0, fix_lam0: bool | None = None,
                 arrays: str = "auto", penalize_input_change: bool = False, gap_tol: float | None = 0.5,
                 scale_lcs: bool = False, polish: int = 3):
        if projection not in PROJECTIONS:
            raise LCSInputError(f"projection: expected one of {PROJECTIONS}, received {projection!r}")
        self.horizon = Horizon.of(model, horizon)
        self.model = model if isinstance(model, LCS) else model[0]
        hz = self.horizon
        N = hz.N
        self.layout = Layout(hz.n_x, hz.n_lam, hz.n_u, with_eta=projection in WITH_ETA)
        self.projection_name = projection
        self.admm_iterations = check_positive("admm_iterations", admm_iterations, integer=True)
        self.rho_scale = check_positive("rho_scale", rho_scale)
        self.Q = weight_matrix("Q", Q, hz.n_x, N)
        self.R = weight_matrix("R", R, hz.n_u, N)
        self.x_des = self._target(x_des)
        if isinstance(QN, str):
            if QN != "dare":
                raise LCSInputError(f"QN: expected a matrix, its diagonal or 'dare', received {QN!r}")
            A_S, B_S, self.target_mode = mode_dynamics(hz, self.x_des[0, -1].numpy(), np.zeros(hz.n_u), hz.N - 1)
            self.QN = dare(A_S, B_S, self.Q[-1], self.R[-1])
        else:
            self.target_mode = None
            self.QN = weight_matrix("QN", QN, hz.n_x, 1)[0]
        G0, U0 = default_consensus_weights(self.layout, projection, hz.input_in_complementarity())
        self.G = weight_matrix("G", G0 if G is None else G, self.layout.n_z, N)
        self.U = weight_matrix("U", U0 if U is None else U, self.layout.n_z, N)
        bounds = Bounds.of(self.layout, x=x_bounds, u=u_bounds, lam=lam_bounds)
        self.bounds = bounds
        path = qp_path or "fast"
        if fix_lam0 is None:
            fix_lam0 = not hz.input_in_complementarity()
        self.fix_lam0 = bool(fix_lam0) and hz.n_lam > 0
        rho = self.rho_scale ** np.arange(self.admm_iterations + 1)
        # the ADMM's system: the model's, or with lam rescaled (scale_lcs); rollouts, the model's
        # LCP and the plan's outputs stay in the model's units
        admm_hz, self.lam_scale = hz.lam_scaled() if scale_lcs else (hz, 1.0)
        if scale_lcs and lam_bounds is not None:  # checked above; in the scaled units here
            scaled = tuple(np.asarray(b, dtype=np.float64) / self.lam_scale for b in lam_bounds)
            bounds = Bounds.of(self.layout, x=x_bounds, u=u_bounds, lam=scaled)
        self.qp = QPStep(admm_hz, self.layout, self.Q, self.R, self.QN, self.G, rho, fix_lam0=self.fix_lam0,
                         bounds=bounds, path=path, solver=qp_solver)
        self.projections = [Projection(admm_hz, self.layout, self.U, kind, solver=projection_solver, big_m=big_m,
                                       options=projection_options)
                            for kind in (("lcp", "c3+") if projection == "auto" else (projection,))]
        self.gap_tol = None if gap_tol is None else check_positive("gap_tol", gap_tol)
        if isinstance(polish, bool) or not isinstance(polish, (int, np.integer)) or polish < 0:
            raise LCSInputError(f"polish: expected a number of mode-fixed QPs, an integer >= 0, received {polish!r}")
        self.polish = int(polish) if hz.n_lam else 0
        self.penalize_input_change = bool(penalize_input_change)
        self.gap_warnings = 0
        self.warm_start = warm_start
        array_ops(torch.zeros(0), arrays)  # checks the name
        self.arrays = arrays
        self.last_plan: Plan | None = None
        self._matrices = OnDevice({k: getattr(self.horizon, k) for k in "ABCdDEFc"})
        self._weights = OnDevice({"Q": self.Q, "R": self.R, "QN": self.QN})
        #: the compiled path (one compiled call per solve of float64 CPU states), or None
        self._compiled = CompiledSolve.of(self)

    def _target(self, x_des: Any) -> torch.Tensor:
        N, nx = self.horizon.N, self.horizon.n_x
        if x_des is None:
            return torch.zeros(1, N + 1, nx, dtype=torch.float64)
        t = torch.as_tensor(np.asarray(x_des, dtype=np.float64))
        if t.shape == (nx,):
            t = t.expand(N + 1, nx)
        if t.shape != (N + 1, nx) or not torch.isfinite(t).all():
            raise LCSInputError(f"x_des: expected finite ({nx},) or ({N + 1}, {nx}), received shape {tuple(t.shape)}")
        return t.unsqueeze(0).clone()

    def _start(self, warm_start: Plan | Any, X0: torch.Tensor) -> torch.Tensor | None:
        """The ADMM's first ``delta`` ``(B, N, n_z)`` from ``warm_start``, or None (cold)."""
        if warm_start is None:
            return None
        if isinstance(warm_start, Plan):
            return self._shift(warm_start, X0.shape[0])
        N, nz = self.horizon.N, self.layout.n_z
        d = torch.as_tensor(warm_start).to(X0)
        if d.shape == (N, nz):
            d = d.expand(X0.shape[0], N, nz)
        if d.shape != (X0.shape[0], N, nz) or not bool(torch.isfinite(d).all()):
            raise LCSInputError(f"warm_start: expected a Plan or a finite delta of shape ({N}, {nz}) or "
                                f"({X0.shape[0]}, {N}, {nz}), received shape {tuple(d.shape)}")
        return d

    def _shift(self, plan: Plan, batch: int) -> torch.Tensor | None:
        """The previous plan's ``delta`` shifted by one step (its last step repeated)."""
        delta = plan.delta if plan.delta.dim() == 3 else plan.delta.unsqueeze(0)
        if delta.shape[0] != batch:
            return None
        return torch.cat([delta[:, 1:], delta[:, -1:]], dim=1)

    @torch.no_grad()
    def solve(self, x0: Any, *, x_des: Any = None, warm_start: Plan | Any = None, u_ref: Plan | Any = None) -> Plan:
        """The plan from ``x0`` ``(n_x,)`` or a batch ``(B, n_x)``. ``warm_start``: a previous
        :class:`Plan` of the same batch size (its ``delta`` shifted by one step starts the ADMM),
        or a starting ``delta`` of the user's ``(N, n_z)`` or ``(B, N, n_z)``. ``u_ref``: with
        ``penalize_input_change``, the inputs the cost measures ``u`` from: a previous
        :class:`Plan` (its ``u`` shifted by one step) or ``(N, n_u)`` / ``(B, N, n_u)`` (None: 0).
        With ``qp_path="fast"``, no bounds and C3+'s layout (``"auto"``, ``"lcp"``, ``"c3+"``)
        the whole solve runs on ``x0``'s device; with the fast QP path and C3+'s layout, float64
        CPU states are planned by one compiled call (:mod:`lcs_cvx.control.compiled_path`)."""
        if self._compiled is not None:
            done = self._compiled.solve(x0, x_des, warm_start, u_ref)
            if done is not None:
                plan, failures = done
                self._warn_failures(failures)
                if self.gap_tol is not None:
                    self._check_gap(plan.gap.reshape(-1), plan.x_model.reshape(plan.gap.numel(), -1))
                return plan
        t_start = time.perf_counter()
        hz, lay = self.horizon, self.layout
        single = np.ndim(x0) == 1
        fast = self.qp.path == "fast" and lay.with_eta and not self.bounds.any()
        X0 = as_batch("x0", x0, hz.n_x)
        if not fast:
            X0 = X0.cpu()
        B, N = X0.shape[0], hz.N
        xp = array_ops(X0, self.arrays if fast else "numpy")
        xd = (self.x_des if x_des is None else self._target(x_des)).to(X0).expand(B, N + 1, hz.n_x)
        delta = self._start(warm_start, X0)
        if delta is None:
            delta = X0.new_zeros(B, N, lay.n_z)
        x0_a, xd_a, delta_a = (xp.wrap(a.contiguous()) for a in (X0, xd, delta.to(X0)))
        mats = self._matrices.on(xp, X0)
        weights = self._weights.on(xp, X0)
        lcp = model_lcp(xp, mats)
        u_ref_a = xp.wrap(self._input_reference(u_ref, X0).contiguous())
        t = time.perf_counter()
        lam0_a = lcp_at(xp, x0_a, mats) / self.lam_scale if self.fix_lam0 else None
        times = {"qp": 0.0, "projection": 0.0, "lcp": time.perf_counter() - t, "model": 0.0}
        plans, failures = [], 0
        with xp.threads():
            qp_step = self.qp.bind(xp, x0_a, lam0_a, xd_a, u_ref_a)
            for proj in self.projections:
                out = admm(xp, qp_step, proj.bind(xp, x0_a, lcp), delta_a, self.admm_iterations,
                           self.rho_scale, last_target_is_delta=lay.with_eta)
                times["qp"] += out["qp"]
                times["projection"] += out["projection"]
                failures += out["failures"]
                z = out["z"]
                u, lam = xp.contiguous(z[..., lay.u]), xp.contiguous(z[..., lay.lam]) * self.lam_scale
                # the plan's states: its inputs and forces through the dynamics (exact in them)
                xs = rollout(x0_a, u, lam, *(mats[k] for k in "ABCd"))
                t = time.perf_counter()
                lm: list[Any] = []
                xm = model_rollout(x0_a, u, mats, lcp, lm)  # the model's own forces under the plan's inputs
                cost = plan_cost(xm, u - u_ref_a, xd_a, weights["Q"], weights["R"], weights["QN"])
                times["model"] += time.perf_counter() - t
                as_t = xp.unwrap
                plans.append({
                    "x": torch.stack([as_t(v) for v in xs], 1), "x_model": torch.stack([as_t(v) for v in xm], 1),
                    "lam_model": torch.stack([as_t(v) for v in lm], 1),
                    "u": as_t(u), "lam": as_t(lam), "delta": as_t(out["delta"]),
                    "primal_residual": as_t(out["primal"]), "dual_residual": as_t(out["dual"]),
                    "complementarity": as_t(violation(xp, xs, u, lam, *(mats[k] for k in "DEFc")))[:, 0],
                    "cost": as_t(cost)})
        self._warn_failures(failures)
        pick, chosen = cheapest(plans)
        t = time.perf_counter()
        pick["polished"] = polish_plan(xp, pick, x0_a, xd_a, u_ref_a, mats, weights, lcp, self.polish, self.bounds)
        times["polish"] = time.perf_counter() - t
        gap = (pick["x_model"] - pick["x"]).abs().flatten(1).amax(1)
        self._check_gap(gap, pick["x_model"])
        names = [self.projections[int(i)].kind for i in chosen.cpu()]
        times["total"] = time.perf_counter() - t_start
        plan = Plan(**pick, gap=gap, times=times, qp_failures=failures, projection=names)
        if single:
            plan = dataclasses.replace(plan, projection=names[0], **{
                f: getattr(plan, f)[0] for f in ("x", "u", "lam", "delta", "primal_residual", "dual_residual",
                                                 "complementarity", "x_model", "lam_model", "gap", "cost",
                                                 "polished")})
        return plan

    def _input_reference(self, u_ref: Plan | Any, X0: torch.Tensor) -> torch.Tensor:
        """``(B, N, n_u)``: the inputs the input cost is measured from (zero unless
        ``penalize_input_change``)."""
        B, N, nu = X0.shape[0], self.horizon.N, self.horizon.n_u
        if not self.penalize_input_change or u_ref is None:
            return X0.new_zeros(B, N, nu)
        if isinstance(u_ref, Plan):
            u = u_ref.u if u_ref.u.dim() == 3 else u_ref.u.unsqueeze(0)
            if u.shape[0] != B:
                return X0.new_zeros(B, N, nu)
            return torch.cat([u[:, 1:], u[:, -1:]], dim=1).to(X0)
        r = torch.as_tensor(np.asarray(u_ref, dtype=np.float64)).to(X0)
        if r.shape == (N, nu):
            r = r.expand(B, N, nu)
        if r.shape != (B, N, nu) or not bool(torch.isfinite(r).all()):
            raise LCSInputError(f"u_ref: expected a Plan or finite inputs of shape ({N}, {nu}) or ({B}, {N}, {nu}), "
                                f"received shape {tuple(r.shape)}")
        return r

    def _warn_failures(self, failures: int) -> None:
        """A :class:`lcs_cvx.FallbackWarning` where QP steps failed (C3's fallback plan)."""
        if failures:
            warnings.warn(
                f"C3: {failures} QP step(s) failed in {self.qp.solver}; their plans fell back to "
                "x_k = x0, lam = u = 0", FallbackWarning, stacklevel=3)

    def _check_gap(self, gap: torch.Tensor, x_model: torch.Tensor) -> None:
        """Count (and warn of) the plans whose gap passes ``gap_tol (1 + max |x_model|)``."""
        if self.gap_tol is None:
            return
        scale = 1.0 + x_model.abs().flatten(1).amax(1)
        over = int((gap > self.gap_tol * scale).sum())
        if over:
            self.gap_warnings += over
            warnings.warn(
                f"C3: {over} plan(s) disagree with the model by more than gap_tol = {self.gap_tol:g} (relative): "
                f"largest gap {float(gap.max()):.3g} between the planned states and the model's rollout of the "
                "plan's inputs; the plan relies on forces the model does not produce (projection "
                f"{self.projection_name!r}; 'lcp' or 'auto' project onto the model's own forces)",
                PlanGapWarning, stacklevel=4)

    def __call__(self, x0: Any, x_des: Any | None = None) -> torch.Tensor:
        """``plan.u[0]`` of the plan from ``x0`` (``(n_u,)``, or ``(B, n_u)`` for a batch),
        warm-started from the previous call's plan when ``warm_start``; ``x_des``: this call's
        target (as :meth:`solve`'s; None: the controller's)."""
        prev = self.last_plan if self.warm_start else None
        plan = self.solve(x0, x_des=x_des, warm_start=prev, u_ref=self.last_plan)
        self.last_plan = plan
        return plan.u[..., 0, :]

    def reset(self) -> None:
        """Forget the previous plan (the next ``ctrl(x0)`` starts cold)."""
        self.last_plan = None
