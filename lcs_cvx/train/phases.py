r"""The phases of a training run, each one step at a time; :func:`run_phases` is their one loop.

A phase says how many steps it makes (:meth:`Phase.length`), makes one (:meth:`Phase.step`,
which returns an :class:`~lcs_cvx.train.state.Outcome`), and how often its steps are recorded and
checkpointed. Recording, checkpoints, callbacks and the progress bar live in :func:`run_phases`
alone.

- :class:`AdamPhase` -- minibatch Adam on ``L(theta) + omega ||C||_F^2`` (eq. (4)) with the
  schedules of :class:`~lcs_cvx.train.phase_options.AdamOptions`.
- :class:`PrunePhase` -- one step: the grown model cut back to ``n_lam`` units
  (:func:`lcs_cvx.resizing.prune_units`), a few Gauss--Newton steps after each removal.
- :class:`RefinePhase` -- Levenberg--Marquardt steps (:mod:`lcs_cvx.second_order`, Lemma 4).
- :class:`PolishPhase` -- Adam on the prediction loss (eq. (6)).
- :class:`RolloutPhase` -- Adam on the simulation error of ``H``-step windows of the training
  trajectories (:mod:`lcs_cvx.simulation_error`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from .._checks import SolverError
from .._kernels.calls import MIN_CHUNK
from ..losses import prediction_fast, regularizer, violation_fast
from ..parameter_constraints import free_entries, mask_gradients_, project_
from ..per_sample import model_loss_info
from ..resizing import prune_units
from ..second_order import gauss_newton_step, newton_step
from ..simulation_error import simulation_error
from ..system import LCS
from .onecall import adam_step, adam_steps, adam_update_from_grads
from .options import FitOptions
from .state import Outcome, TrainState

__all__ = ["AdamPhase", "PrunePhase", "RefinePhase", "PolishPhase", "RolloutPhase", "phases", "run_phases", "divergence"]


def _adam_step(adam: torch.optim.Adam, model: LCS, value: torch.Tensor, iteration: int,
               lr: float) -> float:
    """One Adam step on ``value``; a clear error once the loss or ``F`` is no longer finite
    (``F = G G^T + ...`` overflows first when the parameters blow up). Fixed parameters get no
    gradient; masked entries get a zero one and are held at 0 (:mod:`lcs_cvx.parameter_constraints`)."""
    adam.zero_grad()
    value.backward()
    lcs = isinstance(model, LCS)
    if lcs:
        mask_gradients_(model)
    adam_update_from_grads(adam)
    if lcs:
        project_(model)
    loss = float(value.detach())
    with torch.no_grad():  # a model of per-sample matrices: its parameters finite
        finite_F = bool(torch.isfinite(model.F).all()) if lcs else all(
            bool(torch.isfinite(p).all()) for p in model.parameters())
    _check_divergence(iteration, loss, finite_F, lr)
    return loss


def fast_loss(kind: str, model: Any, x: torch.Tensor, u: torch.Tensor, x_next: torch.Tensor, *, gamma: float,
              eps: float, warm_start: torch.Tensor | None = None, threads: int | None = None) -> Any:
    """The fast violation (``kind="violation"``) or prediction loss of ``model``: an
    :class:`lcs_cvx.LCS`'s (:func:`lcs_cvx.losses.violation_fast`, ``prediction_fast``), or a
    model of per-sample matrices' (``model.sample_lcs``: :mod:`lcs_cvx.per_sample`)."""
    if not isinstance(model, LCS):
        return model_loss_info(kind, model, x, u, x_next, gamma=gamma, eps=eps, warm_start=warm_start)
    if kind == "violation":
        return violation_fast(model, x, u, x_next, gamma=gamma, eps=eps, warm_start=warm_start, threads=threads)
    return prediction_fast(model, x, u, x_next, warm_start=warm_start, threads=threads)


def _check_divergence(iteration: int, loss: float, finite_F: bool, lr: float) -> None:
    error = divergence(iteration, loss, finite_F, lr)
    if error is not None:
        raise error


