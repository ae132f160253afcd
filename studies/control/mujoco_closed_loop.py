r"""C3 and other model-based controllers, closed in MuJoCo: the cart-pole between soft walls of
:mod:`studies.physics.plant`.

Task (as :mod:`studies.physics.mpc_example`): the pole starts tilted towards a wall, some starts
already falling, and the controller must bring it upright, off the walls, with ``|u| <= 4`` N (every
controller's output is clipped to it), control period 0.04 s, 4 s per run. A run succeeds as
:func:`studies.physics.mpc_example.success` says: ``|theta| <= 0.8`` rad throughout and, over the
last second, ``|theta| < 0.1`` rad and no wall contact.

Random starts (seeded, ``seed = 0``): a side ``s = +-1`` with equal odds, then
``x_c ~ U[-0.1, 0.1]`` m, ``theta = s U[0.2, 0.3]`` rad, ``x_c' = s U[0, 0.3]`` m/s,
``theta' = s U[0.5, 1.5]`` rad/s (a box that holds every one of ``SCENARIOS``).

Controllers (all with the stage weights ``Q = diag(5, 20, 0.5, 0.5)`` of ``mpc_example``):

- ``no input``;
- ``C3, learned LCS n_lam=8, free-mode QN``: :class:`lcs_cvx.control.C3` (``"c3+"``, horizon 10,
  10 ADMM iterations, default ``G``, ``U``, ``R = 0.1``) on ``lcs_violation_nlam8.npz``, with
  ``QN`` the Riccati solution of the free mode ``lam = 0`` (``A``, ``B``), which is not the learned
  model's dynamics at the origin: its ``lam`` are partly hidden units, several active there;
- ``C3, learned LCS n_lam=8, active-mode QN``: the same with ``R = 1`` and ``QN = "dare"``, the
  Riccati solution of the learned LCS's affine dynamics *in the contact mode active at the
  target* (:func:`lcs_cvx.control.costs.mode_dynamics`; equal to this study's
  :func:`active_mode_dynamics` to 1e-13);
- ``C3, learned LCS n_lam=2, active-mode QN``: the same on ``lcs_violation_nlam2.npz`` with
  ``R = 3`` (the best learned model found for C3, see the report);
- ``C3, hand-written LCS``: the cart-pole linearised about the upright pole with the plant's
  masses, lengths, damping, wall positions and wall stiffness (:func:`handwritten_lcs`), ``R = 0.3``,
  ``QN = "dare"``, default ``G``, ``U``;
- ``C3 (defaults), ...``: C3 with the package's defaults (projection ``"auto"``, ``QN = "dare"``,
  default ``G``, ``U``) on the learned ``n_lam`` = 8, 4, 2 models and the hand-written LCS,
  ``R = 1`` and the actuator's limit as ``u_bounds`` (inside the QP step); ``C3 (defaults,
  polish=0), ...``: the same without the polish (the ADMM's plan as it is); ``C3 (defaults,
  penalize_input_change), ...``: the same with the input cost measured from the previous plan;
  ``C3 (defaults, scale_lcs), ...``: the same with the ADMM on the rescaled ``lam``;
- ``mode-sequence MPC, learned LCS n_lam=8``: :class:`studies.physics.mpc_example.LCSMPC`;
- ``QP MPC, affine model``: the same QP MPC on an affine least-squares fit (an LCS whose one
  dummy ``lam`` never activates, so the QP is the plain linear MPC with ``|u| <= 4``);
- ``MPPI, MLP model``: sampling MPC (MPPI, :class:`MPPI`) on a small MLP of the dynamics
  (:func:`fit_mlp_dynamics`); the affine and MLP models learn from ``--transitions`` samples of
  :func:`studies.physics.plant.sample_transitions` (the physics study's sampling, seed 0).

One JSON line per finished run goes to ``OUT/mujoco_closed_loop.jsonl`` (a rerun skips the runs
already there); ``OUT/mujoco_closed_loop.md`` and ``OUT/mujoco_closed_loop.png`` are written from
all of them at the end. The fitted affine/MLP models are cached in ``OUT/mujoco_closed_loop_cache/``.

    python -m studies.control.mujoco_closed_loop --out studies/results/control [--starts 50] [--smoke]
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.linalg
import torch
from threadpoolctl import threadpool_limits

import lcs_cvx
from lcs_cvx import LCS, solve_lcp
from lcs_cvx.control import C3
from lcs_cvx.control.costs import dare
from studies.physics.models import AffineModel
from studies.physics.mpc_example import LCSMPC, simulate, success
from studies.physics.plant import Physics, sample_transitions

from . import harness
from .dynamics import MLPDynamics, fit_mlp_dynamics

__all__ = ["starts", "handwritten_lcs", "active_mode_dynamics", "fit_mlp_dynamics", "MPPI", "CONTROLLERS", "main"]

MODELS = os.path.join("studies", "results", "physics", "models")
Q_STAGE = (5.0, 20.0, 0.5, 0.5)
U_MAX = 4.0
MACHINE = "2-core x86-64 VM, 1 torch thread"
DATE = "2026-11-25 (the C3 rows 2026-11-27, the C3 (defaults) rows and their options 2026-11-28)"


def starts(n: int, seed: int = 0) -> np.ndarray:
    """``n`` initial states ``(n, 4)`` tilted towards a wall (the box of the module docstring)."""
    rng = np.random.default_rng(seed)
    out = np.empty((n, 4))
    for i in range(n):
        s = 1.0 if rng.random() < 0.5 else -1.0
        out[i] = (rng.uniform(-0.1, 0.1), s * rng.uniform(0.2, 0.3), s * rng.uniform(0.0, 0.3),
                  s * rng.uniform(0.5, 1.5))
    return out


# ----------------------------------------------------------------------------- models

def handwritten_lcs(physics: Any = None, dt: float | None = None) -> Any:
    r"""The plant as an LCS written from :class:`studies.physics.plant.Physics`: the cart-pole
    (uniform rod, hinge at the cart) linearised about the upright pole, discretised exactly
    (zero-order hold on ``u`` and ``lam`` over ``dt``), with the two walls as complementarity.

    ``lam = (lam_left, lam_right)`` the wall forces on the tip (N), acting along ``J = (1, L)``
    (``d tip / d q`` at ``theta = 0``). MuJoCo's soft wall gives the tip a spring of stiffness
    ``k = stiffness / d`` (s^-2, mass-normalised) and damping ``b = damping / d``, so the force is
    ``m_eff (k r + b r')`` on a penetration ``r``, ``m_eff = 1 / (J M^{-1} J^T)``:
    ``0 <= lam_left _|_ (tip + w) + (b / k) tip' + lam_left / (m_eff k) >= 0`` (and mirrored on
    the right), ``w = wall_distance - tip_radius``, ``tip = x_c + L theta``. ``E = 0``."""
    p = physics or Physics()
    dt = p.control_period if dt is None else dt
    mc, mp, L, g = p.cart_mass, p.pole_mass, p.pole_length, 9.81
    lc, Ih = L / 2, mp * L**2 / 3
    M = np.array([[mc + mp, mp * lc], [mp * lc, Ih]])
    Mi = np.linalg.inv(M)
    K = np.array([[0.0, 0.0], [0.0, mp * g * lc]])  # gravity, linearised
    Dmp = np.diag([p.cart_damping, p.hinge_damping])
    J = np.array([1.0, L])
    Ac = np.block([[np.zeros((2, 2)), np.eye(2)], [Mi @ K, -Mi @ Dmp]])
    Bc = np.concatenate([np.zeros(2), Mi @ np.array([1.0, 0.0])])[:, None]
    Cc = np.concatenate([np.zeros((2, 2)), Mi @ np.stack([J, -J], 1)])
    n = 4 + 1 + 2
    big = np.zeros((n, n))
    big[:4, :4], big[:4, 4:5], big[:4, 5:] = Ac, Bc, Cc
    Phi = scipy.linalg.expm(big * dt)
    A, B, C = Phi[:4, :4], Phi[:4, 4:5], Phi[:4, 5:]
    d_imp = p.wall_impedance
    k, b = p.wall_stiffness / d_imp, p.wall_damping / d_imp
    m_eff = 1.0 / float(J @ Mi @ J)
    w = p.wall_distance - p.tip_radius
    tip = np.array([1.0, L, b / k, b / k * L])  # tip + (b / k) tip'
    D = np.stack([tip, -tip])
    F = np.eye(2) / (m_eff * k)
    return LCS.from_matrices(A=A, B=B, C=C, d=np.zeros(4), D=D, E=np.zeros((2, 1)), F=F, c=np.array([w, w]))


def active_mode_dynamics(matrices: dict[str, np.ndarray], x: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray]:
    """``(A_S, B_S)``: the LCS's affine dynamics in the mode ``S`` active at ``x`` (default the
    origin, ``u = 0``): ``lam_S = -F_SS^{-1} (D_S x + E_S u + c_S)``."""
    m = {k: np.asarray(v, dtype=np.float64) for k, v in matrices.items()}
    x = np.zeros(m["A"].shape[0]) if x is None else np.asarray(x, dtype=np.float64)
    lam = solve_lcp(m["F"], (m["D"] @ x + m["c"])[None, :]).lam.numpy()[0]
    S = lam > 1e-9
    if not S.any():
        return m["A"], m["B"]
    Kc = m["C"][:, S] @ np.linalg.inv(m["F"][np.ix_(S, S)])
    return m["A"] - Kc @ m["D"][S], m["B"] - Kc @ m["E"][S]


def affine_lcs_matrices(W: np.ndarray) -> dict[str, np.ndarray]:
    """An affine least-squares fit ``x' = [x, u, 1] W`` as LCS matrices with one dummy ``lam``
    that never activates (``D = E = 0``, ``F = 1``, ``c = 1``, ``C = 0``)."""
    n_x = W.shape[1]
    n_u = W.shape[0] - n_x - 1
    return {"A": W[:n_x].T, "B": W[n_x:n_x + n_u].T, "C": np.zeros((n_x, 1)), "d": W[-1],
            "D": np.zeros((1, n_x)), "E": np.zeros((1, n_u)), "F": np.eye(1), "c": np.ones(1)}


class MPPI(harness.MPPI):
    """MPPI (:class:`studies.control.harness.MPPI`) on a batched model ``x' = f(x, u)`` (torch)
    with the cost ``sum_k x_k' Q x_k + r u_k^2 + x_N' (terminal Q) x_N`` and ``|u| <= u_max``."""

    def __init__(self, model: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], *, horizon: int = 15,
                 samples: int = 256, sigma: float = 2.0, temperature: float = 1.0, iterations: int = 1,
                 q: tuple[float, ...] = Q_STAGE, r: float = 0.01, terminal: float = 10.0, u_max: float = U_MAX,
                 seed: int = 0) -> None:
        self.model = model
        self.q = torch.tensor(q, dtype=torch.float32)
        self.r, self.terminal = r, terminal
        super().__init__(self._cost, n_u=0, horizon=horizon, samples=samples, sigma=sigma,
                         temperature=temperature, iterations=iterations, u_max=u_max, seed=seed)

    def _cost(self, x0: torch.Tensor, us: torch.Tensor) -> torch.Tensor:
        xs = x0.expand(self.K, 4)
        cost = torch.zeros(self.K)
        for k in range(self.H):
            cost += (xs**2 * self.q).sum(-1) + self.r * us[:, k] ** 2
            xs = self.model(xs, us[:, k:k + 1])
        cost += self.terminal * (xs**2 * self.q).sum(-1)
        return cost

    def __call__(self, x: np.ndarray) -> float:
        return float(self.plan(x))


# ----------------------------------------------------------------------------- controllers

class C3Wrapper:
    """``u = clip(C3(x)[0])`` (NumPy in, float out), recording each plan's complementarity
    violation and its gap to the model's own rollout (``Plan.gap``)."""

    def __init__(self, ctrl: Any, u_max: float = U_MAX) -> None:
        self.ctrl, self.u_max, self.violation, self.gap = ctrl, u_max, [], []

    def __call__(self, x: np.ndarray) -> float:
        u = self.ctrl(torch.from_numpy(np.asarray(x, dtype=np.float64)))
        self.violation.append(float(self.ctrl.last_plan.complementarity))
        self.gap.append(float(self.ctrl.last_plan.gap))
        return float(np.clip(float(u[0]), -self.u_max, self.u_max))


