"""Effect of the differentiable solver path on learning: e_test and wall time per path.

Fig. 1(a)'s cells ``n_lam = 4`` and ``12`` (``n_x = 10``, ``n_u = 4``, truth stiffness 0.5,
noise 1e-2; ``studies/configs/fig1a_n_lam.toml``: the same seeds for the truth, the data, the
initialisation and the minibatch order as that study's trials 0, 1, 2), both losses, trained
by the paper's protocol at a short budget through each differentiable path of
:mod:`studies.solvers.differentiable_paths` that is fast enough.

Protocol (the ``"paper"`` recipe of :func:`lcs_cvx.fit` with the config's options): Adam
(betas (0.9, 0.9), eps 1e-6), constant learning rate (prediction 1e-3, violation 5e-3), batch
200, the objective ``L + omega ||C||_F^2`` with the config's ``gamma``, ``eps`` and ``omega`` in
the authors' convention (violation: ``gamma = 5e-3``, ``eps = 2e-4``, ``omega = 5e-7``;
prediction: ``omega = 1e-6``), the learner ``lcs_cvx.LCS(stiffness=1.0, init_scale=0.1)``; a
fresh permutation of the training set every epoch from the generator ``fit`` seeds. The budget
is shortened: :data:`ITERATIONS` Adam steps on :data:`N_TRAIN` training samples (the paper:
10,000 steps on 50,000), 1,000 noiseless test samples. Every path runs the same loop, written
here (``lcs_cvx.fit`` has no solver option): the minibatch loss of the path (the loss and its
gradient as in :func:`studies.solvers.differentiable_paths.loss_and_lam`), plus the
regulariser, one Adam step. The row ``fit`` is :func:`lcs_cvx.fit` itself (``recipe="paper"``,
the same options and seed) on the fast path: it checks that the loop here is the package's
protocol.

A path is trained when its loss + gradient reaches :data:`MIN_RATE` samples/s at batch 200:
the rate of :mod:`studies.solvers.differentiable_paths` (``OUT/differentiable_paths.jsonl``,
the same loss at ``n_lam = 4``) where it measured the size, else timed on the cell's first 200
samples at the initial model (median of 5 calls after a warm-up); a path below is reported as
"too slow: N samples/s".

Reported per (n_lam, loss, path): e_test (:func:`lcs_cvx.relative_error`, the paper's
``sum ||x'_theta - x'||^2 / sum ||x'||^2`` on the test set with the exact LCP), its mean, min
and max over the trials, the largest difference of a trial's e_test from the fast path's on the
same trial (relative), and the training wall time (s, one thread). A run that raises or
diverges is reported with its error.

    python -m studies.solvers.learning_effect --out studies/results/solvers [--smoke]

Writes ``OUT/learning_effect.jsonl`` (one line per (n_lam, loss, path, trial); a rerun skips
finished runs), ``OUT/learning_effect.md`` and ``OUT/learning_effect.png`` (``--smoke``:
``learning_effect_smoke.*``: ``n_lam = 4``, one trial, 20 steps on 1,000 samples).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

import lcs_cvx  # noqa: E402
from lcs_cvx.losses import regularizer  # noqa: E402
from lcs_cvx.study.cells import expand, setup_cell  # noqa: E402
from lcs_cvx.study.config import load_config  # noqa: E402

from . import differentiable_paths_cells as dp  # noqa: E402
from . import records  # noqa: E402
from .differentiable_paths_report import versions  # noqa: E402

DATE = time.strftime("%Y-%m-%d")
MACHINE = dp.MACHINE
CONFIG = Path(__file__).resolve().parents[1] / "configs" / "fig1a_n_lam.toml"
N_LAMS = (4, 12)
TRIALS = 3
ITERATIONS = 400
N_TRAIN = 10_000
BATCH = 200
LOSSES = ("violation", "prediction")
#: the training loop's paths (``fit``: lcs_cvx.fit on the fast path)
PATHS = ("fit", *dp.PATHS)
#: a path slower than this (loss + gradient, batch 200) is not trained
MIN_RATE = 1_000.0
SMOKE = {"n_lams": (4,), "trials": 1, "iterations": 20, "n_train": 1_000}


def cells(n_lams: tuple[int, ...], trials: int, n_train: int, iterations: int) -> list[dict]:
    """Fig. 1(a)'s cells for ``n_lams`` and trials ``< trials``, with the shorter budget."""
    config = load_config(CONFIG)
    out = []
    for c in expand(config):
        if c["value"] in n_lams and c["trial"] < trials and c["method"] in LOSSES:
            c = json.loads(json.dumps(c))
            c["data"]["n_train"] = n_train
            c["fit"]["iterations"] = iterations
            out.append(c)
    return out


