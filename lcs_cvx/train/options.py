r""":class:`FitOptions`, every option of :func:`lcs_cvx.fit`: one frozen dataclass per training
phase (:mod:`lcs_cvx.train.phase_options`), and the flat keywords of :func:`lcs_cvx.fit` as
aliases of their fields.

A run minimises ``L(theta) + omega ||C||_F^2`` (paper eq. (4)) in up to five phases, in this
order; each phase has its own options:

- :class:`ObjectiveOptions` -- which loss (eq. (9) or (6)) and its constants.
- :class:`AdamOptions` -- minibatch Adam (the paper's protocol, Sec. 5), with optional schedules
  (cosine learning rate, continuation in ``eps``), re-initialisation of saturated units and extra
  units that the pruning phase removes again.
- :class:`PruneOptions` -- pruning the extra units back to the model's ``n_lam``
  (:func:`lcs_cvx.resizing.prune_units`).
- :class:`RefineOptions` -- Levenberg--Marquardt steps (Gauss--Newton or Newton, Lemma 4,
  :mod:`lcs_cvx.second_order`) on large batches.
- :class:`PolishOptions` -- a final Adam polish on the prediction loss (eq. (6)).
- :class:`RolloutOptions` -- simulation-error refinement on windows of trajectories
  (:mod:`lcs_cvx.simulation_error`).
- :class:`RunOptions` -- what is not a phase: restarts, seed, records, checkpoints.

:class:`FitOptions` holds one of each; it is the only representation of a run's options. Most
users pass flat keywords to :func:`lcs_cvx.fit` (``iterations=``, ``lr=``, ``optimizer=``, ...):
each is an alias of one or more fields of the groups (:data:`FLAT_ALIASES`), applied by
:meth:`FitOptions.replace` to exactly those fields. :mod:`lcs_cvx.train.recipes` holds the recipes.
"""

from __future__ import annotations

import dataclasses
import difflib
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

from .._checks import LCSInputError
from .phase_options import (
    OPTIMIZERS,
    AdamOptions,
    ObjectiveOptions,
    PolishOptions,
    PruneOptions,
    RefineOptions,
    RolloutOptions,
    RunOptions,
    option_error,
)

__all__ = [
    "FitOptions", "GROUPS", "FLAT_OPTIONS", "FLAT_ALIASES", "SECOND_ORDER_ALIASES",
    "OPTIMIZER_DEFAULTS", "apply_flat", "split_groups", "known",
]

#: the recipes (:data:`lcs_cvx.train.RECIPES`)
RECIPE_NAMES = ("paper", "best")


