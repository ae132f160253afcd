"""Forward solves of the declared problems (P) and (V) through every installed CVXPY QP solver.

The package declares its two per-sample problems once, as parameterised (DPP) CVXPY problems
(:func:`lcs_cvx.convex_lcp_problem`, (P): the LCP as a convex QP; :func:`lcs_cvx.violation_problem`,
(V): the violation loss with ``phi`` eliminated). This study solves both, one sample at a time as
the package's reference path and the ``cvxpylayers`` forward pass do, with every QP-capable solver
that ``cvxpy.installed_solvers()`` lists, and measures per (problem, setting, solver):

- accuracy: the largest error of ``lam`` against the exact reference, absolute and relative
  (``|lam - lam*|_inf / (1 + |lam*|_inf)``), and the largest relative KKT residual
  (:func:`lcs_cvx.lcp.lcp_residual` for (P), :func:`lcs_cvx.violation.violation_kkt_residual`
  for (V)), both of the raw answer (not clamped at 0);
- failures: exceptions and every status other than ``optimal`` (``optimal_inaccurate``
  included, also counted apart), over all samples -- never dropped; the errors are over the
  samples that returned a ``lam``;
- time: the wall time of each ``problem.solve`` call, the solver's own time
  (``problem.solver_stats.solve_time``, where the solver reports it) and their difference,
  CVXPY's overhead (DPP parameter update, canonicalisation, the solver interface). "Cold" is
  the first solve of a fresh declaration (it includes CVXPY's one-off DPP compilation);
  "warm" the median over the later solves.

References (exact): (P) by enumeration of the ``2^n`` free sets
(``lcs_cvx.solve_lcp(..., method="brute")``) for ``n <= 12``, else the package's pivoting
(``method="fast"``, exact on convergence; its residual is reported); (V) by enumeration of its
``4^n`` pieces (:func:`lcs_cvx.violation.solve_violation_brute`) for ``n <= 6``, else the fast
block principal pivoting (:func:`lcs_cvx.violation.solve_violation_fast`, exact on convergence).

Data: ground truth ``lcs_cvx.random_lcs(n_x=10, n_u=4, n_lam)``, transitions from
``lcs_cvx.make_dataset`` (``x ~ U[-10, 10]``, ``u ~ U[-5, 5]``); the problems are posed for a
model near the truth (every parameter plus ``N(0, 0.1^2)``, as during training), ``(V)`` with
``gamma``, ``eps`` as in the paper's runs. Settings: ``n_lam = 4`` and ``20`` (stiffness 0.5,
``gamma = 1e-2``, ``eps = 1e-4``), and ``stiff``: ``n_lam = 10``, ``G = 0``, stiffness
``1e-5`` (``F + F^T = 2e-5 I``, Fig. 1(c)'s stiffest), ``gamma = 1e-6``, ``eps = 1e-4``.

    python -m studies.solvers.forward_solves --out studies/results/solvers [--smoke]

Writes ``OUT/forward_solves.jsonl`` (one line per (problem, setting, solver); a rerun skips
finished cells) and ``OUT/forward_solves.md`` (``--smoke``: ``forward_solves_smoke.*``, one
small setting, 5 samples).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import cvxpy as cp  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

import lcs_cvx  # noqa: E402
from lcs_cvx.lcp import lcp_residual  # noqa: E402
from lcs_cvx.problems import CLARABEL_OPTIONS, convex_lcp_problem, violation_problem  # noqa: E402
from lcs_cvx.system import LCS  # noqa: E402
from lcs_cvx.violation import (  # noqa: E402
    solve_violation_brute,
    solve_violation_fast,
    violation_kkt_residual,
)

DATE = "2026-11-25"
MACHINE = "2-core x86-64 VM, 1 torch thread"
N_X, N_U = 10, 4
N_SAMPLES = 50
SMOKE_SAMPLES = 5
#: model = truth + this times N(0, 1) per parameter
PERTURB = 0.1
#: a solve whose relative KKT residual is above this is called inaccurate in the advice
ACCURATE = 1e-6


@dataclass(frozen=True)
class Setting:
    name: str
    n_lam: int
    stiffness: float
    g_scale: float
    gamma: float
    eps: float
    description: str


SETTINGS: dict[str, Setting] = {
    "n4": Setting("n4", 4, 0.5, 1.0, 1e-2, 1e-4, "n_lam = 4, stiffness 0.5, gamma 1e-2, eps 1e-4"),
    "n20": Setting("n20", 20, 0.5, 1.0, 1e-2, 1e-4, "n_lam = 20, stiffness 0.5, gamma 1e-2, eps 1e-4"),
    "stiff": Setting("stiff", 10, 1e-5, 0.0, 1e-6, 1e-4,
                     "n_lam = 10, G = 0, stiffness 1e-5, gamma 1e-6, eps 1e-4"),
}
SMOKE_SETTINGS: dict[str, Setting] = {
    "smoke": Setting("smoke", 3, 0.5, 1.0, 1e-2, 1e-4, "n_lam = 3, stiffness 0.5, gamma 1e-2, eps 1e-4"),
}
PROBLEMS = ("P", "V")

#: solver -> (CVXPY keyword options: tight tolerances where the solver takes them, text)
SOLVER_OPTIONS: dict[str, tuple[dict, str]] = {
    "CLARABEL": (dict(CLARABEL_OPTIONS), "tol_gap_abs = tol_gap_rel = tol_feas = 1e-10"),
    "OSQP": ({"eps_abs": 1e-10, "eps_rel": 1e-10, "max_iter": 100_000, "polish": True},
             "eps_abs = eps_rel = 1e-10, max_iter 1e5, polish"),
    "SCS": ({"eps_abs": 1e-9, "eps_rel": 1e-9, "max_iters": 100_000},
            "eps_abs = eps_rel = 1e-9, max_iters 1e5"),
    "CVXOPT": ({"abstol": 1e-8, "reltol": 1e-8, "feastol": 1e-8},
               "abstol = reltol = feastol = 1e-8 (at 1e-9 and tighter CVXOPT raises on (V))"),
    "HIGHS": ({"primal_feasibility_tolerance": 1e-10, "dual_feasibility_tolerance": 1e-10},
              "primal/dual_feasibility_tolerance 1e-10"),
    "SCIP": ({"scip_params": {"numerics/feastol": 1e-9, "limits/gap": 1e-8, "limits/time": 1.0}},
             "numerics/feastol 1e-9, limits/gap 1e-8, limits/time 1 s per solve (spatial "
             "branch and bound on the quadratic objective: without a time limit a (V) solve ran "
             "for over a minute)"),
    "DIFFCP": ({}, "defaults (diffcp's cone solver; no tolerance passed through CVXPY)"),
}

#: installed but not used, with the reason
SKIP_REASON: dict[str, str] = {
    "GLPK": "LP only (CVXPY refuses a quadratic objective)",
    "GLPK_MI": "mixed-integer LP only",
    "SCIPY": "LP / MILP only (scipy.optimize.linprog / milp)",
    "ECOS_BB": "mixed-integer SOCP, superseded",
}

#: QP-capable CVXPY solvers named for this comparison that may be absent, with their pip package
NOT_INSTALLED_CANDIDATES: dict[str, str] = {
    "PIQP": "piqp",
    "PROXQP": "proxsuite",
    "DAQP": "daqp",
    "ECOS": "ecos",
    "CLARABEL": "clarabel",
    "OSQP": "osqp",
    "SCS": "scs",
    "CVXOPT": "cvxopt",
    "HIGHS": "highspy",
    "SCIP": "pyscipopt",
    "GUROBI": "gurobipy (commercial licence)",
    "MOSEK": "mosek (commercial licence)",
}


def solvers() -> list[str]:
    """The installed solvers this study runs, in :data:`SOLVER_OPTIONS` order."""
    inst = set(cp.installed_solvers())
    return [s for s in SOLVER_OPTIONS if s in inst]


def skipped() -> dict[str, str]:
    """Installed solvers not run, with the reason."""
    inst = cp.installed_solvers()
    return {s: SKIP_REASON.get(s, "not a QP solver known to this study") for s in inst
            if s not in SOLVER_OPTIONS}


def not_installed() -> dict[str, str]:
    inst = set(cp.installed_solvers())
    return {s: pkg for s, pkg in NOT_INSTALLED_CANDIDATES.items() if s not in inst}


# -- data -----------------------------------------------------------------------------------------
def make_data(setting: Setting, n: int, seed: int = 0) -> dict[str, torch.Tensor | float]:
    """``F``, ``q`` (B, n) for (P); (V)'s parameter values ``L, b, K, h``; all float64."""
    truth = lcs_cvx.random_lcs(N_X, N_U, setting.n_lam, stiffness=setting.stiffness, seed=seed,
                               g_scale=setting.g_scale)
    data = lcs_cvx.make_dataset(truth, n, seed=seed + 1)
    model = LCS(N_X, N_U, setting.n_lam, stiffness=setting.stiffness, init_scale=0.0)
    gen = torch.Generator().manual_seed(seed + 2)
    with torch.no_grad():
        for name, p in model.named_parameters():
            src = getattr(truth, name)
            step = PERTURB * torch.randn(src.shape, generator=gen, dtype=src.dtype)
            if name == "G" and setting.g_scale == 0.0:
                step = torch.zeros_like(step)  # keep F + F^T = 2 s I
            p.copy_(src + step)
        F = model.F.detach()
        x, u, xn = data.x, data.u, data.x_next
        q = x @ model.D.mT + u @ model.E.mT + model.c
        r = x @ model.A.mT + u @ model.B.mT + model.d - xn
        vals = violation_problem(setting.n_lam).parameter_values(
            model.C.detach(), F, q.detach(), r.detach(), setting.gamma, setting.eps)
    return {"F": F, "q": q.detach(), **{k: v.detach() for k, v in vals.items()}}


