"""Does knowing A and B help? e_test against the training size and against the Adam budget,
learning everything vs with ``A`` and ``B`` fixed to the truth (``LCS.fix(A=..., B=...)``).

    python studies/known_structure.py [--sizes 200,500,1000,5000] [--seeds 0,1,2,3]
        [--budgets 500,1000,2000] [--budget-size 1000] [--out FILE]

Protocol (as the Fig. 1 studies, studies/README.md): ground truth ``random_lcs(4, 2, 3, seed=s)``,
training noise N(0, 1e-2^2), 1,000 noiseless test samples, learner ``LCS(4, 2, 3,
stiffness=1.0, seed=100 + s)``, ``fit(recipe="best", seed=s, refine_batch=N)``: the recommended
recipe with its Gauss--Newton refinement on the whole training set (on its default batches of
500 the refinement stops at the accuracy of 500 samples). The second table varies the Adam
iterations (``iterations=``; default 4,000) at one training size. For each size the "floor" is the
e_test of the truth's ``(D, E, F, c)`` with ``(A, B, C, d)`` refitted by least squares on the
noisy training data (:func:`lcs_cvx.resizing.refit_dynamics`): what the noise leaves when the modes
are known. "At the floor" counts the runs whose final e_test is <= 2 x that floor; "iterations"
is the first recorded iteration with e_test <= 2 x that floor (during the Adam phase of the
"best" recipe: of the model with its extra units, before pruning; the history records every 100
Adam steps and every refinement step; "-": never).

Writes a markdown table (default studies/results/known_structure.md) and prints it.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

import lcs_cvx
from lcs_cvx.resizing import refit_dynamics

N_X, N_U, N_LAM, NOISE = 4, 2, 3, 0.01
HEADERS = {"n": "N", "iterations": "Adam iterations"}
OUT = Path(__file__).resolve().parent / "results" / "known_structure.md"


def floor(truth: lcs_cvx.LCS, train: lcs_cvx.Dataset, test: lcs_cvx.Dataset, known_ab: bool) -> float:
    """e_test of the truth's modes with the output matrices refitted on the noisy data."""
    oracle = lcs_cvx.LCS(N_X, N_U, N_LAM, stiffness=float(truth.stiffness))
    oracle.load_state_dict(truth.state_dict())
    if known_ab:
        oracle.fix(A=truth.A, B=truth.B)
    refit_dynamics(oracle, train.x, train.u, train.x_next)
    return lcs_cvx.relative_error(oracle, test)


def run(seed: int, n: int, iterations: int = 4000) -> list[dict]:
    truth = lcs_cvx.random_lcs(N_X, N_U, N_LAM, seed=seed)
    train = lcs_cvx.make_dataset(truth, n, noise=NOISE, seed=1000 + seed)
    test = lcs_cvx.make_dataset(truth, 1000, seed=2000 + seed)
    target = 2.0 * floor(truth, train, test, known_ab=False)  # the same bar for both learners
    rows = []
    for known in (False, True):
        model = lcs_cvx.LCS(N_X, N_U, N_LAM, stiffness=1.0, seed=100 + seed)
        if known:
            model.fix(A=truth.A, B=truth.B)
        t0 = time.perf_counter()
        result = lcs_cvx.fit(model, train, test=test, recipe="best", seed=seed, refine_batch=n,
                             iterations=iterations, progress=False)
        reached = next((h["iteration"] for h in result.history if h["e_test"] <= target), None)
        rows.append({"seed": seed, "n": n, "iterations": iterations, "known": known, "e_test": lcs_cvx.relative_error(model, test),
                     "floor": floor(truth, train, test, known_ab=known), "target": target,
                     "reached": reached, "wall": time.perf_counter() - t0})
    return rows


def table(rows: list[dict], seeds: list[int], key: str, values: list[int]) -> str:
    lines = [
        f"| {HEADERS[key]} | learned | e_test per seed (" + ", ".join(map(str, seeds)) + ") | median e_test | "
        "median floor | at the floor | iterations to 2 x floor per seed |",
        "| ---: | --- | --- | ---: | ---: | ---: | --- |",
    ]
    for v in values:
        for known in (False, True):
            rs = [r for r in rows if r[key] == v and r["known"] == known]
            label = "C, d, D, E, F, c (A, B fixed)" if known else "everything"
            e = ", ".join(f"{r['e_test']:.1e}" for r in rs)
            ok = sum(r["e_test"] <= r["target"] for r in rs)
            its = ", ".join("-" if r["reached"] is None else str(r["reached"]) for r in rs)
            lines.append(
                f"| {v} | {label} | {e} | {statistics.median(r['e_test'] for r in rs):.1e} | "
                f"{statistics.median(r['floor'] for r in rs):.1e} | {ok} / {len(rs)} | {its} |"
            )
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", default="200,500,1000,5000")
    p.add_argument("--seeds", default="0,1,2,3")
    p.add_argument("--budgets", default="500,1000,2000")
    p.add_argument("--budget-size", type=int, default=1000)
    p.add_argument("--out", default=str(OUT))
    args = p.parse_args()
    torch.set_num_threads(1)
    sizes = [int(s) for s in args.sizes.split(",")]
    seeds = [int(s) for s in args.seeds.split(",")]
    budgets = [int(s) for s in args.budgets.split(",")]
    t0 = time.perf_counter()
    rows = [r for n in sizes for s in seeds for r in run(s, n)]
    short = [r for b in budgets for s in seeds for r in run(s, args.budget_size, b)]
    walls = {k: sum(r["wall"] for r in rows + short if r["known"] == k) for k in (False, True)}
    text = (
        "# Known structure: learning with A and B fixed\n\n"
        f"Command: `python studies/known_structure.py --sizes {args.sizes} --seeds {args.seeds} "
        f"--budgets {args.budgets} --budget-size {args.budget_size}`  \n"
        "Date: 2026-11-24; machine: 2-core x86-64 VM, 24 GiB, one torch thread "
        f"(shared with other jobs); total {time.perf_counter() - t0:.0f} s, fits "
        f"{walls[False]:.0f} s learning everything, {walls[True]:.0f} s with A, B fixed.\n\n"
        f"Ground truth `random_lcs({N_X}, {N_U}, {N_LAM}, seed=s)`, training noise N(0, {NOISE}^2), "
        "1,000 noiseless test samples, learner `LCS(4, 2, 3, stiffness=1.0, seed=100 + s)`, "
        "`fit(recipe=\"best\", seed=s, refine_batch=N)`; see the script's docstring for the floor and the "
        "iteration count.\n\n"
        "## e_test against the training size N (4,000 Adam iterations)\n\n"
        + table(rows, seeds, "n", sizes) + "\n\n"
        f"## e_test against the Adam iterations (N = {args.budget_size})\n\n"
        + table(short, seeds, "iterations", budgets) + "\n"
    )
    Path(args.out).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
