r"""C3 in closed loop on C3's cart-pole with soft walls: success, cost gap to the exact optimum,
time per solve, and the batched fast path.

The plant is the exact LCS of :func:`lcs_cvx.control.c3_cartpole` (C3's published cart-pole
between two soft walls, linearised, ``dt = 0.01`` s) and every controller plans on that same
model. Initial states are drawn uniformly (seed 0) from the box ``|x_c| <= 0.3`` m,
``|theta| <= 0.6`` rad, ``|x_c'| <= 0.6`` m/s, ``|theta'| <= 0.6`` rad/s around C3's published
``x0 = (0.1, -0.5, 0.5, -0.4)``, which is run as well. Controllers:

- ``c3+``: C3 with the closed-form C3+ projection on the fast (affine, batched) QP path (this and
  the other named projections below without the polish: C3's ADMM as published);
- ``c3+ cvxpy``: the same, the QP step solved by CVXPY + Clarabel (timing comparison; a few states);
- ``qp``: C3 with C3's convex (QP) projection, CVXPY + Clarabel;
- ``miqp``: C3 with the exact mixed-integer projection, CVXPY + SCIP (slow: a subset of states);
- ``miqp enum``: the same exact projection by its active sets (``projection_solver="enumerate"``),
  every state;
- ``lcp``: C3 with the projection onto the model's own forces (``projection="lcp"``), fast path;
- ``auto``: C3's default projection (``"auto"``: the ADMM with ``"lcp"`` and with ``"c3+"``, the
  plan whose model rollout costs less), fast path, without the polish;
- ``defaults``: C3's defaults: ``"auto"`` and the polish (``polish=3``: the inputs re-planned in
  the modes the model visits under them), fast path; ``defaults, penalize_input_change``: the
  same with the input cost measured from the previous plan's inputs;
- ``lqr``: ``u = -K x`` from the Riccati equation of ``(A, B, Q, R)``, ignoring the walls.

A run succeeds when ``|x|_inf <= 0.1`` holds for 30 consecutive steps within 600 steps (C3's
criterion). The cost gap compares C3's first plan from each initial state, its inputs rolled out
through the exact LCS, with the optimum of the horizon problem (:mod:`studies.control.exact`).

Units (one initial state x one controller, the exact optimum per state, the batch run) are
appended to ``OUT/cartpole_c3.jsonl`` as they finish and skipped when the command is re-run;
``OUT/cartpole_c3.md`` and ``OUT/cartpole_c3.png`` are rewritten after every phase.

    python -m studies.control.cartpole_c3 --out studies/results/control [--states 100]
        [--miqp-states 20] [--smoke]
"""


from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
import warnings
from collections.abc import Iterable
from typing import Any

import numpy as np
import torch

from lcs_cvx.control import C3, c3_cartpole, closed_loop, dare

from .cartpole_c3_records import (
    BOX,
    CONTROLLERS,
    FILE,
    HOLD,
    MACHINE,
    OPTIONS,
    PROJECTION_SOLVER,
    TOL,
    TRAJ_STATES,
    Settings,
    initial_states,
    jsonable,
    load_records,
    today,
    unit_key,
)
from .cartpole_c3_report import write_report
from .exact import HorizonMIQP, enumerate_optimum, rollout_cost

__all__ = ["Settings", "LQR", "initial_states", "main", "write_report", "load_records", "unit_key", "BOX", "HOLD",
           "TOL"]


class LQR:
    """``u = -K x`` with ``K`` from the Riccati equation of ``(A, B, Q, R)`` of an LCS: the
    contact-free controller (the walls are ignored)."""

    def __init__(self, model: Any, Q: np.ndarray, R: np.ndarray):
        m = model.to_matrices()
        P = dare(m["A"], m["B"], Q, R)
        self.K = np.linalg.solve(R + m["B"].T @ P @ m["B"], m["B"].T @ P @ m["A"])
        self._K = torch.as_tensor(self.K)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return -x @ self._K.mT

    def reset(self) -> None:
        pass


class Recorder:
    """Wraps a controller and keeps each C3 plan's ``times`` and ``qp_failures``."""

    def __init__(self, ctrl: Any):
        self.ctrl, self.phases, self.qp_failures = ctrl, [], 0

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        u = self.ctrl(x)
        plan = getattr(self.ctrl, "last_plan", None)
        if plan is not None:
            self.phases.append(plan.times)
            self.qp_failures += int(np.sum(plan.qp_failures))
        return u


# ----------------------------------------------------------------------------- the runs


