r""":func:`fit_ensemble`: train many models in one batched loop, each exactly as :func:`lcs_cvx.fit`
would train it alone.

Model ``k`` keeps everything of its own run -- its data, initialisation, minibatch order (its
own generator, seeded from its own ``seed``), Adam moments, history and best iterate (a
:class:`~lcs_cvx.train.state.TrainState` each) -- and only the arithmetic is shared: at every
step the ``K`` minibatches go through one call of the stacked fast losses
(:mod:`lcs_cvx.stacked`), and one Adam over the stacked parameters, stepped on the sum of the
``K`` regularised losses ``L_k(theta_k) + omega ||C_k||_F^2`` (eq. (4)), makes each
model's own Adam step (Adam is elementwise, and slice ``k`` of the sum's gradient is model
``k``'s gradient). On CPU tensors each model's numbers are those of its own :func:`fit` bit for
bit (tested); on other devices (torch kernels) to round-off.

:func:`lcs_cvx.fit`'s ``ensemble=True`` trains a run's restarts the same way
(:func:`train_together`).

Scope: the Adam phase with its learning-rate and ``eps`` schedules, ``normalize`` and ``init`` --
the "paper" recipe and the plain defaults (``keep_best`` too for :func:`lcs_cvx.fit`'s restarts,
which have a held-out part; the test sets of :func:`fit_ensemble` are only reported). The parts that change
a model's shape or step it differently (extra units and pruning, refinement, polish,
re-initialisation of saturated units, restarts) are refused with a message; so are
checkpoints (an interrupted ensemble is run again; :mod:`lcs_cvx.study` stores each finished
model as it would a cell of its own).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import torch

from .._checks import LCSInputError, SolverError
from ..data import Dataset
from ..metrics import relative_error
from ..parameter_constraints import check_learnable
from ..scaling import Scaling, fold_back, in_user_coordinates
from ..stacked import StackedLCS, prediction_losses, violation_losses
from ..system import LCS
from .inputs import check_data, fit_options, resolve_keep_best
from .onecall import adam_update_from_grads
from .options import FitOptions
from .phases import AdamPhase, divergence
from .result import FitResult
from .starts import start
from .state import Outcome, TrainState

__all__ = ["fit_ensemble"]


def check_supported(opts: FitOptions, restarts: bool = False) -> None:
    """:class:`LCSInputError` for an option the ensemble loop does not run (module docstring);
    ``restarts``: the runs are a :func:`lcs_cvx.fit`'s restarts (``restarts > 1`` allowed)."""
    a = opts.adam
    refused = {
        "extra_units": (a.extra_units, 0), "reinit_saturated": (a.reinit_saturated, False),
        "refine": (opts.refine.method, None), "polish_iterations": (opts.polish.iterations, 0),
        "rollout_horizon": (None if opts.rollout.horizon == "auto" else opts.rollout.horizon, None),
    }
    if not restarts:  # the models of fit_ensemble have no held-out part to keep an iterate by
        refused["restarts"] = (opts.run.restarts, 1)
        refused["keep_best"] = (bool(opts.run.keep_best), False)
    for name, (value, allowed) in refused.items():
        if value != allowed:
            raise LCSInputError(
                f"{name}: fit_ensemble runs the Adam phase only; expected {allowed!r}, received "
                f"{value!r} (train such models one by one with lcs_cvx.fit)"
            )


class _Member:
    """One model of the ensemble: the user's model, its coordinates of learning and its run."""

    def __init__(self, model: LCS, train: Dataset, test: Dataset | None, opts: FitOptions) -> None:
        self.model, self.opts = model, opts
        r = opts.run
        self.scaling = Scaling.fit(train, model) if r.normalize else None
        fit_data = self.scaling.encode(train) if self.scaling is not None else train
        self.learner = start(model, r.init, self.scaling, fit_data, exact=True)
        score = (lambda m: relative_error(self.in_units(m), test)) if test is not None else None
        self.state = TrainState(self.learner, fit_data, opts, 0, test_score=score)

    def in_units(self, m: LCS) -> LCS:
        """The learner in the user's coordinates (as :func:`lcs_cvx.fit`'s)."""
        return in_user_coordinates(self.scaling, m, self.model)

    def finish(self, wall_time: float) -> FitResult:
        """The model folded back into the user's units and its :class:`FitResult`."""
        st = self.state
        if self.opts.run.keep_best:
            st.restore_best()
        fold_back(self.scaling, self.learner, self.model)
        return FitResult(self.model, st.history, self.opts, [], wall_time, self.scaling)


