"""Learn, control, relearn: the loop a user runs on a robot with a learned LCS.

Round 0 controls the plant with a model fitted on the data given (typically a little random
data); every round then

1. builds a controller on the current model (``make_controller(model)``, e.g. a
   :class:`lcs_cvx.control.C3` with default options),
2. closes the loop on the plant from each start (``plant(x, u) -> x'``, one state at a time:
   a simulator or the robot), recording every transition ``(x, u, x')`` and whether the run
   succeeded (``success(xs, us)``),
3. adds the closed-loop transitions to the data and refits the model from where it is
   (:func:`lcs_cvx.fit` with ``init="model"``: a warm start),

and records the success of each round. The closed-loop transitions are where the controller
takes the system, which random data rarely visits: the point of relearning.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from .._checks import LCSInputError, check_positive
from ..data import Dataset
from ..system import LCS
from ..train import fit

__all__ = ["Round", "Relearning", "relearn"]


@dataclasses.dataclass
class Round:
    """One round: the controller built on the model of ``round`` (0: fitted on the data given),
    its runs from every start, and the data the next fit sees.

    Attributes:
        round: the round's index.
        successes: runs that succeeded, of ``runs``.
        runs: the number of starts.
        transitions: closed-loop transitions this round added.
        data_size: transitions in the data after this round's are added.
        control_s: seconds closing the loops (plant and controller); ``fit_s``: seconds refitting
            after them (0 in the last round, which is not refitted).
        ms_per_step: median milliseconds per controller call.
        success: per start, whether its run succeeded.
    """

    round: int
    successes: int
    runs: int
    transitions: int
    data_size: int
    control_s: float
    fit_s: float
    ms_per_step: float
    success: list[bool]


@dataclasses.dataclass
class Relearning:
    """What :func:`relearn` did: ``rounds`` (one :class:`Round` each), the last ``model`` and
    all the ``data`` (the data given plus every round's closed-loop transitions)."""

    rounds: list[Round]
    model: LCS
    data: Dataset

    def table(self) -> str:
        """The rounds as a markdown table."""
        lines = ["| round | success | closed-loop transitions added | data after the round | "
                 "ms per control step | control s | refit s |", "|---:|---|---:|---:|---:|---:|---:|"]
        for r in self.rounds:
            lines.append(f"| {r.round} | {r.successes}/{r.runs} | {r.transitions:,} | {r.data_size:,} | "
                         f"{r.ms_per_step:.2f} | {r.control_s:.1f} | {r.fit_s:.1f} |")
        return "\n".join(lines)


def _closed_loop(plant: Callable[[np.ndarray, np.ndarray], Any], ctrl: Callable[[np.ndarray], Any],
                 x0: np.ndarray, steps: int, n_u: int) -> tuple[np.ndarray, np.ndarray, list[float]]:
    """One run: ``xs (steps + 1, n_x)``, ``us (steps, n_u)`` and the controller's call times."""
    xs, us, times = [np.asarray(x0, dtype=np.float64)], [], []
    for _ in range(steps):
        t = time.perf_counter()
        u = np.asarray(torch.as_tensor(ctrl(xs[-1])).detach().cpu(), dtype=np.float64).reshape(n_u)
        times.append(time.perf_counter() - t)
        x_next = np.asarray(plant(xs[-1], u), dtype=np.float64).reshape(-1)
        if x_next.shape != xs[-1].shape or not np.all(np.isfinite(x_next)):
            raise LCSInputError(f"plant: expected a finite next state of shape {xs[-1].shape}, received "
                                f"{x_next.shape if x_next.shape != xs[-1].shape else 'a non-finite one'}")
        xs.append(x_next)
        us.append(u)
    return np.stack(xs), np.stack(us), times


def relearn(model: LCS, data: Dataset, plant: Callable[[np.ndarray, np.ndarray], Any],
            make_controller: Callable[[LCS], Callable[[np.ndarray], Any]], starts: Sequence[Any] | np.ndarray,
            success: Callable[[np.ndarray, np.ndarray], bool], *, rounds: int = 3, steps: int = 100,
            fit_options: dict[str, Any] | None = None, warm_start: bool = True, fit_first: bool = True,
            first_round: int = 0,
            on_round: Callable[[Round, LCS, Dataset], None] | None = None,
            progress: Callable[[str], None] | None = None) -> Relearning:
    """Learn -> control -> relearn, ``rounds`` times after round 0 (module docstring).

    Args:
        model: the LCS to learn into (its own start, or a model already fitted: ``fit_first=False``).
        data: the transitions to start from (a :class:`lcs_cvx.Dataset`, e.g. random inputs).
        plant: ``plant(x, u) -> x'`` for one state ``(n_x,)`` and input ``(n_u,)`` (NumPy).
        make_controller: ``make_controller(model) -> ctrl`` with ``ctrl(x) -> u``; called once per
            round on the current model (e.g. ``lambda m: C3(m, 10, Q=Q, R=R, u_bounds=...)``).
        starts: initial states ``(S, n_x)``, the same every round.
        success: ``success(xs, us) -> bool`` for one run's states ``(steps + 1, n_x)`` and inputs.
        rounds: refits after round 0 (``rounds + 1`` rounds are run).
        steps: control steps per run.
        fit_options: keyword arguments of every :func:`lcs_cvx.fit` (``progress=False`` unless
            given).
        warm_start: refit from the current model (``init="model"``); False: every refit starts
            as the first fit does (``fit_options``' own ``init``).
        fit_first: fit ``model`` on ``data`` before the first round (False: ``model`` is already
            fitted).
        first_round: the index of the first round run (to resume: ``model`` and ``data`` as
            ``on_round`` saw them after round ``first_round - 1``, and ``fit_first=False``).
        on_round: called after each round with its :class:`Round`, the model refitted after it
            and the data so far (e.g. to save them: nothing is lost when a long run stops).
        progress: called with a line per round (e.g. ``print``).

    Returns:
        A :class:`Relearning`: the rounds, the last model and all the data. ``model`` is
        updated in place.
    """
    if not isinstance(model, LCS):
        raise LCSInputError(f"model: expected an lcs_cvx.LCS, received {type(model).__name__}")
    if not isinstance(data, Dataset):
        raise LCSInputError(f"data: expected an lcs_cvx.Dataset, received {type(data).__name__}")
    if (data.n_x, data.n_u) != (model.n_x, model.n_u):
        raise LCSInputError(f"data: expected n_x = {model.n_x}, n_u = {model.n_u} (the model's), received "
                            f"n_x = {data.n_x}, n_u = {data.n_u}")
    X0 = np.asarray(starts, dtype=np.float64)
    if X0.ndim != 2 or X0.shape[1] != model.n_x or X0.shape[0] == 0 or not np.all(np.isfinite(X0)):
        raise LCSInputError(f"starts: expected finite initial states of shape (S, {model.n_x}), S >= 1, "
                            f"received shape {X0.shape}")
    for name, value in (("rounds", rounds), ("first_round", first_round)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
            raise LCSInputError(f"{name}: expected an integer >= 0, received {value!r}")
    steps = check_positive("steps", steps, integer=True)
    options = {"progress": False, **(fit_options or {})}
    if fit_first:
        fit(model, data, **options)
    out: list[Round] = []
    for r in range(first_round, rounds + 1):
        ctrl = make_controller(model)
        t0 = time.perf_counter()
        xs_all, us_all, times, ok = [], [], [], []
        for x0 in X0:
            if hasattr(ctrl, "reset"):
                ctrl.reset()  # each run is a new episode
            xs, us, call_times = _closed_loop(plant, ctrl, x0, steps, model.n_u)
            xs_all.append(xs)
            us_all.append(us)
            times += call_times
            ok.append(bool(success(xs, us)))
        control_s = time.perf_counter() - t0
        new = Dataset.from_arrays(np.concatenate([x[:-1] for x in xs_all]), np.concatenate(us_all),
                                  np.concatenate([x[1:] for x in xs_all]))
        data = Dataset.from_arrays(*(torch.cat([getattr(data, k), getattr(new, k).to(getattr(data, k))])
                                     for k in ("x", "u", "x_next")))
        fit_s = 0.0
        if r < rounds:
            t1 = time.perf_counter()
            fit(model, data, **({**options, "init": "model"} if warm_start else options))
            fit_s = time.perf_counter() - t1
        rec = Round(round=r, successes=sum(ok), runs=len(ok), transitions=len(new), data_size=len(data),
                    control_s=control_s, fit_s=fit_s, ms_per_step=1e3 * float(np.median(times)), success=ok)
        out.append(rec)
        if on_round is not None:
            on_round(rec, model, data)
        if progress is not None:
            progress(f"round {r}: {rec.successes}/{rec.runs} succeeded; {rec.transitions} transitions added "
                     f"({rec.data_size} in all); control {control_s:.1f} s, refit {fit_s:.1f} s")
    return Relearning(rounds=out, model=model, data=data)