def _step_loss(loss: str, path: str, model, x, u, xn, opts: dict) -> torch.Tensor:
    value, _ = dp.loss_and_lam(loss, path, model, x, u, xn,
                               gamma=opts.get("gamma", dp.GAMMA), eps=opts.get("eps", dp.EPS))
    return value + regularizer(model, opts["reg"])


def _with_dtype(path: str):
    """ProxSuite's QPLayer allocates its gradients in the default dtype: float64 around it."""
    class _Ctx:
        def __enter__(self):
            self.old = torch.get_default_dtype()
            if path == "qplayer":
                torch.set_default_dtype(torch.float64)

        def __exit__(self, *exc):
            torch.set_default_dtype(self.old)
    return _Ctx()


def probe_rate(loss: str, path: str, model, train, opts: dict) -> float:
    """Samples/s of loss + gradient at batch 200 on the first 200 samples (median of 5 calls
    after one warm-up call)."""
    x, u, xn = train.x[:BATCH], train.u[:BATCH], train.x_next[:BATCH]
    times = []
    for k in range(6):
        t0 = time.perf_counter()
        with _with_dtype(path):
            model.zero_grad()
            _step_loss(loss, path, model, x, u, xn, opts).backward()
        if k:
            times.append(time.perf_counter() - t0)
    model.zero_grad()
    return BATCH / statistics.median(times)


def train_loop(loss: str, path: str, model, train, opts: dict, seed: int) -> tuple[float, float]:
    """The paper protocol's Adam phase (as :func:`lcs_cvx.fit` runs it with one restart);
    returns (wall seconds, mean loss of the last 50 steps)."""
    a = lcs_cvx.RECIPES["paper"].replace(**{k: v for k, v in opts.items() if k in ("lr", "batch_size")}).adam
    gen = torch.Generator().manual_seed(seed * 1_000_003 + 0)
    adam = torch.optim.Adam(model.parameters(), lr=a.lr, betas=a.betas, eps=a.adam_eps)
    n = len(train)
    perm, pos = torch.randperm(n, generator=gen), 0
    size = min(a.batch_size, n)
    tail: list[float] = []
    t0 = time.perf_counter()
    for it in range(opts["iterations"]):
        if pos + size > len(perm):
            perm, pos = torch.randperm(n, generator=gen), 0
        idx = perm[pos:pos + size]
        pos += size
        with _with_dtype(path):
            adam.zero_grad()
            value = _step_loss(loss, path, model, train.x[idx], train.u[idx], train.x_next[idx], opts)
            value.backward()
        adam.step()
        v = float(value.detach())
        if not (math.isfinite(v) and bool(torch.isfinite(model.F).all())):
            raise lcs_cvx.SolverError(f"training diverged at iteration {it + 1}: loss = {v}")
        tail = (tail + [v])[-50:]
    return time.perf_counter() - t0, statistics.fmean(tail)


