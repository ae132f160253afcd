"""The cells of the forward-solve comparison (:mod:`studies.solvers.forward_solves`): its
settings and solvers, the data of each setting, the exact references, and one cell, (problem,
setting, solver), solved sample by sample through the declared CVXPY problem."""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass

import cvxpy as cp
import numpy as np
import torch

import lcs_cvx
from lcs_cvx.lcp import lcp_residual
from lcs_cvx.problems import CLARABEL_OPTIONS, convex_lcp_problem, violation_problem
from lcs_cvx.system import LCS
from lcs_cvx.violation import (
    solve_violation_brute,
    solve_violation_fast,
    violation_kkt_residual,
)

MACHINE = "x86_64 2-core VM, one thread (the other core busy)"
N_SAMPLES = 50
SMOKE_SAMPLES = 5
#: fewer samples for the slow solvers (SCIP's spatial branch and bound runs to its 1 s limit on
#: (V); DIFFCP and CVXOPT take tens to hundreds of ms on the stiff cells)
SAMPLES_FOR: dict[str, int] = {"SCIP": 10, "DIFFCP": 20, "CVXOPT": 25}
#: model = truth + this times N(0, 1) per parameter
PERTURB = 0.1
#: a solve whose relative KKT residual is above this is called inaccurate in the advice
ACCURATE = 1e-6
#: the relative threshold above which a reference entry counts as nonzero (active sets)
ACTIVE_TOL = 1e-9
#: draws over which the active sets of a setting's distribution are also counted
WIDE_SAMPLES = 2000


@dataclass(frozen=True)
class Setting:
    name: str
    n_lam: int
    stiffness: float
    g_scale: float
    gamma: float
    eps: float
    description: str
    n_x: int = 10
    n_u: int = 4
    x_scale: float = 10.0
    zero_c: bool = False
    degenerate: bool = False


SETTINGS: dict[str, Setting] = {
    "n4": Setting("n4", 4, 0.5, 1.0, 1e-2, 1e-4, "n_lam = 4, stiffness 0.5, gamma 1e-2, eps 1e-4"),
    "n20": Setting("n20", 20, 0.5, 1.0, 1e-2, 1e-4, "n_lam = 20, stiffness 0.5, gamma 1e-2, eps 1e-4"),
    "stiff": Setting("stiff", 10, 1e-5, 0.0, 1e-6, 1e-4,
                     "n_lam = 10, G = 0, stiffness 1e-5, gamma 1e-6, eps 1e-4"),
    "modes": Setting("modes", 12, 0.5, 1.0, 1e-2, 1e-4,
                     "many modes: n_lam = 12, n_x = 10, c = 0, x ~ U[-3, 3], stiffness 0.5, "
                     "gamma 1e-2, eps 1e-4", x_scale=3.0, zero_c=True),
    "highdim": Setting("highdim", 10, 0.5, 1.0, 1e-2, 1e-4,
                       "high dimension: n_x = 128, n_u = 4, n_lam = 10, stiffness 0.5, gamma 1e-2, "
                       "eps 1e-4", n_x=128),
    "degenerate": Setting("degenerate", 10, 0.5, 1.0, 1e-2, 1e-4,
                          "degenerate samples: n_lam = 10, 2-4 indices per sample with lam* = 0 "
                          "and zero slack / multiplier (constructed), stiffness 0.5, gamma 1e-2, "
                          "eps 1e-4", degenerate=True),
}
SMOKE_SETTINGS: dict[str, Setting] = {
    "smoke": Setting("smoke", 3, 0.5, 1.0, 1e-2, 1e-4, "n_lam = 3, stiffness 0.5, gamma 1e-2, eps 1e-4"),
    "smoke_degenerate": Setting("smoke_degenerate", 4, 0.5, 1.0, 1e-2, 1e-4,
                                "degenerate samples, n_lam = 4", degenerate=True),
}
PROBLEMS = ("P", "V")

