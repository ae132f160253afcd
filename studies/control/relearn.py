r"""Learn, control, relearn on the MuJoCo cart-pole between soft walls
(:func:`lcs_cvx.control.relearn`), against a model learned from the same number of random
transitions.

Round 0: an LCS (``n_lam = 4``, the physics study's settings: ``recipe="best"``, stiffness 1,
``init_scale`` 0.1; ``--iterations``: Adam steps other than the recipe's) learned from ``--random`` random transitions of
:func:`studies.physics.plant.sample_transitions` (seed 0), then C3 with the package's defaults
(``C3(model, 10, Q=diag(5, 20, 0.5, 0.5), R=[1], u_bounds=(-4, 4))``) closed on MuJoCo from the
50 starts of :mod:`studies.control.mujoco_closed_loop` (4 s each, its success test). Each round
adds the closed-loop transitions and refits from the current model; ``--rounds`` refits.
Baseline: the same LCS learned from as many random transitions as the last round's data holds,
controlled the same way.

Resumable: after each round the model and data go to ``OUT/relearn_cache/`` and the round to
``OUT/relearn.jsonl``; a rerun resumes after the last round there. The report is
``OUT/relearn.md``.

    python -m studies.control.relearn --out studies/results/control [--rounds 3] [--random 500]
        [--iterations N] [--fresh] [--smoke]

``--fresh``: every refit starts as the first fit does instead of from the current model; the
variants write ``relearn_fresh.*`` / ``relearn_itN.*``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
import warnings
from typing import Any

import numpy as np
import torch
from threadpoolctl import threadpool_limits

import lcs_cvx
from lcs_cvx import LCS, Dataset
from lcs_cvx.control import C3, relearn
from studies.physics.plant import CartPoleWalls, Physics, sample_transitions

from .mujoco_closed_loop import Q_STAGE, U_MAX, starts

__all__ = ["MuJoCoPlant", "main"]

N_LAM = 4
FIT = {"recipe": "best", "seed": 0}
MACHINE = "2-core x86-64 VM, 1 torch thread"


class MuJoCoPlant:
    """``plant(x, u) -> x'``: one control period of the MuJoCo cart-pole from state ``x``; keeps
    whether a wall pushed in each period, by the state it led to (:meth:`success` reads them)."""

    def __init__(self) -> None:
        self.sim = CartPoleWalls(Physics())
        self.contact: dict[bytes, bool] = {}

    def __call__(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        self.sim.reset(x)
        x_next, _, contact = self.sim.step(float(np.clip(u[0], -U_MAX, U_MAX)))
        self.contact[x_next.tobytes()] = bool(contact.any())
        return x_next

    def success(self, xs: np.ndarray, us: np.ndarray, last: int = 25) -> bool:
        """:func:`studies.physics.mpc_example.success`: ``|theta| <= 0.8`` throughout, and over the
        last ``last`` periods ``|theta| < 0.1`` and no wall contact."""
        theta = xs[:, 1]
        touched = any(self.contact.get(x.tobytes(), False) for x in xs[-last:])
        return bool(np.all(np.abs(theta) <= 0.8) and np.all(np.abs(theta[-last:]) < 0.1) and not touched)


def controller(model: LCS) -> C3:
    """C3 with the package's defaults and the actuator's limit."""
    return C3(model, 10, Q=list(Q_STAGE), R=[1.0], u_bounds=(-U_MAX, U_MAX))


def random_data(n: int, seed: int = 0) -> Dataset:
    tr = sample_transitions(n, seed=seed)
    return Dataset.from_arrays(tr.x, tr.u, tr.x_next)


def fresh_model(seed: int = 0) -> LCS:
    return LCS(4, 1, N_LAM, stiffness=1.0, init_scale=0.1, seed=seed)


def read_rounds(path: str) -> list[dict[str, Any]]:
    if not os.path.exists(path):
        return []
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Learn, control, relearn on the MuJoCo cart-pole.")
    ap.add_argument("--out", default=os.path.join("studies", "results", "control"))
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--random", type=int, default=500, help="random transitions of round 0")
    ap.add_argument("--starts", type=int, default=50)
    ap.add_argument("--iterations", type=int, default=None, help="Adam steps of each fit (default: the recipe's)")
    ap.add_argument("--fresh", action="store_true", help="refit from a fresh start each round (not warm)")
    ap.add_argument("--smoke", action="store_true", help="3 starts, 1 s runs, 1 round, short fits")
    ap.add_argument("--seed", type=int, default=0,
                    help="seed of the random transitions, the model's start and the fits (default 0)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    steps = 100
    fit_options = dict(FIT, seed=args.seed)
    if args.iterations is not None:
        fit_options["iterations"] = args.iterations
    if args.smoke:
        args.starts, args.rounds, steps = 3, 1, 25
        fit_options.update(iterations=200, restarts=1)
    name = ("relearn" + ("_fresh" if args.fresh else "") + (f"_it{args.iterations}" if args.iterations else "")
            + (f"_seed{args.seed}" if args.seed else "") + ("_smoke" if args.smoke else ""))
    cache = os.path.join(args.out, f"{name}_cache")
    os.makedirs(cache, exist_ok=True)
    log = os.path.join(args.out, f"{name}.jsonl")
    X0 = starts(args.starts)
    plant = MuJoCoPlant()
    done = [r for r in read_rounds(log) if r["kind"] == "round"]
    t0 = time.perf_counter()
    with threadpool_limits(1), warnings.catch_warnings():
        warnings.simplefilter("ignore", lcs_cvx.PlanGapWarning)  # counted in the plans' gaps instead

        def save(rec: Any, model: LCS, data: Dataset) -> None:
            lcs_cvx.save_model(model, os.path.join(cache, f"model_after_{rec.round}.npz"))
            data.save(os.path.join(cache, f"data_after_{rec.round}.npz"))
            with open(log, "a") as f:
                f.write(json.dumps({"kind": "round", **dataclasses.asdict(rec)}) + "\n")

        if len(done) < args.rounds + 1:
            if done:
                last = done[-1]["round"]
                model = lcs_cvx.load_model(os.path.join(cache, f"model_after_{last}.npz"))
                data = Dataset.load(os.path.join(cache, f"data_after_{last}.npz"))
                kw = {"fit_first": False, "first_round": last + 1}
            else:
                model, data, kw = fresh_model(args.seed), random_data(args.random, args.seed), {}
            relearn(model, data, plant, controller, X0, plant.success, rounds=args.rounds, steps=steps,
                    fit_options=fit_options, warm_start=not args.fresh, on_round=save, progress=lambda line: print(line, flush=True), **kw)
        done = [r for r in read_rounds(log) if r["kind"] == "round"]
        baseline = [r for r in read_rounds(log) if r["kind"] == "baseline"]
        if not baseline:
            n = done[-1]["data_size"]
            model = fresh_model(args.seed)
            lcs_cvx.fit(model, random_data(n, args.seed), progress=False, **fit_options)
            res = relearn(model, random_data(args.random, args.seed), plant, controller, X0, plant.success, rounds=0,
                          steps=steps, fit_first=False)
            rec = {"kind": "baseline", "random": n, **dataclasses.asdict(res.rounds[0])}
            with open(log, "a") as f:
                f.write(json.dumps(rec) + "\n")
            baseline = [rec]
    write_report(args, name, done, baseline[0], time.perf_counter() - t0)
    return 0


def _rounds_text(rows: list[dict[str, Any]]) -> str:
    return ", ".join(f"{r['successes']}/{r['runs']}" for r in rows)


def write_report(args: Any, name: str, rounds: list[dict[str, Any]], baseline: dict[str, Any], wall: float) -> None:
    flags = (" --smoke" if args.smoke else f" --rounds {args.rounds} --random {args.random}"
             + (f" --iterations {args.iterations}" if args.iterations else "") + (" --fresh" if args.fresh else "")
             + (f" --seed {args.seed}" if args.seed else ""))
    cmd = f"python -m studies.control.relearn --out {args.out}{flags}"
    refit = ("refitted from a fresh start as the first fit" if args.fresh
             else "the model refitted from where it was (`init=\"model\"`)")
    steps = "" if args.iterations is None else f", {args.iterations:,} Adam steps per fit"
    lines = [
        "# Learn, control, relearn on the MuJoCo cart-pole",
        "",
        f"Written by `{cmd}` on {time.strftime('%Y-%m-%d', time.gmtime())} ({MACHINE}); the rounds are kept in "
        f"`{name}.jsonl` (this invocation ran {wall:.0f} s).",
        "",
        f"**Loop** (`lcs_cvx.control.relearn`): an LCS with n_lam = {N_LAM} learned from {args.random} random "
        f"transitions of `studies.physics.plant.sample_transitions` (seed {args.seed}; `recipe=\"best\"`, stiffness 1, "
        f"init_scale 0.1{steps}), then per round C3 with the package's defaults "
        "(`C3(model, 10, Q=diag(5, 20, 0.5, 0.5), R=[1], u_bounds=(-4, 4))`) closed on MuJoCo from the starts "
        "of `mujoco_closed_loop.md` (its task and success test), the closed-loop transitions added to the data "
        f"and {refit}.",
        "",
        "| round | success | closed-loop transitions added | data after the round | ms per control step | "
        "control s | refit s |",
        "|---:|---|---:|---:|---:|---:|---:|",
    ]
    for r in rounds:
        lines.append(f"| {r['round']} | {r['successes']}/{r['runs']} | {r['transitions']:,} | {r['data_size']:,} | "
                     f"{r['ms_per_step']:.2f} | {r['control_s']:.1f} | {r['fit_s']:.1f} |")
    lines += [
        "",
        f"**Same budget of random data.** The same LCS learned from {baseline['random']:,} random transitions "
        f"(as many as the last round's data) and controlled the same way: {baseline['successes']}/"
        f"{baseline['runs']} successes.",
        "",
    ]
    variants = {"relearn_fresh": "every refit from a fresh start (`--fresh`)",
                "relearn_it12000": "12,000 Adam steps per fit, as the physics study's models (`--iterations 12000`)"}
    found = {k: read_rounds(os.path.join(args.out, f"{k}.jsonl")) for k in variants if k != name}
    found = {k: v for k, v in found.items() if v}
    if found and not args.smoke:
        lines += ["**Variants** (the same command with the flag named; success per round 0, 1, ..., then the "
                  "random-data baseline):", ""]
        for k, rows in found.items():
            rs = [r for r in rows if r["kind"] == "round"]
            base = [r for r in rows if r["kind"] == "baseline"]
            lines.append(f"- {variants[k]}: {_rounds_text(rs)}"
                         + (f"; random data {base[0]['successes']}/{base[0]['runs']}" if base else "") + ".")
        lines.append("")
    seeds = {0 if k == "relearn" else int(k.removeprefix("relearn_seed")): read_rounds(os.path.join(args.out, f"{k}.jsonl"))
             for k in ["relearn"] + [f"relearn_seed{s}" for s in range(1, 10)]}
    seeds = {s: rows for s, rows in seeds.items() if any(r["kind"] == "baseline" for r in rows)}
    if len(seeds) > 1 and not args.smoke and not args.fresh and not args.iterations:
        lines += ["**Seeds** (`--seed S`: the random transitions, the model's start and every fit's minibatches; "
                  "success per round 0, 1, ..., then the random-data baseline):", "",
                  "| seed | rounds | random data |", "|---:|---|---|"]
        for s, rows in sorted(seeds.items()):
            base = next(r for r in rows if r["kind"] == "baseline")
            lines.append(f"| {s} | {_rounds_text([r for r in rows if r['kind'] == 'round'])} | "
                         f"{base['successes']}/{base['runs']} |")
        lines.append("")
    with open(os.path.join(args.out, f"{name}.md"), "w") as f:
        f.write("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    sys.exit(main())
