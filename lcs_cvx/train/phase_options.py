"""The options of one training phase each, as frozen dataclasses validated on construction;
:class:`lcs_cvx.train.options.FitOptions` holds one of each.

- :class:`ObjectiveOptions` -- the loss (eq. (9) or (6)) and its constants.
- :class:`AdamOptions` -- minibatch Adam (Sec. 5), its schedules, re-initialisation, extra units.
- :class:`PruneOptions` -- pruning the extra units (:func:`lcs_cvx.resizing.prune_units`).
- :class:`RefineOptions` -- Levenberg--Marquardt steps (Lemma 4, :mod:`lcs_cvx.second_order`).
- :class:`PolishOptions` -- a final Adam polish on the prediction loss (eq. (6)).
- :class:`RolloutOptions` -- simulation-error refinement on windows of the training trajectories.
- :class:`RunOptions` -- what is not a phase: restarts, seed, records, checkpoints, start.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from .._checks import LCSInputError

__all__ = [
    "ObjectiveOptions", "AdamOptions", "PruneOptions", "RefineOptions", "PolishOptions",
    "RolloutOptions", "RunOptions", "extra_units", "option_error",
]

LOSSES = ("violation", "prediction")
OPTIMIZERS = ("adam", "gauss-newton", "newton")
METHODS = (None, "gauss-newton", "newton")
SCHEDULES = ("constant", "cosine")
INITS = ("model", "increment", "affine")


# -- validation of one field ----------------------------------------------------------------
def option_error(name: str, expected: str, value: Any) -> LCSInputError:
    return LCSInputError(f"{name}: expected {expected}, received {value!r}")


def _number(value: Any) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)


def _positive(obj: Any, *names: str) -> None:
    for name in names:
        if not (_number(v := getattr(obj, name)) and v > 0):
            raise option_error(name, "a finite number > 0", v)


def _nonnegative(obj: Any, *names: str) -> None:
    for name in names:
        if not (_number(v := getattr(obj, name)) and v >= 0):
            raise option_error(name, "a finite number >= 0", v)


def _count(obj: Any, low: int, *names: str) -> None:
    for name in names:
        v = getattr(obj, name)
        if isinstance(v, bool) or not isinstance(v, int) or v < low:
            raise option_error(name, f"an integer >= {low}", v)


def _choice(obj: Any, name: str, allowed: tuple) -> None:
    if getattr(obj, name) not in allowed:
        raise option_error(name, f"one of {allowed}", getattr(obj, name))


# -- the groups -----------------------------------------------------------------------------
@dataclass(frozen=True)
class ObjectiveOptions:
    """The training objective ``L(theta) + reg ||C||_F^2``.

    Attributes:
        loss: ``"violation"`` (``L_eps``, eq. (9)) or ``"prediction"`` (eq. (6)).
        gamma, eps: the violation loss's constants (Lemma 2: ``0 < gamma < sigma_min(F + F^T)``).
        reg: ``omega`` of the regulariser ``omega ||C||_F^2`` (paper Sec. 5: 1e-5).
    """

    loss: str = "violation"
    gamma: float = 1e-2
    eps: float = 1e-4
    reg: float = 1e-5

    def __post_init__(self) -> None:
        _choice(self, "loss", LOSSES)
        _positive(self, "gamma", "eps")
        _nonnegative(self, "reg")


@dataclass(frozen=True)
class AdamOptions:
    """Minibatch Adam on the objective (paper Sec. 5: batch 200, lr 1e-3, betas (0.9, 0.9)).

    Attributes:
        iterations: Adam steps (0: no Adam phase).
        batch_size: minibatch size; minibatches follow a fresh random permutation every epoch
            (a minibatch of all of at least 8,192 training samples is read in storage order:
            :meth:`lcs_cvx.train.state.TrainState.next_batch`).
        lr, betas, adam_eps: Adam's learning rate, betas and epsilon.
        lr_schedule: ``"constant"`` or ``"cosine"`` (from ``lr`` down to ``lr * lr_floor``).
        lr_floor: the cosine schedule's final fraction of ``lr``.
        eps_start: if set, the violation loss's ``eps`` decays geometrically from it to
            ``ObjectiveOptions.eps`` over the first ``eps_fraction`` of the iterations.
        eps_fraction: see ``eps_start``.
        reinit_saturated: every ``reinit_every`` steps of the continuation, re-draw the
            hyperplane of every unit active on >= 98 % of a sample of the data (no gradient
            reaches the boundary of such a unit).
        reinit_every: see ``reinit_saturated``.
        extra_units: Adam trains ``n_lam + extra_units`` units (``"auto"``: :func:`extra_units`),
            which the pruning phase removes again -- the escape from the permutation trap
            (two units on one mode boundary, another boundary unmodelled). Not with a fixed
            ``C, D, E, c, G, H`` or one masked differently per unit: ``"auto"`` then means 0
            and a number > 0 is an error (:func:`lcs_cvx.parameter_constraints.allowed_extra_units`).
    """

    iterations: int = 10_000
    batch_size: int = 200
    lr: float = 1e-3
    betas: tuple[float, float] = (0.9, 0.9)
    adam_eps: float = 1e-6
    lr_schedule: str = "constant"
    lr_floor: float = 0.01
    eps_start: float | None = None
    eps_fraction: float = 0.6
    reinit_saturated: bool = False
    reinit_every: int = 500
    extra_units: int | str = 0

    def __post_init__(self) -> None:
        _choice(self, "lr_schedule", SCHEDULES)
        _positive(self, "lr", "adam_eps", "lr_floor", "eps_fraction")
        _count(self, 0, "iterations")
        _count(self, 1, "batch_size", "reinit_every")
        e = self.extra_units
        if e != "auto" and (isinstance(e, bool) or not isinstance(e, int) or e < 0):
            raise option_error("extra_units", "an integer >= 0 or 'auto'", e)
        b = self.betas
        if not (isinstance(b, (tuple, list)) and len(b) == 2 and all(_number(x) and 0 <= x < 1 for x in b)):
            raise option_error("betas", "two numbers in [0, 1)", b)
        object.__setattr__(self, "betas", tuple(b))
        if self.eps_start is not None and not (_number(self.eps_start) and self.eps_start > 0):
            raise option_error("eps_start", "None or a finite number > 0", self.eps_start)


@dataclass(frozen=True)
class PruneOptions:
    """Pruning the extra units of the Adam phase (:func:`lcs_cvx.resizing.prune_units`).

    Attributes:
        repair: Gauss--Newton steps on the pruning's samples after each removal (0: none).
        batch_size: the samples that score the candidate removals.
        lookahead: the candidates of lowest loss repaired and scored again at each removal, the
            best kept (1: the best candidate only; needs ``repair`` > 0 to differ).
    """

    repair: int = 1
    batch_size: int = 1000
    lookahead: int = 1

    def __post_init__(self) -> None:
        _count(self, 0, "repair")
        _count(self, 1, "batch_size")
        _count(self, 1, "lookahead")


@dataclass(frozen=True)
class RefineOptions:
    """Levenberg--Marquardt steps on the violation loss (:mod:`lcs_cvx.second_order`, Lemma 4).

    Attributes:
        method: ``None`` (no refinement), ``"gauss-newton"`` or ``"newton"``.
        iterations: steps.
        batch_size: samples per step (capped at the data size).
        damping: the initial damping ``mu``.
        record_every: steps between history records (the flat keyword ``eval_every`` sets it
            only with a second-order optimizer: :data:`SECOND_ORDER_ALIASES`).
    """

    method: str | None = None
    iterations: int = 20
    batch_size: int = 5000
    damping: float = 1e-3
    record_every: int = 1

    def __post_init__(self) -> None:
        _choice(self, "method", METHODS)
        _count(self, 0, "iterations")
        _count(self, 1, "batch_size", "record_every")
        _nonnegative(self, "damping")


@dataclass(frozen=True)
class PolishOptions:
    """A final Adam polish on the prediction loss (eq. (6)), constant learning rate.

    Attributes:
        iterations: steps (0: no polish).
        lr: the learning rate.
        batch_size: minibatch size (the flat keyword ``batch_size`` sets it with the Adam
            phase's: :data:`FLAT_ALIASES`).
    """

    iterations: int = 0
    lr: float = 1e-4
    batch_size: int = 200

    def __post_init__(self) -> None:
        _count(self, 0, "iterations")
        _count(self, 1, "batch_size")
        _positive(self, "lr")


@dataclass(frozen=True)
class RolloutOptions:
    """Simulation-error refinement (:mod:`lcs_cvx.simulation_error`): Adam on the mean squared
    error of ``horizon``-step open-loop rollouts of the model from windows of the training
    trajectories, the last phase of a run. Needs the training data as
    :class:`lcs_cvx.Trajectories`.

    The phase keeps its result only where it pays: when a held-out part exists, the model after
    the phase replaces the one before it only if its held-out score
    (:meth:`lcs_cvx.train.holdout.Split.score`) is lower (:attr:`lcs_cvx.FitResult.refinement_kept`).

    Attributes:
        horizon: ``H``, the steps of a window; ``"auto"`` (default): when the data are
            :class:`lcs_cvx.Trajectories`, the held-out horizon where ``holdout_horizon`` names
            one (> 1), else 10 steps (at most the longest training trajectory); no phase with
            transitions; None: no phase. Flat keyword ``rollout_horizon``.
        iterations: Adam steps (``rollout_iterations``).
        lr: the learning rate, constant (``rollout_lr``).
        batch_size: windows per step, drawn at random from every window of every training
            trajectory (``rollout_batch``).
    """

    horizon: int | str | None = "auto"
    iterations: int = 300
    lr: float = 1e-3
    batch_size: int = 64

    def __post_init__(self) -> None:
        if self.horizon is not None and self.horizon != "auto":
            _count(self, 1, "horizon")
        _count(self, 0, "iterations")
        _count(self, 1, "batch_size")
        _positive(self, "lr")


@dataclass(frozen=True)
class RunOptions:
    """What is not a phase.

    Attributes:
        restarts: independent runs (the first from the given model, the others from fresh
            initialisations); the one with the lowest relative error on a held-out ``holdout``
            fraction of the data is returned.
        holdout: see ``restarts``; the fraction held out when ``restarts > 1``, and with
            :class:`lcs_cvx.Trajectories` as data always (whole trajectories: at least two of
            five or more, one of two to four, :func:`lcs_cvx.train.holdout.heldout_runs`),
            unless ``validation`` is given.
        restart_tolerance: with ``restarts > 1``, run a further restart only while no finished
            run *succeeded*: kept its fit -- ended (after pruning and refinement) at a training
            loss at most ``restart_tolerance`` times its loss at the end of the Adam phase
            (pruning extra units can lose the fit Adam found) -- and beat the affine model: a
            held-out error below ``AFFINE_MARGIN`` (one half) of the least-squares affine map's
            (:func:`lcs_cvx.metrics.affine_error`; a run at that level has not used its
            complementarity units). The training guide has measurements. A run without pruning
            or refinement always keeps its fit. None: every restart runs.
        seed: seed of minibatches, restarts' initialisations and re-initialisations.
        eval_every: Adam and polish steps between history records.
        checkpoint_every: Adam and polish steps between checkpoints (the pruning and every
            second-order step are always followed by one).
        keep_best: return the iterate with the lowest held-out score instead of the last (the
            starting model is a candidate too); it needs a held-out part (``validation``, the
            ``holdout`` fraction of whole trajectories, or of transitions with ``restarts >
            1``). A test set never chooses: it is only reported. None (the default): True when
            the training data are :class:`lcs_cvx.Trajectories` with a held-out part, else
            False.
        holdout_horizon: with :class:`lcs_cvx.Trajectories` as data, the held-out score is the
            rollout error at this horizon on the held-out trajectories, relative to the
            recorded change, each coordinate scaled by the spread of its one-step change
            (:func:`lcs_cvx.simulation_error.change_error`). ``"auto"``: 10 steps (at most the
            longest held-out trajectory's), the simulation-error phase's default window; with
            transitions, the one-step relative error. A horizon named here (> 1) is also the
            simulation-error phase's window with ``rollout_horizon="auto"``.
        affine_if_better: return the least-squares affine map as an LCS (``C = 0``) when the
            learned LCS is not better (:attr:`lcs_cvx.FitResult.beats_affine`: its held-out
            score not lower, or its held-out rollouts growing more than the data's and the
            affine map's); the learned model is kept in :attr:`lcs_cvx.FitResult.learned`.
        normalize: learn in normalised coordinates (:class:`lcs_cvx.scaling.Scaling`: ``x``,
            ``u`` and the increment ``x' - x`` scaled by the training set's statistics) and fold
            the result back exactly into the user's units. The losses' constants, the
            initialisation and the step sizes are calibrated for data of unit scale.
        init: where training starts (:mod:`lcs_cvx.train.starts`). ``"model"``: the given
            model's parameters, in the user's units. ``"increment"``: ``x' = x`` plus the mean
            increment for ``(A, B, d)``, and the model's other learnable parameters taken as a
            random draw in the coordinates of learning (a fresh :class:`lcs_cvx.LCS`'s
            ``init_scale * N(0, 1)``: hyperplanes at the data's scale whatever its units).
            ``"affine"``: as ``"increment"``, with ``(A, B, d)`` from the least-squares affine fit
            ``x' ~ A x + B u + d``. Fixed parameters keep their values in every case. A tuple
            of these names: restart ``k`` starts from ``init[k % len(init)]`` (a restart after
            the first is a fresh draw, so ``"model"`` there means that draw, taken in the
            coordinates of learning).
    """

    restarts: int = 1
    holdout: float = 0.1
    restart_tolerance: float | None = None
    seed: int = 0
    eval_every: int = 100
    checkpoint_every: int = 500
    keep_best: bool | None = None
    normalize: bool = True
    init: str | tuple[str, ...] = "increment"
    holdout_horizon: int | str = "auto"
    affine_if_better: bool = False

    def __post_init__(self) -> None:
        _count(self, 1, "restarts", "eval_every", "checkpoint_every")
        if self.holdout_horizon != "auto":
            h = self.holdout_horizon
            if isinstance(h, bool) or not isinstance(h, int) or h < 1:
                raise option_error("holdout_horizon", "an integer >= 1 or 'auto'", h)
        if self.keep_best is not None and not isinstance(self.keep_best, bool):
            raise option_error("keep_best", "True, False or None", self.keep_best)
        if not isinstance(self.affine_if_better, bool):
            raise option_error("affine_if_better", "True or False", self.affine_if_better)
        if isinstance(self.init, (list, tuple)):  # a TOML or JSON list is the tuple
            object.__setattr__(self, "init", tuple(self.init))
            if not self.init or any(k not in INITS for k in self.init):
                raise option_error("init", f"one of {INITS} or a non-empty tuple of them",
                                   list(self.init))
        else:
            _choice(self, "init", INITS)
        if not isinstance(self.normalize, bool):
            raise option_error("normalize", "True or False", self.normalize)
        if not (_number(self.holdout) and 0 < self.holdout < 1):
            raise option_error("holdout", "a fraction in (0, 1)", self.holdout)
        t = self.restart_tolerance
        if t is not None and not (_number(t) and t >= 1):
            raise option_error("restart_tolerance", "None or a finite number >= 1", t)
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise option_error("seed", "an integer", self.seed)

    def init_for(self, restart: int) -> str:
        """The start of restart ``restart`` (0 is the first run): ``init``, or its entry
        ``restart % len(init)`` when ``init`` is a tuple."""
        return self.init[restart % len(self.init)] if isinstance(self.init, tuple) else self.init


def extra_units(option: int | str, n_lam: int) -> int:
    """The extra units the Adam phase trains: ``option``, or for ``"auto"``
    ``min(4, ceil(n_lam / 2))``.

    Spare units keep gradient descent out of the permutation trap (two units on one mode
    boundary, another unmodelled); larger models need more of them, but too many leave small
    models with spare units on a shared boundary after pruning, hence about half of ``n_lam``,
    at most 4 (measurements: the docs' benchmarks page, "Extra units").
    """
    return min(4, math.ceil(n_lam / 2)) if option == "auto" else int(option)