#: solver -> (CVXPY keyword options: tight tolerances where the solver takes them, text)
SOLVER_OPTIONS: dict[str, tuple[dict, str]] = {
    "CLARABEL": (dict(CLARABEL_OPTIONS), "tol_gap_abs = tol_gap_rel = tol_feas = 1e-10"),
    "OSQP": ({"eps_abs": 1e-10, "eps_rel": 1e-10, "max_iter": 100_000, "polish": True},
             "eps_abs = eps_rel = 1e-10, max_iter 1e5, polish"),
    "PIQP": ({"eps_abs": 1e-10, "eps_rel": 1e-10, "eps_duality_gap_abs": 1e-10,
              "eps_duality_gap_rel": 1e-10, "compute_timings": True},
             "eps_abs = eps_rel = eps_duality_gap_abs = eps_duality_gap_rel = 1e-10, "
             "compute_timings (sparse backend)"),
    "PROXQP": ({"eps_abs": 1e-10, "eps_rel": 0.0, "max_iter": 10_000},
               "eps_abs 1e-10, eps_rel 0, max_iter 1e4 (dense backend)"),
    "DAQP": ({}, "defaults (active set: exact up to rounding once the active set is found)"),
    "SCS": ({"eps_abs": 1e-9, "eps_rel": 1e-9, "max_iters": 100_000},
            "eps_abs = eps_rel = 1e-9, max_iters 1e5"),
    "ECOS": ({"abstol": 1e-9, "reltol": 1e-9, "feastol": 1e-9},
             "abstol = reltol = feastol = 1e-9"),
    "CVXOPT": ({"abstol": 1e-8, "reltol": 1e-8, "feastol": 1e-8},
               "abstol = reltol = feastol = 1e-8 (at 1e-9 and tighter CVXOPT raises on (V))"),
    "HIGHS": ({"primal_feasibility_tolerance": 1e-10, "dual_feasibility_tolerance": 1e-10,
               "time_limit": 1.0},
              "primal/dual_feasibility_tolerance 1e-10, time_limit 1 s per solve (without it, "
              "HiGHS's QP solver ran for minutes on some degenerate samples of (P))"),
    "SCIP": ({"scip_params": {"numerics/feastol": 1e-9, "limits/gap": 1e-8, "limits/time": 1.0}},
             "numerics/feastol 1e-9, limits/gap 1e-8, limits/time 1 s per solve (spatial "
             "branch and bound on the quadratic objective: without a time limit a (V) solve ran "
             "for over a minute)"),
    "DIFFCP": ({}, "defaults (diffcp's cone solver; no tolerance passed through CVXPY)"),
}

#: the solvers whose CVXPY interface does something with ``warm_start=True``, and what
WARM_START: dict[str, str] = {
    "OSQP": "solver object updated, previous primal/dual as start",
    "PIQP": "solver object updated in place",
    "PROXQP": "solver object updated, previous solution as start",
    "HIGHS": "previous solution passed as start",
    "SCS": "previous x, y, s as start",
    "CLARABEL": "solver object updated in place (no iterate warm start)",
}

#: installed but not used, with the reason
SKIP_REASON: dict[str, str] = {
    "GLPK": "LP only (CVXPY refuses a quadratic objective)",
    "GLPK_MI": "mixed-integer LP only",
    "SCIPY": "LP / MILP only (scipy.optimize.linprog / milp)",
    "ECOS_BB": "mixed-integer SOCP, superseded",
}

#: the open QP-capable solvers this comparison names, with how to install each when absent
KNOWN_SOLVERS: dict[str, str] = {
    "CLARABEL": "core dependency",
    "OSQP": "cvxpy dependency",
    "SCS": "cvxpy dependency",
    "PIQP": "`pip install lcs_cvx[solvers]`",
    "PROXQP": "`pip install lcs_cvx[solvers]`",
    "DAQP": "`pip install lcs_cvx[solvers]`",
    "ECOS": "`pip install lcs_cvx[solvers]`",
    "CVXOPT": "`pip install cvxopt`",
    "HIGHS": "`pip install highspy`",
    "SCIP": "`pip install lcs_cvx[control]`",
    "DIFFCP": "core dependency",
}
COMMERCIAL = ("GUROBI", "MOSEK", "CPLEX", "XPRESS", "COPT")


def solvers() -> list[str]:
    """The installed solvers this study runs, in :data:`SOLVER_OPTIONS` order."""
    inst = set(cp.installed_solvers())
    return [s for s in SOLVER_OPTIONS if s in inst]


def skipped() -> dict[str, str]:
    """Installed solvers not run, with the reason."""
    inst = cp.installed_solvers()
    return {s: SKIP_REASON.get(s, "not a QP solver known to this study") for s in inst
            if s not in SOLVER_OPTIONS}