class Study:
    def __init__(self, out: str, settings: Settings, cmd: str):
        self.out, self.settings, self.cmd = out, settings, cmd
        self.P = c3_cartpole()
        m = self.P.model.to_matrices()
        self.m = m
        self.Q, self.R = np.diag(self.P.Q), np.diag(self.P.R)
        self.QN = dare(m["A"], m["B"], self.Q, self.R)
        n = max(settings.batch, settings.states, settings.miqp_states, settings.cvxpy_states)
        self.X = initial_states(n)
        os.makedirs(out, exist_ok=True)
        self.path = os.path.join(out, f"{FILE}.jsonl")
        self.done = {unit_key(r) for r in load_records(self.path)}
        self._ctrls: dict[str, Any] = {}

    def x0(self, state: str) -> np.ndarray:
        return self.P.x0.copy() if state == "x0" else self.X[int(state)]

    def controller(self, name: str) -> Any:
        if name not in self._ctrls:
            spec = CONTROLLERS[name]
            if spec is None:
                self._ctrls[name] = LQR(self.P.model, self.Q, self.R)
            else:
                proj, path, polish = spec
                G, U = self.P.weights["c3+" if proj in ("lcp", "auto") else proj]
                ctrl = C3(self.P.model, self.P.horizon, Q=self.P.Q, R=self.P.R, QN="dare", G=G, U=U,
                          projection=proj, qp_path=path, projection_solver=PROJECTION_SOLVER.get(name),
                          polish=polish, **OPTIONS.get(name, {}))
                if not np.allclose(ctrl.QN, self.QN, rtol=1e-10, atol=1e-8):
                    raise RuntimeError("C3's terminal weight differs from the exact problem's")
                self._ctrls[name] = ctrl
        return self._ctrls[name]

    def append(self, rec: dict[str, Any]) -> None:
        rec = {"date": today(), "machine": MACHINE, "load": round(os.getloadavg()[0], 2), **rec}
        with open(self.path, "a") as f:
            f.write(json.dumps(rec, default=jsonable) + "\n")
            f.flush()
            os.fsync(f.fileno())
        self.done.add(unit_key(rec))

    def pending(self, controller: str, states: Iterable[str], steps: int) -> list[str]:
        return [s for s in states if (controller, s, steps) not in self.done]

    # -- one initial state, one controller
    def plan_cost(self, name: str, x0: np.ndarray) -> dict[str, Any]:
        """The cost of the controller's first plan from ``x0``, its inputs rolled out through
        the exact LCS (LQR: its own N-step closed-loop trajectory)."""
        ctrl, N = self.controller(name), self.P.horizon
        if isinstance(ctrl, LQR):
            x, us = torch.as_tensor(x0)[None], []
            with torch.no_grad():
                for _ in range(N):
                    us.append(ctrl(x)[0])
                    x = self.P.model.step(x, us[-1][None])
            u = torch.stack(us).numpy()
            cost, _ = rollout_cost(self.P.model, x0, u, self.Q, self.R, self.QN)
            return {"plan_cost": cost, "plan_u": u.ravel().tolist()}
        ctrl.reset()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            plan = ctrl.solve(x0)
        ctrl.reset()
        u, x = plan.u.numpy(), plan.x.numpy()
        cost, _ = rollout_cost(self.P.model, x0, u, self.Q, self.R, self.QN)
        own = sum(float(x[k] @ self.Q @ x[k] + u[k] @ self.R @ u[k]) for k in range(N)) + float(x[N] @ self.QN @ x[N])
        return {"plan_cost": cost, "plan_cost_planned": own, "plan_complementarity": float(plan.complementarity),
                "plan_gap": float(plan.gap),
                "plan_time": plan.times["total"], "plan_primal_residual": float(plan.primal_residual[-1]),
                "plan_u": u.ravel().tolist(), "plan_warnings": len(caught)}

    def run_unit(self, name: str, state: str, steps: int) -> dict[str, Any]:
        x0 = self.x0(state)
        rec: dict[str, Any] = {"kind": "run", "controller": name, "state": state, "steps": steps, "x0": x0.tolist()}
        try:
            rec.update(self.plan_cost(name, x0))
        except Exception as exc:  # a solver failure is a result, recorded as such
            rec["plan_error"] = f"{type(exc).__name__}: {exc}"
        ctrl = self.controller(name)
        ctrl.reset()
        rec_ctrl = Recorder(ctrl)
        stop = name == "miqp" and self.settings.miqp_stop_when_settled
        t = time.perf_counter()
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                res = closed_loop(rec_ctrl, self.P.model, x0, steps, tol=TOL, hold=HOLD, stop_when_settled=stop)
        except Exception as exc:
            rec.update(error=f"{type(exc).__name__}: {exc}", success=False, wall=time.perf_counter() - t)
            return rec
        wall = time.perf_counter() - t
        x = res.x[0].numpy()
        gap = x @ self.m["D"].T + self.m["c"]  # the wall gaps at u = 0, lam = 0 (E = 0)
        settled = int(res.settled[0])
        times = res.solve_times
        rec.update(
            success=settled >= 0, settled=settled, simulated=int(x.shape[0] - 1), wall=wall,
            stopped_early=bool(x.shape[0] - 1 < steps),
            final_error=float(np.abs(x[-1]).max()), max_abs=np.abs(x).max(0).tolist(),
            contact_steps=int((gap.min(1) < 0).sum()), contact_last100=int((gap[-100:].min(1) < 0).sum()),
            warnings=len(caught), qp_failures=rec_ctrl.qp_failures,
            solve_ms_median=1e3 * float(np.median(times)), solve_ms_p95=1e3 * float(np.percentile(times, 95)),
            solve_us=[int(round(1e6 * v)) for v in times],
        )
        if rec_ctrl.phases:
            rec["phase_ms_median"] = {k: 1e3 * float(np.median([p[k] for p in rec_ctrl.phases]))
                                      for k in ("qp", "projection", "lcp", "model", "total")}
        if state in TRAJ_STATES:
            rec["traj"] = np.round(x[:, :2], 5).tolist()
        return rec

    def run_controller(self, name: str, states: list[str], steps: int) -> None:
        todo = self.pending(name, states, steps)
        print(f"[{name}] {len(todo)} of {len(states)} runs to do ({steps} steps)", flush=True)
        for i, s in enumerate(todo):
            rec = self.run_unit(name, s, steps)
            self.append(rec)
            print(f"[{name}] {i + 1}/{len(todo)} state {s}: success={rec.get('success')} "
                  f"settled={rec.get('settled')} final={rec.get('final_error', float('nan')):.3g} "
                  f"solve median {rec.get('solve_ms_median', float('nan')):.3g} ms, wall {rec['wall']:.1f} s"
                  + (f" ERROR {rec['error']}" if "error" in rec else ""), flush=True)
            if self.settings.report_every_phase and rec["wall"] > 60:  # slow units: keep the report current
                write_report(self.out, self.settings, self.cmd)

    # -- the exact optimum per state
    def run_exact(self, states: list[str]) -> None:
        todo = self.pending("exact", states, self.P.horizon)
        print(f"[exact] {len(todo)} of {len(states)} optima to do", flush=True)
        if not todo:
            return
        problem = HorizonMIQP(self.P.model, self.P.horizon, self.Q, self.R, self.QN, big_m=1000.0)
        n_check = len(states) if self.settings.check_states is None else self.settings.check_states
        check = {"x0"} | {str(i) for i in range(n_check)}
        for s in todo:
            x0 = self.x0(s)
            rec: dict[str, Any] = {"kind": "exact", "controller": "exact", "state": s, "steps": self.P.horizon,
                                   "x0": x0.tolist()}
            try:
                r = problem.solve(x0)
            except Exception as exc:
                rec["error"] = f"{type(exc).__name__}: {exc}"
                self.append(rec)
                continue
            rec.update(cost=r.cost, scip_cost=r.cost, objective=r.objective, scip_objective=r.scip_objective,
                       modes=r.modes.astype(int).tolist(), complementarity=r.complementarity, max_lam=r.max_lam,
                       max_gap=r.max_gap, big_m_active=r.big_m_active, scip_time=r.times["scip"],
                       polish_time=r.times["polish"], status=r.status, u=r.u.ravel().tolist())
            if s in check:
                t = time.perf_counter()
                cost, _ = enumerate_optimum(problem, x0)
                rec.update(enumerated_cost=cost, enumeration_time=time.perf_counter() - t,
                           scip_matches=abs(r.cost - cost) <= 1e-9 * abs(cost), cost=min(r.cost, cost))
            self.append(rec)
            print(f"[exact] state {s}: cost {r.cost:.6g} (SCIP {r.times['scip']:.2f} s, {r.status})"
                  + (f", enumerated {rec['enumerated_cost']:.6g}" if "enumerated_cost" in rec else ""), flush=True)

    # -- many rollouts at once on the fast path
    def run_batch(self) -> None:
        n, steps = self.settings.batch, self.settings.steps
        if ("c3+ batch", f"batch{n}", steps) in self.done:
            print("[batch] done", flush=True)
            return
        ctrl = self.controller("c3+")
        ctrl.reset()
        X0 = torch.as_tensor(self.X[:n])
        with warnings.catch_warnings(record=True) as caught:  # counted, as in the per-state runs
            warnings.simplefilter("always")
            ctrl.solve(X0[:2])  # one warm-up solve (first-call costs), not timed
            t = time.perf_counter()
            res = closed_loop(ctrl, self.P.model, X0, steps, tol=TOL, hold=HOLD)
            wall = time.perf_counter() - t
        ctrl.reset()
        settled = res.settled.numpy()
        final = res.x[:, -1].abs().amax(1).numpy()
        rec = {"kind": "batch", "controller": "c3+ batch", "state": f"batch{n}", "steps": steps, "rollouts": n,
               "wall": wall, "per_step_ms": 1e3 * wall / steps, "solve_ms_median": 1e3 * float(np.median(res.solve_times)),
               "solve_ms_p95": 1e3 * float(np.percentile(res.solve_times, 95)),
               "success_rate": float((settled >= 0).mean()), "settled": settled.tolist(),
               "final_error_median": float(np.median(final)), "warnings": len(caught)}
        self.append(rec)
        print(f"[batch] {n} rollouts x {steps} steps: {wall:.1f} s, success {rec['success_rate']:.3f}", flush=True)

    def run(self) -> None:
        st = self.settings
        rand = [str(i) for i in range(st.states)]
        phases = [
            ("c3+", lambda: self.run_controller("c3+", ["x0"] + rand, st.steps)),
            ("auto", lambda: self.run_controller("auto", ["x0"] + rand, st.steps)),
            ("defaults", lambda: self.run_controller("defaults", ["x0"] + rand, st.steps)),
            ("defaults, penalize_input_change",
             lambda: self.run_controller("defaults, penalize_input_change", ["x0"] + rand, st.steps)),
            ("lcp", lambda: self.run_controller("lcp", ["x0"] + rand, st.steps)),
            ("lqr", lambda: self.run_controller("lqr", ["x0"] + rand, st.steps)),
            ("exact", lambda: self.run_exact(["x0"] + [str(i) for i in range(max(st.states, st.miqp_states))])),
            ("batch", self.run_batch),
            ("c3+ cvxpy", lambda: self.run_controller("c3+ cvxpy", ["x0"] + [str(i) for i in range(st.cvxpy_states)],
                                                      st.qp_steps)),
            ("qp", lambda: self.run_controller("qp", ["x0"] + rand, st.qp_steps)),
            ("miqp enum", lambda: self.run_controller("miqp enum", ["x0"] + rand, st.steps)),
            ("miqp", lambda: self.run_controller("miqp", ["x0"] + [str(i) for i in range(st.miqp_states)],
                                                 st.miqp_steps)),
        ]
        for i, (name, phase) in enumerate(phases):
            t = time.perf_counter()
            phase()
            print(f"phase {name}: {time.perf_counter() - t:.1f} s", flush=True)
            if st.report_every_phase or i == len(phases) - 1:
                write_report(self.out, self.settings, self.cmd)