def _c3_learned(name: str, R: float, active_qn: bool) -> Callable[[dict[str, Any]], Any]:
    def make(ctx: dict[str, Any]) -> Any:
        model = lcs_cvx.load_model(os.path.join(MODELS, f"lcs_{name}.npz"))
        qn: Any = "dare"  # the mode active at the target
        if not active_qn:
            m = model.to_matrices()
            qn = dare(m["A"], m["B"], np.diag(Q_STAGE), np.array([[R]]))
        return C3Wrapper(C3(model, 10, Q=list(Q_STAGE), R=[R], QN=qn, projection="c3+", polish=0))
    return make


def _c3_hand(ctx: dict[str, Any]) -> Any:
    return C3Wrapper(C3(handwritten_lcs(), 10, Q=list(Q_STAGE), R=[0.3], QN="dare", projection="c3+", polish=0))


def _c3_defaults(model: str | None, **options: Any) -> Callable[[dict[str, Any]], Any]:
    """C3 with the package's defaults (projection ``"auto"``, ``QN = "dare"``, default ``G``,
    ``U``, 10 ADMM iterations) on a learned model (``lcs_<model>.npz``; None: the hand-written
    LCS), ``R = 1`` and the actuator's limit as ``u_bounds``; ``options``: other C3 options."""
    def make(ctx: dict[str, Any]) -> Any:
        lcs = handwritten_lcs() if model is None else lcs_cvx.load_model(os.path.join(MODELS, f"lcs_{model}.npz"))
        return C3Wrapper(C3(lcs, 10, Q=list(Q_STAGE), R=[1.0], u_bounds=(-U_MAX, U_MAX), **options))
    return make


