r"""Choosing the number of complementarity variables ``n_lam`` by held-out error.

The paper fixes ``n_lam`` to the ground truth's (Sec. 5); a user's own system has no such
number. :func:`select_n_lam` trains one model per candidate ``n_lam`` with :func:`lcs_cvx.fit`
on the same data and measures each one's relative error (the paper's ``e_test``,
:func:`lcs_cvx.relative_error`)

    e(n) = sum_t ||x'_theta_n(x_t, u_t) - x'_t||^2 / sum_t ||x'_t||^2

on transitions it did not train on: a validation set, or a held-out fraction of the training
set. Given :class:`lcs_cvx.Trajectories`, whole trajectories are held out and the held-out score
is :func:`lcs_cvx.fit`'s (the rollout error at ``holdout_horizon``, 10 steps by default, relative
to the recorded change with each coordinate scaled: :func:`lcs_cvx.simulation_error.change_error`).
:func:`choose` then applies a parsimony rule to the table ``{n: e(n)}``: the smallest ``n``
whose error is within ``(1 + tolerance)`` of the lowest.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ._checks import LCSInputError
from .data import Dataset
from .metrics import relative_error
from .system import DEFAULT_STIFFNESS, LCS
from .train.driver import fit
from .train.holdout import heldout_runs
from .trajectories import Trajectories

__all__ = ["Selection", "select_n_lam", "choose", "EXACT_ERROR"]

#: Held-out relative errors at or below this count as equal in :func:`choose`: a model there
#: reproduces the held-out data to within its training's round-off, and which candidate is
#: lowest is decided by that round-off (it changed with the processor on a noise-free log).
EXACT_ERROR = 1e-9


def choose(errors: Mapping[int, float], tolerance: float = 0.1) -> int:
    """The parsimony rule: the smallest ``n_lam`` whose held-out relative error is within
    ``(1 + tolerance)`` of the lowest, or at most :data:`EXACT_ERROR`,

        n* = min { n : e(n) <= max((1 + tolerance) min_m e(m), EXACT_ERROR) }.

    Why not simply the lowest error: once ``n_lam`` reaches the number of units the data need,
    more units fit the data as well but no better -- the extra ones are saturated or duplicate
    a boundary -- so the held-out errors of the larger candidates differ only by training noise
    (initialisation, batches, the held-out sample), and the arg-min among them is a coin toss
    that leans to the largest model. A model with fewer units has fewer hybrid modes, solves
    its LCP faster and is easier to read; within ``tolerance`` of the best it predicts as well.
    ``tolerance=0`` is the plain arg-min (ties going to the smaller ``n_lam``) above
    :data:`EXACT_ERROR`; below it, every candidate predicts the held-out data exactly but for
    round-off, whose ratios mean nothing.

    Args:
        errors: ``{n_lam: held-out relative error}``; errors that are NaN or inf (a diverged
            run) are never chosen, and at least one must be finite.
        tolerance: the relative slack, a finite number >= 0 (default 0.1: 10 %).

    Returns:
        The chosen ``n_lam``.

    Example:
        >>> from lcs_cvx.selection import choose
        >>> choose({1: 0.30, 2: 0.0104, 4: 0.0100, 8: 0.0101})
        2
        >>> choose({1: 0.30, 2: 0.0104, 4: 0.0100, 8: 0.0101}, tolerance=0.0)
        4
        >>> choose({1: 2e-11, 2: 8e-11, 3: 7e-13})  # all exact but for round-off
        1
    """
    _check_tolerance(tolerance)
    if not isinstance(errors, Mapping) or not errors:
        raise LCSInputError(
            f"errors: expected a non-empty mapping n_lam -> error, received {errors!r}"
        )
    _check_candidates("errors", list(errors))
    values = {}
    for n, e in errors.items():
        if isinstance(e, bool) or not isinstance(e, (int, float, np.floating, np.integer)):
            raise LCSInputError(f"errors: expected numbers as errors, received {e!r} for n_lam={n}")
        if float(e) < 0:
            raise LCSInputError(f"errors: expected errors >= 0, received {e!r} for n_lam={n}")
        values[int(n)] = float(e)
    finite = {n: e for n, e in values.items() if math.isfinite(e)}
    if not finite:
        raise LCSInputError(
            f"errors: expected at least one finite error, received {values!r} (every run diverged)"
        )
    bound = max((1.0 + float(tolerance)) * min(finite.values()), EXACT_ERROR)
    return min(n for n, e in finite.items() if e <= bound)


@dataclass(frozen=True)
class Selection:
    """What :func:`select_n_lam` returns.

    Attributes:
        n_lam: the chosen number of complementarity variables (:func:`choose`).
        model: the chosen candidate's trained model: the one whose held-out error is in the
            table (``refit=True``: retrained on the whole training set, see
            :func:`select_n_lam`).
        table: one dict per candidate, by increasing ``n_lam``: ``n_lam``,
            ``validation_error`` (relative error on the held-out transitions),
            ``train_error`` (on the transitions it trained on), ``wall_time`` (seconds of
            its training run) and ``grows_more`` (on held-out trajectories, its
            :attr:`lcs_cvx.FitResult.grows_more`: such a candidate is not chosen while
            another is not).
        results: the :class:`lcs_cvx.FitResult` of each candidate, by ``n_lam``.
        tolerance: the rule's tolerance.
        validation: where the held-out errors were measured: ``"validation set"`` or
            ``"held-out 20% of train"``.
        refit: the :class:`lcs_cvx.FitResult` of the refit on the whole training set, or None.
    """

    n_lam: int
    model: LCS
    table: list[dict[str, Any]]
    results: dict[int, Any]
    tolerance: float = 0.1
    validation: str = "validation set"
    refit: Any | None = field(default=None, repr=False)

    def summary(self) -> str:
        """The table as text, the chosen row marked ``*``, and the choice in one line."""
        lines = [f"{'n_lam':>6}  {'validation error':>16}  {'train error':>12}  {'wall time':>10}"]
        for row in self.table:
            mark = " *" if row["n_lam"] == self.n_lam else "  "
            lines.append(
                f"{row['n_lam']:>6}{mark}{row['validation_error']:>16.4e}  "
                f"{row['train_error']:>12.4e}  {row['wall_time']:>8.2f} s"
            )
        best = min((r for r in self.table if math.isfinite(r["validation_error"])),
                   key=lambda r: r["validation_error"])
        lines.append(
            f"chosen n_lam={self.n_lam}: the smallest within {100 * self.tolerance:g}% of the lowest "
            f"validation error ({best['validation_error']:.4e} at n_lam={best['n_lam']}; "
            f"{self.validation})" + ("; refit on all of train" if self.refit is not None else "")
        )
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.summary()


def select_n_lam(
    train: Dataset,
    candidates: Iterable[int],
    validation: Dataset | None = None,
    *,
    holdout: float = 0.2,
    tolerance: float = 0.1,
    make_model: Callable[[int], LCS] | None = None,
    stiffness: float = DEFAULT_STIFFNESS,
    kinematics: Any = None,
    seed: int = 0,
    refit: bool = False,
    progress: bool = True,
    **fit_options: Any,
) -> Selection:
    """Learn one LCS per candidate ``n_lam`` and choose among them by held-out error.

    For each ``n`` of ``candidates`` (by increasing ``n``): a model ``make_model(n)`` (default
    ``LCS(train.n_x, train.n_u, n, stiffness=stiffness, seed=seed)`` on the device of a
    :class:`lcs_cvx.Dataset` ``train``), trained by
    ``lcs_cvx.fit(model, part, progress=False, seed=seed, **fit_options)``, where ``part`` is
    ``train`` when ``validation`` is given, else the first part of
    ``train.split(1 - holdout, seed=seed)``; its relative error (:func:`lcs_cvx.relative_error`)
    on ``validation`` or on the held-out part is ``e(n)``. :func:`choose` picks
    ``n* = min {n : e(n) <= (1 + tolerance) min_m e(m)}``.

    Args:
        train: the training transitions, an :class:`lcs_cvx.Dataset`, or
            :class:`lcs_cvx.Trajectories` (held out by whole trajectories; ``validation`` then
            trajectories too, and the score :func:`lcs_cvx.fit`'s ``heldout_error``).
        candidates: the ``n_lam`` to try, distinct integers >= 1 (e.g. ``[1, 2, 4, 8]``).
        validation: held-out transitions with ``train``'s ``n_x`` and ``n_u``; default: split
            ``holdout`` of ``train`` off.
        holdout: the fraction of ``train`` held out when ``validation`` is None, in (0, 1).
        tolerance: the rule's relative slack, >= 0 (:func:`choose`).
        make_model: ``n -> LCS`` building each candidate's initial model, for a model with
            known structure (``model.fix(...)``, ``model.mask(...)``); it must return an
            :class:`lcs_cvx.LCS` with ``train``'s ``n_x``, ``n_u`` and ``n_lam = n``.
        stiffness: ``s`` of the default models (ignored with ``make_model``).
        kinematics: an :class:`lcs_cvx.Kinematics` attached to the default models (ignored
            with ``make_model``).
        seed: seed of the held-out split, of the default models' initialisation and of each
            training run (passed to ``fit`` as ``seed``, over the one of ``options``).
        refit: retrain the chosen ``n_lam`` on the whole of ``train`` (only without
            ``validation``). Default False: the refit is a second full training run of the
            chosen size, and the returned model is then the one whose held-out error was
            measured, not a new one assumed to be as good (it may land elsewhere).
        progress: one line per candidate on stderr when stderr is a terminal.
        **fit_options: passed on to every :func:`lcs_cvx.fit` call: ``options=``, ``recipe=``,
            ``test=``, flat options (``iterations=``, ``normalize=``, ...). Not ``checkpoint``
            or ``resume``: each candidate is a separate run (checkpoint one with ``fit``).

    Returns:
        :class:`Selection` (``print(selection)`` shows the table).

    Raises:
        LCSInputError: empty ``candidates``, one that is not an integer >= 1, a duplicate;
            ``validation`` of other dimensions or empty; ``holdout`` outside (0, 1);
            ``tolerance`` < 0; too few samples for a held-out part; a ``make_model`` result of
            other dimensions; ``refit`` with ``validation``; any error of :func:`lcs_cvx.fit`.

    Example:
        >>> import lcs_cvx
        >>> truth = lcs_cvx.random_lcs(2, 1, 2, seed=0)
        >>> data = lcs_cvx.make_dataset(truth, 500, noise=1e-2, seed=1)
        >>> sel = lcs_cvx.select_n_lam(data, [1, 2, 3], iterations=50, progress=False)
        >>> [row["n_lam"] for row in sel.table], sel.model.n_lam == sel.n_lam
        ([1, 2, 3], True)
    """
    if not isinstance(train, (Dataset, Trajectories)):
        raise LCSInputError(f"train: expected an lcs_cvx.Dataset or lcs_cvx.Trajectories, received {type(train).__name__}")
    by_trajectory = isinstance(train, Trajectories)
    if isinstance(candidates, (str, bytes)) or not isinstance(candidates, Iterable):
        raise LCSInputError(
            f"candidates: expected a list of integers >= 1 such as [1, 2, 4, 8], received {candidates!r}"
        )
    cands = sorted(_check_candidates("candidates", list(candidates)))
    if (isinstance(holdout, bool) or not isinstance(holdout, (int, float, np.floating))
            or not 0.0 < float(holdout) < 1.0):
        raise LCSInputError(f"holdout: expected a fraction in (0, 1), received {holdout!r}")
    _check_tolerance(tolerance)
    for name in ("checkpoint", "resume"):
        if fit_options.get(name) not in (None, False):
            raise LCSInputError(
                f"{name}: expected none in select_n_lam (each candidate is a separate training "
                f"run; checkpoint one with lcs_cvx.fit), received {fit_options[name]!r}"
            )
    if not isinstance(refit, bool):
        raise LCSInputError(f"refit: expected True or False, received {refit!r}")
    if validation is not None:
        if not isinstance(validation, Trajectories if by_trajectory else Dataset):
            raise LCSInputError(
                f"validation: expected an lcs_cvx.{'Trajectories' if by_trajectory else 'Dataset'} "
                f"(as train, or None), received {type(validation).__name__}"
            )
        if (validation.n_x, validation.n_u) != (train.n_x, train.n_u):
            raise LCSInputError(
                f"validation: expected n_x={train.n_x}, n_u={train.n_u} (train's), received "
                f"n_x={validation.n_x}, n_u={validation.n_u}"
            )
        if not by_trajectory and len(validation) == 0:
            raise LCSInputError("validation: expected at least one sample, received an empty dataset")
        if refit:
            raise LCSInputError(
                "refit: expected False with a validation set (the candidates trained on all of "
                "train already), received True"
            )
        part, held, where = train, validation, "validation set"
    elif by_trajectory:
        if len(train) < 2:
            raise LCSInputError("train: expected at least two trajectories to hold whole ones out (or "
                                f"validation=), received {len(train)}")
        held_out = heldout_runs(len(train), holdout)
        part, held = train.split((len(train) - held_out) / len(train), seed=seed)
        where = f"{held_out} held-out trajectories of train's {len(train)}"
    else:
        part, held = train.split(1.0 - holdout, seed=seed)
        if len(part) == 0 or len(held) == 0:
            raise LCSInputError(
                f"train: expected enough samples to hold {holdout:g} of them out, received "
                f"{len(train)} (a part would be empty); pass a validation set"
            )
        where = f"held-out {100 * holdout:g}% of train"

    def build(n: int) -> LCS:
        if make_model is None:
            device = train.x.device if isinstance(train, Dataset) else torch.device("cpu")
            return LCS(train.n_x, train.n_u, n, stiffness=stiffness, seed=seed, kinematics=kinematics).to(device)
        model = make_model(n)
        if not isinstance(model, LCS) or (model.n_x, model.n_u, model.n_lam) != (train.n_x, train.n_u, n):
            got = (f"n_x={model.n_x}, n_u={model.n_u}, n_lam={model.n_lam}" if isinstance(model, LCS)
                   else type(model).__name__)
            raise LCSInputError(
                f"make_model: expected an lcs_cvx.LCS with n_x={train.n_x}, n_u={train.n_u}, "
                f"n_lam={n} for n_lam={n}, received {got}"
            )
        return model

    report = progress and sys.stderr.isatty()
    table, results = [], {}
    for i, n in enumerate(cands, start=1):
        t0 = time.perf_counter()
        if by_trajectory:  # fit scores the held-out trajectories itself
            result = fit(build(n), part, progress=False, seed=seed, validation=held, **fit_options)
            held_error, part_error = result.heldout_error, relative_error(result.model, part.to_transitions())
        else:
            result = fit(build(n), part, progress=False, seed=seed, **fit_options)
            held_error, part_error = relative_error(result.model, held), relative_error(result.model, part)
        wall = time.perf_counter() - t0
        row = {"n_lam": n, "validation_error": held_error, "train_error": part_error, "wall_time": wall,
               "grows_more": bool(result.grows_more) if by_trajectory else False}
        table.append(row)
        results[n] = result
        if report:
            print(f"select_n_lam: n_lam={n} ({i}/{len(cands)}): validation error "
                  f"{row['validation_error']:.4e}, train error {row['train_error']:.4e}, "
                  f"{wall:.1f} s", file=sys.stderr, flush=True)
    # a candidate whose held-out rollouts grow more than the data's and the affine map's is not
    # chosen while another does not (its verdict says so when every one does)
    bounded = not all(r["grows_more"] for r in table)
    chosen = choose({r["n_lam"]: math.inf if r["grows_more"] and bounded else r["validation_error"] for r in table},
                    tolerance)
    model, again = results[chosen].model, None
    if refit:
        again = fit(build(chosen), train, progress=False, seed=seed, **fit_options)
        model = again.model
    return Selection(chosen, model, table, results, float(tolerance), where, again)


def _check_candidates(name: str, values: list[Any]) -> list[int]:
    if not values:
        raise LCSInputError(f"{name}: expected at least one n_lam, received none")
    bad = [v for v in values
           if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1]
    if bad:
        raise LCSInputError(f"{name}: expected integers >= 1 as n_lam, received {bad!r} in {values!r}")
    dup = sorted({int(v) for v in values if values.count(v) > 1})
    if dup:
        raise LCSInputError(f"{name}: expected distinct n_lam, received {dup!r} more than once in {values!r}")
    return [int(v) for v in values]


def _check_tolerance(tolerance: Any) -> None:
    if (isinstance(tolerance, bool) or not isinstance(tolerance, (int, float, np.floating))
            or not 0.0 <= float(tolerance) < math.inf):
        raise LCSInputError(f"tolerance: expected a finite number >= 0, received {tolerance!r}")