def _moved_adam(adam: torch.optim.Adam, old: StackedLCS, new: StackedLCS, keep: list[int]) -> torch.optim.Adam:
    """An Adam over ``new`` (the models ``keep`` of ``old``) with their moments and step counts."""
    group = {k: v for k, v in adam.param_groups[0].items() if k != "params"}
    moved = torch.optim.Adam(new.parameters(), **group)
    index = torch.as_tensor(keep, dtype=torch.long, device=new.A.device)
    for p_old, p_new in zip(old.parameters(), new.parameters(), strict=True):
        st = adam.state.get(p_old)
        if st:
            moved.state[p_new] = {k: (v.clone() if k == "step" else v[index].clone()) for k, v in st.items()}
    return moved


def fit_ensemble(
    models: Sequence[LCS],
    trains: Sequence[Dataset],
    options: FitOptions | None = None,
    *,
    tests: Sequence[Dataset] | None = None,
    seeds: Sequence[int] | None = None,
    recipe: str | None = None,
    throw: bool = True,
    progress: bool = True,
    **overrides: Any,
) -> list[FitResult | SolverError]:
    """Train the LCS ``models[k]`` on ``trains[k]`` (in place), all in one batched loop.

    Each model is trained exactly as ``lcs_cvx.fit(models[k], trains[k], options,
    test=tests[k], recipe=recipe, seed=seeds[k], **overrides)`` would train it (module
    docstring): the same minibatches, steps and history, to the bit on CPU tensors.

    Args:
        models: the :class:`lcs_cvx.LCS` initialisations, of one size, dtype and device.
        trains: one training :class:`lcs_cvx.Dataset` per model; every model's minibatch must
            have the same size (``min(batch_size, len(trains[k]))``).
        options, recipe, **overrides: as in :func:`lcs_cvx.fit`, for every model.
        tests: one test set per model (its e_test is recorded with every history record).
        seeds: one ``seed`` per model (the seed of its minibatch order), overriding the options'.
        throw: a model whose training diverges raises :class:`lcs_cvx.SolverError` (True), or
            (False) leaves the ensemble and gets the error as its result while the others go on.
        progress: a tqdm bar on stderr when it is a terminal.

    Returns:
        One :class:`lcs_cvx.FitResult` per model, in order (or, with ``throw=False``, the
        :class:`lcs_cvx.SolverError` of a model that diverged).

    Example:
        >>> import lcs_cvx
        >>> truth = lcs_cvx.random_lcs(2, 1, 2, seed=0)
        >>> data = [lcs_cvx.make_dataset(truth, 500, seed=k) for k in range(3)]
        >>> models = [lcs_cvx.LCS(2, 1, 2, seed=10 + k) for k in range(3)]
        >>> results = lcs_cvx.fit_ensemble(models, data, recipe="paper", iterations=20,
        ...                                seeds=[0, 1, 2], progress=False)
        >>> tuple(len(r.history) for r in results), results[0].n_fallback
        ((1, 1, 1), 0)
    """
    models, trains = list(models), list(trains)
    K = len(models)
    if K == 0:
        raise LCSInputError("models: expected at least one lcs_cvx.LCS, received none")
    for name, seq in (("trains", trains), ("tests", tests), ("seeds", seeds)):
        if seq is not None and len(seq) != K:
            raise LCSInputError(f"{name}: expected one per model ({K}), received {len(seq)}")
    for k, m in enumerate(models):
        if not isinstance(m, LCS):
            raise LCSInputError(f"models[{k}]: expected an lcs_cvx.LCS, received {type(m).__name__}")
        check_learnable(m)
    opts = [fit_options(options, recipe, dict(overrides) if seeds is None else {**overrides, "seed": seeds[k]})
            for k in range(K)]
    opts = [resolve_keep_best(o, held_out_runs=False) for o in opts]  # transitions, as in fit
    check_supported(opts[0])
    members = [
        _Member(m, check_data(f"trains[{k}]", trains[k], m),
                None if tests is None else check_data(f"tests[{k}]", tests[k], m), opts[k])
        for k, m in enumerate(models)
    ]
    t_start = time.perf_counter()

    def elapsed() -> float:
        return time.perf_counter() - t_start

    errors = train_together([mb.state for mb in members], throw=throw, elapsed=elapsed,
                            progress=progress, label=lambda k: f"models[{k}]: ")
    return [mb.finish(elapsed()) if err is None else err for mb, err in zip(members, errors, strict=True)]


