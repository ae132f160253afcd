r"""The spread over seeds of the cube study's kinematic LCSs: the same fit as the study's cell at
one training size (:mod:`studies.cube.study`), with other seeds (the initialisation and the
batches), at the ``n_lam`` the study's seed-0 fit chose there.

One JSON line per finished ``(model, seed)`` in ``OUT/seeds.jsonl`` (a rerun skips them), the
fitted models in ``OUT/models/seeds/``, and ``OUT/seeds.md``: per seed the test rollouts of the
study (H = 10, 30, whole tosses) and dair_pll's whole-toss metric, the held-out score the fit
was chosen by, and the spread.

    python -m studies.cube.seeds --out studies/results/cube [--size 275] [--seeds 0,1,2,3]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import time

import torch

from lcs_cvx.datasets import cube_tosses

from . import models as M
from .metrics import dair_pll_errors, rollouts
from .tosses import MACHINE, study_parts, subset

__all__ = ["MODELS", "run", "main"]

#: The study's models whose seed spread is measured (spec keys).
MODELS = ("lcs_contact", "lcs_symmetry", "rigid_body", "rigid_body_rounded")
#: When the committed spread was measured.
DATE = "2026-11-28"


def _done(path: str) -> dict[tuple[str, int], dict]:
    if not os.path.exists(path):
        return {}
    with open(path) as f:
        return {(r["key"], r["seed"]): r for r in map(json.loads, filter(str.strip, f))}


def run(out: str, size: int, seeds: list[int], models: tuple[str, ...] = MODELS) -> list[dict]:
    """Fit and evaluate every missing ``(model, seed)`` of ``models``; seed 0 is the study's own
    cell (read from its record and model file, not refitted). Every record in ``OUT/seeds.jsonl``
    is returned (other processes' too: runs of other seeds may go side by side)."""
    torch.set_num_threads(1)
    data = cube_tosses()
    parts = study_parts(len(data))
    train = subset(subset(data, parts["train"]), list(range(size)))
    val, test = subset(data, parts["validation"]), subset(data, parts["test"])
    with open(os.path.join(out, "cube.jsonl")) as f:
        study = {(r["size"], r["key"]): r for r in map(json.loads, filter(str.strip, f))}
    path = os.path.join(out, "seeds.jsonl")
    done = _done(path)
    os.makedirs(os.path.join(out, "models", "seeds"), exist_ok=True)
    for key in models:
        spec = next(s for s in M.specs() if s.key == key)
        cell = study.get((size, key))
        n_lam = cell["fit"].get("n_lam") if cell else None  # None for a rigid body (its units are its contacts)
        for seed in seeds:
            if (key, seed) in done:
                continue
            if cell is None and (seed == 0 or not key.startswith("rigid_body")):  # an LCS reuses the cell's n_lam
                print(f"{key}: no study cell at {size} tosses yet (python -m studies.cube.study --sizes {size} "
                      f"--models {key}); seed {seed} skipped")
                continue
            t0 = time.perf_counter()
            if seed == 0:
                step, info = spec.load(os.path.join(out, cell["model_file"])), cell["fit"]
            else:
                mpath = os.path.join(out, "models", "seeds", f"n{size:03d}_{key}_seed{seed}.npz")
                step, info = spec.fit(train, val, M.Budget(), mpath, n_lams=(n_lam,), seed=seed)
            score = info["heldout_error"] if n_lam is None else next(
                c["heldout_error"] for c in info["candidates"] if c["n_lam"] == n_lam)
            r = rollouts(step, test.xs, (10, 30))
            rec = {"key": key, "model": spec.name, "seed": seed, "size": size, "n_lam": n_lam,
                   "heldout_error": score, "rollout": {h: {k: r[h][k] for k in ("pos", "rot", "diverged")}
                                                       for h in ("H10", "H30", "end")},
                   "dair_pll": dair_pll_errors(step, test.xs), "wall": time.perf_counter() - t0}
            done[(key, seed)] = rec
            with open(path, "a") as f:
                f.write(M.to_json(rec) + "\n")
    done = _done(path)
    return [done[k] for k in sorted(done)]


def _spread(values: list[float]) -> str:
    return f"{statistics.mean(values):.4g} ({min(values):.4g}–{max(values):.4g})"


def write(out: str, records: list[dict], cmd: str) -> str:
    """``OUT/seeds.md``: one row per fit, then the mean and range per model."""
    cols = [("pos H=10 (m)", "H10", "pos"), ("rot H=10 (rad)", "H10", "rot"), ("pos H=30 (m)", "H30", "pos"),
            ("rot H=30 (rad)", "H30", "rot"), ("pos to end (m)", "end", "pos"), ("rot to end (rad)", "end", "rot")]
    L = ["# The cube study's kinematic LCSs and rigid body over seeds", "",
         f"Written by `{cmd}` on {DATE} ({MACHINE}).", "",
         "Each row: the study's fit of that model (`studies/cube/models.py`) at the training size and the n_λ "
         "of the study's seed-0 cell (the rigid body: its start's quantities jittered by the seed, "
         "`lcs_cvx.train.starts.jittered`), with another seed (initialisation and batches); seed 0 is the study's "
         "cell itself. Test rollouts as in `report.md` (position RMS, mean rotation angle); dair_pll's "
         "whole-toss metric as in `contactnets.md`; the held-out score is the validation rollout error at "
         "H = 30 the fit was chosen by.", "",
         "| model | seed | n_λ | held-out score | " + " | ".join(c[0] for c in cols)
         + " | dair_pll position | dair_pll rotation | diverged (end) |",
         "|---|---:|---:|---:|" + "---:|" * len(cols) + "---:|---:|---:|"]
    for r in records:
        L.append(f"| {r['model']} | {r['seed']} | {r['n_lam'] or '—'} | {r['heldout_error']:.4g} | "
                 + " | ".join(f"{r['rollout'][h][k]:.4g}" for _, h, k in cols)
                 + f" | {1000 * r['dair_pll']['pos']:.1f} mm | {math.degrees(r['dair_pll']['rot']):.1f}° | "
                 f"{r['rollout']['end']['diverged']} |")
    L += ["", "Mean (range) over the seeds:", "",
          "| model | seeds | " + " | ".join(c[0] for c in cols) + " | dair_pll position (mm) | dair_pll rotation (°) |",
          "|---|---:|" + "---:|" * len(cols) + "---:|---:|"]
    for key in MODELS:
        rs = [r for r in records if r["key"] == key]
        if rs:
            L.append(f"| {rs[0]['model']} | {len(rs)} | "
                     + " | ".join(_spread([float(r["rollout"][h][k]) for r in rs]) for _, h, k in cols)
                     + f" | {_spread([1000 * r['dair_pll']['pos'] for r in rs])} | "
                     f"{_spread([math.degrees(r['dair_pll']['rot']) for r in rs])} |")
    L += ["", "dair_pll's own angle (`2 atan2(|v|, w)` of `q^-1 q_hat`, no choice between `q_hat` and `-q_hat`), "
          "mean (range) over the seeds:", ""]
    for key in MODELS:
        rs = [r for r in records if r["key"] == key and "rot_atan2" in r["dair_pll"]]
        if rs:
            L.append(f"- {rs[0]['model']}: {_spread([math.degrees(r['dair_pll']['rot_atan2']) for r in rs])}°")
    text = "\n".join(L) + "\n"
    with open(os.path.join(out, "seeds.md"), "w") as f:
        f.write(text)
    return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="The cube study's kinematic LCSs over seeds.")
    ap.add_argument("--out", default=os.path.join("studies", "results", "cube"))
    ap.add_argument("--size", type=int, default=275)
    ap.add_argument("--seeds", default="0,1,2,3")
    ap.add_argument("--models", default=",".join(MODELS), help="comma-separated model keys (default: all of MODELS)")
    args = ap.parse_args(argv)
    records = run(args.out, args.size, [int(s) for s in args.seeds.split(",")], tuple(args.models.split(",")))
    print(write(args.out, records, f"python -m studies.cube.seeds --out {args.out} --size {args.size} "
                                   f"--seeds {args.seeds}"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
