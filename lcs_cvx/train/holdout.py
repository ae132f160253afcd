"""The data of a :func:`lcs_cvx.fit` run split into what it trains on and what it holds out, and
the held-out scores of the learned model and of the least-squares affine map on the same split.

:func:`split_data` takes the user's ``train`` (a :class:`lcs_cvx.Dataset` of transitions or
:class:`lcs_cvx.Trajectories`) and optional ``validation``:

- ``validation`` given: it is the held-out part, ``train`` is trained on whole;
- :class:`~lcs_cvx.Trajectories`: ``holdout`` of the trajectories, whole ones, held out (random
  transitions of one run would leak their neighbours into validation), at least
  :data:`MIN_HELDOUT_RUNS` of five or more (a score on one run is that run's noise) and one of
  two to four, always leaving one to train on; with one trajectory, nothing;
- a :class:`~lcs_cvx.Dataset`: ``holdout`` of the transitions, held out with ``restarts > 1``
  only (as before trajectories were accepted).

The held-out score (:meth:`Split.score`) is the relative error (:func:`lcs_cvx.relative_error`)
on held-out transitions, or on held-out trajectories the rollout error at ``holdout_horizon``
relative to the recorded change, each coordinate scaled by the spread of its one-step change on
the training transitions (:func:`lcs_cvx.simulation_error.change_error`; ``"auto"``: the
simulation-error phase's horizon, :data:`AUTO_ROLLOUT_HORIZON` steps or the longest held-out
run's). One score, asked by every choice a run makes: the kept iterate (``keep_best``), the
kept restart, whether the simulation-error phase is kept, :func:`lcs_cvx.select_n_lam`'s
table, and the verdict against the affine map (:meth:`Split.judge`). The choices ask it through
:meth:`Split.choice_score`: a model whose open-loop rollouts over the whole held-out
trajectories grow past :attr:`Split.growth_bound` (:data:`~lcs_cvx.train.result.GROWTH_SLACK`
times the larger of 1, the data's own, and the affine map's growth) scores ``inf`` there and is
never chosen over one that stays in the data's range.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import Any

import torch

from .._checks import LCSInputError
from ..data import Dataset
from ..metrics import AffineMap, affine_lstsq, relative_error
from ..scaling import Scaling
from ..simulation_error import change_error, rollout_growth
from ..system import LCS
from ..trajectories import Trajectories
from .phase_options import RunOptions
from .result import growth_limit

__all__ = ["Split", "split_data", "affine_lcs", "heldout_runs", "AUTO_ROLLOUT_HORIZON", "MIN_HELDOUT_RUNS"]

#: The simulation-error phase's window with ``rollout_horizon="auto"`` and trajectories as data,
#: unless ``holdout_horizon`` names a rollout horizon (then that one).
AUTO_ROLLOUT_HORIZON = 10

#: The fewest trajectories held out of five or more (:func:`heldout_runs`).
MIN_HELDOUT_RUNS = 2


def heldout_runs(count: int, holdout: float) -> int:
    """How many of ``count >= 2`` trajectories are held out: ``round(holdout * count)``, at least
    :data:`MIN_HELDOUT_RUNS` when that leaves three or more to train on (else at least one), and
    at most ``count - 1``."""
    floor = MIN_HELDOUT_RUNS if count >= MIN_HELDOUT_RUNS + 3 else 1
    return min(max(int(round(holdout * count)), floor), count - 1)


@dataclass(frozen=True)
class Split:
    """``fit``: the training transitions; ``trajectories``: the training trajectories (None when
    the data were transitions); ``holdout``: the held-out transitions or trajectories (None: no
    held-out part); ``horizon``: the rollout horizon of the held-out score (resolved: an
    integer); ``rollout_horizon``: the simulation-error phase's window (None: no such phase)."""

    fit: Dataset
    trajectories: Trajectories | None
    holdout: Dataset | Trajectories | None
    horizon: int
    rollout_horizon: int | None = None

    @functools.cached_property
    def scale(self) -> torch.Tensor:
        """The spread of each coordinate's one-step change on the training transitions
        (``(n_x,)``, float64; :attr:`lcs_cvx.scaling.Scaling.sy`): the held-out score's
        per-coordinate scale on trajectories, the simulation-error loss's."""
        return Scaling.fit(self.fit).sy

    def _score(self, model: Any, holdout: Dataset | Trajectories) -> float:
        if isinstance(holdout, Trajectories):
            return change_error(model, holdout, self.horizon, self.scale)
        return relative_error(model, holdout)

    def score(self, model: Any) -> float:
        """The held-out score of ``model`` (module docstring)."""
        return self._score(model, self.holdout)

    @functools.cached_property
    def affine(self) -> AffineMap:
        """The least-squares affine map of the training transitions."""
        return affine_lstsq(self.fit)

    def affine_score(self) -> float:
        """The held-out score of :attr:`affine`."""
        return self._score(self.affine, self.holdout)

    @functools.cached_property
    def affine_heldout(self) -> float:
        """:meth:`affine_score`, computed once, when first needed (the restarts' test and the
        verdict ask it)."""
        return self.affine_score()

    @property
    def what(self) -> str:
        """The held-out score in words (the verdict's)."""
        if isinstance(self.holdout, Trajectories):
            return f"{self.horizon}-step rollout error relative to the recorded change"
        return "one-step error relative to |x'|^2 (as e_test)"

    def growth(self, model: Any) -> float | None:
        """:func:`lcs_cvx.simulation_error.rollout_growth` on the held-out trajectories (None
        when the held-out part is transitions)."""
        return rollout_growth(model, self.holdout) if isinstance(self.holdout, Trajectories) else None

    def run_scores(self, model: Any) -> tuple[float, ...] | None:
        """The held-out score of ``model`` on each held-out trajectory long enough for the
        horizon, alone (None with held-out transitions, or with fewer than two such
        trajectories: no spread to show). ``model``: an LCS or the :attr:`affine` map."""
        if not isinstance(self.holdout, Trajectories):
            return None
        runs = [i for i, T in enumerate(self.holdout.lengths) if T >= self.horizon]
        if len(runs) < 2:
            return None
        return tuple(self._score(model, Trajectories([self.holdout.xs[i]], [self.holdout.us[i]]))
                     for i in runs)

    def judge(self, model: Any) -> dict[str, Any]:
        """Everything :class:`lcs_cvx.FitResult` reports of ``model`` against the affine map on
        the held-out part (its fields ``heldout_error``, ``affine_heldout_error``,
        ``heldout_growth``, ``affine_heldout_growth``, ``heldout_run_errors``,
        ``affine_heldout_run_errors``; the verdict is :attr:`lcs_cvx.FitResult.verdict`)."""
        trajectories = isinstance(self.holdout, Trajectories)
        return {"heldout_score": self.what,
                "heldout_error": self.score(model), "affine_heldout_error": self.affine_heldout,
                "heldout_growth": self.growth(model),
                "affine_heldout_growth": self.affine_growth() if trajectories else None,
                "heldout_run_errors": self.run_scores(model),
                "affine_heldout_run_errors": self.run_scores(self.affine)}

    @property
    def holds_out_runs(self) -> bool:
        """Whether whole trajectories are held out (then ``keep_best`` defaults to on)."""
        return self.trajectories is not None and self.holdout is not None

    def conclude(self, result: Any, affine_if_better: bool) -> Any:
        """``result`` (a :class:`lcs_cvx.FitResult`) with :meth:`judge`'s fields for its model
        (:attr:`lcs_cvx.FitResult.verdict` says which is better); with ``affine_if_better``,
        when the LCS is not better (:attr:`lcs_cvx.FitResult.beats_affine`), the affine map (as
        an LCS, ``C = 0``) written into the returned model, the learned one kept as ``learned``."""
        model = result.model
        result = dataclasses.replace(result, **self.judge(model))
        if result.beats_affine or not affine_if_better:
            return result
        learned = copy.deepcopy(model)
        affine = affine_lcs(self.affine, model)
        with torch.no_grad():
            for name in ("A", "B", "C", "d"):
                getattr(model, name).copy_(getattr(affine, name))
        return dataclasses.replace(result, learned=learned, returned_affine=True)

    def affine_growth(self) -> float:
        """:meth:`growth` of :attr:`affine` (its rollouts through the same whole trajectories)."""
        return rollout_growth(self.affine, self.holdout)

    @functools.cached_property
    def growth_bound(self) -> float | None:
        """The largest held-out rollout growth of a model a choice may keep:
        :func:`~lcs_cvx.train.result.growth_limit` of :meth:`affine_growth` (None with held-out
        transitions), the verdict's rule (:attr:`lcs_cvx.FitResult.grows_more`)."""
        return growth_limit(self.affine_growth()) if isinstance(self.holdout, Trajectories) else None

    def choice_score(self, model: Any) -> float:
        """:meth:`score`, or ``inf`` when ``model``'s held-out rollouts grow past
        :attr:`growth_bound`: what the kept iterate, the kept restart and the simulation-error
        phase's keep are chosen by."""
        score = self.score(model)
        bound = self.growth_bound
        if bound is None or not math.isfinite(score):
            return score
        return score if self.growth(model) <= bound else math.inf