def train_together(states: list[TrainState], *, throw: bool, elapsed: Callable[[], float],
                   progress: bool = False, label: Callable[[int], str] = lambda k: "") -> list[SolverError | None]:
    """The Adam phase of every run of ``states`` (one :class:`TrainState` each, options equal
    but for the seed, checked by the callers; each state's ``model`` is what it trains), in one
    batched loop: each state ends as its run alone would leave it after the phase.

    Returns, per state, None or the :class:`lcs_cvx.SolverError` of its divergence (with
    ``throw=False``; with ``throw=True`` the first one is raised). ``label(k)`` prefixes state
    ``k``'s error message. Package-internal: :func:`fit_ensemble` and :func:`lcs_cvx.fit`'s
    ``ensemble=True`` restarts end here."""
    o = states[0].options
    check_supported(o, restarts=True)
    sizes = {min(o.adam.batch_size, len(st.train)) for st in states}
    if len(sizes) > 1:
        raise LCSInputError(
            f"trains: expected the same minibatch size for every model (min(batch_size, len(train))), "
            f"received {sorted(sizes)}"
        )
    errors: list[SolverError | None] = [None] * len(states)
    bar = None
    if progress and sys.stderr.isatty():
        from tqdm.auto import tqdm

        bar = tqdm(total=o.adam.iterations, desc=f"fit ({len(states)} together)", unit="it",
                   dynamic_ncols=True)
    try:
        _adam_loop(states, o, sizes.pop(), errors, throw, elapsed, bar, label)
    finally:
        if bar is not None:
            bar.close()
    return errors


def _adam_loop(states: list[TrainState], o: FitOptions, batch: int, errors: list, throw: bool,
               elapsed: Callable[[], float], bar: Any, label: Callable[[int], str]) -> None:
    """The Adam phase of every state, one stacked step at a time (:class:`AdamPhase`'s step and
    :func:`~lcs_cvx.train.phases.run_phases`'s records, for all models at once)."""
    a, obj = o.adam, o.objective
    phase = AdamPhase(o)
    alive = list(range(len(states)))  # the states still training, in stack order
    ens = StackedLCS([st.model for st in states])
    adam = torch.optim.Adam(ens.parameters(), lr=a.lr, betas=a.betas, eps=a.adam_eps)
    # every state's training set, end to end; state k's samples start at starts[k]
    trains = [st.train for st in states]
    X, U, XN = (torch.cat([getattr(d, f) for d in trains]) for f in ("x", "u", "x_next"))
    starts = torch.tensor([0] + [len(d) for d in trains]).cumsum(0)[:-1].to(X.device)
    # the last active sets of every sample (warm starts) and whether it was seen, on the data's
    # device (as in TrainState)
    active: torch.Tensor | None = None
    seen = torch.zeros(len(X), dtype=torch.bool, device=X.device)
    for it in range(states[0].steps["adam"], a.iterations):
        eps, lr = phase.eps_at(it), phase.lr_at(it)
        for group in adam.param_groups:
            group["lr"] = lr
        # (K * B,), model-major, on the data's device (TrainState draws its indices there)
        idx = torch.stack([states[k].next_batch(batch) for k in alive])
        rows = (idx + starts[alive][:, None]).reshape(-1)
        x, u, x_next = (T.index_select(0, rows).reshape(len(alive), batch, -1) for T in (X, U, XN))
        warm_start = None if active is None else active.index_select(0, rows).reshape(len(alive), batch, -1)
        warm = seen.index_select(0, rows).reshape(len(alive), batch).all(1)
        if obj.loss == "violation":
            info = violation_losses(ens, x, u, x_next, gamma=obj.gamma, eps=eps,
                                    warm_start=warm_start, warm=warm)
        else:
            info = prediction_losses(ens, x, u, x_next, warm_start=warm_start, warm=warm)
        if active is None:
            active = torch.zeros(len(X), info.active.shape[2], dtype=torch.bool, device=X.device)
        active[rows] = info.active.reshape(len(rows), -1).to(active.device)
        seen[rows] = True
        value = info.loss + obj.reg * (ens.C**2).sum((1, 2))
        adam.zero_grad()
        value.sum().backward()
        adam_update_from_grads(adam)  # the update of fit's steps (on CPU, compiled)
        losses = value.detach().tolist()
        with torch.no_grad():
            finite_F = torch.isfinite(ens.F).all(2).all(1).tolist()
        failed = []
        for j, k in enumerate(alive):
            st = states[k]
            error = divergence(st.iteration + 1, losses[j], finite_F[j], lr, label(k))
            if error is not None:
                if throw:
                    raise error
                errors[k] = error
                failed.append(j)
                continue
            st.steps["adam"] += 1
            st.add(Outcome(losses[j], eps, lr, info.n_fallback[j], info.fallback_residual[j]))
            n = st.steps["adam"]
            if n % phase.record_every == 0 or n == a.iterations:
                ens.copy_to(j, st.model)
                rec = st.record(phase.name(st), eps, lr, elapsed())
                if bar is not None and j == 0:
                    bar.set_postfix(loss=f"{rec['loss']:.3e}")
        if bar is not None:
            bar.update(1)
        if failed:
            keep = [j for j in range(len(alive)) if j not in failed]
            alive = [alive[j] for j in keep]
            if not alive:
                return
            new = ens.select(keep)
            adam, ens = _moved_adam(adam, ens, new, keep), new
    for j, k in enumerate(alive):
        ens.copy_to(j, states[k].model)
