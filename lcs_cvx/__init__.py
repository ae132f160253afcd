"""lcs_cvx: learning linear complementarity systems (Jin, Aydinoglu, Halm, Posa; L4DC 2022).

The subpackages :mod:`lcs_cvx.control`, :mod:`lcs_cvx.datasets`, :mod:`lcs_cvx.study` and the
modules :mod:`lcs_cvx.bench`, :mod:`lcs_cvx.cli` and :mod:`lcs_cvx.plot` are imported on first access
(``lcs_cvx.datasets.cube_tosses()`` after ``import lcs_cvx``), so that ``import lcs_cvx`` stays
light; none of them imports an optional dependency before it is used.
"""

import importlib as _importlib

from ._checks import FallbackWarning as FallbackWarning
from ._checks import LayerAccuracyWarning as LayerAccuracyWarning
from ._checks import LCSInputError as LCSInputError
from ._checks import PlanGapWarning as PlanGapWarning
from ._checks import SolverError as SolverError
from ._version import __version__ as __version__
from .data import Dataset as Dataset
from .data import make_dataset as make_dataset
from .data import random_lcs as random_lcs
from .hessian import violation_hessian as violation_hessian
from .hessian import violation_hvp as violation_hvp
from .io import load_metadata as load_metadata
from .io import load_model as load_model
from .io import save_model as save_model
from .kinematics import Kinematics as Kinematics
from .lcp import LCPSolution as LCPSolution
from .lcp import solve_lcp as solve_lcp
from .losses import LossInfo as LossInfo
from .losses import prediction_loss as prediction_loss
from .losses import prediction_loss_info as prediction_loss_info
from .losses import regularizer as regularizer
from .losses import violation_loss as violation_loss
from .losses import violation_loss_info as violation_loss_info
from .metrics import affine_error as affine_error
from .metrics import count_modes as count_modes
from .metrics import relative_error as relative_error
from .problems import convex_lcp_problem as convex_lcp_problem
from .problems import violation_problem as violation_problem
from .rigid_body import RigidBodyContact as RigidBodyContact
from .scaling import Scaling as Scaling
from .selection import Selection as Selection
from .selection import select_n_lam as select_n_lam
from .system import LCS as LCS
from .train import RECIPES as RECIPES
from .train import AdamOptions as AdamOptions
from .train import FitOptions as FitOptions
from .train import FitResult as FitResult
from .train import ObjectiveOptions as ObjectiveOptions
from .train import PolishOptions as PolishOptions
from .train import PruneOptions as PruneOptions
from .train import RefineOptions as RefineOptions
from .train import RolloutOptions as RolloutOptions
from .train import RunOptions as RunOptions
from .train import fit as fit
from .train import fit_ensemble as fit_ensemble
from .trajectories import Trajectories as Trajectories
from .trajectories import rollout_error as rollout_error
from .value_and_grad import prediction_value_and_grad as prediction_value_and_grad
from .value_and_grad import violation_value_and_grad as violation_value_and_grad

__all__ = [
    "AdamOptions",
    "affine_error",
    "convex_lcp_problem",
    "count_modes",
    "Dataset",
    "FallbackWarning",
    "fit",
    "fit_ensemble",
    "FitOptions",
    "FitResult",
    "Kinematics",
    "RigidBodyContact",
    "LayerAccuracyWarning",
    "PlanGapWarning",
    "LCPSolution",
    "LCS",
    "LCSInputError",
    "load_metadata",
    "load_model",
    "LossInfo",
    "make_dataset",
    "ObjectiveOptions",
    "PolishOptions",
    "RolloutOptions",
    "prediction_loss",
    "prediction_loss_info",
    "prediction_value_and_grad",
    "PruneOptions",
    "random_lcs",
    "RECIPES",
    "RefineOptions",
    "regularizer",
    "relative_error",
    "rollout_error",
    "RunOptions",
    "save_model",
    "Scaling",
    "select_n_lam",
    "Selection",
    "solve_lcp",
    "SolverError",
    "Trajectories",
    "violation_hessian",
    "violation_hvp",
    "violation_loss",
    "violation_loss_info",
    "violation_problem",
    "violation_value_and_grad",
]

#: Public subpackages and modules imported when first accessed as attributes.
_LAZY = ("bench", "cli", "control", "datasets", "plot", "study")


def __getattr__(name: str):
    if name in _LAZY:
        return _importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