def _as_transitions(name: str, data: Any) -> Dataset:
    if isinstance(data, Trajectories):
        return data.to_transitions()
    if isinstance(data, Dataset):
        return data
    raise LCSInputError(f"{name}: expected an lcs_cvx.Dataset or lcs_cvx.Trajectories, received {type(data).__name__}")


def split_data(train: Any, validation: Any, run: RunOptions, rollout_horizon: int | str | None) -> Split:
    """The :class:`Split` of a run (module docstring); every inconsistency is an
    :class:`LCSInputError` naming its argument."""
    fit_all = _as_transitions("train", train)
    if validation is not None:
        _as_transitions("validation", validation)
        if (validation.n_x, validation.n_u) != (fit_all.n_x, fit_all.n_u):
            raise LCSInputError(f"validation: expected n_x={fit_all.n_x}, n_u={fit_all.n_u} (train's), "
                                f"received n_x={validation.n_x}, n_u={validation.n_u}")
    trajectories = train if isinstance(train, Trajectories) else None
    auto = rollout_horizon == "auto"
    if auto:
        rollout_horizon = None
    if rollout_horizon is not None and trajectories is None:
        raise LCSInputError("rollout_horizon: the simulation-error phase rolls out windows of trajectories; "
                            f"expected train as an lcs_cvx.Trajectories, received {type(train).__name__}")
    holdout: Dataset | Trajectories | None = validation
    if validation is None and trajectories is not None and len(trajectories) >= 2:
        count = len(trajectories)
        trajectories, holdout = trajectories.split((count - heldout_runs(count, run.holdout)) / count,
                                                   seed=run.seed)
    elif validation is None and trajectories is None and run.restarts > 1:
        fit_all, holdout = fit_all.split(1.0 - run.holdout, seed=run.seed)
    fit = trajectories.to_transitions() if trajectories is not None else fit_all
    horizon = run.holdout_horizon
    if horizon == "auto":
        horizon = min(AUTO_ROLLOUT_HORIZON, max(holdout.lengths)) if isinstance(holdout, Trajectories) else 1
    elif horizon > 1:
        if not isinstance(holdout, Trajectories):
            raise LCSInputError("holdout_horizon: a rollout score needs held-out trajectories; expected 1 or "
                                f"'auto' with {'no held-out part' if holdout is None else 'held-out transitions'}, "
                                f"received {horizon}")
        longest = max(holdout.lengths)
        if horizon > longest:
            raise LCSInputError(f"holdout_horizon: expected at most {longest} steps (the longest held-out "
                                f"trajectory's), received {horizon}")
    if trajectories is not None and rollout_horizon is not None and rollout_horizon > max(trajectories.lengths):
        raise LCSInputError(f"rollout_horizon: expected at most {max(trajectories.lengths)} steps (the longest "
                            f"training trajectory's), received {rollout_horizon}")
    if auto and trajectories is not None:
        # train the rollouts at the horizon they are judged at, where the user named one
        named = run.holdout_horizon if run.holdout_horizon != "auto" and run.holdout_horizon > 1 else None
        rollout_horizon = min(named or AUTO_ROLLOUT_HORIZON, max(trajectories.lengths))
    return Split(fit, trajectories, holdout, horizon, rollout_horizon)


def affine_lcs(affine: AffineMap, like: LCS) -> LCS:
    """The affine map ``x' = A x + B u + d`` as an LCS of ``like``'s sizes with ``C = 0`` (its
    units have no effect); ``like``'s other parameters are kept."""
    model = copy.deepcopy(like)
    W = affine.W.to(dtype=model.dtype, device=model.device)
    n_x, n_u = model.n_x, model.n_u
    with torch.no_grad():
        model.A.copy_(W[:n_x].T)
        model.B.copy_(W[n_x:n_x + n_u].T)
        model.d.copy_(W[-1])
        model.C.zero_()
    return model
