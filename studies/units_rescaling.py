"""The same system in other units: e_test of ``fit(recipe="best")`` on data as generated and
on the same data after an exact change of units (state scaled by diag(1e3, 1, 1e-2, 10), input
by diag(1e-2, 1e2)), with and without learning in normalised coordinates.

    python studies/units_rescaling.py [--seeds 0,1,2,3,4,5] [--init increment] [--out studies/results/units_rescaling.md]

Ground truth ``random_lcs(4, 2, 3, seed=0)``, 5,000 training samples with noise 1e-2, 2,000
noiseless test samples; the learner ``LCS(4, 2, 3, seed=s)`` and ``fit(..., seed=s)``. Each
run's e_test is in its own units: the units weight the states differently, so the two numbers
of a seed measure models of the same problem with different weights. One torch thread.
"""

from __future__ import annotations

import argparse
import datetime
import platform
import time

import torch

import lcs_cvx
from lcs_cvx import Dataset

SX = torch.tensor([1e3, 1.0, 1e-2, 10.0], dtype=torch.float64)
SU = torch.tensor([1e-2, 1e2], dtype=torch.float64)


def rescaled(data: Dataset) -> Dataset:
    return Dataset(data.x * SX, data.u * SU, data.x_next * SX, data.lam)


def run(train: Dataset, test: Dataset, seed: int, s_x: torch.Tensor, **options
        ) -> tuple[float, float, float]:
    """e_test in the run's units, CPU seconds, and e_test of the same model's predictions in the
    units as generated (``x' = S_x^-1 x'_run(x_run, u_run)``; ``s_x`` the diagonal of ``S_x``)."""
    model = lcs_cvx.LCS(4, 2, 3, seed=seed)
    t0 = time.process_time()
    lcs_cvx.fit(model, train, recipe="best", seed=seed, progress=False, **options)
    cpu = time.process_time() - t0
    with torch.no_grad():
        pred = model.step(test.x, test.u) / s_x
    target = test.x_next / s_x
    return (lcs_cvx.relative_error(model, test), cpu,
            float(((pred - target) ** 2).sum() / (target ** 2).sum()))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", default="0,1,2,3,4,5")
    p.add_argument("--init", default="increment", help="fit's init for the normalised runs")
    p.add_argument("--out", default=None, help="markdown file to write the table to")
    args = p.parse_args()
    torch.set_num_threads(1)
    truth = lcs_cvx.random_lcs(4, 2, 3, seed=0)
    train = lcs_cvx.make_dataset(truth, 5000, noise=1e-2, seed=1)
    test = lcs_cvx.make_dataset(truth, 2000, seed=2)
    one = torch.ones(4, dtype=torch.float64)
    raw = {"normalize": False, "init": "model"}
    start = {"init": args.init}
    cases = {"as generated": (train, test, one, start),
             "other units": (rescaled(train), rescaled(test), SX, start),
             "as generated, normalize=False": (train, test, one, raw),
             "other units, normalize=False": (rescaled(train), rescaled(test), SX, raw)}
    rows = []
    for seed in (int(s) for s in args.seeds.split(",")):
        row = {"seed": seed}
        for name, (tr, te, s_x, opts) in cases.items():
            row[name] = run(tr, te, seed, s_x, **opts)
        rows.append(row)
        print(seed, "  ".join(f"{n}: {row[n][0]:.2e} ({row[n][1]:.0f} s)" for n in cases), flush=True)
    lines = ["| seed | " + " | ".join(cases) + " | other units, evaluated as generated |",
             "|---" * (len(cases) + 2) + "|"]
    lines += [f"| {r['seed']} | " + " | ".join(f"{r[n][0]:.2e}" for n in cases)
              + f" | {r['other units'][2]:.2e} |" for r in rows]
    ratio = [r["other units"][0] / r["as generated"][0] for r in rows]
    back = [r["other units"][2] / r["as generated"][0] for r in rows]
    lines += ["", "Ratio other units / as generated (normalised), each in its own units: "
              + ", ".join(f"{q:.2f}" for q in ratio) + f"; max {max(ratio):.2f}, min {min(ratio):.2f}.",
              "The same, the model learned in other units evaluated in the units as generated: "
              + ", ".join(f"{q:.2f}" for q in back) + f"; max {max(back):.2f}, min {min(back):.2f}.",
              f"CPU seconds per fit (normalised): mean "
              f"{sum(r['as generated'][1] + r['other units'][1] for r in rows) / (2 * len(rows)):.1f}."]
    print("\n".join(lines))
    if args.out:
        with open(args.out, "w") as f:
            f.write("# The same system in other units\n\n"
                    f"`python studies/units_rescaling.py --seeds {args.seeds} --init {args.init} --out {args.out}`, "
                    f"{datetime.date.today()}, {platform.machine()} VM with 2 cores, 24 GiB, one "
                    "torch thread. " + " ".join(__doc__.split("\n\n")[2].split()) + "\n\n"
                    + "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