def run_one(cell: dict, path: str, rate: float | None) -> dict:
    truth, train, test, learner, opts = setup_cell(cell)
    loss = cell["method"]
    seed = cell["seeds"]["fit"]
    row = {"n_lam": cell["value"], "loss": loss, "path": path, "trial": cell["trial"],
           "iterations": opts["iterations"], "n_train": len(train), "batch": BATCH,
           "options": {k: v for k, v in opts.items() if k != "eval_every"},
           "date": DATE, "machine": MACHINE, "status": "ok"}
    t_start = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if path == "fit":
                res = lcs_cvx.fit(learner, train, test=test, recipe="paper", progress=False,
                                  seed=seed, **opts)
                row.update(wall_s=res.wall_time, final_loss=res.history[-1]["loss"]
                           if res.history else None)
            else:
                if rate is None:
                    rate = probe_rate(loss, path, learner, train, opts)
                row["rate_200"] = rate
                if rate < MIN_RATE:
                    row.update(status="too slow", note=f"too slow: {rate:,.0f} samples/s")
                    row["row_seconds"] = time.perf_counter() - t_start
                    return row
                wall, final = train_loop(loss, path, learner, train, opts, seed)
                row.update(wall_s=wall, final_loss=final)
            row["e_test"] = lcs_cvx.relative_error(learner, test)
    except Exception as exc:  # a failed path is a result
        row.update(status="error", error=f"{type(exc).__name__}: {str(exc)[:300]}")
    row["row_seconds"] = time.perf_counter() - t_start
    return row


def paths_rates(path: Path) -> dict[tuple, float]:
    """``(loss, n_lam, path) -> samples/s`` at batch 200 of the differentiable-paths study at
    ``n_x = 10, n_u = 4`` (its model is a mid-training one: the rate that decides whether a
    path is trained); sizes it did not measure are timed on the cell instead."""
    rates: dict[tuple, float] = {}
    if path.exists():
        for line in path.read_text().splitlines():
            r = json.loads(line) if line.strip() else {}
            if r.get("batch") == 200 and r.get("status") == "ok" and (r["n_x"], r["n_u"]) == (10, 4):
                rates[(r["loss"], r["n_lam"], r["path"])] = r["samples_per_s"]
    return rates


def load(path: Path) -> dict[tuple, dict]:
    return records.load(path, lambda r: (r["n_lam"], r["loss"], r["path"], r["trial"]))


def run(out: Path, smoke: bool = False, paths: tuple[str, ...] = PATHS,
        log: Callable[[str], None] = print) -> dict[tuple, dict]:
    torch.set_num_threads(1)
    out.mkdir(parents=True, exist_ok=True)
    stem = "learning_effect_smoke" if smoke else "learning_effect"
    jpath = out / f"{stem}.jsonl"
    done = load(jpath)
    plan = SMOKE if smoke else {"n_lams": N_LAMS, "trials": TRIALS, "iterations": ITERATIONS,
                                "n_train": N_TRAIN}
    todo = cells(plan["n_lams"], plan["trials"], plan["n_train"], plan["iterations"])
    measured = {} if smoke else paths_rates(out / "differentiable_paths.jsonl")
    for cell in sorted(todo, key=lambda c: (c["value"], c["method"], c["trial"])):
        for path in paths:
            key = (cell["value"], cell["method"], path, cell["trial"])
            if key in done:
                continue
            # a path found too slow on an earlier trial is not probed again
            earlier = [r for (n, lo, p, _), r in done.items()
                       if (n, lo, p) == key[:3] and r.get("rate_200") is not None]
            rate, source = (earlier[0]["rate_200"], earlier[0]["rate_source"]) if earlier else (
                measured.get((cell["method"], cell["value"], path)), "differentiable_paths study")
            row = run_one(cell, path, rate)
            if row.get("rate_200") is not None:
                row["rate_source"] = source if rate is not None else "timed on the cell"
            with jpath.open("a") as fh:
                fh.write(json.dumps(row) + "\n")
            done[key] = row
            log(f"n_lam={key[0]:<3d} {key[1]:10s} {path:17s} trial {key[3]} {row['status']:8s} "
                f"e_test {_e(row.get('e_test'))} wall {_s(row.get('wall_s'))} "
                f"rate {_r(row.get('rate_200'))} [{row['row_seconds']:.1f} s]")
    report(done, out, stem, plan, paths, smoke)
    return done


# -- report ---------------------------------------------------------------------------------------
def _e(x: float | None) -> str:
    return "–" if x is None else f"{x:.2e}"


def _s(x: float | None) -> str:
    return "–" if x is None else f"{x:.1f} s"


def _r(x: float | None) -> str:
    return "–" if x is None else f"{x:,.0f}/s"


