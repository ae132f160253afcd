"""The closed loop of the MuJoCo control studies, once: a controller's calls timed, the runs of
every controller from every start (resumable, one JSON line per run), and MPPI, the sampling
controller the studies put beside C3.

- :class:`Timed`: a controller whose calls are timed, with the plan violations of a C3 wrapper;
- :func:`run_units`: every ``(controller, start)`` run not yet in the study's ``.jsonl``, appended
  as it finishes (a killed study resumes where it stopped);
- :class:`MPPI`: model-predictive path integral control on a batched torch model, with the
  rollout cost a study gives it.

The plants, the success tests and the reports are the studies' own
(:mod:`studies.control.mujoco_closed_loop`, :mod:`studies.control.pusher_closed_loop`); the
LCS's own closed loop (:func:`lcs_cvx.control.closed_loop`, batched over starts) runs C3's
cart-pole study (:mod:`studies.control.cartpole_c3`).
"""

from __future__ import annotations

import glob
import json
import os
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

__all__ = ["Timed", "plan_medians", "read_records", "run_units", "MPPI", "draws_table"]


class Timed:
    """``ctrl`` (a callable, or None: no input) with its calls timed (``times``, seconds);
    :meth:`summary` is what a run's record says of them."""

    def __init__(self, ctrl: Any) -> None:
        self.ctrl, self.times = ctrl, []

    def __call__(self, *args: Any) -> Any:
        t = time.perf_counter()
        u = self.ctrl(*args)
        self.times.append(time.perf_counter() - t)
        return u

    def summary(self) -> dict[str, float]:
        """The median milliseconds per call, and the median complementarity violation of the
        plans of a controller that records them (a ``violation`` list)."""
        out = {"ms_per_step_median": float(1e3 * np.median(self.times)) if self.times else 0.0}
        violation = getattr(self.ctrl, "violation", None)
        if violation is not None:
            out["plan_violation_median"] = float(np.median(violation))
        gap = getattr(self.ctrl, "gap", None)
        if gap is not None:
            out["plan_gap_median"] = float(np.median(gap))
        return out


def plan_medians(records: list[dict[str, Any]]) -> dict[str, float]:
    """The median over runs of the plans' complementarity violation and gap to the model
    (``"violation"``, ``"gap"``; NaN for a controller whose runs do not record them)."""
    return {key: float(np.median([r[f"plan_{key}_median"] for r in records]))
            if f"plan_{key}_median" in records[0] else float("nan") for key in ("violation", "gap")}


def read_records(path: str, steps: int) -> dict[tuple[str, int], dict[str, Any]]:
    """The runs of ``path`` (a JSON-lines file; a missing file: none) of ``steps`` steps, by
    ``(controller, start)``; a later line of the same run replaces an earlier one."""
    done: dict[tuple[str, int], dict[str, Any]] = {}
    if os.path.exists(path):
        with open(path) as f:
            for line in f:
                if line.strip():
                    rec = json.loads(line)
                    if rec.get("steps") == steps:
                        done[(rec["controller"], int(rec["start"]))] = rec
    return done


def run_units(path: str, names: Sequence[str], starts: Sequence[Any], steps: int,
              context: Callable[[], dict[str, Any]],
              run_one: Callable[[str, dict[str, Any], Any], dict[str, Any]],
              describe: Callable[[dict[str, Any]], str]) -> tuple[list[dict[str, Any]], dict[str, Any] | None]:
    """Every run ``run_one(name, ctx, start)`` of the controllers ``names`` from ``starts`` that
    ``path`` does not hold yet, in that order, each appended to ``path`` as it finishes (with its
    ``start`` index) and described on stderr (``describe(record)``). ``context()`` (the fitted
    models the controllers share) is called once, before the first run to do.

    Returns the records of every run, by controller and start, and the context (None when every
    run was done already)."""
    done = read_records(path, steps)
    ctx: dict[str, Any] | None = None
    for name in names:
        for i, start in enumerate(starts):
            if (name, i) in done:
                continue
            if ctx is None:
                ctx = context()
            rec = run_one(name, ctx, start)
            rec["start"] = i
            done[(name, i)] = rec
            with open(path, "a") as f:
                f.write(json.dumps(rec) + "\n")
            print(f"{name:45s} start {i:3d}: {describe(rec)}", file=sys.stderr, flush=True)
    return [done[(n, i)] for n in names for i in range(len(starts)) if (n, i) in done], ctx


