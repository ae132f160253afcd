"""Baselines a grid study trains beside the LCS losses: piecewise-affine and smooth regressors of
the transition ``x' = f(x, u)`` fitted to the same training data.

- ``"affine"`` (:mod:`.affine`): ``x' = A x + B u + d`` by least squares -- one mode.
- ``"mlp"`` (:mod:`.mlp`): a tanh MLP on normalised coordinates, its size and learning rate
  chosen on a held-out validation split.
- ``"parc"`` (:mod:`.parc`): PARC, piecewise-affine regression and classification (Bemporad,
  package ``pyparc``, extra ``baselines``) with K pieces, by default the number of hybrid modes
  of the truth in the training data.

Every baseline is fitted by :func:`fit_baseline` and returns a model with the interface of
:meth:`lcs_cvx.LCS.step` (``step(x (N, n_x), u (N, n_u)) -> x' (N, n_x)``, float64 tensors, and
a ``dtype``), so :func:`lcs_cvx.relative_error` measures its e_test as it measures an LCS's.
A config's ``[baselines.<name>]`` table overrides the defaults of :data:`OPTIONS`; every option
is checked when the config is loaded (:func:`baseline_options`).

A baseline whose own fitting algorithm fails on a problem (PARC merging all its clusters away
when K is close to the number of samples over ``min_number``) raises :class:`BaselineFailed`:
the grid runner records the cell with ``status = "failed"`` -- a result of the method on that
problem, stored once and shown in the reports, not a bug to retry.
"""

from __future__ import annotations

import math
from typing import Any

from ..._checks import LCSInputError
from .failure import BaselineFailed

__all__ = ["BASELINES", "OPTIONS", "BaselineFailed", "baseline_options", "fit_baseline"]

BASELINES = ("affine", "mlp", "parc")


class _Check:
    """A value check with the text of what it expects (for the error message)."""

    def __init__(self, expected: str, ok) -> None:
        self.expected, self.ok = expected, ok


def _is_int(v: Any, lo: int) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= lo


def _is_num(v: Any, lo: float, strict: bool) -> bool:
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    return ok and (v > lo if strict else v >= lo)


_POS_INT = _Check("an integer >= 1", lambda v: _is_int(v, 1))
_NONNEG = _Check("a finite number >= 0", lambda v: _is_num(v, 0, False))
_POS = _Check("a finite number > 0", lambda v: _is_num(v, 0, True))
_BOOL = _Check("true or false", lambda v: isinstance(v, bool))
_FRACTION = _Check("a number in (0, 1)", lambda v: _is_num(v, 0, True) and v < 1)
_HIDDEN = _Check("a non-empty list of layer-size lists, e.g. [[64, 64], [128, 128]]",
                 lambda v: isinstance(v, list) and bool(v) and all(
                     isinstance(h, list) and bool(h) and all(_is_int(n, 1) for n in h) for h in v))
_RATES = _Check("a non-empty list of numbers > 0",
                lambda v: isinstance(v, list) and bool(v) and all(_is_num(r, 0, True) for r in v))
_K = _Check('"modes" (the hybrid modes of the truth in the training data) or an integer >= 1',
            lambda v: v == "modes" or _is_int(v, 1))
_SEPARATION = _Check('"Voronoi" or "Softmax"', lambda v: v in ("Voronoi", "Softmax"))

#: Every option of every baseline: ``{name: {key: (default, check)}}``. The PARC defaults are
#: the settings of the authors' comparison (``separation = "Voronoi"``, ``sigma = 1``,
#: ``alpha = beta = 1e-3``, ``maxiter = 15``, ``cost_tol = 1e-4``, ``min_number = 10``,
#: ``fit_on_partition = true``, K = the modes of the training data); ``kmeans_init`` is PARC's
#: number of k-means++ starts of its initial clustering (its own default, 10).
OPTIONS: dict[str, dict[str, tuple[Any, _Check]]] = {
    "affine": {},
    "mlp": {"hidden": ([[64, 64], [128, 128]], _HIDDEN), "lr": ([3e-3, 1e-2, 3e-2], _RATES),
            "iterations": (5000, _POS_INT), "batch_size": (256, _POS_INT),
            "weight_decay": (0.0, _NONNEG), "val_fraction": (0.1, _FRACTION),
            "eval_every": (250, _POS_INT)},
    "parc": {"K": ("modes", _K), "separation": ("Voronoi", _SEPARATION), "sigma": (1.0, _NONNEG),
             "alpha": (1e-3, _NONNEG), "beta": (1e-3, _NONNEG), "maxiter": (15, _POS_INT),
             "cost_tol": (1e-4, _NONNEG), "min_number": (10, _POS_INT),
             "fit_on_partition": (True, _BOOL), "softmax_maxiter": (100_000, _POS_INT),
             "kmeans_init": (10, _POS_INT)},
}


def baseline_options(name: str, table: dict[str, Any] | None, where: str = "baselines") -> dict[str, Any]:
    """The complete options of baseline ``name``: :data:`OPTIONS`' defaults, overridden by
    ``table`` (a config's ``[baselines.<name>]``).

    Raises:
        LCSInputError: an unknown baseline, an unknown key or a bad value, naming
            ``{where}.{name}.{key}``.
    """
    if name not in BASELINES:
        raise LCSInputError(f"{where}: unknown baseline {name!r}; expected one of {BASELINES}")
    table = {} if table is None else table
    if not isinstance(table, dict):
        raise LCSInputError(f"{where}.{name}: expected a table, received {table!r}")
    spec = OPTIONS[name]
    unknown = sorted(set(table) - set(spec))
    if unknown:
        raise LCSInputError(f"{where}.{name}.{unknown[0]}: unknown key; expected one of {sorted(spec)}")
    out = {}
    for key, (default, check) in spec.items():
        value = table.get(key, default)
        if not check.ok(value):
            raise LCSInputError(f"{where}.{name}.{key}: expected {check.expected}, received {value!r}")
        out[key] = value
    return out


def fit_baseline(name: str, options: dict[str, Any], train: Any, *, seed: int,
                 modes: int) -> tuple[Any, dict[str, Any]]:
    """Fit baseline ``name`` with ``options`` (complete, :func:`baseline_options`) to ``train``
    (an :class:`lcs_cvx.Dataset`); ``seed`` seeds its random draws, ``modes`` is the number of
    hybrid modes of the truth in ``train`` (PARC's ``K = "modes"``).

    Returns ``(model, info)``: the fitted model (``step(x, u)``, ``dtype``) and what the fit
    chose or measured (JSON-able).

    Raises:
        BaselineFailed: the method's own fitting algorithm failed on these data (PARC).
    """
    if name == "affine":
        from .affine import fit
    elif name == "mlp":
        from .mlp import fit
    elif name == "parc":
        from .parc import fit
    else:
        raise LCSInputError(f"name: unknown baseline {name!r}; expected one of {BASELINES}")
    return fit(train, options, seed=seed, modes=modes)
