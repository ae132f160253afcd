r"""What splitting by toss changes: ``select_n_lam`` on the cube tosses with the held-out part
drawn as random transitions (neighbouring samples of one toss on both sides) or as whole tosses.

The training tosses are the first ``--tosses`` of the cube study's training half
(:func:`studies.cube.tosses.split`); the test tosses are its test quarter. For each split,
``lcs_cvx.select_n_lam`` over ``n_lam`` in (2, 4, 8) with the library's default options and 20 %
held out (the user's call, the data given as a :class:`lcs_cvx.Dataset` of transitions or as
:class:`lcs_cvx.Trajectories`; the simulation-error phase and the best iterate, defaults with
trajectories, off in both, so that only the split differs). Reported per candidate: its held-out score (the one-step relative error on the held-out
part) beside its test errors (one-step, and the rollout error ``lcs_cvx.rollout_error`` at
H = 10 and 30 on the test tosses), and the ``n_lam`` each split chooses. A held-out score that
tracks the test errors is one a user can select with.

    python -m studies.cube.split_effect --out studies/results/cube [--tosses 64]

Writes ``OUT/split_effect.md`` and ``OUT/split_effect.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Any

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import torch  # noqa: E402

import lcs_cvx  # noqa: E402
from lcs_cvx.datasets import cube_tosses  # noqa: E402

from .tosses import DATE, MACHINE, split, subset  # noqa: E402

__all__ = ["run", "main"]

CANDIDATES = (2, 4, 8)
HORIZONS = (1, 10, 30)


def run(tosses: int, iterations: int | None = None) -> dict[str, Any]:
    """Both selections and every candidate's test errors (module docstring)."""
    torch.set_num_threads(1)
    data = cube_tosses()
    parts = split(len(data))
    train, test = subset(data, parts["train"][:tosses]), subset(data, parts["test"])
    extra = {} if iterations is None else {"iterations": iterations}
    out: dict[str, Any] = {"tosses": tosses, "candidates": list(CANDIDATES), "splits": {}}
    for name, given in (("random transitions", train.to_transitions()), ("whole tosses", train)):
        t0 = time.perf_counter()
        # only the split differs: neither the simulation-error phase nor the best iterate
        opts = {"rollout_horizon": None, "keep_best": False} if isinstance(given, lcs_cvx.Trajectories) else {}
        sel = lcs_cvx.select_n_lam(given, list(CANDIDATES), holdout=0.2, progress=False, seed=0,
                                   recipe="plain", **opts, **extra)
        rows = []
        for row in sel.table:
            m = sel.results[row["n_lam"]].model
            errs = lcs_cvx.rollout_error(m, test, HORIZONS)
            rows.append({"n_lam": row["n_lam"], "heldout": row["validation_error"], "train": row["train_error"],
                         **{f"test_H{h}": errs[h] for h in HORIZONS}})
            print(f"[split] {name}: n_lam {row['n_lam']}: held-out {row['validation_error']:.4g}, "
                  + ", ".join(f"test H={h} {errs[h]:.4g}" for h in HORIZONS), flush=True)
        out["splits"][name] = {"chosen": sel.n_lam, "rows": rows, "wall": time.perf_counter() - t0}
    return out


def report(res: dict[str, Any], cmd: str) -> str:
    L = ["# Splitting by toss or by transition: what the held-out score says", "",
         f"Written by `{cmd}` on {DATE} ({MACHINE}).", "",
         f"`lcs_cvx.select_n_lam` over n_λ ∈ {tuple(res['candidates'])} on the first {res['tosses']} training tosses "
         "of the cube study's split, default options, 20 % held out: as random transitions (a `Dataset`) or as "
         "whole tosses (`Trajectories`; the simulation-error phase and the best iterate off, so only the split "
         "differs). Test: the "
         "study's 137 test tosses, `lcs_cvx.rollout_error` at H = 1, 10 and 30.", "",
         "| held out as | n_λ | held-out one-step error | test H=1 | test H=10 | test H=30 | chosen |",
         "|---|---:|---:|---:|---:|---:|---|"]
    for name, s in res["splits"].items():
        for r in s["rows"]:
            L.append(f"| {name} | {r['n_lam']} | {r['heldout']:.4g} | {r['test_H1']:.4g} | {r['test_H10']:.4g} | "
                     f"{r['test_H30']:.4g} | {'yes' if r['n_lam'] == s['chosen'] else ''} |")
    L.append("")
    for name, s in res["splits"].items():
        best = min(s["rows"], key=lambda r: r["test_H30"])
        chosen = next(r for r in s["rows"] if r["n_lam"] == s["chosen"])
        held = ", ".join(f"{r['heldout']:.3g}" for r in s["rows"])
        tested = ", ".join(f"{r['test_H1']:.3g}" for r in s["rows"])
        L.append(f"- {name}: chose n_λ = {s['chosen']} (test H=30 {chosen['test_H30']:.4g}); the best on the test "
                 f"tosses at H = 30 is n_λ = {best['n_lam']} ({best['test_H30']:.4g}); held-out errors "
                 f"{held} against test one-step errors {tested}; {s['wall']:.0f} s.")
    return "\n".join(L) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join("studies", "results", "cube"))
    ap.add_argument("--tosses", type=int, default=64)
    ap.add_argument("--iterations", type=int, default=None, help="Adam iterations (default: the library's)")
    args = ap.parse_args(argv)
    res = run(args.tosses, args.iterations)
    cmd = "python -m studies.cube.split_effect " + " ".join(sys.argv[1:] if argv is None else argv)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "split_effect.json"), "w") as f:
        json.dump(res, f, indent=1)
    with open(os.path.join(args.out, "split_effect.md"), "w") as f:
        f.write(report(res, cmd.strip()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
