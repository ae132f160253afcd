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
import json  # noqa: E402
import sys  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from lcs_cvx.violation import (  # noqa: E402
    solve_violation_brute,
    violation_kkt_residual,
)

from . import records  # noqa: E402
from .forward_solves_cells import (  # noqa: E402
    N_SAMPLES,
    PROBLEMS,
    SETTINGS,
    SMOKE_SAMPLES,
    SMOKE_SETTINGS,
    WARM_START,
    Setting,
    make_data,
    not_run,
    run_cell,
    skipped,
    solve_all,
    solvers,
)
from .forward_solves_report import fmt_err, fmt_ms, pareto, report  # noqa: E402

__all__ = ["PROBLEMS", "SETTINGS", "SMOKE_SETTINGS", "WARM_START", "Setting", "make_data", "not_run", "run", "main",
           "skipped", "solve_all", "solve_violation_brute", "solvers", "violation_kkt_residual"]


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
                    f"{row['samples']} rel err {fmt_err(row['max_rel_err'])} res "
                    f"{fmt_err(row['max_residual'])} warm {fmt_ms(row['warm_wall_s'])} ms direct "
                    f"{fmt_ms(row['warm_direct_s'])} ms  [{row['cell_seconds']:.1f} s]")
    report(done, out, stem, settings, smoke)
    if figure if figure is not None else not smoke:
        pareto(done, out / f"{stem}.png", settings)
    return done


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