def divergence(iteration: int, loss: float, finite_F: bool, lr: float, label: str = "") -> SolverError | None:
    """The :class:`lcs_cvx.SolverError` of a step whose loss is not finite or whose ``F`` is not
    (None when both are); ``label`` prefixes the message (a model of an ensemble)."""
    if math.isfinite(loss) and finite_F:
        return None
    return SolverError(
        f"{label}training diverged at iteration {iteration}: loss = {loss}, "
        f"F {'finite' if finite_F else 'not finite'}; lower lr (now {lr:g})"
    )


class Phase:
    """A phase of a run. ``key`` names its step counter in :attr:`TrainState.steps`."""

    key: str = ""
    #: steps between history records (None: the phase is not recorded) and between checkpoints
    record_every: int | None = None
    checkpoint_every: int = 1
    #: whether its steps count on the progress bar
    counted: bool = True

    def __init__(self, options: FitOptions) -> None:
        self.options = options

    def name(self, state: TrainState) -> str:
        """The ``phase`` of its history records."""
        return self.key

    def length(self, state: TrainState) -> int:
        raise NotImplementedError

    def step(self, state: TrainState) -> Outcome:
        raise NotImplementedError

    def steps(self, state: TrainState, limit: int) -> list[Outcome]:
        """At least one and at most ``limit`` steps (default: one, :meth:`step`)."""
        return [self.step(state)]


class AdamPhase(Phase):
    """Minibatch Adam with the learning-rate and ``eps`` schedules, re-initialisation of
    saturated units, and the fast solver warm-started from each sample's last active sets."""

    key = "adam"

    def __init__(self, options: FitOptions) -> None:
        super().__init__(options)
        self.record_every = options.run.eval_every
        self.checkpoint_every = options.run.checkpoint_every
        self.per_sample = False  # a model of per-sample matrices: no units to re-draw

    def length(self, state: TrainState) -> int:
        self.per_sample = not isinstance(state.work, LCS)
        return self.options.adam.iterations

    def eps_at(self, it: int) -> float:
        """Continuation: ``eps`` decays geometrically from ``eps_start`` over ``eps_fraction``."""
        a, eps = self.options.adam, self.options.objective.eps
        if a.eps_start is None:
            return eps
        frac = min(1.0, it / max(1.0, a.eps_fraction * a.iterations))
        return a.eps_start * (eps / a.eps_start) ** frac

    def lr_at(self, it: int) -> float:
        a = self.options.adam
        if a.lr_schedule == "constant":
            return a.lr
        c = 0.5 * (1.0 + math.cos(math.pi * it / max(1, a.iterations)))
        return a.lr * (a.lr_floor + (1.0 - a.lr_floor) * c)

    def _reinit_at(self, it: int) -> bool:
        a = self.options.adam
        return a.reinit_saturated and not self.per_sample and it > 0 and it % a.reinit_every == 0 and it < a.eps_fraction * a.iterations

    def steps(self, state: TrainState, limit: int) -> list[Outcome]:
        """Up to ``limit`` steps in one compiled call (:func:`lcs_cvx.train.onecall.adam_steps`,
        the numbers of :meth:`step`'s, bit for bit), up to the next re-initialisation of
        saturated units; one :meth:`step` where that does not apply (another dtype or device,
        the first step, a re-initialisation, a minibatch solved in parts) or where the first
        step's minibatch needs the reference solvers."""
        a, obj = self.options.adam, self.options.objective
        it0 = state.steps["adam"]
        size = min(a.batch_size, len(state.train))
        if (state.arrays is None or state.active is None or limit < 2 or self._reinit_at(it0)
                or size >= 2 * MIN_CHUNK):  # a minibatch solved in parts (calls.chunks): one step a call
            return [self.step(state)]
        limit = next((j for j in range(1, limit) if self._reinit_at(it0 + j)), limit)
        before = (state.perm, state.pos, state.generator.get_state())
        rows = np.stack([state.next_batch(size).numpy() for _ in range(limit)])
        eps = [self.eps_at(it0 + j) for j in range(limit)]
        lr = [self.lr_at(it0 + j) for j in range(limit)]
        active, seen = state.warm_tables()
        done = adam_steps(state.adam, state.work, obj.loss, state.arrays, rows, active, seen, gamma=obj.gamma,
                          eps=eps, lr=lr, reg=obj.reg)
        n = 0 if done is None else done[0]
        if n < limit:  # the minibatches of the steps not made are drawn again by the next steps
            state.perm, state.pos = before[0], before[1]
            state.generator.set_state(before[2])
            for _ in range(n):
                state.next_batch(size)
        if n == 0:
            return [self.step(state)]
        _, losses, diverged = done
        if diverged:
            with torch.no_grad():
                finite_F = bool(torch.isfinite(state.work.F).all())
            _check_divergence(state.iteration + n, float(losses[n - 1]), finite_F, lr[n - 1])
        return [Outcome(float(losses[j]), eps[j], lr[j]) for j in range(n)]

    def step(self, state: TrainState) -> Outcome:
        a, obj = self.options.adam, self.options.objective
        it = state.steps["adam"]
        eps, lr = self.eps_at(it), self.lr_at(it)
        for group in state.adam.param_groups:
            group["lr"] = lr
        if self._reinit_at(it):
            reinit_saturated(state)
        idx = state.next_batch(min(a.batch_size, len(state.train)))
        if state.arrays is not None:  # one call: loss, gradient and update without autograd, on
            # the minibatch's rows where they lie, the active sets read from and written to the tables
            width = state.work.n_lam * (2 if obj.loss == "violation" else 1)
            done = adam_step(state.adam, state.work, obj.loss, *state.arrays, None, gamma=obj.gamma, eps=eps,
                             reg=obj.reg, threads=state.threads, rows=idx.numpy(),
                             tables=state.warm_tables(width))
            if done is not None:
                loss, finite_F, _ = done
                _check_divergence(state.iteration + 1, loss, finite_F, lr)
                return Outcome(loss, eps, lr)
        x, u, x_next = state.batch(idx)
        info = fast_loss(obj.loss, state.work, x, u, x_next, gamma=obj.gamma, eps=eps,
                         warm_start=state.warm_start(idx), threads=state.threads)
        state.remember(idx, info.active)
        value = info.loss + regularizer(state.work, obj.reg)
        loss = _adam_step(state.adam, state.work, value, state.iteration + 1, lr)
        return Outcome(loss, eps, lr, info.n_fallback, info.fallback_residual)


