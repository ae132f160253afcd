"""The flat keywords of :func:`lcs_cvx.fit` and the recipes, as values of :class:`FitOptions`.

Most users pass flat keywords (``iterations=``, ``lr=``, ``optimizer=``, ...; :data:`FLAT_OPTIONS`):
:func:`resolve_options` maps them onto the groups of :mod:`lcs_cvx.train.options`, and
:meth:`FitOptions.flat` maps back. ``optimizer="gauss-newton"`` or ``"newton"`` means no Adam
phase and the refinement as the optimiser, with its own defaults (50 steps on batches of 5,000,
a record after every step).
"""

from __future__ import annotations

from typing import Any

from .._checks import LCSInputError
from .options import GROUPS, OPTIMIZERS, RECIPE_NAMES, FitOptions, RefineOptions, option_error

__all__ = ["FLAT_OPTIONS", "RECIPES", "RECIPE_VERSIONS", "resolve_options", "from_flat", "to_flat", "split_groups"]

#: flat keyword -> (group, field), for the keywords whose meaning does not depend on the optimizer
_FLAT: dict[str, tuple[str, str]] = {
    "loss": ("objective", "loss"), "gamma": ("objective", "gamma"), "eps": ("objective", "eps"),
    "reg": ("objective", "reg"),
    **{k: ("adam", k) for k in ("lr", "betas", "adam_eps", "lr_schedule", "lr_floor", "eps_start",
                                "eps_fraction", "reinit_saturated", "reinit_every", "extra_units")},
    "prune_repair": ("prune", "repair"), "prune_batch": ("prune", "batch_size"),
    "prune_lookahead": ("prune", "lookahead"),
    "refine": ("refine", "method"), "refine_iterations": ("refine", "iterations"),
    "refine_batch": ("refine", "batch_size"), "damping": ("refine", "damping"),
    "polish_iterations": ("polish", "iterations"), "polish_lr": ("polish", "lr"),
    **{k: ("run", k) for k in ("restarts", "holdout", "restart_tolerance", "seed", "eval_every",
                               "checkpoint_every", "keep_best", "normalize", "init")},
}

#: (group, field) -> the flat keyword that sets it
_KEYWORD = {v: k for k, v in _FLAT.items()} | {
    ("adam", "iterations"): "iterations", ("adam", "batch_size"): "batch_size",
    ("refine", "iterations"): "iterations", ("refine", "batch_size"): "batch_size",
    ("polish", "batch_size"): "batch_size", ("refine", "record_every"): "eval_every"}

#: Every flat keyword :func:`lcs_cvx.fit` takes. ``optimizer``, ``iterations`` and ``batch_size``
#: mean the Adam phase's with ``optimizer="adam"`` and the refinement's otherwise.
FLAT_OPTIONS: tuple[str, ...] = ("optimizer", "iterations", "batch_size", *_FLAT)

#: Defaults that depend on the optimizer (applied to flat keywords nobody set).
_OPTIMIZER_DEFAULTS: dict[str, dict[str, Any]] = {
    "adam": {},
    "gauss-newton": {"iterations": 50, "batch_size": 5000, "eval_every": 1, "checkpoint_every": 1},
    "newton": {"iterations": 50, "batch_size": 5000, "eval_every": 1, "checkpoint_every": 1},
}

#: The recipes, as the flat keywords they set (see the docs' training page for the measurements).
_RECIPE_KEYWORDS: dict[str, dict[str, Any]] = {
    # the paper's protocol (Sec. 5): Adam, constant lr 1e-3, fixed eps, one run from the given
    # model, in the data's own coordinates
    "paper": {"optimizer": "adam", "lr": 1e-3, "lr_schedule": "constant", "eps_start": None,
              "refine": None, "restarts": 1, "reinit_saturated": False, "normalize": False,
              "init": "model"},
    # cosine lr from 1e-2, eps continuation, saturated-unit re-initialisation, extra units then
    # pruning (a look-ahead of 3 repaired candidates per removal), a Gauss--Newton refinement:
    # 4,000 Adam steps instead of 10,000; a second run from another kind of start, the run of
    # lower held-out error kept
    "best": {"optimizer": "adam", "lr": 1e-2, "lr_schedule": "cosine", "eps_start": 1e-2,
             "eps_fraction": 0.6, "reinit_saturated": True, "iterations": 4000,
             "extra_units": "auto", "prune_repair": 1, "prune_lookahead": 3,
             "refine": "gauss-newton", "refine_iterations": 10, "refine_batch": 500,
             "restarts": 2, "restart_tolerance": None, "init": ("increment", "model")},
}
assert tuple(_RECIPE_KEYWORDS) == RECIPE_NAMES