@dataclass(frozen=True)
class FitOptions:
    """Every option of :func:`lcs_cvx.fit`, grouped by phase (frozen).

    Example:
        >>> import lcs_cvx
        >>> opts = lcs_cvx.RECIPES["paper"].replace(iterations=2000, lr=5e-3)
        >>> opts.adam.iterations, opts.adam.lr, opts.objective.loss
        (2000, 0.005, 'violation')
    """

    objective: ObjectiveOptions = field(default_factory=ObjectiveOptions)
    adam: AdamOptions = field(default_factory=AdamOptions)
    prune: PruneOptions = field(default_factory=PruneOptions)
    refine: RefineOptions = field(default_factory=RefineOptions)
    polish: PolishOptions = field(default_factory=PolishOptions)
    rollout: RolloutOptions = field(default_factory=RolloutOptions)
    run: RunOptions = field(default_factory=RunOptions)
    #: the recipe these options came from (``"paper"``, ``"best"``) or None.
    recipe: str | None = None

    def __post_init__(self) -> None:
        for name, cls in GROUPS.items():
            if not isinstance(getattr(self, name), cls):
                raise option_error(name, f"an lcs_cvx.{cls.__name__}", getattr(self, name))
        if self.recipe is not None and self.recipe not in RECIPE_NAMES:
            raise option_error("recipe", f"one of {(None, *RECIPE_NAMES)}", self.recipe)
        a = self.adam
        if a.eps_start is not None and a.eps_start < self.objective.eps:
            raise option_error("eps_start", f"None or a number >= eps = {self.objective.eps!r}", a.eps_start)
        if a.extra_units != 0 and self.refine.method is None:
            raise _extra_units_error(self.optimizer, self.refine.method)
        if self.objective.loss == "prediction" and self.refine.method is not None:
            raise LCSInputError(
                "optimizer: the second-order methods are for the violation loss (Lemma 4); "
                f"received loss='prediction' with optimizer={self.optimizer!r}, "
                f"refine={self.refine.method!r}"
            )

    @property
    def optimizer(self) -> str:
        """``"adam"``, or the second-order method when there is no Adam phase."""
        if self.adam.iterations == 0 and self.refine.method is not None:
            return self.refine.method
        return "adam"

    def flat(self) -> dict[str, Any]:
        """A read-only view of these options as the flat keywords of :func:`lcs_cvx.fit`
        (:data:`FLAT_OPTIONS`), with ``recipe``: each keyword shows the first field it aliases
        (:data:`FLAT_ALIASES`, :data:`SECOND_ORDER_ALIASES`). Passing the view back to
        :func:`lcs_cvx.train.resolve_options` gives these options again when they came from
        flat keywords."""
        aliases = _aliases(self.optimizer)
        out: dict[str, Any] = {"recipe": self.recipe}
        for keyword in _VIEW_ORDER:
            if keyword == "optimizer":
                out[keyword] = self.optimizer
            elif aliases[keyword]:
                group, name = aliases[keyword][0]
                out[keyword] = getattr(getattr(self, group), name)
            else:
                out[keyword] = _UNUSED[keyword]
        out["betas"] = list(out["betas"])
        return out

    def replace(self, **overrides: Any) -> FitOptions:
        """A copy with ``overrides`` applied: whole groups (``adam=AdamOptions(...)``) first,
        then flat keywords (:data:`FLAT_OPTIONS`), each on exactly the fields it aliases
        (:func:`apply_flat`); every other field keeps its value."""
        groups = split_groups(overrides)
        base = dataclasses.replace(self, **groups) if groups else self
        return apply_flat(base, known(overrides)) if overrides else base


GROUPS = {"objective": ObjectiveOptions, "adam": AdamOptions, "prune": PruneOptions,
           "refine": RefineOptions, "polish": PolishOptions, "rollout": RolloutOptions,
           "run": RunOptions}


# -- the flat keywords: aliases of fields ---------------------------------------------------
#: A field of :class:`FitOptions`: ``(group, name)``, e.g. ``("adam", "lr")``.
Field = tuple[str, str]


def _same_names(group: str, *names: str) -> dict[str, tuple[Field, ...]]:
    return {name: ((group, name),) for name in names}


#: The flat keywords of :func:`lcs_cvx.fit` (all but ``optimizer``) as aliases: keyword -> the
#: fields of :class:`FitOptions` it sets with ``optimizer="adam"``; :data:`SECOND_ORDER_ALIASES`
#: lists the keywords that alias other fields with a second-order optimizer. A keyword sets
#: exactly its fields, and no field has two keywords. ``iterations`` is the Adam phase's.
#: ``batch_size`` is the minibatch of the Adam phase *and* of the polish: the polish has no
#: keyword of its own for it, so ``batch_size=`` sets both (a flat-keyword user's polish runs on
#: the training batch); ``polish=PolishOptions(batch_size=...)`` sets the polish's alone, and a
#: later ``replace`` that does not name ``batch_size`` keeps it.
FLAT_ALIASES: Mapping[str, tuple[Field, ...]] = MappingProxyType({
    "iterations": (("adam", "iterations"),),
    "batch_size": (("adam", "batch_size"), ("polish", "batch_size")),
    **_same_names("objective", "loss", "gamma", "eps", "reg"),
    **_same_names("adam", "lr", "betas", "adam_eps", "lr_schedule", "lr_floor", "eps_start",
                  "eps_fraction", "reinit_saturated", "reinit_every", "extra_units"),
    "prune_repair": (("prune", "repair"),), "prune_batch": (("prune", "batch_size"),),
    "prune_lookahead": (("prune", "lookahead"),),
    "refine": (("refine", "method"),), "refine_iterations": (("refine", "iterations"),),
    "refine_batch": (("refine", "batch_size"),), "damping": (("refine", "damping"),),
    "polish_iterations": (("polish", "iterations"),), "polish_lr": (("polish", "lr"),),
    "rollout_horizon": (("rollout", "horizon"),), "rollout_iterations": (("rollout", "iterations"),),
    "rollout_lr": (("rollout", "lr"),), "rollout_batch": (("rollout", "batch_size"),),
    **_same_names("run", "restarts", "holdout", "restart_tolerance", "seed", "eval_every",
                  "checkpoint_every", "keep_best", "normalize", "init", "holdout_horizon",
                  "affine_if_better"),
})