def _lcsmpc_learned(ctx: dict[str, Any]) -> Any:
    return LCSMPC(lcs_cvx.load_model(os.path.join(MODELS, "lcs_violation_nlam8.npz")).to_matrices())


def _qp_affine(ctx: dict[str, Any]) -> Any:
    return LCSMPC(affine_lcs_matrices(ctx["affine_W"]), use_contacts=False)


def _mppi_mlp(ctx: dict[str, Any]) -> Any:
    return MPPI(ctx["mlp"], **ctx["mppi"])


#: name -> factory(context) of a controller ``x -> u`` (None: no input)
CONTROLLERS: dict[str, Callable[[dict[str, Any]], Any]] = {
    "no input": lambda ctx: None,
    "C3, learned LCS n_lam=8, free-mode QN": _c3_learned("violation_nlam8", 0.1, False),
    "C3, learned LCS n_lam=8, active-mode QN": _c3_learned("violation_nlam8", 1.0, True),
    "C3, learned LCS n_lam=2, active-mode QN": _c3_learned("violation_nlam2", 3.0, True),
    "C3, hand-written LCS": _c3_hand,
    "C3 (defaults), learned LCS n_lam=8": _c3_defaults("violation_nlam8"),
    "C3 (defaults), learned LCS n_lam=4": _c3_defaults("violation_nlam4"),
    "C3 (defaults), learned LCS n_lam=2": _c3_defaults("violation_nlam2"),
    "C3 (defaults), hand-written LCS": _c3_defaults(None),
    "C3 (defaults, polish=0), learned LCS n_lam=8": _c3_defaults("violation_nlam8", polish=0),
    "C3 (defaults, polish=0), learned LCS n_lam=4": _c3_defaults("violation_nlam4", polish=0),
    "C3 (defaults, polish=0), learned LCS n_lam=2": _c3_defaults("violation_nlam2", polish=0),
    "C3 (defaults, polish=0), hand-written LCS": _c3_defaults(None, polish=0),
    "C3 (defaults, penalize_input_change), learned LCS n_lam=8": _c3_defaults("violation_nlam8",
                                                                             penalize_input_change=True),
    "C3 (defaults, penalize_input_change), learned LCS n_lam=4": _c3_defaults("violation_nlam4",
                                                                             penalize_input_change=True),
    "C3 (defaults, penalize_input_change), learned LCS n_lam=2": _c3_defaults("violation_nlam2",
                                                                             penalize_input_change=True),
    "C3 (defaults, scale_lcs), learned LCS n_lam=8": _c3_defaults("violation_nlam8", scale_lcs=True),
    "C3 (defaults, scale_lcs), learned LCS n_lam=4": _c3_defaults("violation_nlam4", scale_lcs=True),
    "C3 (defaults, scale_lcs), learned LCS n_lam=2": _c3_defaults("violation_nlam2", scale_lcs=True),
    "mode-sequence MPC, learned LCS n_lam=8": _lcsmpc_learned,
    "QP MPC, affine model": _qp_affine,
    "MPPI, MLP model": _mppi_mlp,
}

