"""Time a training iteration per model: K models trained one after another with ``lcs_cvx.fit``
(the per-cell loop of ``lcs-cvx study run``) against the same K models in one
``lcs_cvx.fit_ensemble``, side by side in one process, one torch thread.

Every model is a cell of Fig. 1(a)'s kind (``n_x = 10``, ``n_u = 4``, the truth's stiffness 0.5,
the learner's 1.0, ``init_scale`` 0.1, noise 1e-2) trained with the "paper" recipe and the
authors' constants (violation: lr 5e-3, gamma 5e-3, eps 2e-4, reg 5e-7; prediction: lr 1e-3),
batch 200, on its own truth and data. The training sets are small (``--n-train``, default
1,000: five minibatches an epoch) so that the warm starts of the pivoting, which hold in all but
the first epoch of a paper-length run, hold in all but the first five iterations here. No test
set: e_test costs the same per model on both paths.

For each round, for each (n_lam, K), both paths train fresh copies of the same K models for
``--iterations`` steps, in alternating order; the table gives the median over rounds of the
wall time per iteration per model, and per-cell / ensemble.

    python studies/ensemble_timing.py [--n-lam 4 8 20] [--models 1 5 10 30] [--loss violation]
        [--iterations 50] [--rounds 3] [--out FILE]
"""

from __future__ import annotations

import argparse
import copy
import platform
import statistics
import time
import warnings

import torch

import lcs_cvx

OPTIONS = {
    "violation": {"lr": 5e-3, "gamma": 5e-3, "eps": 2e-4, "reg": 5e-7},
    "prediction": {"lr": 1e-3, "reg": 1e-6},
}


def cells(n_lam: int, K: int, n_train: int) -> tuple[list, list]:
    """K learners and their training sets, each from its own truth."""
    models, trains = [], []
    for k in range(K):
        truth = lcs_cvx.random_lcs(10, 4, n_lam, stiffness=0.5, seed=1000 + k)
        trains.append(lcs_cvx.make_dataset(truth, n_train, noise=0.01, seed=2000 + k))
        models.append(lcs_cvx.LCS(10, 4, n_lam, stiffness=1.0, init_scale=0.1, seed=3000 + k))
    return models, trains


def per_cell(models, trains, kw) -> float:
    t0 = time.perf_counter()
    for k, m in enumerate(models):
        lcs_cvx.fit(copy.deepcopy(m), trains[k], seed=k, progress=False, **kw)
    return time.perf_counter() - t0


def ensemble(models, trains, kw) -> float:
    t0 = time.perf_counter()
    lcs_cvx.fit_ensemble([copy.deepcopy(m) for m in models], trains, seeds=list(range(len(models))),
                         progress=False, **kw)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n-lam", type=int, nargs="+", default=[4, 8, 20])
    ap.add_argument("--models", type=int, nargs="+", default=[1, 5, 10, 30])
    ap.add_argument("--loss", choices=sorted(OPTIONS), default="violation")
    ap.add_argument("--iterations", type=int, default=50)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--n-train", type=int, default=1000)
    ap.add_argument("--out", default=None, help="also write the table here")
    args = ap.parse_args()
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")
    kw = {"recipe": "paper", "loss": args.loss, "iterations": args.iterations, "batch_size": 200,
          "eval_every": args.iterations, **OPTIONS[args.loss]}
    grid = [(n, K) for n in args.n_lam for K in args.models]
    data = {(n, K): cells(n, K, args.n_train) for n, K in grid}
    ensemble(*cells(2, 2, 400), {**kw, "iterations": 2})  # the first Adam's one-off imports
    times: dict[tuple, dict[str, list[float]]] = {g: {"cell": [], "ens": []} for g in grid}
    for r in range(args.rounds):
        for g in grid:
            runs = [("cell", per_cell), ("ens", ensemble)]
            for name, fn in (runs if r % 2 == 0 else runs[::-1]):
                times[g][name].append(fn(*data[g], kw) / (args.iterations * g[1]) * 1e3)
        print(f"round {r + 1}/{args.rounds} done", flush=True)
    lines = [
        f"{args.loss} loss, paper recipe, batch 200, {args.iterations} iterations, "
        f"{args.n_train} training samples per model, median of {args.rounds} rounds; "
        f"{platform.machine()}, torch {torch.__version__}, one torch thread",
        "",
        "| n_lam | K | per-cell loop (ms / it / model) | ensemble (ms / it / model) | per-cell / ensemble |",
        "|---:|---:|---:|---:|---:|",
    ]
    for (n, K), t in times.items():
        c, e = statistics.median(t["cell"]), statistics.median(t["ens"])
        lines.append(f"| {n} | {K} | {c:.3f} | {e:.3f} | {c / e:.2f} |")
    text = "\n".join(lines)
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
