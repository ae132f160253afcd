"""LCP algorithms for simulation and control: accuracy, failures and speed.

Compares, on ``0 <= lam _|_ F lam + q >= 0`` with ``F + F^T > 0`` (one ``F``, a batch of
``q``, as an LCS poses them): Lemke's method, projected Gauss--Seidel, semismooth
Fischer--Burmeister Newton, the convex problem (P) with OSQP (through CVXPY and directly) and
with Clarabel (``lcs_cvx.solve_lcp(..., method="cvxpy")``), and the package's batched block
principal pivoting (``lcs_cvx.solve_lcp(..., method="fast")``, compiled; and its array kernel,
``solve_lcp_fast(..., arrays="numpy")``). The algorithms other than the
package's are in :mod:`studies.solvers.lcp_algos`.

Problems (seeded; ``q`` uniform in ``[-1, 1]^n`` unless said):

- ``random``: ``F = G G^T + H - H^T + s I``, entries of ``G``, ``H`` uniform in ``[-1, 1]``,
  ``s = 0.5`` (:func:`lcs_cvx.random_lcs`'s ``F``);
- ``stiff``: ``G = 0``, ``s = 1e-5`` (Fig. 1(c)'s stiffest setting: ``F + F^T = 2e-5 I``,
  ``F`` nearly skew-symmetric);
- ``scaled``: ``D F D`` and ``D q`` with the ``random`` ``F``, ``D = diag(10^u)``,
  ``u ~ U[-2, 2]`` (rows and columns scaled by factors spanning 1e4; the same ``D`` on both
  sides keeps ``F + F^T > 0``);
- ``degenerate``: the ``random`` ``F``; ``q = w* - F lam*`` built from a known solution in which
  each index is, with equal odds, ``lam_i > 0 = w_i``, ``lam_i = 0 < w_i`` or
  ``lam_i = w_i = 0`` (at least one such degenerate index per sample).

Reference ``lam*``: the constructed solution (``degenerate``); else enumeration
(``method="brute"``) for ``n <= 12`` and batch <= 200; else the pivoting solution (its residual is
reported beside it). A sample fails when the method reports non-convergence, returns a
non-finite value, or leaves a relative LCP residual (``lcs_cvx.lcp.lcp_residual``) above
``1e-6``; failures are counted, never dropped.

    python -m studies.solvers.lcp_algorithms --out studies/results/solvers [--smoke]

Writes ``OUT/lcp_algorithms.jsonl`` (one line per (method, problem, n, batch); a rerun skips
finished cells), ``OUT/lcp_algorithms.md`` and ``OUT/lcp_algorithms.png`` (``--smoke``:
``lcp_algorithms_smoke.*``).
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
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

import lcs_cvx  # noqa: E402
from lcs_cvx.lcp import lcp_residual, solve_lcp_brute, solve_lcp_fast  # noqa: E402

from . import lcp_algos, records  # noqa: E402

DATE = "2026-11-25 (the two `pivoting` rows: 2026-11-26)"
MACHINE = "2-core x86-64 VM, 1 torch thread"
FAIL_RESIDUAL = 1e-6
ACC_BATCH = 200
#: estimated seconds above which a cell at the largest batch is skipped
SKIP_SECONDS = 60.0

Solver = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, dict]]


def _wrap(fn: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]) -> Solver:
    def run(F: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
        lam, ok = fn(F, q)
        return lam, ok, {}
    return run


def _pivoting(F: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", lcs_cvx.FallbackWarning)
        sol = lcs_cvx.solve_lcp(torch.from_numpy(F), torch.from_numpy(q), method="fast")
    return sol.lam.numpy(), np.ones(q.shape[0], dtype=bool), {"n_fallback": sol.n_fallback}


def _pivoting_arrays(F: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", lcs_cvx.FallbackWarning)
        sol = solve_lcp_fast(torch.from_numpy(F), torch.from_numpy(q), arrays="numpy")
    return sol.lam.numpy(), np.ones(q.shape[0], dtype=bool), {"n_fallback": sol.n_fallback}


def _clarabel(F: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    try:
        sol = lcs_cvx.solve_lcp(torch.from_numpy(F), torch.from_numpy(q), method="cvxpy")
    except lcs_cvx.SolverError:
        return np.full_like(q, np.nan), np.zeros(q.shape[0], dtype=bool), {}
    return sol.lam.numpy(), np.ones(q.shape[0], dtype=bool), {}


#: name -> (solver, description)
METHODS: dict[str, tuple[Solver, str]] = {
    "pivoting": (_pivoting, "lcs_cvx.solve_lcp(method='fast'): block principal pivoting, compiled "
                 "(one float64 CPU F: each sample pivoted on its own)"),
    "pivoting_arrays": (_pivoting_arrays, "the same pivoting in the array kernel "
                        "(solve_lcp_fast(arrays='numpy')): the whole batch per NumPy operation"),
    "lemke": (_wrap(lcp_algos.lemke), "Lemke, covering vector 1, lexicographic ratio test; "
              "Python loop over samples"),
    "pgs": (_wrap(lcp_algos.pgs), "projected Gauss-Seidel, batched; tol 1e-12, 1000 sweeps"),
    "fb_newton": (_wrap(lcp_algos.fb_newton), "semismooth Fischer-Burmeister Newton + Armijo, "
                  "batched; converged at residual 1e-10, 100 iterations"),
    "osqp_direct": (_wrap(lcp_algos.osqp_direct), "(P) in OSQP directly, one setup, per-sample "
                    "updates; eps 1e-10, polish"),
    "osqp_cvxpy": (_wrap(lcp_algos.osqp_cvxpy), "(P) declared by lcs_cvx.convex_lcp_problem, "
                   "OSQP through CVXPY per sample; eps 1e-10, polish"),
    "clarabel": (_clarabel, "lcs_cvx.solve_lcp(method='cvxpy'): (P), Clarabel per sample"),
}

PROBLEMS = ("random", "stiff", "scaled", "degenerate")


def make_problem(problem: str, n: int, batch: int, seed: int = 0
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``(F, q, lam_star)`` (``lam_star`` only for ``degenerate``), float64, seeded."""
    rng = np.random.default_rng([seed, n, PROBLEMS.index(problem)])
    G = rng.uniform(-1.0, 1.0, (n, n))
    H = rng.uniform(-1.0, 1.0, (n, n))
    if problem == "stiff":
        F = H - H.T + 1e-5 * np.eye(n)
    else:
        F = G @ G.T + H - H.T + 0.5 * np.eye(n)
    q = rng.uniform(-1.0, 1.0, (batch, n))
    lam_star = None
    if problem == "scaled":
        d = 10.0 ** rng.uniform(-2.0, 2.0, n)
        F = d[:, None] * F * d[None, :]
        q = q * d
    elif problem == "degenerate":
        kind = rng.integers(0, 3, (batch, n))
        kind[np.arange(batch), rng.integers(0, n, batch)] = 2  # at least one degenerate index
        lam_star = np.where(kind == 0, rng.uniform(0.1, 1.0, (batch, n)), 0.0)
        w_star = np.where(kind == 1, rng.uniform(0.1, 1.0, (batch, n)), 0.0)
        q = w_star - lam_star @ F.T
    return F, q, lam_star