MPPI_SETTINGS = {"horizon": 15, "samples": 512, "sigma": 2.0, "temperature": 0.3, "iterations": 1}


# ----------------------------------------------------------------------------- study

def _context(out: str, smoke: bool, n_transitions: int) -> dict[str, Any]:
    """The fitted affine and MLP models (cached under ``out``)."""
    cache = os.path.join(out, "mujoco_closed_loop_cache" + ("_smoke" if smoke else ""))
    os.makedirs(cache, exist_ok=True)
    data_path = os.path.join(cache, f"transitions_{n_transitions}.npz")
    if os.path.exists(data_path):
        z = np.load(data_path)
        x, u, xn = z["x"], z["u"], z["x_next"]
    else:
        tr = sample_transitions(n_transitions, seed=0)
        x, u, xn = tr.x, tr.u, tr.x_next
        np.savez(data_path, x=x, u=u, x_next=xn)
    W = AffineModel.fit(x, u, xn).W
    mlp_path = os.path.join(cache, f"mlp_{n_transitions}.pt")
    iterations = 200 if smoke else 6000
    if os.path.exists(mlp_path):
        blob = torch.load(mlp_path)
        mlp = MLPDynamics({k: np.zeros(4 if k != "su" else 1) for k in ("mx", "sx", "su", "my", "sy")})
        mlp.load_state_dict(blob["state"])
        val = blob["val"]
    else:
        mlp, val = fit_mlp_dynamics(x, u, xn, iterations=iterations)
        torch.save({"state": mlp.state_dict(), "val": val}, mlp_path)
    mlp.eval()
    return {"affine_W": W, "mlp": mlp, "mlp_val": val, "n_transitions": len(x),
            "mppi": dict(MPPI_SETTINGS, samples=64 if smoke else MPPI_SETTINGS["samples"])}


