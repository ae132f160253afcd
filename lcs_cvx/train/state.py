"""The state of one training run: everything needed to continue it exactly.

:class:`TrainState` holds the model being trained (the user's, or a grown copy with extra units
until the pruning phase), the optimisers, the random generator and the epoch permutation, the
steps done per phase, the history and the accumulators of the current record, and the fast
solver's last active sets per training sample (warm starts). :meth:`TrainState.state_dict` and
:meth:`TrainState.load_state_dict` are the one place that (de)serialises it: tensors and plain
types only, loadable with ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from .._checks import LCSInputError
from .._kernels.calls import MIN_CHUNK
from ..data import Dataset
from ..parameter_constraints import allowed_extra_units
from ..resizing import add_units
from ..scaling import Scaling
from ..simulation_error import Windows
from ..system import LCS
from .onecall import data_arrays
from .options import FitOptions
from .phase_options import extra_units

#: The smallest minibatch of every training sample that :meth:`TrainState.next_batch` takes in
#: storage order: a batch solved in parts (:data:`lcs_cvx._kernels.calls.MIN_CHUNK`), whose
#: rows drawn at random are a cache miss each; a smaller one, which the caches hold, is taken in
#: the permutation's order like any other minibatch.
IN_ORDER_FROM = 2 * MIN_CHUNK

__all__ = ["TrainState", "Outcome", "PHASES"]

#: The phases, in the order a run goes through them.
PHASES = ("adam", "prune", "refine", "polish", "rollout")


@dataclass(frozen=True)
class Outcome:
    """What one step of a phase reports: its regularised loss (None: nothing to record), the
    ``eps`` and learning rate it used, and the samples its solver handed to the reference
    (``n_fallback``) with the worst relative KKT residual among them."""

    loss: float | None
    eps: float
    lr: float | None
    n_fallback: int = 0
    fallback_residual: float = 0.0


class TrainState:
    """One run of :func:`lcs_cvx.fit` (one restart)."""

    def __init__(self, model: LCS, train: Dataset, options: FitOptions, restart: int, *,
                 test_score: Callable[[LCS], float] | None = None,
                 validate: Callable[[LCS], float] | None = None,
                 windows: Windows | None = None, scaling: Scaling | None = None,
                 threads: int | None = None, kinematics: Any = None,
                 sigma: torch.Tensor | None = None) -> None:
        self.model, self.train, self.options, self.restart = model, train, options, restart
        # the compiled kernels' threads, and the training data as arrays for the one-call steps
        # (:mod:`lcs_cvx.train.onecall`; None where they are not float64 CPU tensors)
        self.threads = threads
        lcs = isinstance(model, LCS)  # else a model of per-sample matrices (its own losses, no units)
        self.arrays = data_arrays(train) if lcs else None
        # the simulation-error phase: windows of the training trajectories (user's units), the
        # coordinates the model is learned in and the user's model's kinematics
        self.windows, self.scaling, self.kinematics = windows, scaling, kinematics
        # the simulation error's scale of each coordinate in the data's units, for a model learned
        # in them (a model of per-sample matrices): the spread of its one-step change
        self.rollout_sigma = None if sigma is None else sigma.to(dtype=model.dtype, device=self.device)
        # the held-out score (None: no held-out part): what every choice follows -- the kept
        # iterate (``keep_best``) and whether the simulation-error phase's result is kept; the
        # model and score before that phase; whether it was kept
        self.validate = validate
        self.rollout_start: tuple[float, dict[str, torch.Tensor]] | None = None
        self.rollout_kept: bool | None = None
        # e_test of a model being trained (the error on ``test`` of the model in the user's
        # units): recorded only, never chosen by
        self.test_score = test_score
        if options.run.keep_best and validate is None:
            raise LCSInputError("keep_best: expected a held-out part to choose the iterate by (validation=, "
                                "or Trajectories with a holdout fraction; a test set is only reported), "
                                "received keep_best=True without one")
        self.keeps_best = bool(options.run.keep_best)
        a = options.adam
        self.generator = torch.Generator().manual_seed(options.run.seed * 1_000_003 + restart)
        # the model Adam trains: the user's, or a larger one the pruning phase cuts back
        self.n_extra = allowed_extra_units(model, a.extra_units, extra_units(a.extra_units, model.n_lam)) if lcs else 0
        self.work = add_units(model, self.n_extra, self.generator) if self.n_extra else model
        self.adam = torch.optim.Adam(self.work.parameters(), lr=a.lr, betas=a.betas, eps=a.adam_eps)
        self.polish_adam = torch.optim.Adam(model.parameters(), lr=options.polish.lr,
                                            betas=a.betas, eps=a.adam_eps)
        self.rollout_adam = torch.optim.Adam(model.parameters(), lr=options.rollout.lr,
                                             betas=a.betas, eps=a.adam_eps)
        self.perm = self._permutation()
        self.pos = 0
        self.steps = dict.fromkeys(PHASES, 0)
        self.history: list[dict[str, Any]] = []
        self.damping = options.refine.damping
        self.best: tuple[float, dict[str, torch.Tensor]] | None = None
        if self.keeps_best:  # the start is a candidate too
            self._consider(validate(model))
        self._reset_stretch()
        # the fast solver's final active sets per training sample: the warm start of the
        # sample's next visit; the loss does not depend on them, the solver's work does
        self.active: torch.Tensor | None = None
        self.seen = torch.zeros(len(train), dtype=torch.bool, device=self.device)
        self._views: tuple | None = None

    @property
    def iteration(self) -> int:
        """Optimiser steps done in this run (Adam, second-order, polish and rollout steps)."""
        return self.steps["adam"] + self.steps["refine"] + self.steps["polish"] + self.steps["rollout"]

    # -- data
    @property
    def device(self) -> torch.device:
        """The training data's device: of the minibatch indices and the warm-start tables."""
        return self.train.x.device

    def _permutation(self) -> torch.Tensor:
        """A random permutation of the training samples, drawn on the run's CPU generator (the
        same numbers on every device) and held on the data's device: a GPU run's minibatches
        and warm starts are gathered there, without a copy through the host per step."""
        return torch.randperm(len(self.train), generator=self.generator).to(self.device)

    def next_batch(self, size: int) -> torch.Tensor:
        """The indices of the next minibatch (on the data's device): a fresh permutation every
        epoch. A minibatch of every training sample, of at least :data:`IN_ORDER_FROM`, is
        taken in storage order: its rows are read one after another instead of one cache miss
        each (the benchmarks page's fit step); only the order of the sums over the samples
        changes. The permutation is drawn all the same, so that the run's random numbers (and
        the samples that re-initialisations look at) are those of any other batch size."""
        if self.pos + size > len(self.perm):
            self.perm = self._permutation()
            self.pos = 0
        if size >= len(self.perm) >= IN_ORDER_FROM:
            self.pos = len(self.perm)
            return torch.arange(len(self.perm), device=self.perm.device)
        idx = self.perm[self.pos : self.pos + size]
        self.pos += size
        return idx

    def batch(self, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        d = self.train
        return d.x[idx], d.u[idx], d.x_next[idx]

    def warm_start(self, idx: torch.Tensor) -> torch.Tensor | None:
        """The active sets of the samples ``idx`` from their last visit (None unless all were seen)."""
        return self.active[idx] if self.active is not None and bool(self.seen[idx].all()) else None

    def warm_tables(self, width: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(active, seen)`` as arrays on their tensors' memory (made again when either tensor
        is replaced, by :meth:`load_state_dict`); ``width``: the active sets' width, for a table
        not made yet (nothing seen)."""
        if self.active is None and width is not None:
            self.active = torch.zeros(len(self.train), width, dtype=torch.bool, device=self.device)
        if self._views is None or self._views[0] is not self.active or self._views[1] is not self.seen:
            self._views = (self.active, self.seen, self.active.numpy(), self.seen.numpy())
        return self._views[2], self._views[3]

    def remember(self, idx: torch.Tensor, active: torch.Tensor | np.ndarray) -> None:
        if self.active is None:
            self.active = torch.zeros(len(self.train), active.shape[1], dtype=torch.bool, device=self.device)
        if isinstance(active, np.ndarray):
            rows = idx.numpy()
            table, seen = self.warm_tables()
            table[rows] = active
            seen[rows] = True
            return
        self.active[idx] = active.to(self.active.device)
        self.seen[idx] = True

    # -- records
    def _reset_stretch(self) -> None:
        self.acc_loss, self.acc_n, self.acc_fallback, self.acc_residual = 0.0, 0, 0, 0.0

    def add(self, out: Outcome) -> None:
        """Accumulate one step's outcome into the current record."""
        if out.loss is not None:
            self.acc_loss += out.loss
            self.acc_n += 1
        self.acc_fallback += out.n_fallback
        self.acc_residual = max(self.acc_residual, out.fallback_residual)

    def record(self, phase: str, eps: float, lr: float | None, elapsed: float) -> dict[str, Any]:
        """Close the current stretch of steps as one history record: the mean training loss, the
        test error ``e_test`` (with a test set; reported only) and, with ``keep_best``, the
        held-out score ``heldout`` that picks the iterate returned."""
        tracked = self.work is self.model  # not while a grown model is trained
        heldout = self.validate(self.work) if self.keeps_best and tracked else None
        rec = {
            "iteration": self.iteration, "phase": phase,
            "loss": self.acc_loss / max(1, self.acc_n), "eps": eps, "lr": lr,
            "e_test": self.test_score(self.work) if self.test_score is not None else None,
            "heldout": heldout, "wall_time": elapsed, "restart": self.restart,
            "n_fallback": self.acc_fallback, "fallback_residual": self.acc_residual,
        }
        self._reset_stretch()
        self.history.append(rec)
        if heldout is not None:
            self._consider(heldout)
        return rec

    def _consider(self, score: float) -> None:
        """Keep the model's parameters as the best iterate if ``score`` is the lowest so far (a
        NaN score, a diverged rollout, counts as infinite)."""
        score = math.inf if math.isnan(score) else score
        if self.best is None or score < self.best[0]:
            self.best = (score, {k: p.detach().clone() for k, p in self.model.named_parameters()})

    def restore_best(self) -> None:
        """Load the best iterate (``keep_best``) into the model."""
        if self.best is not None:
            with torch.no_grad():
                for k, v in self.best[1].items():
                    getattr(self.model, k).copy_(v)

    # -- serialisation (the one place)
    def state_dict(self) -> dict[str, Any]:
        grown = self.work is not self.model

        def params(m: LCS) -> dict[str, torch.Tensor]:
            return {k: v.detach().clone() for k, v in m.state_dict().items()}

        return {
            "model": params(self.model), "work": params(self.work) if grown else None,
            # after the pruning, the Adam moments belong to the discarded grown model
            "adam": self.adam.state_dict() if grown or self.n_extra == 0 else None,
            "polish_adam": self.polish_adam.state_dict(), "rollout_adam": self.rollout_adam.state_dict(),
            "generator": self.generator.get_state(), "perm": self.perm, "pos": self.pos,
            "steps": dict(self.steps), "history": self.history, "damping": self.damping,
            "best": None if self.best is None else {"score": self.best[0], "params": self.best[1]},
            "stretch": [self.acc_loss, self.acc_n, self.acc_fallback, self.acc_residual],
            "active": self.active, "seen": self.seen,
            "rollout_start": None if self.rollout_start is None else {
                "score": self.rollout_start[0], "params": self.rollout_start[1]},
            "rollout_kept": self.rollout_kept,
        }

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.model.load_state_dict(st["model"])
        if st["work"] is not None:
            self.work.load_state_dict(st["work"])
        else:
            self.work = self.model  # pruned already
        if st["adam"] is not None:
            self.adam.load_state_dict(st["adam"])
        self.polish_adam.load_state_dict(st["polish_adam"])
        self.rollout_adam.load_state_dict(st["rollout_adam"])
        self.generator.set_state(st["generator"])
        self.perm, self.pos = st["perm"].to(self.device), st["pos"]
        self.steps, self.history, self.damping = dict(st["steps"]), st["history"], st["damping"]
        self.best = None if st["best"] is None else (st["best"]["score"], st["best"]["params"])
        self.acc_loss, self.acc_n, self.acc_fallback, self.acc_residual = st["stretch"]
        self.active = None if st["active"] is None else st["active"].to(self.device)
        self.seen = st["seen"].to(self.device)
        start = st["rollout_start"]
        self.rollout_start = None if start is None else (start["score"], start["params"])
        self.rollout_kept = st["rollout_kept"]

