"""The recipes, as values of :class:`FitOptions`, and :func:`resolve_options`: options from a
recipe and flat keywords.

The flat keywords (``iterations=``, ``lr=``, ``optimizer=``, ...; :data:`FLAT_OPTIONS`) are
aliases of fields of :class:`FitOptions`, defined in :mod:`lcs_cvx.train.options`
(:data:`~lcs_cvx.train.options.FLAT_ALIASES`) and applied by :meth:`FitOptions.replace`.
``optimizer="gauss-newton"`` or ``"newton"`` means no Adam phase and the refinement as the
optimiser, with its own defaults (100 steps on batches of 5,000, a record after every step, three
runs: :data:`~lcs_cvx.train.options.OPTIMIZER_DEFAULTS`).
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Any

from .options import FLAT_OPTIONS, RECIPE_NAMES, FitOptions, apply_flat, known
from .phase_options import option_error

__all__ = ["DEFAULT_RECIPE", "FLAT_OPTIONS", "PLAIN", "RECIPES", "RECIPE_VERSIONS", "resolve_options"]

#: The recipes, as the flat keywords they set (see the docs' training page for the measurements).
_RECIPE_KEYWORDS: dict[str, dict[str, Any]] = {
    # the paper's protocol (Sec. 5): Adam, constant lr 1e-3, fixed eps, one run from the given
    # model, in the data's own coordinates
    "paper": {"optimizer": "adam", "lr": 1e-3, "lr_schedule": "constant", "eps_start": None,
              "refine": None, "restarts": 1, "reinit_saturated": False, "normalize": False,
              "init": "model", "rollout_horizon": None},
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
RECIPE_VERSIONS: MappingProxyType[str, int] = MappingProxyType({"paper": 1, "best": 3})
assert tuple(RECIPE_VERSIONS) == RECIPE_NAMES


#: What ``loss="prediction"`` turns off of a recipe unless the call sets it: the parts that are
#: the violation loss's own (Lemma 4's refinement, and the extra units its pruning removes).
VIOLATION_ONLY: MappingProxyType[str, Any] = MappingProxyType({"refine": None, "extra_units": 0})

#: The recipe :func:`lcs_cvx.fit` takes for an :class:`lcs_cvx.LCS` when neither ``options`` nor
#: ``recipe`` is given: the recommended one.
DEFAULT_RECIPE = "best"

#: The name of :class:`FitOptions`' own defaults (no recipe; ``FitOptions().recipe`` is None).
PLAIN = "plain"


def resolve_options(recipe: str | None = None, **options: Any) -> FitOptions:
    """:class:`FitOptions` from flat keywords: defaults < optimizer defaults < ``recipe`` <
    ``options``; unknown names are rejected with the list of valid ones. ``recipe`` None or
    ``"plain"``: no recipe, the defaults of :class:`FitOptions`. With ``loss="prediction"`` the
    recipe's violation-only parts (:data:`VIOLATION_ONLY`) are off unless ``options`` sets them.

    The default options with the recipe's keywords and then ``options`` applied as by
    :meth:`FitOptions.replace` (:func:`~lcs_cvx.train.options.apply_flat`): a second-order
    ``optimizer`` brings its defaults (:data:`~lcs_cvx.train.options.OPTIMIZER_DEFAULTS`) for the
    keywords neither the recipe nor ``options`` set."""
    known(options)
    if recipe == PLAIN:
        recipe = None
    if recipe is not None and recipe not in RECIPE_NAMES:
        raise option_error("recipe", f"one of {(*RECIPE_NAMES, PLAIN)}", recipe)
    explicit = {**(_RECIPE_KEYWORDS[recipe] if recipe else {}), **options}
    if explicit.get("loss") == "prediction":  # the recipe's violation-only parts, unless given
        explicit.update({k: v for k, v in VIOLATION_ONLY.items() if k not in options})
    return apply_flat(FitOptions(recipe=recipe), explicit)


#: The named option sets (read-only): ``"paper"`` (the paper's protocol) and ``"best"`` (what
#: this package recommends). ``fit(model, data, RECIPES["best"], lr=...)`` starts from one and
#: overrides.
RECIPES: MappingProxyType[str, FitOptions] = MappingProxyType(
    {name: resolve_options(name) for name in RECIPE_NAMES})