def run_one(name: str, ctx: dict[str, Any], x0: np.ndarray, steps: int, last: int) -> dict[str, Any]:
    """One closed-loop run of controller ``name`` from ``x0`` in MuJoCo
    (:func:`studies.physics.mpc_example.simulate`) and its record."""
    ctrl = CONTROLLERS[name](ctx)
    timed = harness.Timed(ctrl)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run = simulate(None if ctrl is None else lambda x: float(timed(x)), x0, steps)
    xf = run["x"][-1]
    rec = {"controller": name, "x0": [float(v) for v in x0], "steps": steps,
           "success": success(run, last), "final_abs_theta": float(abs(xf[1])), "final_abs_x_c": float(abs(xf[0])),
           "final_error": float(np.linalg.norm(xf)), "max_abs_theta": float(np.abs(run["x"][:, 1]).max()),
           "contact_steps_last": int(run["contact"][-last:].any(axis=1).sum()),
           "ms_per_step_median": 0.0, "max_abs_u": float(np.abs(run["u"]).max())}
    rec.update(timed.summary())
    return rec


def main(argv: list[str] | None = None) -> int:
    """The study, with one BLAS thread: C3's constructor solves dense KKT systems (one per ADMM
    level), and with BLAS threads competing for the two cores it took 2 to 20 s instead of 0.1 s."""
    with threadpool_limits(1):
        return _main(argv)


def _main(argv: list[str] | None = None) -> int:
    global MODELS  # the factories read the learned models from here
    ap = argparse.ArgumentParser(description="C3 and baselines in closed loop on the MuJoCo cart-pole with walls.")
    ap.add_argument("--out", default=os.path.join("studies", "results", "control"))
    ap.add_argument("--starts", type=int, default=50)
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--transitions", type=int, default=20000)
    ap.add_argument("--only", nargs="*", default=None, help="controller names (default all)")
    ap.add_argument("--smoke", action="store_true", help="2 starts, 0.8 s runs, a small MLP: a quick check")
    ap.add_argument("--models", default=MODELS,
                    help=f"the learned LCSs' folder (default {MODELS}: the physics study's)")
    ap.add_argument("--tag", default=None,
                    help="another draw of the learned models (with --models): runs and report as "
                         "mujoco_closed_loop_<tag>.*, and a row per tag in the main report's seed table")
    args = ap.parse_args(argv)
    MODELS = args.models
    torch.set_num_threads(1)
    if args.smoke:
        args.starts, args.seconds, args.transitions = 2, 0.8, 1000
    os.makedirs(args.out, exist_ok=True)

    period = Physics().control_period
    steps = int(round(args.seconds / period))
    last = min(int(round(1.0 / period)), steps)
    names = list(CONTROLLERS) if not args.only else args.only
    t0 = time.perf_counter()
    records, ctx = harness.run_units(
        os.path.join(args.out, _stem(args) + ".jsonl"), names, starts(args.starts), steps,
        lambda: _context(args.out, args.smoke, args.transitions),
        lambda name, ctx, x0: run_one(name, ctx, x0, steps, last),
        lambda rec: (f"success={rec['success']} |θ_T|={rec['final_abs_theta']:.3f} "
                     f"{rec['ms_per_step_median']:.2f} ms"))
    if ctx is None and not args.tag:  # every run was there: the report still describes the models (cached)
        ctx = _context(args.out, args.smoke, args.transitions)
    write_report(records, names, args, steps, last, time.perf_counter() - t0, ctx)
    return 0


def _stem(args: Any) -> str:
    return "mujoco_closed_loop" + (f"_{args.tag}" if args.tag else "")


#: the rows whose spread over draws of the learned models the seed table gives
SEED_ROWS = ("C3 (defaults), learned LCS n_lam=8", "C3 (defaults), learned LCS n_lam=4",
             "C3 (defaults), learned LCS n_lam=2")


def _seeds(args: Any, steps: int) -> list[str]:
    """The seed table of the main report (:func:`studies.control.harness.draws_table`)."""
    if args.tag or args.smoke:
        return []
    return harness.draws_table(
        args.out, "mujoco_closed_loop", SEED_ROWS, steps, summarise,
        "The same `C3 (defaults)` rows on LCSs the physics study learned from other seeds of its fits "
        "(`python -m studies.physics.cartpole_walls --config studies/configs/physics_cartpole.toml --out "
        "studies/results/physics_seedsAB --seeds A B --losses violation`, then this study with `--models "
        "studies/results/physics_seedsAB/models --tag seedsAB`): each draw keeps, per `n_lam`, the restart "
        "of lowest validation error among its seeds and both starts.")


def summarise(records: list[dict[str, Any]], names: list[str]) -> dict[str, dict[str, float]]:
    out = {}
    for n in names:
        rs = [r for r in records if r["controller"] == n]
        if not rs:
            continue
        out[n] = {"runs": len(rs), "success": sum(r["success"] for r in rs),
                  "final_abs_theta": float(np.median([r["final_abs_theta"] for r in rs])),
                  "final_abs_x_c": float(np.median([r["final_abs_x_c"] for r in rs])),
                  "final_error": float(np.median([r["final_error"] for r in rs])),
                  "ms": float(np.median([r["ms_per_step_median"] for r in rs])),
                  **harness.plan_medians(rs)}
    return out