def not_run() -> dict[str, str]:
    """Known QP solvers absent here -> the table's text (how to install, or commercial)."""
    inst = set(cp.installed_solvers())
    out = {s: f"not installed — {how}" for s, how in KNOWN_SOLVERS.items() if s not in inst}
    out.update({s: "skipped: commercial, not licensed here" for s in COMMERCIAL if s not in inst})
    return out


def samples_for(solver: str, n: int) -> int:
    return min(n, SAMPLES_FOR.get(solver, n))


# -- data -----------------------------------------------------------------------------------------
def _model(setting: Setting, seed: int) -> tuple[LCS, LCS]:
    truth = lcs_cvx.random_lcs(setting.n_x, setting.n_u, setting.n_lam, stiffness=setting.stiffness,
                               seed=seed, g_scale=setting.g_scale)
    if setting.zero_c:
        truth.c.zero_()
    model = LCS(setting.n_x, setting.n_u, setting.n_lam, stiffness=setting.stiffness, init_scale=0.0)
    gen = torch.Generator().manual_seed(seed + 2)
    with torch.no_grad():
        for name, p in model.named_parameters():
            src = getattr(truth, name)
            step = PERTURB * torch.randn(src.shape, generator=gen, dtype=src.dtype)
            if name == "G" and setting.g_scale == 0.0:
                step = torch.zeros_like(step)  # keep F + F^T = 2 s I
            if name == "c" and setting.zero_c:
                step = torch.zeros_like(step)
            p.copy_(src + step)
    return truth, model


