r"""Learning a tossed cube from real data: the 550 ContactNets cube tosses
(:func:`lcs_cvx.datasets.cube_tosses`), LCSs learned by :func:`lcs_cvx.fit` against an affine
least-squares map and a tuned MLP, along a learning curve of training tosses.

1. Split by toss, 50 / 25 / 25 % (dair_pll's proportions for real data): a fixed permutation of
   the 550 tosses (NumPy ``default_rng(0)``) gives 275 training, 138 validation and 137 test
   tosses (:func:`split`). The training sets are the first ``n`` training tosses for ``n`` in
   :data:`SIZES` (nested: a larger size extends a smaller one); every size is validated on the
   whole validation quarter (not scaled with the size) and tested on the whole test quarter.
2. Models (:mod:`studies.cube.models`): affine least squares, a residual MLP tuned on the
   validation tosses, the LCS of :func:`lcs_cvx.select_n_lam` with default options, the LCS with
   the known structure of a tossed cube, and, where the installed library has them, both LCSs
   trained on the tosses as trajectories with the simulation-error (rollout) phase.
3. Metrics on the test tosses (:mod:`studies.cube.metrics`): one-step errors per state group,
   open-loop rollouts at 10 and 30 steps (every window) and from each toss's first state to its
   end (position error in m, rotation error in rad, growth and divergence).
4. One JSON line per finished ``(size, model)`` cell in ``OUT/cube.jsonl`` (a rerun skips the
   cells already there), the fitted models in ``OUT/models/``, and at the end ``OUT/report.md``,
   ``OUT/learning_curve.png`` and ``OUT/rollouts.png`` (:mod:`studies.cube.report`).

    python -m studies.cube.study --out studies/results/cube [--sizes 2,4,...] [--models ...] [--smoke]

``--smoke``: sizes 2 and 4, 8 validation and 8 test tosses, tiny budgets (a check, in about a
minute); written to ``cube_smoke.jsonl`` and ``report_smoke.md`` so as not to mix with the study.
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

from . import models as M  # noqa: E402
from .metrics import one_step, rollouts  # noqa: E402
from .report import write_report  # noqa: E402
from .tosses import DATE, MACHINE, SPLIT_SEED, split, study_parts, subset  # noqa: E402

__all__ = ["SIZES", "SPLIT_SEED", "DATE", "MACHINE", "split", "subset", "run", "main"]

#: Training sizes (tosses) of the learning curve; 275 is all of the training half.
SIZES = (2, 4, 8, 16, 32, 64, 128, 275)
HORIZONS = (10, 30)


def _read(path: str) -> dict[tuple[int, str], dict[str, Any]]:
    done: dict[tuple[int, str], dict[str, Any]] = {}
    if os.path.exists(path):
        with open(path) as f:
            for line in f:
                if line.strip():
                    rec = json.loads(line)
                    done[(rec["size"], rec["model"])] = rec
    return done


def evaluate(step: M.Stepper, test: lcs_cvx.Trajectories) -> dict[str, Any]:
    """The test metrics of a stepper (:mod:`studies.cube.metrics`)."""
    t0 = time.perf_counter()
    out = {"one_step": one_step(step, test.xs), "rollout": rollouts(step, test.xs, HORIZONS)}
    out["eval_wall"] = time.perf_counter() - t0
    return out


def run(out: str, sizes: list[int], smoke: bool = False, only: list[str] | None = None,
        log: Any = sys.stderr) -> list[dict[str, Any]]:
    """Fit and evaluate every missing ``(size, model)`` cell; return all the cells' records."""
    torch.set_num_threads(1)
    os.makedirs(out, exist_ok=True)
    data = cube_tosses()
    parts = study_parts(len(data), smoke)
    budget = M.SMOKE_BUDGET if smoke else M.Budget()
    train_all, val, test = (subset(data, parts[k]) for k in ("train", "validation", "test"))
    path = os.path.join(out, "cube_smoke.jsonl" if smoke else "cube.jsonl")
    done = _read(path)
    specs = [s for s in M.specs() if only is None or s.key in only]
    for size in sizes:
        train = subset(train_all, list(range(size)))
        for spec in specs:
            if (size, spec.name) in done:
                continue
            mpath = M.model_path(out, size, spec) if not smoke else M.model_path(out, size, spec).replace(
                f"{os.sep}models{os.sep}", f"{os.sep}models_smoke{os.sep}")
            os.makedirs(os.path.dirname(mpath), exist_ok=True)
            t0 = time.perf_counter()
            twin = next((r for r in done.values() if r["size"] == size and r["key"] == spec.twin), None)
            extra = {"n_lams": (twin["fit"]["n_lam"],)} if twin is not None else {}
            step, info = spec.fit(train, val, budget, mpath, **extra)
            rec = {"size": size, "model": spec.name, "key": spec.key, "transitions": sum(train.lengths),
                   "fit": info, **evaluate(step, test), "model_file": os.path.relpath(mpath, out),
                   "wall": time.perf_counter() - t0}
            done[(size, spec.name)] = json.loads(M.to_json(rec))
            with open(path, "a") as f:
                f.write(M.to_json(rec) + "\n")
            r = rec["rollout"]
            print(f"n={size:4d} {spec.name:40s} fit {info['wall']:7.1f} s  pos H30 {r['H30']['pos']:.4f} m  "
                  f"rot H30 {r['H30']['rot']:.3f} rad  end {r['end']['pos']:.4f} m {r['end']['rot']:.3f} rad  "
                  f"diverged {r['end']['diverged']}/{r['end']['rollouts']}", file=log, flush=True)
    order = [s.name for s in M.specs()]
    return [done[k] for k in sorted(done, key=lambda k: (k[0], order.index(k[1]) if k[1] in order else 99))]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="The cube-toss study: LCSs vs affine and MLP on real data.")
    ap.add_argument("--out", default=os.path.join("studies", "results", "cube"))
    ap.add_argument("--sizes", default=None, help="comma-separated training sizes (tosses), default "
                    + ",".join(map(str, SIZES)))
    ap.add_argument("--models", default=None, help="comma-separated model keys (default all): "
                    + ",".join(s.key for s in M.specs()))
    ap.add_argument("--smoke", action="store_true", help="sizes 2,4, 8 validation/test tosses, tiny budgets")
    ap.add_argument("--no-report", action="store_true", help="fit and evaluate only")
    args = ap.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",")] if args.sizes else ([2, 4] if args.smoke else list(SIZES))
    only = args.models.split(",") if args.models else None
    t0 = time.perf_counter()
    records = run(args.out, sizes, smoke=args.smoke, only=only)
    if not args.no_report:
        cmd = "python -m studies.cube.study --out " + args.out + (" --smoke" if args.smoke else "") + (
            f" --sizes {args.sizes}" if args.sizes else "") + (f" --models {args.models}" if args.models else "")
        write_report(args.out, records, cmd=cmd, smoke=args.smoke, wall=time.perf_counter() - t0)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