def draw(shape: tuple[int, ...], generator: torch.Generator, like: torch.Tensor,
         scale: float = 0.1) -> torch.Tensor:
    """``scale * N(0, 1)`` of ``shape`` on ``like``'s device and dtype, drawn on ``generator``
    (a CPU generator: the run's, :class:`~lcs_cvx.train.state.TrainState`) in float64 and then
    moved, so that a run draws the same numbers on every device and dtype."""
    return (scale * torch.randn(shape, generator=generator, dtype=torch.float64)).to(
        device=like.device, dtype=like.dtype)


def reinit_saturated(state: TrainState) -> None:
    """Re-draw the hyperplane ``(D_i, E_i, c_i)`` and ``C[:, i]`` of the units active on >= 98 %
    of a sample of the data (no gradient reaches their boundary) and zero their Adam moments.
    Only free entries are re-drawn (fixed parameters and masked entries keep their values)."""
    m = state.work
    idx = state.perm[: min(2000, len(state.perm))]
    with torch.no_grad():
        lam = m.solve_lcp(state.train.x[idx], state.train.u[idx]).lam
        sat = ((lam > 0).to(torch.float64).mean(0) >= 0.98).nonzero().squeeze(1)
        if sat.numel() == 0:
            return
        for name, rows in (("D", True), ("E", True), ("c", True), ("C", False)):
            p = getattr(m, name)
            shape = (sat.numel(),) + tuple(p.shape[1:]) if rows else (p.shape[0], sat.numel())
            new = draw(shape, state.generator, p)
            free = free_entries(m, name)
            if rows:
                p[sat] = torch.where(free[sat], new, p[sat])
            else:
                p[:, sat] = torch.where(free[:, sat], new, p[:, sat])
            moments = state.adam.state.get(p)
            for key in ("exp_avg", "exp_avg_sq") if moments else ():
                if rows:
                    moments[key][sat] = 0.0
                else:
                    moments[key][:, sat] = 0.0