def reference(problem: str, F: np.ndarray, q: np.ndarray, lam_star: np.ndarray | None
              ) -> tuple[np.ndarray, str, float]:
    """``(lam_ref, kind, its max residual)``."""
    Ft, qt = torch.from_numpy(F), torch.from_numpy(q)
    if lam_star is not None:
        lam, kind = lam_star, "constructed"
    elif q.shape[1] <= 12 and q.shape[0] <= ACC_BATCH:
        lam, kind = solve_lcp_brute(Ft, qt).lam.numpy(), "brute"
    else:
        lam, kind = _pivoting(F, q)[0], "pivoting"
    res = float(lcp_residual(Ft, qt, torch.from_numpy(lam)).max())
    return lam, kind, res


def _time(fn: Solver, F: np.ndarray, q: np.ndarray, repeats: int
          ) -> tuple[float, int, tuple[np.ndarray, np.ndarray, dict]]:
    times, out = [], None
    for k in range(repeats):
        t0 = time.perf_counter()
        out = fn(F, q)
        times.append(time.perf_counter() - t0)
        if k == 0 and times[0] > 5.0:
            break
    return float(np.median(times)), len(times), out


def _f(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def run_cell(method: str, problem: str, n: int, batch: int, seed: int = 0) -> dict:
    fn = METHODS[method][0]
    F, q, lam_star = make_problem(problem, n, batch, seed)
    lam_ref, ref_kind, ref_res = reference(problem, F, q, lam_star)
    repeats = 7 if batch == 1 else 3
    fn(F, q[:1])  # warm-up (CVXPY compilation, imports)
    t, reps, (lam, ok, extra) = _time(fn, F, q, repeats)
    finite = np.isfinite(lam).all(-1)
    lam_c = np.where(finite[:, None], lam, 0.0)
    res = lcp_residual(torch.from_numpy(F), torch.from_numpy(q), torch.from_numpy(lam_c)).numpy()
    res = np.where(finite, res, np.inf)
    err = np.where(finite, np.abs(lam_c - lam_ref).max(-1), np.inf)
    rel = err / (1.0 + np.abs(lam_ref).max(-1))
    fail = ~ok | ~finite | (res > FAIL_RESIDUAL)
    return {
        "method": method, "problem": problem, "n": n, "batch": batch, "seed": seed,
        "reference": ref_kind, "reference_residual": ref_res,
        "time_s": t, "repeats": reps, "time_per_sample_s": t / batch, "samples_per_s": batch / t,
        "max_abs_err": _f(err.max()), "median_abs_err": _f(float(np.median(err))),
        "max_rel_err": _f(rel.max()), "max_residual": _f(res.max()),
        "median_residual": _f(float(np.median(res))),
        "n_fail": int(fail.sum()), "n_not_converged": int((~ok).sum()),
        "fail_rate": float(fail.mean()), "skipped": None, **extra,
    }


def plan(smoke: bool) -> tuple[list[tuple[str, str, int, int]], tuple[int, ...], int]:
    """Cells in run order: accuracy cells (every problem, batch ``ACC_BATCH``) first, then the
    speed cells (``random``, the other batches; the largest last)."""
    ns = (3,) if smoke else (4, 10, 20)
    acc = 20 if smoke else ACC_BATCH
    big = 50 if smoke else 50_000
    cells = [(m, p, n, acc) for n in ns for p in PROBLEMS for m in METHODS]
    cells += [(m, "random", n, 1) for n in ns for m in METHODS]
    cells += [(m, "random", n, big) for n in ns for m in METHODS]
    return cells, ns, acc


def load(path: Path) -> dict[tuple, dict]:
    return records.load(path, lambda r: (r["method"], r["problem"], r["n"], r["batch"]))


def run(out: Path, smoke: bool = False, log: Callable[[str], None] = print) -> dict[tuple, dict]:
    torch.set_num_threads(1)
    out.mkdir(parents=True, exist_ok=True)
    stem = "lcp_algorithms_smoke" if smoke else "lcp_algorithms"
    jpath = out / f"{stem}.jsonl"
    done = load(jpath)
    cells, ns, acc = plan(smoke)
    big = max(b for *_, b in cells)
    with jpath.open("a") as fh:
        for key in cells:
            if key in done:
                continue
            method, problem, n, batch = key
            if batch == big and not smoke:
                base = done.get((method, "random", n, acc))
                est = base["time_per_sample_s"] * batch if base else 0.0
                if est > SKIP_SECONDS:
                    rec = {"method": method, "problem": problem, "n": n, "batch": batch,
                           "skipped": f"estimated {est:.0f} s > {SKIP_SECONDS:.0f} s "
                                      f"(from batch {acc})"}
                    done[key] = rec
                    fh.write(json.dumps(rec) + "\n")
                    fh.flush()
                    log(f"skip {key}: {rec['skipped']}")
                    continue
            rec = run_cell(method, problem, n, batch)
            done[key] = rec
            fh.write(json.dumps(rec) + "\n")
            fh.flush()
            log(f"{method:12s} {problem:10s} n={n:3d} B={batch:6d} {rec['samples_per_s']:10.1f}/s "
                f"err {rec['max_abs_err']} res {rec['max_residual']} fail {rec['n_fail']}")
    report(done, out, stem, ns, acc, big, smoke)
    return done


def _e(x: float | None) -> str:
    return "inf/nan" if x is None else f"{x:.1e}"


def _rate(x: float) -> str:
    return f"{x:,.0f}" if x >= 10 else f"{x:.2g}"


def report(done: dict[tuple, dict], out: Path, stem: str, ns: tuple[int, ...], acc: int, big: int,
           smoke: bool) -> None:
    methods = list(METHODS)
    cmd = "python -m studies.solvers.lcp_algorithms --out " + str(out) + (" --smoke" if smoke else "")
    L = [
        "# LCP algorithms: accuracy, failures, speed",
        "",
        f"Command: `{cmd}`. Date {DATE}; machine: {MACHINE} (NumPy/BLAS one thread). "
        "Study code: `studies/solvers/lcp_algorithms.py`, algorithms `studies/solvers/lcp_algos.py`.",
        "",
        "The LCP `0 <= lam ⟂ F lam + q >= 0`, one `F` per (problem, n) and a batch of `q`. "
        "Problems: `random` (`F = GGᵀ + H − Hᵀ + 0.5 I`), `stiff` (`G = 0`, `s = 1e-5`: "
        "`F + Fᵀ = 2e-5 I`), `scaled` (`D F D`, `D q`, `D` spanning 1e4), `degenerate` "
        "(constructed solution with `lam_i = w_i = 0` entries). Reference: enumeration "
        "(`brute`, n <= 12), the constructed solution (`degenerate`), else the pivoting solution. "
        f"A sample fails if the method reports non-convergence, is non-finite, or its relative "
        f"LCP residual `|min(lam, w)|_inf / (1 + |q|_inf)` exceeds {FAIL_RESIDUAL:g}.",
        "",
        "| method | what |",
        "| --- | --- |",
    ]
    L += [f"| `{m}` | {d} |" for m, (_, d) in METHODS.items()]
    L += ["", f"## Accuracy and failures (batch {acc})", "",
          "Each entry: max |lam − lam*| / max residual / failures out of the batch.", ""]
    for p in PROBLEMS:
        refs = [f"n = {n}: {r['reference']} (max residual {_e(r['reference_residual'])})"
                for n in ns for r in [done.get(("pivoting", p, n, acc))]
                if r and "reference" in r]
        L += [f"**{p}** -- reference " + ", ".join(refs), "",
              "| method | " + " | ".join(f"n = {n}" for n in ns) + " |",
              "| --- | " + " | ".join("---" for _ in ns) + " |"]
        for m in methods:
            row = []
            for n in ns:
                r = done.get((m, p, n, acc))
                row.append("–" if r is None or r.get("skipped") else
                           f"{_e(r['max_abs_err'])} / {_e(r['max_residual'])} / {r['n_fail']}")
            L.append(f"| `{m}` | " + " | ".join(row) + " |")
        L.append("")
    batches = (1, acc, big)
    L += ["## Speed (`random`, samples/s, median of repeats)", "",
          "| method | " + " | ".join(f"n={n}, B={b:,}" for n in ns for b in batches) + " |",
          "| --- | " + " | ".join("---:" for _ in ns for _ in batches) + " |"]
    skipped = []
    for m in methods:
        row = []
        for n in ns:
            for b in batches:
                r = done.get((m, "random", n, b))
                if r is None:
                    row.append("–")
                elif r.get("skipped"):
                    row.append("skipped")
                    skipped.append(f"`{m}` n = {n}, B = {b:,}: {r['skipped']}")
                else:
                    f = f" ({r['n_fail']} fail)" if r["n_fail"] else ""
                    row.append(_rate(r["samples_per_s"]) + f)
        L.append(f"| `{m}` | " + " | ".join(row) + " |")
    L.append("")
    if skipped:
        L += ["Skipped: " + "; ".join(skipped) + ".", ""]
    L += ["## Which to use", "", advice(done, ns, acc, big), ""]
    (out / f"{stem}.md").write_text("\n".join(L))
    plot(done, out / f"{stem}.png", acc)


def advice(done: dict[tuple, dict], ns: tuple[int, ...], acc: int, big: int) -> str:
    """A paragraph computed from the cells."""
    fails: dict[str, list[str]] = {}
    for (m, p, n, b), r in done.items():
        if b == acc and not r.get("skipped") and r["n_fail"]:
            fails.setdefault(m, []).append(f"{p} n={n} ({r['n_fail']}/{b})")
    robust = [m for m in METHODS if m not in fails]
    parts = []
    robust_s = ", ".join(f"`{m}`" for m in robust) if robust else "none"
    parts.append(f"Methods with no failure on any problem at batch {acc}: {robust_s}.")
    for m, f in fails.items():
        parts.append(f"`{m}` fails on " + ", ".join(f) + ".")
    for b in (1, acc, big):
        rates = {m: r["samples_per_s"] for m in robust for n in [ns[len(ns) // 2]]
                 if (r := done.get((m, "random", n, b))) and not r.get("skipped")}
        if len(rates) >= 2:
            order = sorted(rates, key=rates.get, reverse=True)
            parts.append(f"Fastest failure-free method at n = {ns[len(ns) // 2]}, batch {b:,}: "
                         f"`{order[0]}` ({_rate(rates[order[0]])} samples/s, "
                         f"{rates[order[0]] / rates[order[1]]:.1f}x `{order[1]}`).")
    parts.append(
        "For batches of LCPs with one `F` (simulation rollouts, training losses), a batched "
        "exact active-set method is the choice when it is failure-free and fastest above; "
        "an iterative method (PGS, FB Newton) only pays where its failures are acceptable or "
        "a warm start makes it cheap; the QP routes (OSQP, Clarabel) are references, "
        "limited by per-sample setup and calls.")
    return " ".join(parts)


def plot(done: dict[tuple, dict], path: Path, acc: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    markers = dict(zip(METHODS, "osD^vpX*h", strict=False))
    colors = dict(zip(PROBLEMS, ("C0", "C1", "C2", "C3"), strict=True))
    fig, ax = plt.subplots(figsize=(7.5, 5))
    for (m, p, n, b), r in sorted(done.items()):
        if b != acc or r.get("skipped"):
            continue
        y = r["max_rel_err"]
        y = 1e2 if y is None else max(y, 1e-17)
        ax.scatter(r["time_per_sample_s"], y, marker=markers[m], color=colors[p],
                   s=20 + 3 * n, alpha=0.8, edgecolors="k", linewidths=0.3)
    for m, mk in markers.items():
        ax.scatter([], [], marker=mk, color="gray", label=m)
    for p, c in colors.items():
        ax.scatter([], [], marker="s", color=c, label=p)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(f"time per sample [s] (batch {acc}, 1 thread)")
    ax.set_ylabel("max |lam − lam*| / (1 + |lam*|)")
    ax.set_title("LCP algorithms: accuracy vs time (marker size ~ n;\n"
                 "floored at 1e-17, non-finite drawn at 1e2)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("studies/results/solvers"))
    ap.add_argument("--smoke", action="store_true", help="n = 3, batches 1/20/50 (seconds)")
    args = ap.parse_args(argv)
    run(args.out, smoke=args.smoke, log=lambda s: print(s, flush=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
