r"""C3 and other model-based controllers, closed in MuJoCo: push the box of the pusher-slider
(:mod:`studies.physics.pusher_plant`) to a goal pose.

Task. The slider starts at rest at the world origin with heading ``Theta_0 ~ U[-0.2, 0.2]`` rad,
the pusher at rest behind its back face (gap ``U[0, 1]`` cm, offset ``p_y ~ U[-2, 2]`` cm, as the
pusher study's trajectories start). The goal pose is ``(X_g, Y_g, 0)`` with ``X_g ~ U[12, 18]`` cm
and ``Y_g ~ U[-4, 4]`` cm (seed 0; heading goal 0, so a start must also turn the box by up to
0.2 rad and move it sideways). A run lasts ``T = 6`` s (120 control periods of 0.05 s); every
controller's command is clipped to ``|u_x|, |u_y| <= 10`` cm/s. **Success**: at the end, the
position error ``||(X, Y) - (X_g, Y_g)|| <= 2`` cm and the heading error ``|Theta| <= 0.2`` rad.

The planning model: world pose plus the slider-frame state. The learned LCSs (and the affine and
MLP models) predict the slider-frame state ``x = (p_x, p_y, v_x, v_y, omega)`` only. Every
controller plans in the frame of the slider at the current step (where its pose is ``0``; the
goal is re-expressed in that frame at every step) and appends the pose ``(X, Y, Theta)`` to the
state. Over one period the slider's displacement in the frame at the period's start is taken
from the pusher's kinematics: the pusher moves ``dt u`` (its servo follows the command), so the
slider moves ``dt u - (p' - p)`` (the pusher's displacement less the change of its position
relative to the slider), and turns by ``dt omega'``; on the pusher study's transitions this
reproduces the translation to an RMS of ~0.005 cm per period (of 0.24 cm), where ``dt v'`` misses
by 0.1 cm (the velocity at a period's end is not its mean). So the augmented model is

    X' = X + cos(Theta) delta_x - sin(Theta) delta_y,   Y' = Y + sin(Theta) delta_x + cos(Theta) delta_y,
    Theta' = Theta + dt omega',   (delta_x, delta_y) = dt u - (p' - p),

linear in ``(x, u, p', omega')`` once the rotation is frozen at the current heading
(``Theta = 0`` in the planning frame): for an LCS, ``p'`` and ``omega'`` are rows of
``A x + B u + C lam + d`` and the augmented system is again an LCS (:func:`augment`), the same at
every step, so one C3 is built once and only the target moves. The MLP controller rolls the pose
out exactly (the rotation by the planned heading included), :func:`compose`.

Controllers (all with the stage weights :data:`Q_STAGE` on ``(p_x, p_y, v_x, v_y, omega, X, Y,
Theta)`` about the target ``(-6, 0, 0, 0, 0, goal)``, i.e. the pusher touching the back face at
its centre and the box at rest at the goal; ``R`` on ``u``; terminal ``QN_FACTOR Q``):

- ``C3, learned LCS``: :class:`lcs_cvx.control.C3` (``"c3+"``, fast path, horizon 10, 10 ADMM
  iterations, default ``G``, ``U``, ``R = diag(1, 1)``, without the polish) on the pose-augmented ``lcs_violation_n20000.npz`` or
  ``lcs_prediction_n20000.npz`` (the models the pusher study selected at its largest size, both
  ``n_lam = 16``);
- ``C3, hand-written LCS``: the quasi-static pusher-slider (:func:`handwritten_lcs`), one per
  contact offset ``p_y`` on a 1 cm grid, the nearest to the current ``p_y`` used;
- ``C3 (defaults), ...``: the same three models with C3's defaults (projection ``"auto"``, the
  polish) and the actuator's limit as ``u_bounds`` (inside the QP step) instead of ``"c3+"``
  and clipping; ``C3 (defaults, penalize_input_change), ...``: the learned models so, with the
  input cost measured from the previous plan's inputs; ``C3 (defaults, polish=0), ...``: the
  three models without the polish, and ``C3 (defaults, polish=0, 20 ADMM iterations), ...``:
  the learned models so, with 20 ADMM iterations;
- ``QP MPC, affine model``: linear MPC on the least-squares affine model with the pose appended
  (CVXPY, Clarabel, ``|u| <= 10`` as a constraint, horizon 10);
- ``MPPI, MLP model``: sampling MPC (:class:`MPPI`) on a tanh MLP of the dynamics
  (:func:`studies.control.dynamics.fit_mlp_dynamics`, as in :mod:`studies.control.mujoco_closed_loop`, for a
  2-input, 5-state model). The affine and MLP models learn from ``--transitions`` samples of
  :func:`studies.physics.pusher_plant.sample_transitions` (the pusher study's sampling, seed 0).

One JSON line per finished run goes to ``OUT/pusher_closed_loop.jsonl`` (a rerun skips the runs
already there); ``OUT/pusher_closed_loop.md`` and ``OUT/pusher_closed_loop.png`` are written from
all of them at the end. The fitted affine and MLP models are cached in
``OUT/pusher_closed_loop_cache/``.

    python -m studies.control.pusher_closed_loop --out studies/results/control [--starts 50] [--smoke]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from collections.abc import Callable
from typing import Any

import cvxpy as cp
import numpy as np
import torch
from threadpoolctl import threadpool_limits

import lcs_cvx
from lcs_cvx.control import C3
from studies.physics.models import AffineModel
from studies.physics.pusher_plant import PusherSlider, sample_transitions

from . import harness
from .dynamics import MLPDynamics, fit_mlp_dynamics
from .pusher_closed_loop_report import write_report
from .pusher_task import (
    C3_LEARNED_R,
    DT,
    HEADING_TOL,
    HORIZON,
    MODELS,
    POS_TOL,
    Q_STAGE,
    QN_FACTOR,
    R_STAGE,
    TOUCH,
    U_MAX,
    affine_matrices,
    as_lcs,
    augment,
    compose,
    displacement,
    handwritten_lcs,
    starts,
    to_local,
    wrap_angle,
)

__all__ = ["starts", "augment", "as_lcs", "displacement", "compose", "to_local", "handwritten_lcs",
           "MPPI", "CONTROLLERS", "main"]


# ----------------------------------------------------------------------------- controllers
#
# A controller is called as ctrl(x, target) with x the slider-frame state (5,) and target the goal
# pose in the slider's current frame (3,), and returns u (2,) (before clipping).

def _x_des(target: np.ndarray) -> np.ndarray:
    return np.concatenate([[TOUCH, 0.0, 0.0, 0.0, 0.0], target])


class C3Controller:
    """C3 on a pose-augmented LCS (one C3 per model, or one per contact-offset grid point,
    chosen by the nearest ``p_y``), warm-started from its previous plan when the same C3 plans
    again; records each plan's complementarity violation."""

    def __init__(self, ctrls: list[Any], grid: np.ndarray | None = None) -> None:
        self.ctrls, self.grid = ctrls, grid
        self.prev: dict[int, Any] = {}
        self.violation: list[float] = []
        self.gap: list[float] = []
        self.last = -1

    def __call__(self, x: np.ndarray, target: np.ndarray) -> np.ndarray:
        j = 0 if self.grid is None else int(np.argmin(np.abs(self.grid - x[1])))
        z0 = torch.from_numpy(np.concatenate([x, np.zeros(3)]))
        warm = self.prev.get(j) if j == self.last else None
        plan = self.ctrls[j].solve(z0, x_des=_x_des(target), warm_start=warm, u_ref=warm)
        self.prev[j], self.last = plan, j
        self.violation.append(float(plan.complementarity))
        self.gap.append(float(plan.gap))
        return plan.u[0].numpy()