class MPPI:
    """Model-predictive path integral control (sampling MPC) on a batched model.

    ``samples`` input sequences ``u = mean + sigma * noise`` ``(samples, horizon, n_u)`` (the first
    sample the mean itself), clipped to ``|u| <= u_max``, scored by ``cost(x0, us)`` (the study's
    rollout of its model and its cost, ``(samples,)``; a NaN or infinite cost counts as 1e9); the
    new mean is the average weighted by ``exp(-(cost - min cost) / temperature)``, repeated
    ``iterations`` times per control step, and is shifted by one step between calls. ``n_u = 0``
    means a scalar input (``u`` of shape ``(samples, horizon)``, a float returned)."""

    def __init__(self, cost: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], *, n_u: int, horizon: int,
                 samples: int, sigma: float, temperature: float, iterations: int, u_max: float,
                 seed: int = 0) -> None:
        self.cost, self.H, self.K, self.n_u = cost, horizon, samples, n_u
        self.sigma, self.temperature, self.iterations, self.u_max = sigma, temperature, iterations, u_max
        self.gen = torch.Generator().manual_seed(seed)
        self.shape = (horizon, n_u) if n_u else (horizon,)
        self.mean = torch.zeros(self.shape)

    @torch.no_grad()
    def plan(self, x: np.ndarray, *args: Any) -> torch.Tensor:
        """The first input of the new mean (and the mean shifted for the next call)."""
        x0 = torch.as_tensor(np.asarray(x), dtype=torch.float32)
        for _ in range(self.iterations):
            noise = torch.randn((self.K, *self.shape), generator=self.gen) * self.sigma
            noise[0] = 0.0  # keep the mean itself among the samples
            us = (self.mean + noise).clamp(-self.u_max, self.u_max)
            cost = torch.nan_to_num(self.cost(x0, us, *args), nan=1e9, posinf=1e9)
            w = torch.softmax(-(cost - cost.min()) / self.temperature, 0)
            self.mean = (w.reshape(-1, *[1] * len(self.shape)) * us).sum(0)
        u0 = self.mean[0]
        self.mean = torch.cat([self.mean[1:], self.mean[-1:]])
        return u0


def draws_table(out: str, stem: str, rows: Sequence[str], steps: int,
                summarise: Callable[[list[dict[str, Any]], list[str]], dict[str, dict[str, Any]]],
                how: str) -> list[str]:
    """The success of ``rows`` on every draw of the learned models whose runs ``out`` holds:
    ``stem.jsonl`` (the study's own models, its fits' seeds 0 and 1) and ``stem_seedsAB.jsonl``
    (``--models ... --tag seedsAB``: a draw with the fits' seeds A and B); a report section, or
    nothing with one draw. ``how``: the commands of a draw, in words."""
    draws = {"0, 1": os.path.join(out, f"{stem}.jsonl")}
    for path in sorted(glob.glob(os.path.join(out, f"{stem}_seeds*.jsonl"))):
        draws[", ".join(os.path.basename(path)[len(stem) + len("_seeds"):-len(".jsonl")])] = path
    if len(draws) < 2:
        return []
    found = {d: summarise(list(read_records(p, steps).values()), list(rows)) for d, p in draws.items()}
    lines = ["## The spread over draws of the learned models", "", how, "",
             "| controller | " + " | ".join(f"fits' seeds {d}" for d in draws) + " |",
             "|---|" + "---|" * len(draws)]
    for row in rows:
        cells = [f"{found[d][row]['success']}/{found[d][row]['runs']}" if row in found[d] else "" for d in draws]
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    return lines + [""]
