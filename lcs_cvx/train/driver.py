r""":func:`fit`: learn an LCS from transitions or trajectories by minimising ``L(theta) + omega
||C||_F^2`` (paper eq. (4)), with restarts, checkpoints and resume, and score it against the
least-squares affine map on held-out data.

A run goes through the phases of :mod:`lcs_cvx.train.phases` (Adam, pruning, second-order
refinement, polish; options in :mod:`lcs_cvx.train.options`). With ``restarts > 1`` the runs start
from different initialisations (the first from ``model``), train on ``1 - holdout`` of the data,
and the one with the lowest relative error on the held-out part is returned.

Checkpoints hold every finished restart and the running one's :class:`TrainState`; they are
written atomically, and ``resume=True`` continues a killed run to exactly the result of an
uninterrupted one (wall times aside).
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import torch

from .._checks import LCSInputError
from .._kernels.calls import resolve_threads
from ..data import Dataset
from ..io import atomic_write
from ..metrics import relative_error
from ..parameter_constraints import check_learnable
from ..scaling import Scaling, fold_back, in_user_coordinates
from ..simulation_error import Windows
from ..system import LCS
from ..trajectories import Trajectories
from .ensemble import train_together
from .holdout import split_data
from .inputs import check_data, check_per_sample, fit_options, per_sample_options, resolve_keep_best
from .log import record_logger
from .options import FitOptions
from .phases import run_phases
from .recipes import DEFAULT_RECIPE, PLAIN
from .result import FitResult, lowest
from .starts import fresh_like, jittered, start
from .state import TrainState

__all__ = ["FitResult", "fit", "CHECKPOINT_FORMAT"]

#: 4: the run state of :class:`TrainState` (with the simulation-error phase) and grouped options.
CHECKPOINT_FORMAT = 4
#: With ``restart_tolerance``, a run succeeds only with a held-out error below this fraction of
#: the least-squares affine map's (:func:`lcs_cvx.metrics.affine_error`).
AFFINE_MARGIN = 0.5


class _Checkpoint:
    """The checkpoint file: finished restarts (``done``) and the running one's state."""

    def __init__(self, path: str | None, options: FitOptions) -> None:
        self.path, self.options, self.flat = path, dataclasses.asdict(options), options.flat()

    def load(self) -> dict | None:
        if self.path is None or not os.path.exists(self.path):
            return None
        try:
            ckpt = torch.load(self.path, weights_only=True)
        except Exception as exc:  # a corrupt file must not be silently overwritten
            raise LCSInputError(f"checkpoint: could not read {self.path!r}: {exc}") from exc
        if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
            got = ckpt.get("format") if isinstance(ckpt, dict) else type(ckpt).__name__
            raise LCSInputError(
                f"checkpoint: {self.path!r} has format {got!r}, expected {CHECKPOINT_FORMAT} "
                "(written by another version of lcs_cvx); start afresh with resume=False"
            )
        if ckpt["options"] != self.options:  # named by the flat keywords where they differ
            saved, mine = ckpt["flat"], self.flat
            if saved == mine:
                saved, mine = _dotted(ckpt["options"]), _dotted(self.options)
            diff = sorted(k for k in set(saved) | set(mine) if saved.get(k) != mine.get(k))
            raise LCSInputError(
                f"checkpoint: {self.path!r} was written with other options (differing: {diff}); "
                "resume with the same options or start afresh with resume=False"
            )
        return ckpt

    def save(self, restart: int, done: list[dict], run: dict | None, elapsed: float) -> None:
        if self.path is None:
            return
        obj = {"format": CHECKPOINT_FORMAT, "options": self.options, "flat": self.flat,
               "restart": restart,
               "done": done, "run": run, "elapsed": elapsed}
        atomic_write(self.path, lambda f: torch.save(obj, f), name="checkpoint")