#: The keywords that alias other fields with ``optimizer="gauss-newton"`` or ``"newton"``: there
#: is no Adam phase and the refinement is the optimizer, so ``iterations`` and ``batch_size`` are
#: the refinement's (``batch_size`` still the Adam phase's and the polish's as well), and
#: ``eval_every`` also sets the refinement's ``record_every``. ``refine``, ``refine_iterations`` and
#: ``refine_batch`` describe a refinement *after* an Adam phase and set no field then:
#: ``refine`` must be None, the other two are ignored (so a recipe's refinement settings do not
#: stop a switch to a second-order optimizer), and :meth:`FitOptions.flat` shows None and the
#: refinement's defaults for them.
SECOND_ORDER_ALIASES: Mapping[str, tuple[Field, ...]] = MappingProxyType({
    "iterations": (("refine", "iterations"),),
    "batch_size": (("refine", "batch_size"), ("adam", "batch_size"), ("polish", "batch_size")),
    "eval_every": (("run", "eval_every"), ("refine", "record_every")),
    "refine": (), "refine_iterations": (), "refine_batch": (),
})
_SECOND_ORDER_TABLE = MappingProxyType({**FLAT_ALIASES, **SECOND_ORDER_ALIASES})
#: What :meth:`FitOptions.flat` shows for the keywords without a field (second-order optimizer).
_UNUSED: Mapping[str, Any] = MappingProxyType({
    "refine": None, "refine_iterations": RefineOptions.iterations,
    "refine_batch": RefineOptions.batch_size})

#: Every flat keyword :func:`lcs_cvx.fit` takes: ``optimizer`` and the aliases
#: (:data:`FLAT_ALIASES`). ``iterations`` and ``batch_size`` mean the Adam phase's with
#: ``optimizer="adam"`` and the refinement's otherwise, and ``eval_every`` also sets the
#: refinement's record interval then (:data:`SECOND_ORDER_ALIASES`); ``optimizer`` itself is
#: applied by :func:`apply_flat`.
FLAT_OPTIONS: tuple[str, ...] = ("optimizer", *FLAT_ALIASES)
#: The order of the keys of :meth:`FitOptions.flat`.
_VIEW_ORDER = (*FLAT_OPTIONS[3:], *FLAT_OPTIONS[:3])

_SECOND_ORDER_DEFAULTS = MappingProxyType(
    {"iterations": 100, "batch_size": 5000, "eval_every": 1, "checkpoint_every": 1, "restarts": 3})
#: What ``optimizer=`` sets besides the optimizer when it changes the optimizer: these keywords'
#: values, unless the same call names them. A second-order optimizer takes 100 steps on batches
#: of 5,000, records and checkpoints after every step (each step costs as much as many Adam
#: steps), and makes three runs, keeping the one of lowest held-out error: a single
#: Levenberg--Marquardt run from a random start converges to a local minimum of the violation
#: loss about as often as to the data's system, and runs from other starts rarely all do;
#: ``"adam"`` takes back the defaults of :class:`AdamOptions` and :class:`RunOptions`.
OPTIMIZER_DEFAULTS: Mapping[str, Mapping[str, Any]] = MappingProxyType({
    "adam": MappingProxyType({
        "iterations": AdamOptions.iterations, "batch_size": AdamOptions.batch_size,
        "eval_every": RunOptions.eval_every, "checkpoint_every": RunOptions.checkpoint_every,
        "restarts": RunOptions.restarts}),
    "gauss-newton": _SECOND_ORDER_DEFAULTS,
    "newton": _SECOND_ORDER_DEFAULTS,
})
assert tuple(OPTIMIZER_DEFAULTS) == OPTIMIZERS


def _aliases(optimizer: str) -> Mapping[str, tuple[Field, ...]]:
    return FLAT_ALIASES if optimizer == "adam" else _SECOND_ORDER_TABLE


