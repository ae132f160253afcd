"""Training an LCS: :func:`fit` and its options.

- :mod:`~lcs_cvx.train.phase_options` -- the options of each phase, frozen dataclasses.
- :mod:`~lcs_cvx.train.options` -- :class:`FitOptions`, one of each, and the flat keywords of
  :func:`fit` as an alias table onto its fields.
- :mod:`~lcs_cvx.train.recipes` -- the recipes, read-only :class:`FitOptions` values.
- :mod:`~lcs_cvx.train.inputs` -- the data and options of a call, checked once.
- :mod:`~lcs_cvx.train.result` -- :class:`FitResult`.
- :mod:`~lcs_cvx.train.state` -- :class:`TrainState`, one run's state (serialises itself).
- :mod:`~lcs_cvx.train.phases` -- Adam, pruning, second-order refinement and polish, on one loop.
- :mod:`~lcs_cvx.train.driver` -- :func:`fit`: restarts, checkpoints and resume, progress.
- :mod:`~lcs_cvx.train.ensemble` -- :func:`fit_ensemble`: many models in one batched loop.
"""

from .driver import CHECKPOINT_FORMAT as CHECKPOINT_FORMAT
from .driver import fit as fit
from .ensemble import fit_ensemble as fit_ensemble
from .options import FitOptions as FitOptions
from .phase_options import AdamOptions as AdamOptions
from .phase_options import ObjectiveOptions as ObjectiveOptions
from .phase_options import PolishOptions as PolishOptions
from .phase_options import PruneOptions as PruneOptions
from .phase_options import RefineOptions as RefineOptions
from .phase_options import RolloutOptions as RolloutOptions
from .phase_options import RunOptions as RunOptions
from .phase_options import extra_units as extra_units
from .recipes import DEFAULT_RECIPE as DEFAULT_RECIPE
from .recipes import FLAT_OPTIONS as FLAT_OPTIONS
from .recipes import RECIPES as RECIPES
from .recipes import resolve_options as resolve_options
from .result import FitResult as FitResult
from .state import TrainState as TrainState

__all__ = [
    "fit", "fit_ensemble", "FitResult", "FitOptions", "RECIPES", "FLAT_OPTIONS", "ObjectiveOptions", "AdamOptions",
    "PruneOptions", "RefineOptions", "PolishOptions", "RolloutOptions", "RunOptions", "TrainState", "extra_units",
    "resolve_options", "CHECKPOINT_FORMAT", "DEFAULT_RECIPE",
]