class PrunePhase(Phase):
    """One step: the grown model pruned back to the user's ``n_lam`` units (deletion or
    elimination, scored after a least-squares refit; :func:`lcs_cvx.resizing.prune_units`), then loaded
    into the user's model. Not recorded itself (its repair steps' fallbacks count in the next
    record); checkpointed after."""

    key = "prune"
    counted = False

    def length(self, state: TrainState) -> int:
        return int(state.work is not state.model)

    def step(self, state: TrainState) -> Outcome:
        o = self.options
        x, u, x_next = state.batch(state.next_batch(min(o.prune.batch_size, len(state.train))))

        fallbacks = [0, 0.0]  # of the repair steps' solves, counted in the next record

        def repair(kept: LCS) -> None:  # Gauss--Newton steps after each removal
            mu = o.refine.damping
            for _ in range(o.prune.repair):
                res = gauss_newton_step(kept, x, u, x_next, gamma=o.objective.gamma,
                                        eps=o.objective.eps, reg=o.objective.reg, damping=mu)
                mu = res.damping
                fallbacks[0] += res.n_fallback
                fallbacks[1] = max(fallbacks[1], res.fallback_residual)

        pruned = prune_units(state.work, state.model.n_lam, x, u, x_next, reg=o.objective.reg,
                             repair=repair if o.prune.repair else None, lookahead=o.prune.lookahead)
        state.model.load_state_dict(pruned.state_dict())
        state.work = state.model
        return Outcome(None, o.objective.eps, None, fallbacks[0], fallbacks[1])


class RefinePhase(Phase):
    """Levenberg--Marquardt steps on large batches: Gauss--Newton with the solution's
    sensitivity, or damped Newton with Lemma 4's Hessian. Checkpointed after every step."""

    key = "refine"

    def __init__(self, options: FitOptions) -> None:
        super().__init__(options)
        self.record_every = options.refine.record_every

    def name(self, state: TrainState) -> str:
        return str(self.options.refine.method)

    def length(self, state: TrainState) -> int:
        r = self.options.refine
        return r.iterations if r.method is not None else 0

    def step(self, state: TrainState) -> Outcome:
        r, obj = self.options.refine, self.options.objective
        step = gauss_newton_step if r.method == "gauss-newton" else newton_step
        x, u, x_next = state.batch(state.next_batch(min(r.batch_size, len(state.train))))
        res = step(state.model, x, u, x_next, gamma=obj.gamma, eps=obj.eps, reg=obj.reg,
                   damping=state.damping)
        state.damping = res.damping
        return Outcome(res.loss, obj.eps, None, res.n_fallback, res.fallback_residual)


class PolishPhase(Phase):
    """Adam on the prediction loss (eq. (6)) of the final model, constant learning rate."""

    key = "polish"

    def __init__(self, options: FitOptions) -> None:
        super().__init__(options)
        self.record_every = options.run.eval_every
        self.checkpoint_every = options.run.checkpoint_every

    def length(self, state: TrainState) -> int:
        return self.options.polish.iterations

    def step(self, state: TrainState) -> Outcome:
        p, obj = self.options.polish, self.options.objective
        idx = state.next_batch(min(p.batch_size, len(state.train)))
        if state.arrays is not None:  # one call, as Adam's steps
            done = adam_step(state.polish_adam, state.model, "prediction", *state.arrays, None, gamma=obj.gamma,
                             eps=obj.eps, reg=obj.reg, threads=state.threads, rows=idx.numpy())
            if done is not None:
                loss, finite_F, _ = done
                _check_divergence(state.iteration + 1, loss, finite_F, p.lr)
                return Outcome(loss, obj.eps, p.lr)
        info = fast_loss("prediction", state.model, *state.batch(idx), gamma=obj.gamma, eps=obj.eps,
                         threads=state.threads)
        value = info.loss + regularizer(state.model, obj.reg)
        loss = _adam_step(state.polish_adam, state.model, value, state.iteration + 1, p.lr)
        return Outcome(loss, obj.eps, p.lr, info.n_fallback, info.fallback_residual)