def stats(done: dict, n_lam: int, loss: str, path: str, trials: int) -> dict:
    rows = [done.get((n_lam, loss, path, t)) for t in range(trials)]
    rows = [r for r in rows if r is not None]
    ok = [r for r in rows if r["status"] == "ok"]
    out = {"rows": rows, "ok": ok}
    if ok:
        e = [r["e_test"] for r in ok]
        out.update(mean=statistics.fmean(e), lo=min(e), hi=max(e),
                   wall=statistics.fmean(r["wall_s"] for r in ok))
        fast = {r["trial"]: r["e_test"] for r in (done.get((n_lam, loss, "fast", t))
                                                   for t in range(trials))
                if r is not None and r["status"] == "ok"}
        d = [abs(r["e_test"] - fast[r["trial"]]) / fast[r["trial"]] for r in ok if r["trial"] in fast]
        out["dfast"] = max(d) if d else None
    return out


def report(done: dict, out: Path, stem: str, plan: dict, paths, smoke: bool) -> None:
    cmd = "python -m studies.solvers.learning_effect --out " + str(out) + (" --smoke" if smoke else "")
    trials = plan["trials"]
    lines = [
        "# Effect of the differentiable solver path on learning",
        "",
        f"Command: `{cmd}` (resumable: one JSON line per (n_λ, loss, path, trial) in "
        f"`{stem}.jsonl`).  ",
        f"Date: {DATE}. Machine: {MACHINE} ({platform.machine()}, Python "
        f"{platform.python_version()}).  ",
        f"Versions: {versions()}.",
        "",
        f"Fig. 1(a) cells n_λ ∈ {list(plan['n_lams'])} (n_x = 10, n_u = 4, stiffness 0.5, "
        f"noise 1e-2; the seeds of `studies/configs/fig1a_n_lam.toml`, trials 0–{trials - 1}); "
        f"the paper protocol at a short budget: **{plan['iterations']} Adam steps of batch "
        f"{BATCH} on {plan['n_train']:,} training samples** (paper: 10,000 steps on 50,000), "
        "1,000 noiseless test samples, Adam betas (0.9, 0.9), constant lr (prediction 1e-3, "
        "violation 5e-3), γ = 5e-3, ε = 2e-4, ω = 5e-7 (violation) / ω = 1e-6 (prediction), "
        "learner `LCS(stiffness=1.0, init_scale=0.1)`. Every path runs the same Adam loop "
        "(written in the study: `lcs_cvx.fit` has no solver option); `fit` is `lcs_cvx.fit` "
        "itself (`recipe=\"paper\"`, fast path), the check that the loop is the package's "
        f"protocol. A path is trained when its loss + gradient at batch {BATCH} reaches "
        f"{MIN_RATE:,.0f} samples/s (n_λ = 4: the rate of `differentiable_paths.md`; n_λ = 12: "
        "timed on the cell at the initial model); otherwise \"too slow\". e_test = "
        "`lcs_cvx.relative_error` (exact LCP); **max |Δ| vs fast** = the largest relative "
        "difference of a trial's e_test from the `fast` path's on the same trial; wall = "
        "training time per run (mean over trials, one thread; for `fit`, `FitResult.wall_time`, "
        "which also holds its e_test records every 100 steps and, in the process's first run, "
        "one-off start-up costs).",
        "",
        "| n_λ | loss | path | e_test mean | e_test min – max | max rel. Δ vs fast | wall s / run | "
        "× fast wall | samples/s @ 200 | status |",
        "|---:|---|---|---:|---|---:|---:|---:|---:|---|",
    ]
    for n_lam in plan["n_lams"]:
        for loss in LOSSES:
            fast = stats(done, n_lam, loss, "fast", trials)
            for path in paths:
                st = stats(done, n_lam, loss, path, trials)
                if not st["rows"]:
                    continue
                status = sorted({r.get("note") or r.get("error") or r["status"] for r in st["rows"]})
                rate = next((r["rate_200"] for r in st["rows"] if r.get("rate_200")), None)
                if st["ok"]:
                    ratio = f"{st['wall'] / fast['wall']:.1f}" if fast.get("wall") else "–"
                    lines.append(
                        f"| {n_lam} | {loss} | {path} | {st['mean']:.2e} | {st['lo']:.2e} – "
                        f"{st['hi']:.2e} | {_e(st['dfast'])} | {st['wall']:.1f} | {ratio} | "
                        f"{_r(rate)} | {'; '.join(status)} ({len(st['ok'])}/{len(st['rows'])}) |")
                else:
                    lines.append(f"| {n_lam} | {loss} | {path} | – | – | – | – | – | {_r(rate)} | "
                                 f"{'; '.join(status)} |")
    lines += ["", "## Summary", "", summary(done, plan, paths), ""]
    (out / f"{stem}.md").write_text("\n".join(lines))
    try:
        plot(done, out / f"{stem}.png", plan, paths)
    except ImportError:
        pass