def _build_c3(m: dict[str, np.ndarray], **kw: Any) -> Any:
    Q = np.diag(Q_STAGE)
    opts = {"Q": Q, "R": list(R_STAGE), "QN": QN_FACTOR * Q, "projection": "c3+", "admm_iterations": 10, "polish": 0}
    opts.update(kw)
    return C3(as_lcs(augment(m)), HORIZON, **opts)


def _c3_learned(name: str, defaults: bool = False, admm_iterations: int = 10, polish: int = 3,
                **options: Any) -> Callable[[dict[str, Any]], Any]:
    """C3 on a learned model: ``"c3+"`` as tuned on the violation-loss model (without the
    polish), or (``defaults``) the package's default projection and polish with the actuator's
    limit as ``u_bounds`` (and ``admm_iterations``, ``polish``)."""
    def make(ctx: dict[str, Any]) -> Any:
        key = ("c3", name, defaults, admm_iterations, polish, tuple(sorted(options)))
        if key not in ctx["cache"]:
            m = lcs_cvx.load_model(os.path.join(MODELS, f"lcs_{name}.npz")).to_matrices()
            kw: dict[str, Any] = {"projection": "auto", "u_bounds": (-U_MAX, U_MAX),
                                  "admm_iterations": admm_iterations, "polish": polish, **options} if defaults else {}
            ctx["cache"][key] = [_build_c3({k: np.asarray(v) for k, v in m.items()}, R=list(C3_LEARNED_R), **kw)]
        return C3Controller(ctx["cache"][key])
    return make


