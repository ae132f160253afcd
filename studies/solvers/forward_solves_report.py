"""The report of the forward-solve comparison (:mod:`studies.solvers.forward_solves`): its tables
(``OUT/forward_solves.md``), the advice drawn from them and the accuracy--time figure, from the
cells' records (:mod:`studies.solvers.forward_solves_cells`)."""

from __future__ import annotations

import importlib.metadata
import math
import subprocess
import sys
from pathlib import Path

import numpy as np

from .forward_solves_cells import (
    ACCURATE,
    MACHINE,
    N_SAMPLES,
    PERTURB,
    PROBLEMS,
    SMOKE_SAMPLES,
    SOLVER_OPTIONS,
    WARM_START,
    WIDE_SAMPLES,
    Setting,
    not_run,
    skipped,
    solvers,
    today,
)


def fmt_err(x: float | None) -> str:
    return "–" if x is None else f"{x:.1e}"


def fmt_ms(x: float | None) -> str:
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
    return (fmt_ms(w["wall_s"]), _rate(w["failures"], w["statuses"], r["samples"]),
            fmt_err(w["max_rel_err"]))


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
        f"Date: {', '.join(dates) or today()}. Machine: {MACHINE}, {_cpu()}.  ",
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
                f"Reference: {r0['reference']} (its max residual {fmt_err(r0['reference_max_residual'])}); "
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
                    f"{fmt_err(r['max_rel_err'])} | {fmt_err(r['max_err'])} | {fmt_err(r['max_residual'])} | "
                    f"{fmt_ms(r['cold_wall_s'])} | {fmt_ms(r['warm_wall_s'])} | {fmt_ms(r['warm_solver_s'])} | "
                    f"{fmt_ms(r['warm_direct_s'])} | {fmt_ms(r['warm_overhead_s'])} | {w[0]} | {w[1]} | "
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