#: A recipe's version goes up whenever its options change. A study cell of a recipe past version 1
#: carries the version in its key (:func:`lcs_cvx.study.cells.cell_key`), so a resumed study never
#: takes a cell trained under an earlier version for one of the current recipe. ``"best"``
#: version 2 added the restart that runs when the first run lost its fit or ended at the affine
#: map's error; version 3 always makes the second run (from the other start; the run of lower
#: held-out error is kept) and prunes with a look-ahead of 3 repaired candidates.
RECIPE_VERSIONS: dict[str, int] = {"paper": 1, "best": 3}
assert tuple(RECIPE_VERSIONS) == RECIPE_NAMES


def split_groups(overrides: dict[str, Any]) -> dict[str, Any]:
    """Take the whole groups (``adam=AdamOptions(...)``) out of ``overrides`` (in place) and return
    them; ``refine="gauss-newton"`` is the flat keyword, ``refine=RefineOptions(...)`` the group."""
    return {k: overrides.pop(k) for k in list(overrides)
            if k in GROUPS and isinstance(overrides[k], GROUPS[k])}


def known(options: dict[str, Any]) -> dict[str, Any]:
    unknown = sorted(set(options) - set(FLAT_OPTIONS))
    if unknown:
        raise LCSInputError(
            f"options: unknown option(s) {unknown}; valid options are {sorted(FLAT_OPTIONS)}"
        )
    return options


def from_flat(flat: dict[str, Any], recipe: str | None) -> FitOptions:
    """The grouped options of a complete set of flat keywords."""
    groups: dict[str, dict[str, Any]] = {name: {} for name in GROUPS}
    for name, (group, attr) in _FLAT.items():
        groups[group][attr] = flat[name]
    optimizer = flat["optimizer"]
    if optimizer not in OPTIMIZERS:
        raise option_error("optimizer", f"one of {OPTIMIZERS}", optimizer)
    groups["polish"]["batch_size"] = flat["batch_size"]
    if optimizer == "adam":
        groups["adam"].update(iterations=flat["iterations"], batch_size=flat["batch_size"])
    else:
        if flat["refine"] is not None:
            raise LCSInputError(
                f"refine: a refinement follows the Adam phase; expected None with "
                f"optimizer={optimizer!r}, received {flat['refine']!r}"
            )
        groups["adam"].update(iterations=0, batch_size=flat["batch_size"])
        groups["refine"].update(method=optimizer, iterations=flat["iterations"],
                                batch_size=flat["batch_size"], record_every=flat["eval_every"])
    built = {}
    for name, cls in GROUPS.items():
        try:
            built[name] = cls(**groups[name])
        except LCSInputError as exc:  # name the keyword the user wrote, not the group's field
            attr, _, rest = str(exc).partition(":")
            keyword = _KEYWORD.get((name, attr), attr)
            raise LCSInputError(f"{keyword}:{rest}") from None
    if optimizer != "adam" and built["adam"].extra_units != 0:
        raise LCSInputError(
            "extra_units: the pruned model needs a refinement phase; expected optimizer='adam' "
            f"with refine set, received optimizer={optimizer!r}, refine=None"
        )
    return FitOptions(**built, recipe=recipe)


def resolve_options(recipe: str | None = None, **options: Any) -> FitOptions:
    """:class:`FitOptions` from flat keywords: defaults < optimizer defaults < ``recipe`` <
    ``options``; unknown names are rejected with the list of valid ones."""
    known(options)
    if recipe is not None and recipe not in RECIPE_NAMES:
        raise option_error("recipe", f"one of {RECIPE_NAMES}", recipe)
    explicit = {**(_RECIPE_KEYWORDS[recipe] if recipe else {}), **options}
    optimizer = explicit.get("optimizer", "adam")
    defaults = _DEFAULT_FLAT | _OPTIMIZER_DEFAULTS.get(optimizer, {})
    return from_flat({**defaults, **explicit}, recipe)




def to_flat(options: FitOptions) -> dict[str, Any]:
    """:meth:`FitOptions.flat`: the options as flat keywords, with ``recipe``."""
    out = {name: getattr(getattr(options, group), attr) for name, (group, attr) in _FLAT.items()}
    if options.optimizer == "adam":
        out.update(optimizer="adam", iterations=options.adam.iterations,
                   batch_size=options.adam.batch_size)
    else:
        out.update(optimizer=options.refine.method, iterations=options.refine.iterations,
                   batch_size=options.refine.batch_size, refine=None,
                   refine_iterations=RefineOptions.iterations, refine_batch=RefineOptions.batch_size)
    out["betas"] = list(out["betas"])
    return {"recipe": options.recipe, **out}


_DEFAULT_FLAT = {k: v for k, v in FitOptions().flat().items() if k != "recipe"}
_DEFAULT_FLAT["betas"] = tuple(_DEFAULT_FLAT["betas"])

#: The named option sets: ``"paper"`` (the paper's protocol) and ``"best"`` (what this package
#: recommends). ``fit(model, data, RECIPES["best"], lr=...)`` starts from one and overrides.
RECIPES: dict[str, FitOptions] = {name: resolve_options(name) for name in RECIPE_NAMES}
