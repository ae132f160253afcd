"""Forward solves of the declared problems (P) and (V) through every installed CVXPY QP solver.

The package declares its two per-sample problems once, as parameterised (DPP) CVXPY problems
(:func:`lcs_cvx.convex_lcp_problem`, (P): the LCP as a convex QP; :func:`lcs_cvx.violation_problem`,
(V): the violation loss with ``phi`` eliminated). This study solves both, one sample at a time as
the package's reference path and the ``cvxpylayers`` forward pass do, with every QP-capable solver
that ``cvxpy.installed_solvers()`` lists, and measures per (problem, setting, solver):

- the form the solver receives: a QP (quadratic objective passed as such: OSQP, PIQP, ProxQP,
  DAQP, HiGHS through CVXPY's QP path, Clarabel and SCS through its conic path with a quadratic
  objective) or an SOCP (ECOS, CVXOPT, SCIP, DIFFCP take no quadratic objective: CVXPY rewrites
  ``1/2 ||R lam||^2`` as an epigraph variable with a second-order cone);
- accuracy: the largest error of ``lam`` against the exact reference, absolute and relative
  (``|lam - lam*|_inf / (1 + |lam*|_inf)``), and the largest relative KKT residual
  (:func:`lcs_cvx.lcp.lcp_residual` for (P), :func:`lcs_cvx.violation.violation_kkt_residual`
  for (V)), both of the raw answer (not clamped at 0);
- failures: exceptions and every status other than ``optimal`` (``optimal_inaccurate``
  included, also counted apart), over all samples -- never dropped; the errors are over the
  samples that returned a ``lam``;
- time, per solve, with ``warm_start=False`` (every solve starts the solver afresh):
  (a) the wall time of ``problem.solve`` (a DPP re-solve: parameter update, the cached
  canonicalisation applied to the new values, the solver interface, the solver, the unpacking);
  (b) the solver's own time, ``problem.solver_stats.solve_time`` where the solver reports it;
  (c) the solver called directly on the canonicalised data: ``data, chain, inverse_data =
  problem.get_problem_data(solver)`` once per sample (not timed), then the timed call
  ``chain.solve_via_data(problem, data, warm_start=False, solver_opts=...)`` -- the solver and
  CVXPY's thin interface to it (its conversion of the data into the solver's format), nothing
  of the parameter update or canonicalisation. CVXPY's overhead is (a) - (c). "Cold" is the
  first ``problem.solve`` of a fresh declaration (it includes CVXPY's one-off DPP compilation),
  "warm" the median over the later solves;
- warm starts: for the solvers whose CVXPY interface uses ``warm_start=True`` (OSQP, PIQP,
  ProxQP, HiGHS, SCS: the previous solution as the starting point; Clarabel: the solver object
  updated in place rather than rebuilt), the same samples solved again in the same order on a
  fresh declaration with ``warm_start=True``: median wall time, failures and error.

References (exact): (P) by enumeration of the ``2^n`` free sets
(``lcs_cvx.solve_lcp(..., method="brute")``) for ``n <= 12``, else the package's pivoting
(``method="fast"``, exact on convergence; its residual is reported); (V) by enumeration of its
``4^n`` pieces (:func:`lcs_cvx.violation.solve_violation_brute`) for ``n <= 6``, else the fast
block principal pivoting (:func:`lcs_cvx.violation.solve_violation_fast`, exact on convergence);
the degenerate samples by their construction. Per cell the number of distinct active sets of the
references is counted: for (P) the free set ``{i : lam*_i > 0}``, for (V) the piece (the free
set and the set where ``K lam* - h > 0``).

Data: ground truth ``lcs_cvx.random_lcs(n_x, n_u, n_lam)``, transitions from
``lcs_cvx.make_dataset`` (``x ~ U[-x_scale, x_scale]``, ``u ~ U[-5, 5]``); the problems are posed
for a model near the truth (every parameter plus ``N(0, 0.1^2)``, as during training), (V) with
``gamma``, ``eps`` as in the paper's runs. Settings (the data distributions of the paper's
Fig. 1, and beyond):

- ``n4``, ``n20``: ``n_x = 10, n_u = 4``, ``n_lam = 4`` and ``20``, stiffness 0.5,
  ``gamma = 1e-2``, ``eps = 1e-4``;
- ``stiff``: ``n_lam = 10``, ``G = 0``, stiffness ``1e-5`` (``F + F^T = 2e-5 I``, Fig. 1(c)'s
  stiffest), ``gamma = 1e-6``;
- ``modes``: many modes -- ``n_lam = 12`` at ``n_x = 10``, ``c = 0`` and ``x ~ U[-3, 3]`` so
  that ``q`` is centred at 0 with ``x`` and ``u`` of comparable weight and the samples spread
  over many active sets (counted among the cell's samples and among 2000 draws);
- ``highdim``: ``n_x = 128, n_u = 4, n_lam = 10`` (the problems' size is ``n_lam``: only the
  data's dimension grows);
- ``degenerate``: weakly active constraints, ``n_lam = 10``: per sample a partition of the
  indices into an active set (``lam*_i > 0 = w*_i``), an inactive set (``lam*_i = 0 < w*_i``) and
  2--4 degenerate indices with ``lam*_i = w*_i = 0``; (P) gets ``q = w* - F lam*``, whose unique
  solution (``F`` is positive definite) is ``lam*``. (V) gets the analogous construction:
  ``lam*`` with zeros, ``h = K lam* - s`` with 2--4 exact zeros in ``s`` (the kinks of
  ``pos(K lam - h)``), multipliers ``mu*`` (positive on the inactive set, zero on the degenerate
  indices) and ``b = L^{-T} (mu* - K^T pos(s)) - L lam*``, so that ``lam*`` satisfies (V)'s
  KKT conditions with some ``lam*_i = mu*_i = 0`` (strong convexity makes it the unique
  minimiser). ``b`` and ``h`` are set directly: they are (V)'s parameters for ``q = sqrt(gamma)
  h`` and an ``r`` with ``eps C^T r = L^T b - q``, which exists as ``C`` has full column rank.

Sample counts: 50 per cell, fewer for the slow solvers (:data:`SAMPLES_FOR`); the tables give
each cell's count. The open QP solvers this comparison names but that are not installed appear in
the tables as "not installed" with the extra that brings them (``pip install lcs_cvx[solvers]``
for PIQP, ProxQP, DAQP and ECOS); the commercial ones (Gurobi, MOSEK, CPLEX, Xpress, COPT) as
"skipped: commercial, not licensed here" unless installed. Solvers that fail are never dropped.

    python -m studies.solvers.forward_solves --out studies/results/solvers [--smoke]

Writes ``OUT/forward_solves.jsonl`` (one line per (problem, setting, solver); a rerun skips
finished cells), ``OUT/forward_solves.md`` and the accuracy--time figure ``OUT/forward_solves.png``
(``--smoke``: ``forward_solves_smoke.*``, two small settings, 5 samples, no figure).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import importlib.metadata  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import subprocess  # noqa: E402
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

from . import records  # noqa: E402

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
    row["date"] = _today()
    row["machine"] = MACHINE
    return row


# -- the run --------------------------------------------------------------------------------------
def plan(smoke: bool) -> tuple[dict[str, Setting], int]:
    return (SMOKE_SETTINGS, SMOKE_SAMPLES) if smoke else (SETTINGS, N_SAMPLES)


def load(path: Path) -> dict[tuple, dict]:
    return records.load(path, lambda row: (row["problem"], row["setting"], row["solver"]))


def run(out: Path, smoke: bool = False, log: Callable[[str], None] = print,
        figure: bool | None = None) -> dict[tuple, dict]:
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
                log(f"({problem}) {setting.name:10s} {solver:9s} fail {row['failures']}/"
                    f"{row['samples']} rel err {_e(row['max_rel_err'])} res "
                    f"{_e(row['max_residual'])} warm {_ms(row['warm_wall_s'])} ms direct "
                    f"{_ms(row['warm_direct_s'])} ms  [{row['cell_seconds']:.1f} s]")
    report(done, out, stem, settings, smoke)
    if figure if figure is not None else not smoke:
        pareto(done, out / f"{stem}.png", settings)
    return done


# -- report ---------------------------------------------------------------------------------------
def _today() -> str:
    return time.strftime("%Y-%m-%d")


def _e(x: float | None) -> str:
    return "–" if x is None else f"{x:.1e}"


def _ms(x: float | None) -> str:
    return "–" if x is None else f"{1e3 * x:.2f}"


def _rate(fail: int, statuses: dict[str, int], n: int) -> str:
    s = f"{fail}/{n}"
    inacc = statuses.get("optimal_inaccurate", 0)
    errors = sum(c for k, c in statuses.items() if k.startswith("error"))
    notes = ([f"{inacc} inacc."] if inacc else []) + ([f"{errors} raised"] if errors else [])
    return s + (f" ({', '.join(notes)})" if notes else "")


def _versions() -> str:
    names = ["cvxpy", "numpy", "scipy", "torch", "clarabel", "osqp", "scs", "piqp", "proxsuite",
             "daqp", "ecos", "cvxopt", "highspy", "PySCIPOpt", "diffcp"]
    out = []
    for name in names:
        try:
            out.append(f"{name} {importlib.metadata.version(name)}")
        except importlib.metadata.PackageNotFoundError:
            pass
    return ", ".join(out)


def _cpu() -> str:
    try:
        text = subprocess.run(["lscpu"], capture_output=True, text=True, check=False).stdout
        for line in text.splitlines():
            if line.startswith("Model name:"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown CPU"


def _ws(r: dict) -> tuple[str, str, str]:
    w = r.get("warm_start")
    if not w:
        return "–", "–", "–"
    return (_ms(w["wall_s"]), _rate(w["failures"], w["statuses"], r["samples"]),
            _e(w["max_rel_err"]))


def report(done: dict[tuple, dict], out: Path, stem: str, settings: dict[str, Setting],
           smoke: bool) -> None:
    cmd = ("nice -n 10 python -m studies.solvers.forward_solves --out " + str(out)
           + (" --smoke" if smoke else ""))
    run_solvers = solvers()
    dates = sorted({r["date"] for r in done.values() if "date" in r})
    absent = not_run()
    lines = [
        "# Forward solves of (P) and (V) through CVXPY's QP solvers",
        "",
        f"Command: `OMP_NUM_THREADS=1 {cmd}` (resumable: one JSON line per (problem, setting, "
        f"solver) in `{stem}.jsonl`).  ",
        f"Date: {', '.join(dates) or _today()}. Machine: {MACHINE}, {_cpu()}.  ",
        f"Versions: Python {sys.version.split()[0]}, {_versions()}.",
        "",
        "Each problem is the package's declaration (`lcs_cvx.convex_lcp_problem` for (P), "
        "`lcs_cvx.violation_problem` for (V)), created fresh per cell and solved one sample at a "
        f"time, {N_SAMPLES if not smoke else SMOKE_SAMPLES} samples per cell (fewer for slow "
        "solvers: column **n**). Data: `random_lcs(n_x, n_u, n_lam)` ground truth, "
        "`make_dataset` transitions, problems posed for the truth with every parameter "
        f"perturbed by N(0, {PERTURB}^2); the degenerate samples are constructed from chosen "
        "solutions (see the module docstring).",
        "",
        "Settings: " + "; ".join(f"`{s.name}`: {s.description}" for s in settings.values()) + ".",
        "",
        "Columns: **form** = what the solver receives (QP: the quadratic objective as such; "
        "SOCP: CVXPY rewrites it with a second-order cone, for solvers that take no quadratic "
        "objective); **fail** = exceptions + every status other than `optimal` (`inacc.` = "
        "`optimal_inaccurate`, `raised` = exceptions, both already in fail), never dropped; **rel err** = max over samples "
        "of |lam − lam*|∞ / (1 + |lam*|∞) against the exact reference; **abs err** = max "
        "|lam − lam*|∞; **KKT res** = max relative LCP residual (P) / KKT residual (V) of the raw "
        "answer. Times in ms per solve, all with `warm_start=False` unless marked: **cold** = the "
        "first `problem.solve` of a fresh declaration (includes CVXPY's DPP compilation); "
        "**wall** = median `problem.solve` of the later samples (a DPP re-solve; calls that raised "
        "are left out of every time); **solver** = "
        "median `solver_stats.solve_time` (– where not reported); **direct** = median "
        "`chain.solve_via_data` on the canonicalised data from `problem.get_problem_data` (the "
        "solver and CVXPY's conversion of the data into its format); **overhead** = median "
        "(wall − direct): CVXPY's parameter update, canonicalisation and unpacking; **ws** = the "
        "same samples in the same order with `warm_start=True` (median wall, failures, rel err), "
        "for the solvers whose CVXPY interface uses it (– for the others).",
        "",
    ]
    header = ("| solver | form | n | fail | rel err | abs err | KKT res | cold | wall | solver | "
              "direct | overhead | ws wall | ws fail | ws rel err |")
    sep = "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"
    for problem in PROBLEMS:
        title = ("(P): the LCP as a convex QP" if problem == "P"
                 else "(V): the violation problem, phi eliminated")
        lines += [f"## {title}", ""]
        for setting in settings.values():
            rows = [done[(problem, setting.name, s)] for s in run_solvers
                    if (problem, setting.name, s) in done]
            if not rows:
                continue
            r0 = max(rows, key=lambda r: r["samples"])
            lines += [
                f"### `{setting.name}`: {setting.description}",
                "",
                f"Reference: {r0['reference']} (its max residual {_e(r0['reference_max_residual'])}); "
                f"max |lam*| = {r0['max_abs_lam_ref']:.3g}; distinct active sets"
                f"{' (pieces)' if problem == 'V' else ''} among the {r0['samples']} samples: "
                f"{r0['active_sets']}"
                + (f" (among {WIDE_SAMPLES} draws: {r0['active_sets_wide']} of 2^{r0['n_lam']})"
                   if r0.get("active_sets_wide") else "") + ".",
                "",
                header,
                sep,
            ]
            for r in rows:
                w = _ws(r)
                lines.append(
                    f"| {r['solver']} | {r['form']} | {r['samples']} | "
                    f"{_rate(r['failures'], r['statuses'], r['samples'])} | "
                    f"{_e(r['max_rel_err'])} | {_e(r['max_err'])} | {_e(r['max_residual'])} | "
                    f"{_ms(r['cold_wall_s'])} | {_ms(r['warm_wall_s'])} | {_ms(r['warm_solver_s'])} | "
                    f"{_ms(r['warm_direct_s'])} | {_ms(r['warm_overhead_s'])} | {w[0]} | {w[1]} | "
                    f"{w[2]} |")
            for why in dict.fromkeys(absent.values()):
                names = ", ".join(s for s, w in absent.items() if w == why)
                lines.append(f"| {names} | {why} |" + " |" * 13)
            lines.append("")
    lines += ["## Solvers", "", "| solver | status | form | options | warm_start=True does |",
              "| --- | --- | --- | --- | --- |"]
    forms = {r["solver"]: r["form"] for r in done.values()}
    for s in run_solvers:
        lines.append(f"| {s} | run | {forms.get(s, '–')} | {SOLVER_OPTIONS[s][1]} | "
                     f"{WARM_START.get(s, 'nothing (ignored by the interface)')} |")
    for s, why in absent.items():
        lines.append(f"| {s} | {why} | | | |")
    lines += [""]
    sk = skipped()
    if sk:
        lines += ["Installed, not run: " + "; ".join(f"{s} ({why})" for s, why in sk.items()) + ".", ""]
    if not smoke:
        lines += [f"Figure: `{stem}.png`, max relative error of lam against the warm wall time "
                  "per solve, one panel per (problem, setting), failing solvers annotated.", ""]
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
                f"residual {tally[best][1]:.1e}); it is the one to use, with its residual checked.")
            out.append(f"- ({problem}): no solver is free of failures with KKT residual <= "
                       f"{ACCURATE:g} in every setting.{pick}")
    ws = {}
    for r in done.values():
        w = r.get("warm_start")
        if w and w["wall_s"] and r["warm_wall_s"]:
            ws.setdefault(r["solver"], []).append(w["wall_s"] / r["warm_wall_s"])
    if ws:
        out.append("- `warm_start=True` against a fresh start, median ratio of the warm wall "
                   "times over the cells: " + ", ".join(
                       f"{s} {float(np.median(v)):.2f}" for s, v in sorted(ws.items())) + ".")
    raised = {}
    for r in done.values():
        w = r.get("warm_start")
        if w:
            k = sum(c for st, c in w["statuses"].items() if st.startswith("error")) - sum(
                c for st, c in r["statuses"].items() if st.startswith("error"))
            if k > 0:
                errs = sorted(st for st in w["statuses"] if st.startswith("error"))
                raised.setdefault(r["solver"], [0, 0, set()])
                raised[r["solver"]][0] += k
                raised[r["solver"]][1] += r["samples"]
                raised[r["solver"]][2].update(errs)
    for s, (k, n, errs) in raised.items():
        verdict = ("its warm-start path through CVXPY is unusable with these versions"
                   if k > n / 2 else "occasional: the reused solver object fails where a fresh one does not")
        out.append(f"- {s} with `warm_start=True` raises where a fresh start does not: {k} of "
                   f"{n} solves ({', '.join(sorted(errs))}); {verdict} (the ws columns count "
                   "those as failures).")
    over = [r["warm_overhead_s"] / r["warm_wall_s"] for r in done.values()
            if r.get("warm_overhead_s") is not None and r.get("warm_wall_s")]
    if over:
        out.append(f"- CVXPY's overhead (wall − direct) is a median {100 * float(np.median(over)):.0f} % "
                   "of a warm `problem.solve` over all cells: for these small problems the "
                   "parameter update, canonicalisation and unpacking cost as much as or more than "
                   "the solver. For batches, the package's exact batched pivoting "
                   "(`solve_lcp(method=\"fast\")`, the fast violation loss) is the forward solver; "
                   "CVXPY solvers serve as references and for the `cvxpylayers` path.")
    return "\n".join(out)


# -- figure ---------------------------------------------------------------------------------------
def pareto(done: dict[tuple, dict], path: Path, settings: dict[str, Setting]) -> None:
    """Max relative lam error (log, floored at 1e-16) against warm wall time per solve (log), one
    panel per (problem, setting), one marker per solver; failures annotated."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run_solvers = solvers()
    markers = "osD^v<>pPXh*"
    colours = [plt.get_cmap("tab10")(i) for i in range(10)] + ["k"]
    style = {s: (markers[i % len(markers)], colours[i % len(colours)])
             for i, s in enumerate(run_solvers)}
    names = list(settings)
    fig, axes = plt.subplots(len(PROBLEMS), len(names), figsize=(3.6 * len(names), 7.2),
                             squeeze=False)
    ceiling = 1e3
    for i, problem in enumerate(PROBLEMS):
        for j, name in enumerate(names):
            ax = axes[i][j]
            nothing = []
            for s in run_solvers:
                r = done.get((problem, name, s))
                if r is None:
                    continue
                if r["warm_wall_s"] is None or r["max_rel_err"] is None:
                    nothing.append(f"{s} {r['failures']}/{r['samples']}")
                    continue
                err = r["max_rel_err"]
                y = ceiling if err is None else min(max(err, 1e-16), ceiling)
                mk, col = style[s]
                ax.scatter([r["warm_wall_s"] * 1e3], [y], marker=mk, color=col, s=42,
                           edgecolors="k" if r["failures"] else "none", linewidths=0.8,
                           label=s if (i, j) == (0, 0) else None, zorder=3)
                if r["failures"]:
                    ax.annotate(f"{s} {r['failures']}/{r['samples']} fail", (r["warm_wall_s"] * 1e3, y),
                                fontsize=6, xytext=(4, 2), textcoords="offset points")
            if nothing:
                ax.text(0.02, 0.98, "no answer: " + ", ".join(nothing), transform=ax.transAxes,
                        fontsize=6, va="top", color="firebrick")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_ylim(1e-17, 1e4)
            ax.axhline(ACCURATE, color="0.7", lw=0.6, ls="--")
            ax.set_title(f"({problem}) {name}", fontsize=9)
            ax.grid(True, which="major", lw=0.3)
            if i == len(PROBLEMS) - 1:
                ax.set_xlabel("warm wall time per solve [ms]")
            if j == 0:
                ax.set_ylabel("max rel. error of lam (floor 1e-16)")
    fig.legend(loc="lower center", ncol=len(run_solvers), fontsize=8, frameon=False)
    fig.suptitle("Forward solves through CVXPY: accuracy vs warm time per solve (errors above "
                 f"{ceiling:g} plotted at {ceiling:g}; black edge: some failures; dashed: "
                 f"{ACCURATE:g})", fontsize=10)
    fig.tight_layout(rect=(0, 0.05, 1, 0.96))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("studies/results/solvers"))
    ap.add_argument("--smoke", action="store_true",
                    help=f"two small settings, {SMOKE_SAMPLES} samples (seconds)")
    args = ap.parse_args(argv)
    run(args.out, smoke=args.smoke, log=lambda s: print(s, flush=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