HAND_GRID = np.arange(-4.0, 4.0 + 1e-9, 1.0)


def _c3_hand(ctx: dict[str, Any], defaults: bool = False, polish: int = 3) -> Any:
    key = ("c3", "hand", defaults, polish)
    kw: dict[str, Any] = {"projection": "auto", "u_bounds": (-U_MAX, U_MAX), "polish": polish} if defaults else {}
    if key not in ctx["cache"]:
        ctx["cache"][key] = [_build_c3(handwritten_lcs(float(py)), **kw) for py in HAND_GRID]
    return C3Controller(ctx["cache"][key], HAND_GRID)


class AffineMPC:
    """Linear MPC on the affine model with the pose appended (:func:`augment` with no ``lam``):
    the stage cost of the study, ``|u| <= U_MAX`` as constraints (CVXPY, Clarabel; the previous
    plan, shifted, if it fails)."""

    def __init__(self, W: np.ndarray, horizon: int = HORIZON) -> None:
        am = affine_matrices(W)
        m = augment({**am, "C": np.zeros((5, 1)), "D": np.zeros((1, 5)), "E": np.zeros((1, 2)),
                     "F": np.eye(1), "c": np.ones(1)})
        A, B, d = m["A"], m["B"], m["d"]
        N = horizon
        self.x0, self.xd = cp.Parameter(8), cp.Parameter(8)
        x, u = cp.Variable((N + 1, 8)), cp.Variable((N, 2))
        Qh = np.sqrt(np.asarray(Q_STAGE))
        cost, cons = 0, [x[0] == self.x0, cp.abs(u) <= U_MAX]
        for k in range(N):
            cons.append(x[k + 1] == A @ x[k] + B @ u[k] + d)
            cost += cp.sum_squares(cp.multiply(Qh, x[k] - self.xd)) + cp.sum_squares(cp.multiply(np.sqrt(R_STAGE), u[k]))
        cost += QN_FACTOR * cp.sum_squares(cp.multiply(Qh, x[N] - self.xd))
        self.problem, self.u = cp.Problem(cp.Minimize(cost), cons), u
        self.plan = np.zeros((N, 2))
        self.failures = 0

    def __call__(self, x: np.ndarray, target: np.ndarray) -> np.ndarray:
        self.x0.value = np.concatenate([x, np.zeros(3)])
        self.xd.value = _x_des(target)
        try:
            self.problem.solve(solver=cp.CLARABEL)
            ok = self.u.value is not None and self.problem.status in ("optimal", "optimal_inaccurate")
        except cp.error.SolverError:
            ok = False
        if ok:
            self.plan = np.asarray(self.u.value)
        else:
            self.failures += 1
            self.plan = np.concatenate([self.plan[1:], self.plan[-1:]])
        return self.plan[0]


def _qp_affine(ctx: dict[str, Any]) -> Any:
    return AffineMPC(ctx["affine_W"])


class MPPI(harness.MPPI):
    """MPPI (:class:`studies.control.harness.MPPI`) on a batched model ``x' = f(x, u)`` (torch)
    with the pose rolled out exactly (:func:`compose`, batched), the study's cost
    (:data:`Q_STAGE`, :data:`R_STAGE`, ``QN_FACTOR``) about the target, and ``|u| <= U_MAX``."""

    def __init__(self, model: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], *, horizon: int = 15,
                 samples: int = 256, sigma: float = 3.0, temperature: float = 1.0, iterations: int = 1,
                 seed: int = 0) -> None:
        self.model = model
        self.q = torch.tensor(Q_STAGE, dtype=torch.float32)
        self.r = torch.tensor(R_STAGE, dtype=torch.float32)
        super().__init__(self._cost, n_u=2, horizon=horizon, samples=samples, sigma=sigma,
                         temperature=temperature, iterations=iterations, u_max=U_MAX, seed=seed)

    def _cost(self, x0: torch.Tensor, us: torch.Tensor, xd: torch.Tensor) -> torch.Tensor:
        xs = x0.expand(self.K, 5)
        pose = torch.zeros(self.K, 3)
        cost = torch.zeros(self.K)
        for k in range(self.H):
            z = torch.cat([xs, pose], -1)
            cost += ((z - xd) ** 2 * self.q).sum(-1) + (us[:, k] ** 2 * self.r).sum(-1)
            xn = self.model(xs, us[:, k])
            dxy = DT * us[:, k] - (xn[:, 0:2] - xs[:, 0:2])
            c, s = torch.cos(pose[:, 2]), torch.sin(pose[:, 2])
            pose = torch.stack([pose[:, 0] + c * dxy[:, 0] - s * dxy[:, 1],
                                pose[:, 1] + s * dxy[:, 0] + c * dxy[:, 1], pose[:, 2] + DT * xn[:, 4]], -1)
            xs = xn
        z = torch.cat([xs, pose], -1)
        cost += QN_FACTOR * ((z - xd) ** 2 * self.q).sum(-1)
        return cost

    def __call__(self, x: np.ndarray, target: np.ndarray) -> np.ndarray:
        xd = torch.as_tensor(_x_des(target), dtype=torch.float32)
        return self.plan(x, xd).numpy().astype(np.float64)


