"""Loss + gradient throughput against the paper's authors' learners, side by side in one process.

The authors' learners (DAIRLab/Learning-LCS, ``lcs/lcs_learning.py``: ``LCS_VN`` for the violation
loss, ``LCS_PN`` for the prediction loss; CasADi with qpOASES, one QP per sample) are imported from
a checkout the user names (``--authors``: the folder that holds their ``lcs`` package; nothing of
theirs is in this repository) and called exactly as their training loops call them:
``learner.step(x, u, x_next, theta)`` returns the mean loss and the mean gradient in ``theta``.
Beside it, lcs_cvx's two ways to the same numbers: ``violation_value_and_grad`` /
``prediction_value_and_grad`` (the loss and its gradient in one call, as the authors' ``step``
returns them) and ``violation_loss`` / ``prediction_loss`` followed by ``.backward()`` (through
torch's autograd, as a user composing losses runs them; the engine's own cost is then part of the
time).

Both sides get the same model and the same batch. The model is a random ground truth
(:func:`lcs_cvx.random_lcs`, stiffness 0.5) with every parameter perturbed by ``0.05 N(0, 1)``
(a mid-training model, as in :mod:`lcs_cvx.bench`), its ``G`` made upper triangular (the authors'
``G`` is); ``theta`` is its parameters in the authors' layout (``vec`` is column-major). Their
objectives differ from the package's by constant factors: their (V) objective with ``(gamma,
eps)`` is twice the package's with ``(gamma / 2, 2 eps)``, and their prediction loss twice the
package's. So the package runs at ``(gamma / 2, 2 eps)`` and each row checks that ``lam``, the loss
and the gradient agree (``lam`` to the QP solver's accuracy): the two sides compute the same thing.

Timing: one torch thread, both sides interleaved (one authors' call, then the package's calls for
as long, per repeat), ``repeats`` repeats after a warm-up, median; samples/s = batch / median.

A training step (``--steps``, the "training step" columns): one step of the authors' training
loop as their Fig. 1 scripts run it (``evaluations/*/run_train.py``: a random minibatch of
``batch`` drawn by ``np.random.permutation``, ``learner.step``, their ``Adam.step`` on
``theta``), timed over ``STEP_CALLS`` steps per repeat, against one step of
:func:`lcs_cvx.fit` with ``recipe="paper"`` on ``STEP_DATA`` samples (the wall time of
``fit(..., iterations=STEP_ITERATIONS)`` over its iterations: the data checks, the minibatch, the
warm starts, the loss and gradient, Adam, the records), interleaved the same way.

    python -m studies.solvers.authors_speed --authors /path/to/Learning-LCS \
        --out studies/results/solvers [--sizes fig1|paper|N_X,N_U,N_LAM ...] [--batch 200]

Sizes: ``fig1`` (default) every ``(n_x, n_u, n_lam)`` of the paper's Fig. 1 -- panel (a)
``(10, 4, {1, 4, 8, 12, 16, 20})``, (b) ``({2, 8, 16, 32, 64, 128}, 4, 10)``, (c) ``(8, 4, 10)``,
(d, e) ``(4, 4, 4)``. Writes ``OUT/authors_speed.jsonl`` (one line per (size, loss); a rerun
skips finished rows) and ``OUT/authors_speed.md``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

import lcs_cvx  # noqa: E402
from lcs_cvx.authors import FIG1_SIZES, LOSSES, PAPER_SIZES, load_authors, run_row, table  # noqa: E402

from . import records  # noqa: E402


def parse_sizes(items: list[str]) -> list[tuple[int, int, int]]:
    sizes: list[tuple[int, int, int]] = []
    for item in items:
        if item == "fig1":
            sizes += FIG1_SIZES
        elif item == "paper":
            sizes += PAPER_SIZES
        else:
            parts = item.split(",")
            if len(parts) != 3 or not all(p.strip().isdigit() for p in parts):
                raise SystemExit(f"--sizes: expected fig1, paper or N_X,N_U,N_LAM, received {item!r}")
            sizes.append(tuple(int(p) for p in parts))
    return list(dict.fromkeys(sizes))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--authors", required=True, type=Path,
                    help="folder holding the authors' 'lcs' package (a DAIRLab/Learning-LCS checkout)")
    ap.add_argument("--out", type=Path, default=Path("studies/results/solvers"))
    ap.add_argument("--sizes", nargs="+", default=["fig1"])
    ap.add_argument("--losses", nargs="+", default=list(LOSSES), choices=LOSSES)
    ap.add_argument("--batch", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--name", default="authors_speed")
    ap.add_argument("--steps", action=argparse.BooleanOptionalAction, default=True,
                    help="also time a training step against the authors' (default on)")
    ap.add_argument("--redo", action="store_true", help="measure the chosen rows again (replacing them)")
    args = ap.parse_args(argv)
    try:
        lcs_learning, authors_optim = load_authors(args.authors)
    except lcs_cvx.LCSInputError as exc:
        raise SystemExit(f"--{exc}") from None

    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    jsonl = args.out / f"{args.name}.jsonl"
    done = records.load(jsonl, lambda r: (r["n_x"], r["n_u"], r["n_lam"], r["loss"], r["batch"]))
    for size in parse_sizes(args.sizes):
        for loss in args.losses:
            key = (*size, loss, args.batch)
            if key in done and not args.redo:
                continue
            row = run_row(lcs_learning, size, loss, args.batch, args.repeats,
                          optim=authors_optim if args.steps else None)
            row["date"] = str(datetime.date.today())
            done[key] = row
            with jsonl.open("a") as f:  # a later line of the same key replaces an earlier one
                f.write(json.dumps(row) + "\n")
            print(table([row]).splitlines()[-1], flush=True)
    rows = sorted(done.values(), key=lambda r: (r["loss"], r["n_lam"] if r["n_x"] == 10 else 99, r["n_x"]))
    dates = sorted({r.get("date", "undated") for r in rows})
    head = (f"`python -m studies.solvers.authors_speed --authors PATH --out {args.out}`, "
            f"rows measured {', '.join(dates)} (the date of each in the .jsonl), "
            f"{platform.machine()} {os.cpu_count()}-core machine, one torch "
            f"thread, batch {args.batch}, median of {args.repeats} interleaved repeats; casadi "
            f"{__import__('casadi').__version__}, lcs_cvx {lcs_cvx.__version__}.\n\n")
    (args.out / f"{args.name}.md").write_text(head + table(rows) + "\n")


if __name__ == "__main__":
    main()