def reference(problem: str, data: dict) -> tuple[np.ndarray, str, float]:
    """``(lam_ref, how, its max residual)``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", lcs_cvx.FallbackWarning)
        if problem == "P":
            F, q = data["F"], data["q"]
            n = q.shape[1]
            method = "brute" if n <= 12 else "fast"
            sol = lcs_cvx.solve_lcp(F, q, method=method)
            how = "enumeration (2^n free sets)" if n <= 12 else "pivoting (solve_lcp fast)"
            return sol.lam.numpy(), how, float(lcp_residual(F, q, sol.lam).max())
        vals = {k: data[k] for k in ("L", "b", "K", "h")}
        n = vals["b"].shape[1]
        if n <= 6:
            sol = solve_violation_brute(vals)
            how = "enumeration (4^n pieces)"
        else:
            sol = solve_violation_fast(vals)
            how = f"pivoting (solve_violation_fast, {sol.n_fallback} fallbacks)"
        return sol.lam.numpy(), how, float(violation_kkt_residual(vals, sol.lam).max())


def residual(problem: str, data: dict, lam: np.ndarray) -> np.ndarray:
    t = torch.from_numpy(lam)
    if problem == "P":
        return lcp_residual(data["F"], data["q"][: len(lam)], t).numpy()
    vals = {"L": data["L"], "K": data["K"], "b": data["b"][: len(lam)], "h": data["h"][: len(lam)]}
    return violation_kkt_residual(vals, t).numpy()


# -- one cell -------------------------------------------------------------------------------------
def _declaration(problem: str, n: int):
    """A fresh declaration (not the package's cached one), so that the first solve is cold."""
    factory = convex_lcp_problem if problem == "P" else violation_problem
    return factory.__wrapped__(n)


def solve_all(problem: str, data: dict, solver: str, n: int | None = None,
              warm_start: bool = True) -> dict:
    """Solve ``problem`` for the first ``n`` samples of ``data`` with ``solver`` on a fresh
    declaration; per-sample ``lam`` (NaN on failure), status, wall and solver times."""
    q = data["q"]
    B, nl = q.shape
    n = B if n is None else n
    decl = _declaration(problem, nl)
    par = decl.parameters
    if problem == "P":
        F = data["F"].numpy()
        par["R"].value = np.linalg.cholesky(F + F.T).T
        par["F"].value = F
        per_sample = {"q": q.numpy()}
    else:
        par["L"].value = data["L"].numpy()
        par["K"].value = data["K"].numpy()
        per_sample = {"b": data["b"].numpy(), "h": data["h"].numpy()}
    opts = SOLVER_OPTIONS[solver][0]
    lam = np.full((n, nl), np.nan)
    status: list[str] = []
    wall = np.full(n, np.nan)
    stime = np.full(n, np.nan)
    for i in range(n):
        for k, v in per_sample.items():
            par[k].value = v[i]
        t0 = time.perf_counter()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                decl.problem.solve(solver=solver, warm_start=warm_start, **opts)
            st = str(decl.problem.status)
        except Exception as exc:  # counted as a failure, with its type
            st = f"error: {type(exc).__name__}"
        wall[i] = time.perf_counter() - t0
        status.append(st)
        if not st.startswith("error"):
            value = decl.variables["lam"].value
            if value is not None:
                lam[i] = value
            s = decl.problem.solver_stats.solve_time if decl.problem.solver_stats else None
            # DIFFCP reports a time larger than the call's wall time: not the solve's own time
            if s is not None and 0.0 <= float(s) <= wall[i]:
                stime[i] = float(s)
    return {"lam": lam, "status": status, "wall": wall, "solver_time": stime}


def _f(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def run_cell(problem: str, setting: Setting, solver: str, n: int) -> dict:
    data = make_data(setting, n)
    lam_ref, how, ref_res = reference(problem, data)
    t0 = time.perf_counter()
    out = solve_all(problem, data, solver)
    elapsed = time.perf_counter() - t0
    lam, status = out["lam"], out["status"]
    got = np.isfinite(lam).all(1)
    err = np.abs(lam - lam_ref).max(1)
    rel = err / (1.0 + np.abs(lam_ref).max(1))
    res = residual(problem, data, np.where(got[:, None], lam, 0.0))
    ok = np.array([s == "optimal" for s in status]) & got
    wall, st = out["wall"], out["solver_time"]
    warm_wall, warm_st = wall[1:], st[1:]
    has_st = bool(np.isfinite(st).any())
    counts: dict[str, int] = {}
    for s in status:
        counts[s] = counts.get(s, 0) + 1
    return {
        "problem": problem, "setting": setting.name, "solver": solver,
        "n_lam": setting.n_lam, "samples": n, "setting_description": setting.description,
        "options": SOLVER_OPTIONS[solver][1], "warm_start": True,
        "reference": how, "reference_max_residual": ref_res,
        "max_abs_lam_ref": float(np.abs(lam_ref).max()),
        "failures": int((~ok).sum()), "failure_rate": float((~ok).mean()),
        "inaccurate": counts.get("optimal_inaccurate", 0), "statuses": counts,
        "returned": int(got.sum()),
        "max_err": _f(float(err[got].max())) if got.any() else None,
        "max_rel_err": _f(float(rel[got].max())) if got.any() else None,
        "median_rel_err": _f(float(np.median(rel[got]))) if got.any() else None,
        "max_residual": _f(float(res[got].max())) if got.any() else None,
        "median_residual": _f(float(np.median(res[got]))) if got.any() else None,
        "cold_wall_s": _f(float(wall[0])),
        "cold_solver_s": _f(float(st[0])),
        "warm_wall_s": _f(float(np.median(warm_wall))) if len(warm_wall) else None,
        "warm_solver_s": _f(float(np.nanmedian(warm_st))) if has_st and len(warm_st) else None,
        "warm_overhead_s": _f(float(np.nanmedian(warm_wall - warm_st)))
        if has_st and len(warm_st) else None,
        "solver_time_reported": has_st,
        "cell_seconds": elapsed,
        "date": DATE, "machine": MACHINE,
    }


# -- the run --------------------------------------------------------------------------------------
def plan(smoke: bool) -> tuple[dict[str, Setting], int]:
    return (SMOKE_SETTINGS, SMOKE_SAMPLES) if smoke else (SETTINGS, N_SAMPLES)


def load(path: Path) -> dict[tuple, dict]:
    done: dict[tuple, dict] = {}
    if path.exists():
        for line in path.read_text().splitlines():
            if line.strip():
                row = json.loads(line)
                done[(row["problem"], row["setting"], row["solver"])] = row
    return done


def run(out: Path, smoke: bool = False, log: Callable[[str], None] = print) -> dict[tuple, dict]:
    torch.set_num_threads(1)
    out.mkdir(parents=True, exist_ok=True)
    stem = "forward_solves_smoke" if smoke else "forward_solves"
    jpath = out / f"{stem}.jsonl"
    done = load(jpath)
    settings, n = plan(smoke)
    for setting in settings.values():
        for problem in PROBLEMS:
            for solver in solvers():
                key = (problem, setting.name, solver)
                if key in done:
                    continue
                row = run_cell(problem, setting, solver, n)
                with jpath.open("a") as fh:
                    fh.write(json.dumps(row) + "\n")
                done[key] = row
                log(f"({problem}) {setting.name:6s} {solver:9s} fail {row['failures']}/{n} "
                    f"rel err {_e(row['max_rel_err'])} res {_e(row['max_residual'])} "
                    f"warm {_ms(row['warm_wall_s'])} ms  [{row['cell_seconds']:.1f} s]")
    report(done, out, stem, settings, n, smoke)
    return done


# -- report ---------------------------------------------------------------------------------------
def _e(x: float | None) -> str:
    return "–" if x is None else f"{x:.1e}"


def _ms(x: float | None) -> str:
    return "–" if x is None else f"{1e3 * x:.2f}"


def _rate(row: dict) -> str:
    s = f"{row['failures']}/{row['samples']}"
    if row["inaccurate"]:
        s += f" ({row['inaccurate']} inacc.)"
    return s


def report(done: dict[tuple, dict], out: Path, stem: str, settings: dict[str, Setting], n: int,
           smoke: bool) -> None:
    cmd = "python -m studies.solvers.forward_solves --out " + str(out) + (" --smoke" if smoke else "")
    run_solvers = solvers()
    lines = [
        "# Forward solves of (P) and (V) through CVXPY's QP solvers",
        "",
        f"Command: `{cmd}` (resumable: one JSON line per (problem, setting, solver) in "
        f"`{stem}.jsonl`).  ",
        f"Date: {DATE}. Machine: {MACHINE}. CVXPY {cp.__version__}.",
        "",
        "Each problem is the package's declaration (`lcs_cvx.convex_lcp_problem` for (P), "
        "`lcs_cvx.violation_problem` for (V)), created fresh per cell and solved one sample at a "
        f"time, {n} samples per cell, with CVXPY's default `warm_start=True`. Data: "
        f"`random_lcs(n_x={N_X}, n_u={N_U}, n_lam)` ground truth, `make_dataset` transitions, "
        f"problems posed for the truth with every parameter perturbed by N(0, {PERTURB}^2).",
        "",
        "Settings: " + "; ".join(f"`{s.name}`: {s.description}" for s in settings.values()) + ".",
        "",
        "Columns: **fail** = exceptions + every status other than `optimal` (`inacc.` = "
        "`optimal_inaccurate`, already in fail), never dropped; **rel err** = max over samples "
        "of |lam − lam*|∞ / (1 + |lam*|∞) against the exact reference; **abs err** = max "
        "|lam − lam*|∞; **KKT res** = max relative LCP residual (P) / KKT residual (V) of the raw "
        "answer; times in ms: **cold** = the first `problem.solve` of a fresh declaration "
        "(includes CVXPY's DPP compilation), **warm wall** = median of the later calls, "
        "**warm solver** = median `solver_stats.solve_time` (– where not reported), "
        "**overhead** = median (wall − solver time): CVXPY's parameter update, "
        "canonicalisation and interface.",
        "",
    ]
    for problem in PROBLEMS:
        title = ("(P): the LCP as a convex QP" if problem == "P"
                 else "(V): the violation problem, phi eliminated")
        lines += [f"## {title}", ""]
        for setting in settings.values():
            rows = [done[(problem, setting.name, s)] for s in run_solvers
                    if (problem, setting.name, s) in done]
            if not rows:
                continue
            r0 = rows[0]
            lines += [
                f"### `{setting.name}`: {setting.description}",
                "",
                f"Reference: {r0['reference']} (its max residual {_e(r0['reference_max_residual'])}); "
                f"max |lam*| = {r0['max_abs_lam_ref']:.3g}.",
                "",
                "| solver | fail | rel err | abs err | KKT res | cold ms | warm wall ms | "
                "warm solver ms | overhead ms |",
                "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
            ]
            for r in rows:
                lines.append(
                    f"| {r['solver']} | {_rate(r)} | {_e(r['max_rel_err'])} | {_e(r['max_err'])} | "
                    f"{_e(r['max_residual'])} | {_ms(r['cold_wall_s'])} | {_ms(r['warm_wall_s'])} | "
                    f"{_ms(r['warm_solver_s'])} | {_ms(r['warm_overhead_s'])} |")
            lines.append("")
    lines += ["## Solvers", "", "| solver | options |", "| --- | --- |"]
    lines += [f"| {s} | {SOLVER_OPTIONS[s][1]} |" for s in run_solvers]
    lines += [""]
    sk = skipped()
    if sk:
        lines += ["Installed, not run: " + "; ".join(f"{s} ({why})" for s, why in sk.items()) + ".", ""]
    ni = not_installed()
    if ni:
        lines += ["Not installed (not measured): " + "; ".join(f"{s} (`pip install {p}`)"
                                                            for s, p in ni.items()) + ".", ""]
    lines += ["## Which solver for forward solves", "", advice(done, settings, run_solvers), ""]
    (out / f"{stem}.md").write_text("\n".join(lines))


def advice(done: dict[tuple, dict], settings: dict[str, Setting], run_solvers: list[str]) -> str:
    """The recommendation, from the numbers: per problem, the fastest warm solver among those with
    no failure and a KKT residual <= ACCURATE in every setting; and the accurate ones."""
    out = []
    for problem in PROBLEMS:
        good, worst_time = [], {}
        for s in run_solvers:
            rows = [done.get((problem, st, s)) for st in settings]
            if any(r is None for r in rows):
                continue
            if all(r["failures"] == 0 and r["max_residual"] is not None
                   and r["max_residual"] <= ACCURATE for r in rows):
                good.append(s)
                worst_time[s] = max(r["warm_wall_s"] for r in rows)
        if good:
            best = min(good, key=lambda s: worst_time[s])
            others = ", ".join(f"{s} {1e3 * worst_time[s]:.2f} ms" for s in
                               sorted(good, key=lambda s: worst_time[s]))
            out.append(f"- ({problem}): solvers with no failure and KKT residual <= {ACCURATE:g} in "
                       f"every setting, by their slowest setting's warm wall time per solve: "
                       f"{others}. Use **{best}** for forward solves of ({problem}).")
        else:
            tally = {}
            for s in run_solvers:
                rows = [done.get((problem, st, s)) for st in settings]
                if all(r is not None for r in rows):
                    tally[s] = (sum(r["failures"] for r in rows),
                                max((r["max_residual"] or math.inf) for r in rows))
            best = min(tally, key=lambda s: tally[s]) if tally else None
            pick = "" if best is None else (
                f" Fewest failures: **{best}** ({tally[best][0]} over all settings, worst KKT "
                f"residual {tally[best][1]:.1e}); it is the one to use, with its residual checked "
                "(the stiff setting is where every solver loses accuracy or fails).")
            out.append(f"- ({problem}): no solver is free of failures with KKT residual <= "
                       f"{ACCURATE:g} in every setting.{pick}")
    out.append("- Every CVXPY path costs milliseconds per sample, most of it CVXPY's overhead "
               "rather than the solver; for batches, the package's exact batched pivoting "
               "(`solve_lcp(method=\"fast\")`, the fast violation loss) is the forward solver, and "
               "CVXPY solvers serve as references and for the `cvxpylayers` path.")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("studies/results/solvers"))
    ap.add_argument("--smoke", action="store_true", help=f"n_lam = 3, {SMOKE_SAMPLES} samples (seconds)")
    args = ap.parse_args(argv)
    run(args.out, smoke=args.smoke, log=lambda s: print(s, flush=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
