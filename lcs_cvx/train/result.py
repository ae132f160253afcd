""":class:`FitResult`, what :func:`lcs_cvx.fit` and :func:`lcs_cvx.fit_ensemble` return, and
the rule that picks the kept run among restarts (:func:`lowest`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from ..scaling import Scaling
from ..system import LCS
from .options import FitOptions

__all__ = ["FitResult", "lowest", "growth_limit", "DIVERGING_GROWTH", "GROWTH_SLACK"]

#: A held-out rollout that grows past this multiple of the largest recorded state is called
#: diverging by :attr:`FitResult.verdict`.
DIVERGING_GROWTH = 10.0

#: The learned model's held-out rollouts "grow more" than the data's and the affine map's when
#: their growth passes this multiple of the larger of 1 (the data's own) and the affine map's:
#: then :attr:`FitResult.beats_affine` is False whatever the errors say (an error over short
#: windows does not see a model that leaves the data's range over a whole run).
GROWTH_SLACK = 1.5


def growth_limit(affine_growth: float | None) -> float:
    """The largest held-out rollout growth that does not "grow more": :data:`GROWTH_SLACK` times
    the larger of 1 (the data's own) and the affine map's growth (1 where that is None or not
    finite: a diverging affine map licenses nothing)."""
    finite = affine_growth is not None and math.isfinite(affine_growth)
    return GROWTH_SLACK * max(1.0, affine_growth if finite else 1.0)


def _spread(scores: tuple[float, ...] | None) -> str:
    """`` (per-run range LO-HI)``: the range of per-run held-out scores ('' without them)."""
    return "" if not scores else f" (per-run range {min(scores):.3g}-{max(scores):.3g})"


def lowest(scores: list[float]) -> int:
    """Index of the lowest score, the first of equal ones: the restart :func:`fit` keeps."""
    return min(range(len(scores)), key=scores.__getitem__)


@dataclass(frozen=True)
class FitResult:
    """What :func:`fit` returns.

    Attributes:
        model: the trained model (the same object as the ``model`` argument, updated in place).
        history: one dict per record: ``iteration``, ``phase`` (``"adam"``, ``"gauss-newton"``,
            ``"newton"`` or ``"polish"``), ``loss`` (mean regularised training loss since the last
            record), ``eps``, ``lr``, ``e_test`` (the test set's relative error, reported only;
            None without ``test``), ``heldout`` (the held-out score ``keep_best`` chooses the
            returned iterate by; None without ``keep_best``), ``wall_time`` (s),
            ``restart``, ``n_fallback`` (samples the fast solvers handed to the reference solver
            since the last record) and ``fallback_residual`` (the worst relative KKT residual of those
            reference answers; 0.0 when there were none -- pivoting's own answers are exact).
        settings: the resolved :class:`FitOptions`.
        restart_scores: held-out relative error of each restart that ran (empty with one run;
            fewer than ``restarts`` when ``restart_tolerance`` stopped them early).
        wall_time: seconds, summed over resumed pieces.
        scaling: the normalised coordinates the model was learned in
            (:class:`lcs_cvx.scaling.Scaling`; None with ``normalize=False``). ``loss`` in the
            history is in those coordinates; ``e_test``, ``heldout`` and the restart scores are in
            the user's.
        heldout_error: the held-out score of the learned model (:func:`lcs_cvx.relative_error`
            on held-out transitions; on held-out trajectories the rollout error at
            ``holdout_horizon`` relative to the recorded change, each coordinate scaled,
            :func:`lcs_cvx.simulation_error.change_error`); None without a held-out part.
        heldout_score: that score in words (None without a held-out part).
        affine_heldout_error: the same score of the least-squares affine map fitted on the same
            training part: the learned LCS contains that map (``C = 0``), so it should score
            below it.
        heldout_growth: with held-out trajectories, the largest ``max_t ||x_hat_t|| / max_t
            ||x_t||`` of the learned model's rollouts over each whole held-out trajectory
            (:func:`lcs_cvx.simulation_error.rollout_growth`: near 1 for a stable model, inf when
            a rollout overflows).
        affine_heldout_growth: the same growth of the affine map's rollouts (None without
            held-out trajectories).
        heldout_run_errors, affine_heldout_run_errors: the held-out score on each held-out
            trajectory alone, of the learned model and of the affine map (None with held-out
            transitions or fewer than two held-out trajectories): the spread behind the score.
        learned: with ``affine_if_better`` when the affine map scored at least as well, the
            learned LCS (:attr:`model` then holds the affine map, ``C = 0``); else None.
        returned_affine: whether :attr:`model` holds the affine map.
        refinement_kept: whether the simulation-error phase's result was kept (its held-out score
            lower than before the phase); None when the phase did not run or had no held-out
            data to decide on. With ``keep_best`` or a phase that was kept, the held-out data
            chose the model, so :attr:`heldout_error` is optimistic: score a separate test set
            for an unbiased number.
    """

    model: LCS
    history: list[dict[str, Any]]
    settings: FitOptions
    restart_scores: list[float] = field(default_factory=list)
    wall_time: float = 0.0
    scaling: Scaling | None = None
    heldout_error: float | None = None
    affine_heldout_error: float | None = None
    heldout_growth: float | None = None
    learned: LCS | None = None
    returned_affine: bool = False
    refinement_kept: bool | None = None
    affine_heldout_growth: float | None = None
    heldout_score: str | None = None
    heldout_run_errors: tuple[float, ...] | None = None
    affine_heldout_run_errors: tuple[float, ...] | None = None

    @property
    def grows_more(self) -> bool | None:
        """Whether the learned model's held-out rollouts grow more than the data's and the
        affine map's: :attr:`heldout_growth` above :data:`GROWTH_SLACK` times the larger of 1
        and :attr:`affine_heldout_growth` (a NaN growth counts as growing; None without held-out
        trajectories)."""
        if self.heldout_growth is None:
            return None
        return not self.heldout_growth <= growth_limit(self.affine_heldout_growth)

    @property
    def beats_affine(self) -> bool | None:
        """Whether the learned model is better than the affine map on the held-out part: its
        score lower and its rollouts not growing more (:attr:`grows_more`); None without a
        held-out part."""
        if self.heldout_error is None or self.affine_heldout_error is None:
            return None
        return self.heldout_error < self.affine_heldout_error and not self.grows_more

    @property
    def verdict(self) -> str:
        """The learned model against the affine map on held-out data, one item per line: the
        held-out score and its scale, each model's score with its per-run range, the largest
        rollout growth (with trajectories) and the conclusion."""
        if self.beats_affine is None:
            return "no held-out data: the learned LCS was not compared with the affine map"
        lines = [f"held-out score: {self.heldout_score} (0: exact)",
                 f"  LCS: {self.heldout_error:.4g}{_spread(self.heldout_run_errors)}",
                 f"  affine least squares: {self.affine_heldout_error:.4g}{_spread(self.affine_heldout_run_errors)}"]
        if self.heldout_growth is not None:
            growth = f"  largest rollout growth (max |x| of a rollout over its run's; 1: the data's own): " \
                     f"LCS {self.heldout_growth:.3g}"
            if not self.heldout_growth <= DIVERGING_GROWTH:
                growth += " (its open-loop rollouts DIVERGE)"
            if self.affine_heldout_growth is not None:
                growth += f", affine {self.affine_heldout_growth:.3g}"
            lines.append(growth)
        if self.beats_affine:
            return "\n".join([*lines, "verdict: the LCS is better"])
        why = ""
        if self.grows_more and self.heldout_error < self.affine_heldout_error:
            why = " (lower error, but its rollouts leave the data's range)"
        lines.append(f"verdict: the LCS is NOT better than the affine map{why}" +
                     ("; the affine map is returned (affine_if_better)" if self.returned_affine
                      else "; fit(..., affine_if_better=True) returns the affine map"))
        return "\n".join(lines)

    def plot(self, **kwargs: Any) -> Any:
        """The training as a figure: :func:`lcs_cvx.plot.history` of this result (``ax``,
        ``path``); a :class:`matplotlib.figure.Figure`."""
        from ..plot import history

        return history(self, **kwargs)

    @property
    def kept_restart(self) -> int:
        """The run :attr:`model` comes from: the index of the lowest of :attr:`restart_scores`
        (the first of equal ones; 0 with one run). The history holds every run's records, so
        ``history[-1]`` is the last run's record, not necessarily the returned model's: that
        run's records are :attr:`kept_history`."""
        return lowest(self.restart_scores) if self.restart_scores else 0

    @property
    def kept_history(self) -> list[dict[str, Any]]:
        """The records of the :attr:`kept_restart` run (the whole history with one run)."""
        return [h for h in self.history if h.get("restart", 0) == self.kept_restart]

    @property
    def n_fallback(self) -> int:
        """Samples handed to the reference solver over the whole training."""
        return sum(h.get("n_fallback", 0) for h in self.history)

    @property
    def fallback_residual(self) -> float:
        """The worst relative KKT residual of the reference solver's answers (0.0: none)."""
        return max((h.get("fallback_residual", 0.0) for h in self.history), default=0.0)