def _mppi_mlp(ctx: dict[str, Any]) -> Any:
    return MPPI(ctx["mlp"], **ctx["mppi"])


#: name -> factory(context) of a controller ``(x, target) -> u`` (None: no input)
CONTROLLERS: dict[str, Callable[[dict[str, Any]], Any]] = {
    "no input": lambda ctx: None,
    "C3, learned LCS (violation loss)": _c3_learned("violation_n20000"),
    "C3, learned LCS (prediction loss)": _c3_learned("prediction_n20000"),
    "C3, hand-written LCS": _c3_hand,
    "C3 (defaults), learned LCS (violation loss)": _c3_learned("violation_n20000", defaults=True),
    "C3 (defaults), learned LCS (prediction loss)": _c3_learned("prediction_n20000", defaults=True),
    "C3 (defaults), hand-written LCS": lambda ctx: _c3_hand(ctx, defaults=True),
    "C3 (defaults, penalize_input_change), learned LCS (violation loss)": _c3_learned(
        "violation_n20000", True, penalize_input_change=True),
    "C3 (defaults, penalize_input_change), learned LCS (prediction loss)": _c3_learned(
        "prediction_n20000", True, penalize_input_change=True),
    "C3 (defaults, polish=0), learned LCS (violation loss)": _c3_learned("violation_n20000", True, polish=0),
    "C3 (defaults, polish=0), learned LCS (prediction loss)": _c3_learned("prediction_n20000", True, polish=0),
    "C3 (defaults, polish=0), hand-written LCS": lambda ctx: _c3_hand(ctx, defaults=True, polish=0),
    "C3 (defaults, polish=0, 20 ADMM iterations), learned LCS (violation loss)": _c3_learned(
        "violation_n20000", True, 20, polish=0),
    "C3 (defaults, polish=0, 20 ADMM iterations), learned LCS (prediction loss)": _c3_learned(
        "prediction_n20000", True, 20, polish=0),
    "QP MPC, affine model": _qp_affine,
    "MPPI, MLP model": _mppi_mlp,
}

MPPI_SETTINGS = {"horizon": 15, "samples": 256, "sigma": 3.0, "temperature": 1.0, "iterations": 1}


# ----------------------------------------------------------------------------- study

def _context(out: str, smoke: bool, n_transitions: int) -> dict[str, Any]:
    """The fitted affine and MLP models (cached under ``out``), and a cache of built C3s."""
    cache = os.path.join(out, "pusher_closed_loop_cache" + ("_smoke" if smoke else ""))
    os.makedirs(cache, exist_ok=True)
    w_path = os.path.join(cache, f"affine_{n_transitions}.npz")
    mlp_path = os.path.join(cache, f"mlp_{n_transitions}.pt")
    iterations = 200 if smoke else 6000
    if os.path.exists(w_path) and os.path.exists(mlp_path):
        W = np.load(w_path)["W"]
        blob = torch.load(mlp_path)
        mlp = MLPDynamics({k: np.zeros(5 if k != "su" else 2) for k in ("mx", "sx", "su", "my", "sy")})
        mlp.load_state_dict(blob["state"])
        val = blob["val"]
    else:
        tr = sample_transitions(n_transitions, seed=0)
        W = AffineModel.fit(tr.x, tr.u, tr.x_next).W
        mlp, val = fit_mlp_dynamics(tr.x, tr.u, tr.x_next, iterations=iterations)
        np.savez(w_path, W=W)
        torch.save({"state": mlp.state_dict(), "val": val}, mlp_path)
    mlp.eval()
    return {"affine_W": W, "mlp": mlp, "mlp_val": val, "n_transitions": n_transitions, "cache": {},
            "mppi": dict(MPPI_SETTINGS, samples=64 if smoke else MPPI_SETTINGS["samples"])}


