r"""Control hook: a short-horizon MPC on a learned LCS, run on the MuJoCo cart-pole with walls.

The model is an LCS learned by the physics study (physical units, ``lcs_cvx.load_model``):
``x' = A x + B u + C lam + d``, ``0 <= lam _|_ w = D x + E u + F lam + c >= 0``. For a fixed
contact mode ``s_k in {0, 1}^{n_lam}`` at each step of the horizon the LCS step is affine, and
the horizon problem is a QP (CVXPY, Clarabel), declared once with ``x0`` and the modes as
parameters::

    min  sum_k (x_k - x_ref)' Q (x_k - x_ref) + r u_k^2 + x_N' Q_N x_N + rho * 1'sigma
    s.t. x_0 = x0,  x_{k+1} = A x_k + B u_k + C lam_k + d,  |u_k| <= u_max,
         w_k = D x_k + E u_k + F lam_k + c,
         0 <= lam_k <= M s_k                 (lam_i = 0 off the mode)
         -sigma_k <= w_k <= M (1 - s_k) + sigma_k,  sigma_k >= 0   (w_i = 0 on it, >= 0 off it)

``sigma`` relaxes the mode's validity so that a wrong guess stays feasible (at a cost
``rho``). Should Clarabel (then OSQP) fail on a QP, the previous plan, shifted, is used. The modes come from simulating the LCS under the previous input sequence (shifted);
after each QP the LCS is re-simulated under its inputs and, if the modes changed, the QP is
solved again (at most ``mode_iterations`` times). The first input is applied to MuJoCo for one
control period (zero-order hold), and the loop repeats.

The task: the pole starts tilted towards a wall (it falls onto the wall if nothing is done) and
the controller must bring it upright and keep it there with a limited force ``|u| <= u_max``.
Three controllers are compared in MuJoCo: no input, the same MPC with the contacts removed from
the model (``C = 0``: the LCS's free mode only), and the MPC on the full learned LCS. A run
succeeds when the pole never passes ``|theta| = 0.8`` rad and, over the last second,
``|theta| < 0.1`` rad and the tip touches no wall.

    python -m studies.physics.mpc_example [--model studies/results/physics/models/lcs_violation_nlam8.npz]
        [--out studies/results/physics] [--horizon 10] [--seconds 4]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["LCSMPC", "MPCSettings", "simulate", "main"]


@dataclass(frozen=True)
class MPCSettings:
    horizon: int = 10
    u_max: float = 4.0
    q: tuple[float, float, float, float] = (5.0, 20.0, 0.5, 0.5)  # x_c, theta, x_c', theta'
    r: float = 0.01
    terminal: float = 10.0  # Q_N = terminal * Q
    rho: float = 1e3  # penalty on the mode-validity slack
    big_m: float = 1e3
    mode_iterations: int = 3


class LCSMPC:
    """The mode-fixed QP of the module docstring for one LCS (matrices in physical units)."""

    def __init__(self, matrices: dict[str, np.ndarray], settings: MPCSettings = MPCSettings(),
                 use_contacts: bool = True) -> None:
        import cvxpy as cp

        self.m = {k: np.asarray(v, dtype=np.float64) for k, v in matrices.items()}
        if not use_contacts:
            self.m["C"] = np.zeros_like(self.m["C"])
        self.settings, self.use_contacts = settings, use_contacts
        A, B, C, d, D, E, F, c = (self.m[k] for k in ("A", "B", "C", "d", "D", "E", "F", "c"))
        n_x, n_u, n_lam, N = A.shape[0], B.shape[1], C.shape[1], settings.horizon
        self.n_lam = n_lam
        self.x0 = cp.Parameter(n_x)
        self.s = cp.Parameter((N, n_lam), nonneg=True)
        x = cp.Variable((N + 1, n_x))
        u = cp.Variable((N, n_u))
        lam = cp.Variable((N, n_lam))
        sig = cp.Variable((N, n_lam), nonneg=True)
        Q = np.diag(settings.q)
        M = settings.big_m
        cons = [x[0] == self.x0, cp.abs(u) <= settings.u_max]
        cost = 0
        for k in range(N):
            w = D @ x[k] + E @ u[k] + F @ lam[k] + c
            cons += [
                x[k + 1] == A @ x[k] + B @ u[k] + C @ lam[k] + d,
                lam[k] >= 0,
                lam[k] <= M * self.s[k],
                w >= -sig[k],
                w <= M * (1 - self.s[k]) + sig[k],
            ]
            cost += cp.quad_form(x[k], Q) + settings.r * cp.sum_squares(u[k]) + settings.rho * cp.sum(sig[k])
        cost += settings.terminal * cp.quad_form(x[N], Q)
        self.problem = cp.Problem(cp.Minimize(cost), cons)
        self.u, self.x, self.lam = u, x, lam
        self.plan = np.zeros((N, n_u))
        self.qp_solves = self.qp_failures = self.qp_inaccurate = 0

    def _modes(self, x0: np.ndarray, us: np.ndarray) -> np.ndarray:
        """Active sets ``(N, n_lam)`` of the LCS simulated from ``x0`` under ``us``."""
        from lcs_cvx import solve_lcp

        A, B, C, d, D, E, F, c = (self.m[k] for k in ("A", "B", "C", "d", "D", "E", "F", "c"))
        x, modes = x0, []
        for u in us:
            lam = solve_lcp(F, (D @ x + E @ u + c)[None, :]).lam.numpy()[0]
            modes.append(lam > 1e-9)
            x = A @ x + B @ u + C @ lam + d
        return np.asarray(modes, dtype=np.float64)

    def _solve(self) -> bool:
        """Solve the QP (Clarabel, OSQP if Clarabel fails); True if it returned a plan."""
        import cvxpy as cp

        self.qp_solves += 1
        for solver in ("CLARABEL", "OSQP"):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # "solution may be inaccurate"
                try:
                    self.problem.solve(solver=solver)
                except cp.error.SolverError:
                    continue
            if self.problem.status in ("optimal", "optimal_inaccurate") and self.u.value is not None:
                self.qp_inaccurate += self.problem.status == "optimal_inaccurate"
                return True
        return False

    def __call__(self, x0: np.ndarray) -> float:
        """The first input of the plan from state ``x0``."""
        guess = np.vstack([self.plan[1:], self.plan[-1:]])
        modes = self._modes(x0, guess)
        self.x0.value = x0
        for _ in range(self.settings.mode_iterations):
            self.s.value = modes
            if not self._solve():  # numerical failure: keep the shifted plan
                self.qp_failures += 1
                self.plan = guess
                break
            self.plan = np.asarray(self.u.value)
            new = self._modes(x0, self.plan)
            if np.array_equal(new, modes):
                break
            modes = new
        return float(np.clip(self.plan[0, 0], -self.settings.u_max, self.settings.u_max))


def simulate(controller: Any, x0: np.ndarray, steps: int, physics: Any = None) -> dict[str, np.ndarray]:
    """Closed loop in MuJoCo: ``controller(x) -> u`` every control period (None: u = 0)."""
    from .plant import CartPoleWalls, Physics

    sim = CartPoleWalls(physics or Physics())
    sim.reset(x0)
    xs, us, contact = [sim.state], [], []
    for _ in range(steps):
        u = 0.0 if controller is None else controller(xs[-1])
        x, _, con = sim.step(u)
        xs.append(x)
        us.append(u)
        contact.append(con)
    return {"x": np.asarray(xs), "u": np.asarray(us), "contact": np.asarray(contact)}


def success(run: dict[str, np.ndarray], last: int) -> bool:
    theta = run["x"][:, 1]
    return bool(np.all(np.abs(theta) <= 0.8) and np.all(np.abs(theta[-last:]) < 0.1)
                and not run["contact"][-last:].any())


#: Initial states (x_c, theta, x_c', theta'): tilted towards a wall, some already falling.
SCENARIOS = (
    (0.0, 0.25, 0.0, 0.5),
    (0.0, -0.25, 0.0, -0.5),
    (0.05, 0.3, 0.0, 1.0),
    (-0.05, -0.3, 0.0, -1.0),
    (0.1, 0.2, 0.3, 1.5),
    (-0.1, -0.2, -0.3, -1.5),
)


def main(argv: list[str] | None = None) -> int:
    import lcs_cvx

    ap = argparse.ArgumentParser(description="MPC on a learned LCS, run on the MuJoCo cart-pole.")
    here = os.path.join("studies", "results", "physics")
    ap.add_argument("--model", default=os.path.join(here, "models", "lcs_violation_nlam8.npz"))
    ap.add_argument("--out", default=here, help="writes mpc.md, mpc.json and mpc.png here")
    ap.add_argument("--horizon", type=int, default=MPCSettings.horizon)
    ap.add_argument("--u-max", type=float, default=MPCSettings.u_max)
    ap.add_argument("--seconds", type=float, default=4.0)
    args = ap.parse_args(argv)
    from .plant import Physics

    physics = Physics()
    steps = int(round(args.seconds / physics.control_period))
    last = int(round(1.0 / physics.control_period))
    model = lcs_cvx.load_model(args.model)
    matrices = model.to_matrices()
    settings = MPCSettings(horizon=args.horizon, u_max=args.u_max)
    results: dict[str, list[dict[str, Any]]] = {}
    runs: dict[str, list[dict[str, np.ndarray]]] = {}
    t0 = time.perf_counter()
    for name, make in (("no input", lambda: None),
                       ("MPC, free-mode model (C = 0)", lambda: LCSMPC(matrices, settings, use_contacts=False)),
                       ("MPC, learned LCS", lambda: LCSMPC(matrices, settings, use_contacts=True))):
        results[name], runs[name] = [], []
        for x0 in SCENARIOS:
            ctrl = make()
            tc = time.perf_counter()
            run = simulate(ctrl, np.asarray(x0, dtype=np.float64), steps, physics)
            results[name].append({
                "x0": list(x0), "success": success(run, last),
                "max_abs_theta": float(np.abs(run["x"][:, 1]).max()),
                "final_abs_theta": float(abs(run["x"][-1, 1])),
                "contact_steps": int(run["contact"].any(axis=1).sum()),
                "max_abs_u": float(np.abs(run["u"]).max()),
                "ms_per_step": 1e3 * (time.perf_counter() - tc) / steps,
                "qp_solves": getattr(ctrl, "qp_solves", 0),
                "qp_failures": getattr(ctrl, "qp_failures", 0),
                "qp_inaccurate": getattr(ctrl, "qp_inaccurate", 0),
            })
            runs[name].append(run)
            print(f"{name:32s} x0={x0}: success={results[name][-1]['success']}, "
                  f"max|θ|={results[name][-1]['max_abs_theta']:.3f}", file=sys.stderr, flush=True)
    wall = time.perf_counter() - t0
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "mpc.json"), "w") as f:
        json.dump({"model": args.model, "settings": vars(settings), "seconds": args.seconds,
                   "results": results, "wall_time_s": wall}, f, indent=1)
    # plot the first scenario where the two MPCs disagree (else the first)
    ok = {n: [r["success"] for r in rs] for n, rs in results.items()}
    names = list(results)
    shown = next((i for i in range(len(SCENARIOS)) if ok[names[1]][i] != ok[names[2]][i]), 0)
    _plot({n: runs[n][shown] for n in names}, physics, os.path.join(args.out, "mpc.png"),
          f"x0 = {SCENARIOS[shown]}")
    lines = [
        "# MPC on the learned LCS, run in MuJoCo",
        "",
        f"Written by `python -m studies.physics.mpc_example --model {args.model}` "
        f"({wall:.0f} s). Horizon {settings.horizon} steps of {physics.control_period:g} s, "
        f"|u| ≤ {settings.u_max:g} N, {args.seconds:g} s per run, Q = diag{settings.q}, r = {settings.r}. "
        "Success: |θ| ≤ 0.8 rad throughout and, over the last second, |θ| < 0.1 rad with no wall "
        "contact.",
        "",
        "Each cell: success (✓/✗), max |θ| (rad), control periods with a wall contact, max |u| (N).",
        "",
        "| x0 = (x_c, θ, ẋ_c, θ̇) | " + " | ".join(results) + " |",
        "|---" * (len(results) + 1) + "|",
    ]
    for i, x0 in enumerate(SCENARIOS):
        cells = [f"{'✓' if r['success'] else '✗'} {r['max_abs_theta']:.2f} rad, {r['contact_steps']} contact, "
                 f"{r['max_abs_u']:.1f} N" for r in (results[n][i] for n in results)]
        lines.append(f"| {x0} | " + " | ".join(cells) + " |")
    lines.append("| **successes** | " + " | ".join(
        f"**{sum(r['success'] for r in rs)}/{len(rs)}**" for rs in results.values()) + " |")
    ms = np.mean([r["ms_per_step"] for r in results[names[2]]])
    qp = {n: (sum(r["qp_solves"] for r in rs), sum(r["qp_failures"] for r in rs),
              sum(r["qp_inaccurate"] for r in rs)) for n, rs in list(results.items())[1:]}
    lines += ["", f"The LCS MPC took {ms:.0f} ms per control period on average (CVXPY + Clarabel, "
              f"up to {settings.mode_iterations} QPs per period). QPs solved / failed (shifted "
              "plan used) / solved inaccurately: "
              + "; ".join(f"{n}: {a} / {b} / {c}" for n, (a, b, c) in qp.items()) + ".", "",
              f"![MPC runs, x0 = {SCENARIOS[shown]}](mpc.png)", ""]
    with open(os.path.join(args.out, "mpc.md"), "w") as f:
        f.write("\n".join(lines))
    print("\n".join(lines))
    return 0


def _plot(runs: dict[str, dict[str, np.ndarray]], physics: Any, path: str, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for name, run in runs.items():
        t = np.arange(run["x"].shape[0]) * physics.control_period
        tip = run["x"][:, 0] + physics.pole_length * np.sin(run["x"][:, 1])
        axes[0].plot(t, run["x"][:, 1], label=name)
        axes[1].plot(t, tip, label=name)
        axes[2].step(t[:-1], run["u"], where="post", label=name)
    inner = physics.wall_distance - physics.tip_radius
    for s in (-1, 1):
        axes[1].axhline(s * inner, color="gray", lw=1)
    for ax, lab in zip(axes, ("pole angle θ (rad)", "pole tip x (m), walls in grey", "input u (N)"), strict=True):
        ax.set_xlabel("time (s)")
        ax.set_ylabel(lab)
        ax.grid(alpha=0.3)
    axes[0].set_ylim(-1.0, 1.0)  # a falling pole leaves the plot
    axes[1].set_ylim(-0.5, 0.5)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"Closed loop in MuJoCo, {title}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