def write_report(records: list[dict[str, Any]], names: list[str], args: Any, steps: int, last: int,
                 wall: float, ctx: dict[str, Any] | None) -> None:
    summ = summarise(records, names)
    cmd = "python -m studies.control.mujoco_closed_loop --out " + args.out + (
        " --smoke" if args.smoke else f" --starts {args.starts}") + (
        f" --models {args.models} --tag {args.tag}" if args.tag else "")
    lines = [
        "# C3 and baselines in closed loop on the MuJoCo cart-pole with soft walls",
        "",
        f"Written by `{cmd}` on {time.strftime('%Y-%m-%d') if args.tag else DATE} ({MACHINE}); the runs are kept "
        f"in `{_stem(args)}.jsonl`"
        + (f" (this invocation ran {wall:.0f} s, skipping the runs already there)." if wall >= 1 else "."),
        "",
        f"**Task.** {args.starts} random starts (seed 0): side `s = ±1`, `x_c ~ U[-0.1, 0.1]` m, "
        "`θ = s U[0.2, 0.3]` rad, `ẋ_c = s U[0, 0.3]` m/s, `θ̇ = s U[0.5, 1.5]` rad/s (the pole "
        "tilted and falling towards a wall; the box holds the six scenarios of "
        "`studies.physics.mpc_example`). "
        f"{steps} control periods of 0.04 s ({steps * 0.04:g} s), every input clipped to |u| ≤ {U_MAX:g} N. "
        f"**Success**: |θ| ≤ 0.8 rad throughout and, over the last {last} periods, |θ| < 0.1 rad and "
        "no wall contact (`studies.physics.mpc_example.success`). Stage weights Q = diag(5, 20, 0.5, 0.5) "
        "for every controller.",
        "",
        "| controller | success | median final \\|θ\\| (rad) | median final \\|x_c\\| (m) | "
        "median final ‖x‖ | median ms per control step | median plan complementarity violation | "
        "median plan gap to the model |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for n, s in summ.items():
        viol = "" if math.isnan(s["violation"]) else f"{s['violation']:.3f}"
        gap = "" if math.isnan(s["gap"]) else f"{s['gap']:.3f}"
        lines.append(f"| {n} | {s['success']}/{s['runs']} ({100 * s['success'] / s['runs']:.0f} %) | "
                     f"{s['final_abs_theta']:.3f} | {s['final_abs_x_c']:.3f} | {s['final_error']:.3f} | "
                     f"{s['ms']:.2f} | {viol} | {gap} |")
    lines += ["", "Time per control step: the controller's call only (not MuJoCo), median over a run, "
              "then median over the runs. Plan gap: `Plan.gap`, the largest difference between the "
              "planned states and the model's own rollout of the plan's inputs.", ""]
    if args.tag:  # another draw of the learned models: its table; the main report discusses them
        lines += ["These models: another draw of the physics study's fits (`--models`); the main report, "
                  "`mujoco_closed_loop.md`, sets them beside its own.", ""]
        with open(os.path.join(args.out, _stem(args) + ".md"), "w") as f:
            f.write("\n".join(lines))
        print("\n".join(lines))
        return
    if ctx is not None:
        lines += [f"The affine and MLP models learn from {ctx['n_transitions']} transitions of "
                  "`studies.physics.plant.sample_transitions` (seed 0); the MLP's held-out error "
                  f"(normalised increment, mean squared) is {ctx['mlp_val']:.4f}. MPPI: "
                  + ", ".join(f"{k} {v}" for k, v in ctx["mppi"].items()) + ".", ""]
    draws = _seeds(args, steps)
    lines += _FINDINGS + _versus_mlp(summ) + ([""] + draws if draws else []) + ["", "The pusher–slider has its own closed-loop study, `pusher_closed_loop.md` "
                                              "(`studies/control/pusher_closed_loop.py`): its learned LCS plans in the slider's "
                                              "frame, so the world pose is appended to the model there."] + ["", "![final |θ| and success per controller](mujoco_closed_loop.png)", ""]
    with open(os.path.join(args.out, _stem(args) + ".md"), "w") as f:
        f.write("\n".join(lines))
    _plot(records, list(summ), os.path.join(args.out, _stem(args) + ".png"))
    print("\n".join(lines))


_FINDINGS = [
    "## C3 with its defaults on the learned LCS",
    "",
    "The `C3 (defaults)` rows: `C3(model, 10, Q=Q, R=[1.0], u_bounds=(-4, 4))`, everything else "
    "the package's default: projection `\"auto\"` (the ADMM with the `\"c3+\"` and the `\"lcp\"` "
    "projections, the plan whose rollout through the model's own LCP costs less), then the polish "
    "(at most three QPs in the contact modes the model visits under the plan's inputs, the plan "
    "applied the one whose model rollout costs least), `QN = \"dare\"` in the mode active at the "
    "target, default `G`, `U`, the input bound inside the QP step on the fast path. On every model, "
    "the learned `n_lam` = 8, 4 and 2 LCSs and the hand-written one, they succeed from every start "
    "at 2.0 to 2.5 ms per control step, and the plans applied are what the models do (median plan "
    "gap 0.000: a polished plan is its model's own rollout).",
    "",
    "The `C3 (defaults, polish=0)` rows are the same controllers without the polish. There the "
    "`n_lam = 2` model parks the cart against the right wall in 28 of 50 starts (median final "
    "|x_c| 0.16 m), and the runs on the `n_lam` = 8 and 4 models end further from the target "
    "(median final |x_c| 0.049 and 0.020 m against 0.002 and 0.005 with it): the ADMM's plan "
    "relies on forces the model does not produce (median gap 0.10 to 0.40), and its inputs are "
    "not the best ones in the contact modes it found. The ADMM finds the modes; the polish finds "
    "the inputs that are optimal in them. (The `polish=0` rows ran on 2026-11-27, before C3's model "
    "LCPs called the compiled kernel directly: their times per step are those of that code.) "
    "(Without the polish, the `n_lam = 2` model's failures "
    "looked like a model error: near the right wall it has no `lam` active and predicts that the "
    "cart stays put; with the polish the same model succeeds from every start.) The `\"lcp\"` "
    "projection sets `lam_k` to the model's own LCP solution at the plan's `(x_k, u_k)`, so the QP "
    "step is pulled towards forces the model produces; the per-unit `\"c3+\"` projection of the "
    "rows below ignores `D x + E u + F lam + c`, which in a learned model (dense `F`, `E` not zero, "
    "`lam` active at the target) is far from any point it proposes.",
    "",
    "DAIRLab/c3's options, measured with the polish: `penalize_input_change=True` (the input cost "
    "measured from the previous plan's inputs) succeeds from every start on the three learned "
    "models too and ends nearest the target (median final ||x|| 0.003, 0.003 and 0.007 against "
    "0.009, 0.012 and 0.015), at the same cost per step, and it did better on the pusher-slider "
    "(`pusher_closed_loop.md`) and on C3's cart-pole (`cartpole_c3.md`) too. It stays an option: it "
    "changes the problem solved (the input cost is measured from the previous plan, not from 0, so a "
    "plan from `ctrl.solve(x0)` and one from `ctrl(x0)` differ), which a user asks for. `scale_lcs=True` "
    "(the ADMM on `lam = s lam_s`, `s = ||A|| / ||C||`, 4.4, 14.5 and 13.7 on the `n_lam` = 8, "
    "4, 2 models) gives the defaults' results to the third digit; without the polish it lost "
    "most starts (12/50, 0/50, 0/50: the default `G` and `U` then weigh forces `s` times larger).",
    "",
    "## What makes C3 with the per-unit projection work, or not, on the learned LCS",
    "",
    "All numbers below come from probes on the six scenarios of `studies.physics.mpc_example` "
    "(4 s runs), before the 50-start runs of the table.",
    "",
    "- **The learned `lam` are not contacts.** The learned LCSs have `lam` active at the upright "
    "origin (`lcs_violation_nlam8`: five of eight; `lcs_violation_nlam2`: one of two), so the "
    "Riccati solution of the *free* mode `lam = 0` is not the terminal cost of the learned "
    "model's dynamics near the target. With it, C3 on the `n_lam = 2` model lets the pole "
    "fall in 4 of 6 scenarios (final |θ| up to 3.9 rad); with `QN` the Riccati solution of the mode "
    "active at the target (`QN = \"dare\"`, which takes that mode) the pole ends upright "
    "(|θ| ≈ 0.015 rad) in every scenario with `R = 3` (in 5 of 6 with `R = 1`). That is the one "
    "change that made C3 do something useful on a learned model.",
    "- **But C3 on the `n_lam = 2` model parks the cart against a wall.** It ends at "
    "x_c ≈ +0.17 m, from either side, the tip touching the right wall, so every run fails the "
    "no-contact part of the test (table: median final |x_c| 0.17 m). At that state the learned "
    "model has no `lam` active and predicts that the state stays put under `u = 0`: the learned "
    "model's wall is not where the plant's is. Horizon 20, `Q` on x_c 50, `R` 1 to 10, or `u_bounds` "
    "(CVXPY path, ~38 ms per step) instead of clipping did not fix it. Warm-starting the ADMM with "
    "the model's own rollout under the previous plan's inputs gave 2 of 6.",
    "- **On the `n_lam = 8` model the ADMM does not reach a complementarity-feasible plan.** Its "
    "primal residual stays at 0.3 to 1.2 and the plans' complementarity violation at ~0.4 "
    "(table: 0.43) with 10, 30 or 60 iterations, and still 0.46 with `rho_scale = 4` and 12 "
    "iterations (consensus weight up to 1.7e7). The planned `lam` go *negative* (-0.2 to -0.46) "
    "where the projection says 0: the projection's `(lam, eta)` is not on the plane "
    "`eta = D x + E u + F lam + c` of any `(x, u)` (the learned `F` is dense, the hidden `lam` "
    "coupled), and the QP step splits the difference between the two targets. The plans then "
    "exploit forces the model would not produce: planned θ falls while the model's own rollout of "
    "the planned inputs rises. C3 fails on this model **even with the learned LCS itself as the "
    "plant and no input bound** (0 of 6), so the failure is C3 on this model, not the model's "
    "error against MuJoCo. Weighting `G` 100:1 on `lam`:`eta` with `U` 1:1 brings the violation "
    "to 0.09, but the pole still rests at θ ≈ 0.21 rad. Scaling `G` (1 to 100) or `U` (weight on "
    "`eta` 1e4, 1 or 0.01) to the learned `lam`'s magnitude, horizon 5 or 20, `QN = 10 Q`, "
    "the active-mode `QN`, or setting the small learned `E` to 0 (so that C3 fixes `lam_0` by the "
    "LCP at `x0`) succeed in 0 of 6 scenarios. So do the `n_lam = 4` and the prediction-loss models "
    "(`n_lam` = 2, 4, 8) with the default or the active-mode `QN`.",
    "- **The `\"qp\"` and `\"miqp\"` projections** with C3's published `G`, `U` (0 on `u`) gave "
    "worse plans on the learned models (violation ~4.8): the learned `E` is not zero, so the "
    "projection could move `u` as far as it liked to reach a contact mode, and the QP step ignored "
    "that `u`; the default `U` now weighs `u` (1000, as `x`) when `E` is not zero. `\"miqp\"` "
    "takes ~24 s per solve with `n_lam = 8`.",
    "- **C3 itself is not the problem on an LCS that is a physical model.** On the hand-written "
    "LCS of the plant (two walls, diagonal `F`, `E = 0`, no `lam` active at the target) C3 with "
    "its default `G`, `U` succeeds in 49 of 50 starts at ~0.7 ms per step, the plans' violation "
    "~0 (`R = 0.3` chosen on the six scenarios: `R = 0.1` gave 4 of 6, the pole swinging past 0.8 rad "
    "on the two fastest starts; `R = 0.1` with horizon 20 gave 6 of 6).",
    "- **The mode-sequence MPC** (`LCSMPC`), which fixes each step's contact mode from the model's "
    "own simulation and solves one QP per guess, succeeds on the same learned `n_lam = 8` LCS in "
    "every start; C3 on it does not. The MPPI's settings were chosen on the six scenarios too "
    "(256 samples: 2 to 3 of 4 at temperatures 0.3 to 3; 512 samples at temperature 0.3: 6 of 6).",
    "",
    "Where C3 on the learned LCS stands against the MLP controller:",
    "",
]


def _versus_mlp(summ: dict[str, dict[str, float]]) -> list[str]:
    """A sentence per C3-on-a-learned-LCS row: whether it beats MPPI on the MLP model."""
    mlp = summ.get("MPPI, MLP model")
    if mlp is None:
        return []
    out = []
    for n, s in summ.items():
        if not (n.startswith("C3, learned") or n.startswith("C3 (defaults), learned")
                or n.startswith("C3 (defaults, polish=0), learned")):
            continue
        verdict = "does not beat" if s["success"] / s["runs"] <= mlp["success"] / mlp["runs"] else "beats"
        out.append(f"- **{n}** {verdict} the MLP controller: {s['success']}/{s['runs']} successes against "
                   f"MPPI's {mlp['success']}/{mlp['runs']} (it is {mlp['ms'] / max(s['ms'], 1e-9):.0f}x faster "
                   "per control step).")
    return out


def _plot(records: list[dict[str, Any]], names: list[str], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(14, 0.5 * len(names) + 2.5))
    rng = np.random.default_rng(0)
    for j, n in enumerate(names):
        rs = [r for r in records if r["controller"] == n]
        th = np.array([max(r["final_abs_theta"], 1e-4) for r in rs])
        ok = np.array([r["success"] for r in rs], dtype=bool)
        y = j + rng.uniform(-0.2, 0.2, len(rs))
        axes[0].scatter(th[ok], y[ok], s=10, color="tab:green")
        axes[0].scatter(th[~ok], y[~ok], s=10, color="tab:red", marker="x")
    axes[0].set_yticks(range(len(names)), names)
    axes[0].set_xscale("log")
    axes[0].axvline(0.1, color="gray", lw=1)
    axes[0].set_xlabel("final |θ| (rad), log scale; 0.1 in grey; green: success, red x: failure")
    rates = [np.mean([r["success"] for r in records if r["controller"] == n]) for n in names]
    axes[1].barh(range(len(names)), rates)
    axes[1].set_yticks(range(len(names)), names)
    axes[1].set_xlim(0, 1)
    axes[1].set_xlabel("success rate")
    axes[0].set_ylim(len(names) - 0.5, -0.5)
    axes[1].invert_yaxis()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
