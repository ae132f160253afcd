"""The inputs of :func:`lcs_cvx.fit` and :func:`lcs_cvx.fit_ensemble`, checked once at the
boundary: the data against the model (:func:`check_data`) and the options from ``options``,
``recipe`` and flat keywords (:func:`fit_options`), with ``keep_best``'s default resolved for the
data (:func:`resolve_keep_best`)."""

from __future__ import annotations

import dataclasses
from typing import Any

import torch

from .._checks import LCSInputError
from ..data import Dataset
from ..system import LCS
from .options import FitOptions, split_groups
from .recipes import resolve_options

__all__ = ["check_data", "check_per_sample", "fit_options", "per_sample_options", "resolve_keep_best"]


def check_data(name: str, data: Any, model: LCS) -> Dataset:
    """``data`` as a :class:`lcs_cvx.Dataset` of ``model``'s sizes, dtype and device, with finite
    values (checked once: the training loop does not check again), or a clear error."""
    if not isinstance(data, Dataset):
        raise LCSInputError(f"{name}: expected an lcs_cvx.Dataset, received {type(data).__name__}")
    if data.n_x != model.n_x or data.n_u != model.n_u:
        raise LCSInputError(
            f"{name}: expected n_x={model.n_x}, n_u={model.n_u} (the model's), received "
            f"n_x={data.n_x}, n_u={data.n_u}"
        )
    if len(data) == 0:
        raise LCSInputError(f"{name}: expected at least one sample, received an empty dataset")
    for field_name in ("x", "u", "x_next"):  # checked once here: the training loop does not
        t = getattr(data, field_name)
        if not t.is_floating_point() or not bool(torch.isfinite(t).all()):
            raise LCSInputError(
                f"{name}: expected finite real values in {field_name}, received "
                f"{'dtype ' + str(t.dtype) if not t.is_floating_point() else 'NaN/inf entries'}"
            )
    check = getattr(model, "check_states", None)
    if check is not None:  # a model of a body's states: its quaternions normalised, or an error
        data = Dataset(check(name, data.x), data.u, check(name, data.x_next), data.lam)
    if data.x.device == model.device and data.x.dtype == model.dtype:
        return data
    kw = {"device": model.device, "dtype": model.dtype}
    return Dataset(data.x.to(**kw), data.u.to(**kw), data.x_next.to(**kw),
                   None if data.lam is None else data.lam.to(**kw))


def resolve_keep_best(opts: FitOptions, held_out_runs: bool) -> FitOptions:
    """``opts`` with ``keep_best=None`` resolved: on where whole runs are held out
    (``held_out_runs``), else off; an explicit True or False is kept."""
    if opts.run.keep_best is not None:
        return opts
    return dataclasses.replace(opts, run=dataclasses.replace(opts.run, keep_best=held_out_runs))


def fit_options(options: FitOptions | None, recipe: str | None, overrides: dict[str, Any]) -> FitOptions:
    """The options of a :func:`lcs_cvx.fit` call: ``options`` with ``overrides`` (flat keywords
    or whole groups) applied, or ``recipe``'s with them; exactly one of ``options``, ``recipe``
    may be given."""
    if options is None:
        groups = split_groups(overrides)
        return resolve_options(recipe, **overrides).replace(**groups)
    if not isinstance(options, FitOptions):
        raise LCSInputError(
            f"options: expected an lcs_cvx.FitOptions (e.g. lcs_cvx.RECIPES['best']), received "
            f"{type(options).__name__}"
        )
    if recipe is not None:
        raise LCSInputError(
            f"recipe: expected None when options are given (they already hold one), received {recipe!r}"
        )
    return options.replace(**overrides)


def check_per_sample(model: Any) -> None:
    """:class:`LCSInputError` when a model of per-sample matrices has nothing to learn."""
    if not any(p.requires_grad for p in model.parameters()):
        raise LCSInputError("model: expected at least one learnable quantity, received a model whose every "
                            "parameter is fixed (requires_grad False)")


def per_sample_options(opts: FitOptions, overrides: dict[str, Any]) -> FitOptions:
    """``opts`` for a model of per-sample matrices (:class:`lcs_cvx.RigidBodyContact`): it learns
    its physical quantities in their own units from where it is (``normalize`` and ``init`` do
    not apply), has no units to add or re-draw (``extra_units="auto"`` and ``reinit_saturated``
    off), and is trained by Adam (a second-order refinement is an error)."""
    if opts.refine.method is not None:
        raise LCSInputError(f"optimizer: expected 'adam' for a model of per-sample matrices (the second-order "
                            f"steps are an LCS's), received refinement {opts.refine.method!r}")
    if opts.adam.extra_units not in (0, "auto"):
        raise LCSInputError(f"extra_units: expected 0 for a model of per-sample matrices (its units are its "
                            f"contacts), received {opts.adam.extra_units!r}")
    adam = dataclasses.replace(opts.adam, extra_units=0, reinit_saturated=False)
    return dataclasses.replace(opts, adam=adam, run=dataclasses.replace(opts.run, normalize=False))