def split_groups(overrides: dict[str, Any]) -> dict[str, Any]:
    """Take the whole groups (``adam=AdamOptions(...)``) out of ``overrides`` (in place) and return
    them; ``refine="gauss-newton"`` is the flat keyword, ``refine=RefineOptions(...)`` the group."""
    return {k: overrides.pop(k) for k in list(overrides)
            if k in GROUPS and isinstance(overrides[k], GROUPS[k])}


def known(options: dict[str, Any]) -> dict[str, Any]:
    """``options``, after checking that each is a flat keyword (:data:`FLAT_OPTIONS`)."""
    unknown = sorted(set(options) - set(FLAT_OPTIONS))
    if unknown:
        near = {k: difflib.get_close_matches(k, FLAT_OPTIONS, n=1) for k in unknown}
        hint = "; ".join(f"did you mean {m[0]!r} for {k!r}?" for k, m in near.items() if m)
        raise LCSInputError(
            f"options: unknown option(s) {unknown}; valid options are {sorted(FLAT_OPTIONS)}"
            + (f"; {hint}" if hint else "")
        )
    return options


def apply_flat(options: FitOptions, keywords: dict[str, Any]) -> FitOptions:
    """``options`` with the flat keywords ``keywords`` (:data:`FLAT_OPTIONS`) applied, each on
    exactly the fields it aliases; an invalid value is refused naming its keyword.

    ``optimizer`` acts only when it changes :attr:`FitOptions.optimizer`: to ``"gauss-newton"``
    or ``"newton"`` it sets ``adam.iterations = 0`` and ``refine.method`` (refused while a
    refinement follows the Adam phase, or with extra units: nothing would prune them), to
    ``"adam"`` it resets ``refine`` to :class:`RefineOptions` (no refinement); either way the
    keywords of :data:`OPTIMIZER_DEFAULTS` that ``keywords`` does not name take the new
    optimizer's defaults. The other keywords alias the fields of :data:`FLAT_ALIASES`, with a
    second-order optimizer those of :data:`SECOND_ORDER_ALIASES`.
    """
    current = options.optimizer
    optimizer = keywords.get("optimizer", current)
    if optimizer not in OPTIMIZERS:
        raise option_error("optimizer", f"one of {OPTIMIZERS}", optimizer)
    groups = {name: getattr(options, name) for name in GROUPS}
    fields: dict[str, dict[str, Any]] = {name: {} for name in GROUPS}
    if optimizer != current:
        keywords = {**OPTIMIZER_DEFAULTS[optimizer], **keywords}
        if optimizer == "adam":
            groups["refine"] = RefineOptions()
        else:
            fields["adam"]["iterations"] = 0
            fields["refine"]["method"] = optimizer
    if optimizer != "adam":  # a refinement after the Adam phase: the one named, or the one there
        refine = keywords.get("refine", options.refine.method if current == "adam" else None)
        if refine is not None:
            raise LCSInputError(
                f"refine: a refinement follows the Adam phase; expected None with "
                f"optimizer={optimizer!r}, received {refine!r}"
            )
    aliases = _aliases(optimizer)
    keyword_of: dict[Field, str] = {}
    for keyword, value in keywords.items():
        if keyword == "optimizer":
            continue
        for group, name in aliases[keyword]:
            fields[group][name] = value
            keyword_of[(group, name)] = keyword
    for group, values in fields.items():
        if values:
            try:
                groups[group] = dataclasses.replace(groups[group], **values)
            except LCSInputError as exc:  # name the keyword the user wrote, not the field
                name, _, rest = str(exc).partition(":")
                raise LCSInputError(f"{keyword_of.get((group, name), name)}:{rest}") from None
    if optimizer != "adam" and groups["adam"].extra_units != 0 and (
            "optimizer" in keywords or "extra_units" in keywords):
        raise _extra_units_error(optimizer, None)
    return dataclasses.replace(options, **groups)


def _extra_units_error(optimizer: str, refine: str | None) -> LCSInputError:
    """Extra units need an Adam phase to train them and a refinement after their pruning."""
    return LCSInputError(
        "extra_units: the pruned model needs a refinement phase; expected optimizer='adam' "
        f"with refine set, received optimizer={optimizer!r}, refine={refine!r}"
    )