class RolloutPhase(Phase):
    """Adam on the simulation error (:func:`lcs_cvx.simulation_error.simulation_error`) of
    ``batch_size`` windows of ``H`` steps drawn at random from the training trajectories,
    constant learning rate. Recorded and checkpointed as the polish. With ``keep_best`` it starts
    from the best iterate so far (the model the run would otherwise return). With a held-out
    part, the model before the phase comes back at its end unless the held-out score fell
    (``state.rollout_kept``)."""

    key = "rollout"

    def __init__(self, options: FitOptions) -> None:
        super().__init__(options)
        self.record_every = options.run.eval_every
        self.checkpoint_every = options.run.checkpoint_every

    def length(self, state: TrainState) -> int:
        return self.options.rollout.iterations if state.windows is not None else 0

    def step(self, state: TrainState) -> Outcome:
        ro, obj = self.options.rollout, self.options.objective
        if state.steps["rollout"] == 0:
            if state.options.run.keep_best:  # refine the model a run would return, its best so far
                state.restore_best()
            if state.validate is not None:
                state.rollout_start = (state.validate(state.model), _parameters(state.model))
        w = state.windows
        idx = torch.randint(len(w), (min(ro.batch_size, len(w)),), generator=state.generator)
        kw = {"dtype": state.model.dtype, "device": state.model.device}
        x0, us, xs = (t.to(**kw) for t in w.batch(idx))
        value = (simulation_error(state.model, x0, us, xs, state.scaling, state.kinematics, sigma=state.rollout_sigma)
                 + regularizer(state.model, obj.reg))
        loss = _adam_step(state.rollout_adam, state.model, value, state.iteration + 1, ro.lr)
        if state.steps["rollout"] + 1 == ro.iterations and state.rollout_start is not None:
            before, params = state.rollout_start  # kept only where it pays on held-out data
            state.rollout_kept = state.validate(state.model) < before
            if not state.rollout_kept:
                with torch.no_grad():
                    for name, value in params.items():
                        getattr(state.model, name).copy_(value)
        return Outcome(loss, obj.eps, ro.lr)


def _parameters(model: LCS) -> dict[str, torch.Tensor]:
    return {name: p.detach().clone() for name, p in model.named_parameters()}


def phases(options: FitOptions) -> list[Phase]:
    """The phases of a run, in order."""
    return [AdamPhase(options), PrunePhase(options), RefinePhase(options), PolishPhase(options),
            RolloutPhase(options)]


def run_phases(
    state: TrainState,
    *,
    callbacks: Sequence[Callable[[dict, LCS], Any]],
    save: Callable[[], None],
    elapsed: Callable[[], float],
    bar: Any = None,
) -> bool:
    """Run ``state``'s phases to the end, or until a callback asks to stop (then True).

    The one loop: after each step it accumulates the step's outcome, advances the progress bar,
    closes a history record every ``record_every`` steps of the phase (and at its last step) and
    hands it to the callbacks, and writes a checkpoint (``save``) every ``checkpoint_every``
    steps, when a callback stops the run, and at the end."""
    for phase in phases(state.options):
        n = phase.length(state)
        while state.steps[phase.key] < n:
            # the steps up to the next record, checkpoint or the phase's end, which a phase may
            # make in one call
            k = state.steps[phase.key]
            stop = min([n] + [(k // every + 1) * every for every in (phase.record_every, phase.checkpoint_every)
                              if every])
            for out in phase.steps(state, stop - k):
                state.steps[phase.key] += 1
                k = state.steps[phase.key]
                state.add(out)
                if bar is not None and phase.counted:
                    bar.update(1)
            if phase.record_every is not None and (k % phase.record_every == 0 or k == n):
                rec = state.record(phase.name(state), out.eps, out.lr, elapsed())
                if bar is not None:
                    bar.set_postfix({k: f"{rec[k]:.3e}" for k in ("loss", "heldout", "e_test")
                                     if rec[k] is not None})
                if any(bool(cb(rec, state.model)) for cb in callbacks):
                    save()
                    return True
            if k % phase.checkpoint_every == 0 or phase.record_every is None:
                save()
    save()
    return False