def simulate(ctrl: Callable[[np.ndarray, np.ndarray], np.ndarray] | None, start: np.ndarray, steps: int
             ) -> dict[str, np.ndarray]:
    """One run in MuJoCo from ``start`` (a row of :func:`starts`): states, world poses, inputs."""
    sim = PusherSlider()
    sim.reset(TOUCH - float(start[0]), float(start[1]))
    origin = np.array([0.0, 0.0, float(start[2])])
    goal = np.asarray(start[3:6], dtype=np.float64)

    def world() -> np.ndarray:
        return compose(origin, sim.pose)

    xs, poses, us = [sim.state], [world()], []
    for _ in range(steps):
        x, pose = xs[-1], poses[-1]
        u = np.zeros(2) if ctrl is None else np.clip(np.asarray(ctrl(x, to_local(pose, goal)), dtype=np.float64),
                                                       -U_MAX, U_MAX)
        if not np.isfinite(u).all():
            u = np.zeros(2)
        x_next, _, _ = sim.step(u)
        xs.append(x_next)
        poses.append(world())
        us.append(u)
    return {"x": np.array(xs), "pose": np.array(poses), "u": np.array(us)}


def run_one(name: str, ctx: dict[str, Any], start: np.ndarray, steps: int) -> dict[str, Any]:
    """One closed-loop run of controller ``name`` from ``start`` in MuJoCo (:func:`simulate`)
    and its record."""
    ctrl = CONTROLLERS[name](ctx)
    timed = harness.Timed(ctrl)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run = simulate(None if ctrl is None else timed, start, steps)
    pf, goal = run["pose"][-1], start[3:6]
    pos_err = float(np.linalg.norm(pf[:2] - goal[:2]))
    head_err = abs(wrap_angle(pf[2] - goal[2]))
    rec = {"controller": name, "start_params": [float(v) for v in start], "steps": steps,
           "success": bool(pos_err <= POS_TOL and head_err <= HEADING_TOL),
           "final_position_error": pos_err, "final_heading_error": head_err,
           "min_position_error": float(np.linalg.norm(run["pose"][:, :2] - goal[:2], axis=1).min()),
           "final_abs_p_y": float(abs(run["x"][-1, 1])),
           "ms_per_step_median": 0.0,
           "max_abs_u": float(np.abs(run["u"]).max()),
           "path": [[round(float(p[0]), 3), round(float(p[1]), 3), round(float(p[2]), 4)] for p in run["pose"][::2]]}
    rec.update(timed.summary())
    return rec


def main(argv: list[str] | None = None) -> int:
    """The study, with one BLAS thread (C3's constructor solves dense KKT systems)."""
    with threadpool_limits(1):
        return _main(argv)


def _main(argv: list[str] | None = None) -> int:
    global MODELS  # the factories read the learned models from here
    ap = argparse.ArgumentParser(description="C3 and baselines pushing the MuJoCo pusher-slider to a goal pose.")
    ap.add_argument("--out", default=os.path.join("studies", "results", "control"))
    ap.add_argument("--starts", type=int, default=50)
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--transitions", type=int, default=20000)
    ap.add_argument("--only", nargs="*", default=None, help="controller names (default all)")
    ap.add_argument("--smoke", action="store_true", help="2 starts, 0.5 s runs, a small MLP: a quick check")
    ap.add_argument("--models", default=MODELS, help=f"the learned LCSs' folder (default {MODELS}: the pusher study's)")
    ap.add_argument("--tag", default=None,
                    help="another draw of the learned models (with --models): runs and report as "
                         "pusher_closed_loop_<tag>.*, and a column per tag in the main report's seed table")
    args = ap.parse_args(argv)
    MODELS = args.models
    torch.set_num_threads(1)
    if args.smoke:
        args.starts, args.seconds, args.transitions = 2, 0.5, 1000
    os.makedirs(args.out, exist_ok=True)
    steps = int(round(args.seconds / DT))
    names = list(CONTROLLERS) if not args.only else args.only
    t0 = time.perf_counter()
    records, ctx = harness.run_units(
        os.path.join(args.out, "pusher_closed_loop" + (f"_{args.tag}" if args.tag else "") + ".jsonl"), names,
        starts(args.starts), steps,
        lambda: _context(args.out, args.smoke, args.transitions),
        lambda name, ctx, st: run_one(name, ctx, st, steps),
        lambda rec: (f"success={rec['success']} pos {rec['final_position_error']:.2f} cm "
                     f"head {rec['final_heading_error']:.3f} rad {rec['ms_per_step_median']:.2f} ms"))
    if ctx is None:  # every run was done: the cached models, for the report's description
        ctx = _context(args.out, args.smoke, args.transitions)
    write_report(records, names, args, steps, time.perf_counter() - t0, ctx)
    return 0


if __name__ == "__main__":
    sys.exit(main())