def make_data(setting: Setting, n: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """``F``, ``q`` (B, n) for (P); (V)'s parameter values ``L, b, K, h``; all float64. For a
    degenerate setting also the constructed solutions ``lam_P``, ``lam_V``."""
    truth, model = _model(setting, seed)
    data = lcs_cvx.make_dataset(truth, n, seed=seed + 1, x_scale=setting.x_scale)
    with torch.no_grad():
        F = model.F.detach()
        x, u, xn = data.x, data.u, data.x_next
        q = x @ model.D.mT + u @ model.E.mT + model.c
        r = x @ model.A.mT + u @ model.B.mT + model.d - xn
        vals = violation_problem(setting.n_lam).parameter_values(
            model.C.detach(), F, q.detach(), r.detach(), setting.gamma, setting.eps)
    out = {"F": F, "q": q.detach(), **{k: v.detach() for k, v in vals.items()}}
    if setting.degenerate:
        out.update(_degenerate(out, n, seed + 3))
    return out


def _degenerate(data: dict, n: int, seed: int) -> dict[str, torch.Tensor]:
    """Samples with weakly active constraints, built from chosen solutions (module docstring)."""
    rng = np.random.default_rng(seed)
    F, L, K = (data[k].numpy() for k in ("F", "L", "K"))
    m = F.shape[0]
    q, lam_p, b, h, lam_v = (np.zeros((n, m)) for _ in range(5))
    for i in range(n):
        # (P): classes 0 active (lam > 0 = w), 1 inactive (lam = 0 < w), 2 degenerate (both 0)
        cls = _classes(rng, m)
        lam = np.where(cls == 0, rng.uniform(1.0, 10.0, m), 0.0)
        w = np.where(cls == 1, rng.uniform(1.0, 10.0, m), 0.0)
        q[i], lam_p[i] = w - F @ lam, lam
        # (V): lam* zero off the active set, kinks s_j = 0, multipliers zero on degenerate indices
        cls = _classes(rng, m)
        lam = np.where(cls == 0, rng.uniform(1.0, 10.0, m), 0.0)
        s = rng.uniform(1.0, 10.0, m) * rng.choice([-1.0, 1.0], m)
        s[rng.choice(m, int(rng.integers(2, min(4, m) + 1)), replace=False)] = 0.0
        mu = np.where(cls == 1, rng.uniform(1.0, 10.0, m), 0.0)
        h[i] = K @ lam - s
        b[i] = np.linalg.solve(L.T, mu - K.T @ np.maximum(s, 0.0)) - L @ lam
        lam_v[i] = lam
    t = torch.from_numpy
    return {"q": t(q), "b": t(b), "h": t(h), "lam_P": t(lam_p), "lam_V": t(lam_v)}


def _classes(rng: np.random.Generator, m: int) -> np.ndarray:
    n_deg = int(rng.integers(2, min(4, m - 1) + 1))
    cls = rng.integers(0, 2, m)
    cls[rng.choice(m, n_deg, replace=False)] = 2
    return cls


def reference(problem: str, data: dict) -> tuple[np.ndarray, str, float]:
    """``(lam_ref, how, its max residual)``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", lcs_cvx.FallbackWarning)
        if f"lam_{problem}" in data:
            lam = data[f"lam_{problem}"]
            how = ("construction (lam*, w* chosen, q = w* - F lam*)" if problem == "P"
                   else "construction (lam*, kinks, multipliers chosen; b, h from them)")
            return lam.numpy(), how, float(residual(problem, data, lam.numpy()).max())
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
    t = torch.from_numpy(np.ascontiguousarray(lam))
    if problem == "P":
        return lcp_residual(data["F"], data["q"][: len(lam)], t).numpy()
    vals = {"L": data["L"], "K": data["K"], "b": data["b"][: len(lam)], "h": data["h"][: len(lam)]}
    return violation_kkt_residual(vals, t).numpy()


def active_sets(problem: str, data: dict, lam: np.ndarray) -> int:
    """The number of distinct active sets (P) / pieces (V) of the reference solutions."""
    tol = ACTIVE_TOL * (1.0 + np.abs(lam).max(1, keepdims=True))
    keys = lam > tol
    if problem == "V":
        s = lam @ data["K"].numpy().T - data["h"][: len(lam)].numpy()
        keys = np.concatenate([keys, s > ACTIVE_TOL * (1.0 + np.abs(s).max(1, keepdims=True))], 1)
    return len({row.tobytes() for row in keys})


def wide_active_sets(setting: Setting, n: int = WIDE_SAMPLES) -> int | None:
    """Distinct active sets of (P) among ``n`` draws of the setting's distribution (the fast
    pivoting solves them); ``None`` for the constructed degenerate samples."""
    if setting.degenerate:
        return None
    data = make_data(setting, n)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", lcs_cvx.FallbackWarning)
        lam = lcs_cvx.solve_lcp(data["F"], data["q"], method="fast").lam.numpy()
    return active_sets("P", data, lam)


# -- one cell -------------------------------------------------------------------------------------
def _declaration(problem: str, n: int):
    """A fresh declaration (not the package's cached one), so that the first solve is cold."""
    factory = convex_lcp_problem if problem == "P" else violation_problem
    return factory.__wrapped__(n)


def _fresh(problem: str, data: dict):
    """A fresh declaration with the shared parameters set; the per-sample ones by name."""
    q = data["q"]
    decl = _declaration(problem, q.shape[1])
    par = decl.parameters
    if problem == "P":
        F = data["F"].numpy()
        par["R"].value = np.linalg.cholesky(F + F.T).T
        par["F"].value = F
        return decl, {"q": q.numpy()}
    par["L"].value = data["L"].numpy()
    par["K"].value = data["K"].numpy()
    return decl, {"b": data["b"].numpy(), "h": data["h"].numpy()}


def form(problem: str, data: dict, solver: str) -> str:
    """``QP`` when the solver receives the quadratic objective as such, else ``SOCP``."""
    decl, per_sample = _fresh(problem, data)
    for k, v in per_sample.items():
        decl.parameters[k].value = v[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pdata, _, _ = decl.problem.get_problem_data(solver)
    return "QP" if pdata.get("P") is not None else "SOCP"


def solve_all(problem: str, data: dict, solver: str, n: int | None = None,
              warm_start: bool = False, direct: bool = False) -> dict:
    """Solve ``problem`` for the first ``n`` samples of ``data`` with ``solver`` on a fresh
    declaration; per-sample ``lam`` (NaN on failure), status, wall and solver times, and with
    ``direct`` the time of the solver called on the canonicalised data (``chain.solve_via_data``)."""
    decl, per_sample = _fresh(problem, data)
    par = decl.parameters
    B, nl = data["q"].shape
    n = B if n is None else n
    opts = SOLVER_OPTIONS[solver][0]
    lam = np.full((n, nl), np.nan)
    status: list[str] = []
    wall, stime, dtime = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
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
            # DIFFCP reports a time larger than the call's wall time: not the solve's own time;
            # ProxQP reports 0 (its timings are off): not reported either
            if s is not None and 0.0 < float(s) <= wall[i]:
                stime[i] = float(s)
        if direct:
            dtime[i] = _direct_time(decl.problem, solver, opts)
    cold = float(wall[0]) if n else math.nan
    raised = np.array([st.startswith("error") for st in status], dtype=bool)
    wall[raised] = np.nan  # a call that raised is no solve: kept out of the warm times
    return {"lam": lam, "status": status, "wall": wall, "solver_time": stime, "direct": dtime,
            "cold": cold}


def _direct_time(problem: cp.Problem, solver: str, opts: dict) -> float:
    """Wall time of ``chain.solve_via_data`` on this sample's canonicalised data (NaN if it
    raises); ``get_problem_data`` is not timed."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            pdata, chain, _ = problem.get_problem_data(solver, solver_opts=dict(opts))
            o = {k: (dict(v) if isinstance(v, dict) else v) for k, v in opts.items()}
            t0 = time.perf_counter()
            chain.solve_via_data(problem, pdata, warm_start=False, verbose=False, solver_opts=o)
            return time.perf_counter() - t0
    except Exception:
        return math.nan


def _f(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def _accuracy(problem: str, data: dict, lam: np.ndarray, status: list[str],
              lam_ref: np.ndarray) -> dict:
    lam_ref = lam_ref[: len(lam)]
    got = np.isfinite(lam).all(1)
    err = np.abs(lam - lam_ref).max(1)
    rel = err / (1.0 + np.abs(lam_ref).max(1))
    res = residual(problem, data, np.where(got[:, None], lam, 0.0))
    ok = np.array([s == "optimal" for s in status]) & got
    counts: dict[str, int] = {}
    for s in status:
        counts[s] = counts.get(s, 0) + 1
    some = bool(got.any())
    return {
        "failures": int((~ok).sum()), "failure_rate": float((~ok).mean()),
        "inaccurate": counts.get("optimal_inaccurate", 0), "statuses": counts,
        "returned": int(got.sum()),
        "max_err": _f(float(err[got].max())) if some else None,
        "max_rel_err": _f(float(rel[got].max())) if some else None,
        "median_rel_err": _f(float(np.median(rel[got]))) if some else None,
        "max_residual": _f(float(res[got].max())) if some else None,
        "median_residual": _f(float(np.median(res[got]))) if some else None,
    }


def _median(x: np.ndarray) -> float | None:
    x = x[np.isfinite(x)]
    return _f(float(np.median(x))) if len(x) else None


def today() -> str:
    return time.strftime("%Y-%m-%d")


def run_cell(problem: str, setting: Setting, solver: str, n: int) -> dict:
    n = samples_for(solver, n)
    data = make_data(setting, n)
    lam_ref, how, ref_res = reference(problem, data)
    t0 = time.perf_counter()
    out = solve_all(problem, data, solver, direct=True)
    acc = _accuracy(problem, data, out["lam"], out["status"], lam_ref)
    wall, st, dt = out["wall"], out["solver_time"], out["direct"]
    row = {
        "problem": problem, "setting": setting.name, "solver": solver,
        "n_lam": setting.n_lam, "n_x": setting.n_x, "samples": n,
        "setting_description": setting.description,
        "options": SOLVER_OPTIONS[solver][1], "form": form(problem, data, solver),
        "reference": how, "reference_max_residual": ref_res,
        "max_abs_lam_ref": float(np.abs(lam_ref).max()),
        "active_sets": active_sets(problem, data, lam_ref),
        "active_sets_wide": wide_active_sets(setting) if problem == "P" else None,
        **acc,
        "cold_wall_s": _f(out["cold"]),
        "cold_solver_s": _f(float(st[0])),
        "warm_wall_s": _median(wall[1:]),
        "warm_solver_s": _median(st[1:]),
        "warm_direct_s": _median(dt[1:]),
        "warm_overhead_s": _median(wall[1:] - dt[1:]),
        "direct_failures": int((~np.isfinite(dt)).sum()),
        "solver_time_reported": bool(np.isfinite(st).any()),
    }
    if solver in WARM_START:
        ws = solve_all(problem, data, solver, warm_start=True)
        wacc = _accuracy(problem, data, ws["lam"], ws["status"], lam_ref)
        row["warm_start"] = {
            "what": WARM_START[solver], "wall_s": _median(ws["wall"][1:]),
            "solver_s": _median(ws["solver_time"][1:]),
            **{k: wacc[k] for k in ("failures", "inaccurate", "max_rel_err", "max_residual",
                                    "statuses")},
        }
    else:
        row["warm_start"] = None
    row["cell_seconds"] = time.perf_counter() - t0
    row["date"] = today()
    row["machine"] = MACHINE
    return row