def _dotted(d: dict, prefix: str = "") -> dict:
    """``{"adam": {"lr": 1e-3}}`` as ``{"adam.lr": 1e-3}``."""
    out: dict = {}
    for k, v in d.items():
        out.update(_dotted(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def kept_fit(history: list[dict[str, Any]], tolerance: float | None) -> bool:
    """Whether a run kept the fit its Adam phase found: its last refinement record's training
    loss at most ``tolerance`` times its last Adam record's (True without a tolerance, and for a
    run with no records of either phase)."""
    adam = [h["loss"] for h in history if h["phase"] == "adam"]
    refined = [h["loss"] for h in history if h["phase"] in ("gauss-newton", "newton")]
    if tolerance is None or not adam or not refined:
        return True
    return refined[-1] <= tolerance * adam[-1]


def close_run(state: TrainState, r: Any, holdout_score: Callable[[LCS], float] | None) -> dict:
    """A finished run as a checkpoint's ``done`` entry: its best iterate restored (with
    ``keep_best``), its held-out score (NaN without a held-out part), its history, whether it
    kept its fit (:func:`kept_fit`) and its parameters."""
    if r.keep_best:
        state.restore_best()
        start, best = state.rollout_start, state.best
        if start is not None and best is not None:
            # the phase is kept where one of its iterates is the one returned
            state.rollout_kept = best[0] < start[0]
    model = state.model
    return {"score": holdout_score(model) if holdout_score is not None else math.nan,
            "history": state.history, "kept": kept_fit(state.history, r.restart_tolerance),
            "refinement_kept": state.rollout_kept,
            "params": {k: v.detach().clone() for k, v in model.state_dict().items()}}


def _restarts_together(done: list[dict], history: list[dict], r: Any, opts: FitOptions,
                       learner_for: Callable[[int], LCS], fit_data: Dataset,
                       test_score: Callable[[LCS], float] | None,
                       holdout_score: Callable[[LCS], float] | None, elapsed: Callable[[], float]) -> LCS:
    """``fit(ensemble=True)``: the restarts not in ``done`` trained in one batched loop
    (:func:`lcs_cvx.train.ensemble.train_together`), then closed as the sequential loop closes
    each (best iterate, held-out score, ``done`` and ``history``). Returns the last learner."""
    remaining = range(len(done), r.restarts)
    learners = [learner_for(k) for k in remaining]
    states = [TrainState(m, fit_data, opts, k, test_score=test_score, validate=holdout_score)
              for m, k in zip(learners, remaining, strict=True)]
    train_together(states, throw=True, elapsed=elapsed)
    for st in states:
        done.append(close_run(st, r, holdout_score))
        history.extend(st.history)
    return learners[-1]


def fit(
    model: LCS,
    train: Dataset | Trajectories,
    options: FitOptions | None = None,
    *,
    validation: Dataset | Trajectories | None = None,
    test: Dataset | None = None,
    recipe: str | None = None,
    callbacks: Sequence[Callable[[dict, LCS], Any]] = (),
    log: Any = None,
    checkpoint: str | os.PathLike | None = None,
    resume: bool = False,
    progress: bool = True,
    ensemble: bool = False,
    threads: int | None = None,
    **overrides: Any,
) -> FitResult:
    """Learn the LCS ``model`` from ``train`` (in place): minimise ``L(theta) + omega ||C||_F^2``.

    Args:
        model: an :class:`lcs_cvx.LCS`, the initialisation (float64 recommended).
        train: :class:`lcs_cvx.Dataset` of transitions ``(x, u, x')``, or
            :class:`lcs_cvx.Trajectories`: then whole trajectories are held out (``holdout``),
            the held-out score can be a rollout error (``holdout_horizon``) and the
            simulation-error phase can run (``rollout_horizon``).
        options: a :class:`FitOptions` (e.g. ``lcs_cvx.RECIPES["paper"]``); default: ``recipe``'s.
        validation: held-out data (transitions or trajectories) instead of a part of ``train``:
            the held-out score that every choice follows (the kept iterate, the kept restart,
            whether the simulation-error phase is kept) and :attr:`FitResult.heldout_error`.
        test: optional dataset; its relative error (the paper's e_test) is recorded with every
            history record. It is only reported: no choice of the fit looks at it (the same
            model is returned with and without it).
        recipe: when ``options`` is not given: ``"best"`` (the recommended options; the
            default for an :class:`lcs_cvx.LCS`), ``"paper"`` (the paper's protocol) or
            ``"plain"`` (:class:`FitOptions`' own defaults). None: ``"best"``
            (:data:`~lcs_cvx.train.recipes.DEFAULT_RECIPE`) for an LCS trained by Adam;
            ``"plain"`` with ``optimizer="gauss-newton"`` or ``"newton"`` (their own defaults)
            and for a model of per-sample matrices.
        callbacks: ``cb(record, model)`` after every history record; a true return value stops
            training (a checkpoint is written first).
        log: every history record also goes to ``log``: a callable of the record, or a directory
            (created if missing) where TensorBoard event files get one scalar per record for the
            loss, the held-out score, e_test, the learning rate, eps, the wall time and the
            phase (:mod:`lcs_cvx.train.log`; ``tensorboard --logdir DIRECTORY`` shows them).
        checkpoint: path of the checkpoint file (written atomically; not a model file -- use
            :func:`lcs_cvx.save_model` for that).
        resume: continue from ``checkpoint`` if it exists (the options must be the same).
        progress: a tqdm bar on stderr when it is a terminal.
        ensemble: train the restarts (``restarts > 1``) together in one batched loop
            (:func:`lcs_cvx.fit_ensemble`'s), with the same result, history and restart scores as
            one after the other. Only for options without extra units, refinement, polish or
            re-initialisation of saturated units, and without callbacks; a checkpoint is written
            when they have all finished (a killed run restarts the unfinished ones), and the first
            restart that diverges raises at once.
        threads: threads of the compiled kernels on minibatches of at least ``2 *
            lcs_cvx._kernels.calls.MIN_CHUNK`` samples (float64 CPU; see
            :func:`lcs_cvx.violation_loss`): the same numbers for every count. Default
            ``torch.get_num_threads()`` (``OMP_NUM_THREADS``, ``torch.set_num_threads``); not
            part of the options (a checkpoint resumes with any).
        **overrides: flat options (:data:`lcs_cvx.train.FLAT_OPTIONS`: ``loss``, ``optimizer``,
            ``iterations``, ``lr``, ``gamma``, ``eps``, ``reg``, ``seed``, ...) or whole groups
            (``adam=AdamOptions(...)``), applied on top of ``options`` or ``recipe``.

    Returns:
        :class:`FitResult`.

    Example:
        >>> import lcs_cvx
        >>> truth = lcs_cvx.random_lcs(2, 1, 2, seed=0)
        >>> data = lcs_cvx.make_dataset(truth, 500, seed=1)
        >>> model = lcs_cvx.LCS(2, 1, 2, seed=2)
        >>> result = lcs_cvx.fit(model, data, recipe="plain", optimizer="gauss-newton", iterations=5,
        ...                      progress=False)
        >>> len(result.history), len(result.restart_scores), result.n_fallback
        (15, 3, 0)
    """
    lcs = isinstance(model, LCS)  # else a model of per-sample matrices (lcs_cvx.RigidBodyContact)
    if not lcs and not callable(getattr(model, "sample_lcs", None)):
        raise LCSInputError(f"model: expected an lcs_cvx.LCS or a model of per-sample matrices "
                            f"(lcs_cvx.RigidBodyContact), received {type(model).__name__}")
    check_learnable(model) if lcs else check_per_sample(model)
    resolve_threads(threads)
    if options is None and recipe is None:  # "best" is Adam's recipe
        recipe = DEFAULT_RECIPE if lcs and overrides.get("optimizer", "adam") == "adam" else PLAIN
    opts = fit_options(options, recipe, overrides)
    if not lcs:
        opts = per_sample_options(opts, overrides)
    split = split_data(train, validation, opts.run, opts.rollout.horizon)
    opts = resolve_keep_best(opts, split.holds_out_runs)
    fit_user = check_data("train", split.fit, model)
    split = dataclasses.replace(split, fit=fit_user)  # the affine reference on the model's device too
    if isinstance(split.holdout, Dataset):
        split = dataclasses.replace(split, holdout=check_data("validation", split.holdout, model))
    holdout = split.holdout
    windows = Windows(split.trajectories, split.rollout_horizon) if split.rollout_horizon is not None else None
    test = check_data("test", test, model) if test is not None else None
    store = _Checkpoint(os.fspath(checkpoint) if checkpoint is not None else None, opts)
    ckpt = store.load() if resume else None
    r = opts.run

    # the coordinates of learning: normalised (folded back at the end) or the user's own
    scaling = Scaling.fit(fit_user, model) if r.normalize and lcs else None
    # known kinematics: the one-step losses train the velocity rows (the held configuration rows'
    # targets are their own prediction); rollouts and scores integrate the configuration
    fit_rows = model.kinematics.one_step(fit_user) if model.kinematics is not None else fit_user
    fit_data = scaling.encode(fit_rows) if scaling is not None else fit_rows

    def in_units(m: LCS) -> LCS:
        return in_user_coordinates(scaling, m, model)

    def score_on(data: Dataset) -> Callable[[LCS], float]:
        return lambda m: relative_error(in_units(m), data)

    def holdout_score(m: LCS) -> float:  # inf where the held-out rollouts leave the data's range
        return split.choice_score(in_units(m))

    test_score = score_on(test) if test is not None else None  # recorded only
    validate = holdout_score if holdout is not None else None
    user_callbacks = [lambda rec, m, cb=cb: cb(rec, in_units(m)) for cb in callbacks]
    if ensemble and log is not None:
        raise LCSInputError("log: expected None with ensemble=True (the restarts are trained together; "
                            f"their records are in the result's history), received {type(log).__name__}")
    log_record, close_log = record_logger(log)
    if log_record is not None:  # first, so that a record is logged before a callback stops the run
        user_callbacks.insert(0, lambda rec, m: log_record(rec) and False)
    done: list[dict] = [] if ckpt is None else ckpt["done"]
    t_offset = 0.0 if ckpt is None else ckpt["elapsed"]
    bar = None
    if progress and sys.stderr.isatty():
        from tqdm.auto import tqdm

        total = r.restarts * (opts.adam.iterations + opts.polish.iterations
                              + (opts.refine.iterations if opts.refine.method else 0)
                              + (opts.rollout.iterations if windows is not None else 0))
        bar = tqdm(total=total, desc="fit", unit="it", dynamic_ncols=True)
    t_start = time.perf_counter()

    def elapsed() -> float:
        return t_offset + time.perf_counter() - t_start

    def learner_for(restart: int) -> LCS:
        """The start of a restart in the coordinates of learning (restart 0: from ``model``)."""
        if not lcs:  # a physical model starts where it is; a restart from its quantities jittered
            return model if restart == 0 else jittered(model, seed=r.seed * 7919 + restart)
        base = model if restart == 0 else fresh_like(model, seed=r.seed * 7919 + restart)
        return start(base, r.init_for(restart), scaling, fit_data, exact=restart == 0)

    def succeeded(run: dict) -> bool:
        """Whether a finished run kept its fit and beat the affine map (``restart_tolerance``)."""
        return run.get("kept", False) and run["score"] < AFFINE_MARGIN * split.affine_heldout

    history: list[dict] = [h for d in done for h in d["history"]]
    stopped = False
    learner = None
    if ensemble and r.restart_tolerance is not None:
        raise LCSInputError("restart_tolerance: restarts trained together all run; expected None "
                            f"with ensemble=True, received {r.restart_tolerance!r}")
    if ensemble and windows is not None:
        raise LCSInputError("rollout_horizon: restarts trained together run the Adam phase only; expected "
                            f"None with ensemble=True, received {opts.rollout.horizon!r} (a "
                            f"{split.rollout_horizon}-step phase on these trajectories)")
    if ensemble and callbacks:
        raise LCSInputError("callbacks: expected none with ensemble=True (the restarts are "
                            f"trained together), received {len(callbacks)}")
    try:
        if ensemble and len(done) < r.restarts:
            learner = _restarts_together(done, history, r, opts, learner_for, fit_data, test_score,
                                         validate, elapsed)
            if bar is not None:
                bar.update(bar.total - bar.n)
        for restart in range(len(done), r.restarts):
            if r.restart_tolerance is not None and any(succeeded(d) for d in done):
                break
            learner = learner_for(restart)
            state = TrainState(learner, fit_data, opts, restart, test_score=test_score, validate=validate,
                               windows=windows, scaling=scaling, threads=threads,
                               kinematics=model.kinematics,
                               sigma=None if lcs or windows is None else split.scale)
            if ckpt is not None and ckpt["restart"] == restart and ckpt["run"] is not None:
                state.load_state_dict(ckpt["run"])
                if bar is not None:
                    bar.update(state.iteration)

            def save(state: TrainState = state, restart: int = restart) -> None:
                store.save(restart, done, state.state_dict(), elapsed())

            stopped = run_phases(state, callbacks=user_callbacks, save=save, elapsed=elapsed, bar=bar)
            done.append(close_run(state, r, validate))
            history.extend(state.history)
            if stopped:
                break
    finally:
        if bar is not None:
            bar.close()
        close_log()
    scores = [d["score"] for d in done] if r.restarts > 1 else []
    refinement_kept = None
    if done:  # the chosen run (also when a resumed checkpoint had finished them all)
        best = lowest(scores) if r.restarts > 1 else -1
        if learner is None:  # every restart came from the checkpoint
            learner = learner_for(0)
        learner.load_state_dict(done[best]["params"])
        refinement_kept = done[best].get("refinement_kept")
        fold_back(scaling, learner, model)
    if not stopped:
        store.save(r.restarts, done, None, elapsed())
    result = FitResult(model, history, opts, scores, elapsed(), scaling, refinement_kept=refinement_kept)
    return split.conclude(result, r.affine_if_better and lcs) if holdout is not None else result