def summary(done: dict, plan: dict, paths) -> str:
    trials = plan["trials"]
    out = []
    for n_lam in plan["n_lams"]:
        for loss in LOSSES:
            fast = stats(done, n_lam, loss, "fast", trials)
            if not fast["ok"]:
                continue
            parts = []
            for p in paths:
                if p == "fast":
                    continue
                st = stats(done, n_lam, loss, p, trials)
                if not st["rows"]:
                    continue
                if not st["ok"]:
                    parts.append(f"{p}: {st['rows'][0].get('note') or st['rows'][0].get('error') or st['rows'][0]['status']}")
                    continue
                parts.append(f"{p}: e_test within {_e(st['dfast'])} (rel.) of fast, "
                             f"{st['wall'] / fast['wall']:.0f}× its wall time")
            out.append(f"- n_λ = {n_lam}, {loss}: fast e_test {fast['mean']:.2e} "
                       f"({fast['lo']:.2e} – {fast['hi']:.2e}), {fast['wall']:.1f} s per run; "
                       + "; ".join(parts) + ".")
    # the answer: is a path's e_test difference from fast above the spread over trials?
    within, beyond, failed = [], [], []
    for n_lam in plan["n_lams"]:
        for loss in LOSSES:
            fast = stats(done, n_lam, loss, "fast", trials)
            if not fast["ok"]:
                continue
            spread = fast["hi"] / fast["lo"] - 1.0
            for p in paths:
                if p in ("fast", "fit"):
                    continue
                st = stats(done, n_lam, loss, p, trials)
                if any(r["status"] == "error" for r in st["rows"]):
                    failed.append(f"{p} ({loss}, n_λ = {n_lam})")
                if st["ok"] and st.get("dfast") is not None:
                    tag = f"{p} ({loss}, n_λ = {n_lam}: {st['dfast']:.1e} vs spread {spread:.0%})"
                    (within if st["dfast"] < spread else beyond).append(tag)
    if trials > 1 and (within or beyond or failed):
        out.append(
            "- Does the solver change e_test? The largest relative difference of a trial's "
            "e_test from the fast path's on the same trial, against the fast path's spread over "
            f"the trials (max/min − 1): below it for {', '.join(within) or 'none'}"
            + (f"; above it for {', '.join(beyond)}" if beyond else "")
            + (f"; runs failed for {', '.join(failed)}" if failed else "") + ". "
            "What it costs is wall time: the column × fast wall.")
    return "\n".join(out)


def plot(done: dict, path: Path, plan: dict, paths) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(n, lo) for n in plan["n_lams"] for lo in LOSSES]
    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 4), squeeze=False)
    for ax, (n_lam, loss) in zip(axes[0], panels, strict=True):
        for k, p in enumerate(paths):
            st = stats(done, n_lam, loss, p, plan["trials"])
            for r in st["ok"]:
                ax.scatter(r["wall_s"], r["e_test"], color=f"C{k}", s=20)
            ax.scatter([], [], color=f"C{k}", label=p)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("training wall time per run [s]")
        ax.set_title(f"n_λ = {n_lam}, {loss}", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("e_test")
    axes[0][-1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("studies/results/solvers"))
    ap.add_argument("--smoke", action="store_true", help="n_lam = 4, one trial, 20 steps")
    ap.add_argument("--paths", nargs="+", default=list(PATHS), choices=PATHS)
    args = ap.parse_args(argv)
    run(args.out, smoke=args.smoke, paths=tuple(args.paths), log=lambda s: print(s, flush=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