# ----------------------------------------------------------------------------- command line


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join("studies", "results", "control"))
    ap.add_argument("--states", type=int, default=None, help="random initial states (default 100; smoke 3)")
    ap.add_argument("--miqp-states", type=int, default=None, help="random states for the miqp projection (default 20)")
    ap.add_argument("--cvxpy-states", type=int, default=None, help="random states for c3+ on the CVXPY QP path (default 5)")
    ap.add_argument("--batch", type=int, default=None, help="rollouts in the batched run (default 1000)")
    ap.add_argument("--smoke", action="store_true", help="a few states and steps (seconds)")
    ap.add_argument("--report-only", action="store_true", help="rewrite the report from OUT's units")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    base = Settings.smoke() if args.smoke else Settings()
    over = {k: v for k, v in (("states", args.states), ("miqp_states", args.miqp_states),
                              ("cvxpy_states", args.cvxpy_states), ("batch", args.batch)) if v is not None}
    settings = dataclasses.replace(base, **over)
    cmd = "python -m studies.control.cartpole_c3 " + " ".join(argv if argv is not None else sys.argv[1:])
    cmd = cmd.replace(" --report-only", "").strip()
    if args.report_only:
        write_report(args.out, settings, cmd)
        return 0
    print(f"cartpole_c3: {settings}, {platform.machine()}, out {args.out}", flush=True)
    Study(args.out, settings, cmd).run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
