r"""Training an LCS: :func:`fit` minimises ``L(theta) + omega ||C||_F^2`` (paper eq. equ.loss).

Optimisers (``optimizer=``):

- ``"adam"`` -- the paper's protocol (Sec. 5): minibatches of ``batch_size`` (200) drawn at
  random (a fresh permutation every epoch), Adam with ``betas = (0.9, 0.9)``, ``eps = 1e-6``,
  learning rate 1e-3 (the paper's text; the authors' own runs used 5e-3 for the violation loss
  and 1e-3 for the prediction loss -- pass ``lr=5e-3`` to match them). Last iterate unless
  ``keep_best=True``.
- ``"gauss-newton"`` / ``"newton"`` -- Levenberg--Marquardt steps of
  :mod:`lcs_cvx.second_order` on large minibatches (``batch_size``, default 5,000, capped at N):
  the Gauss--Newton matrix with the solution's sensitivity, or Lemma 4's full Hessian with a line
  search. Violation loss only.

Recipes (``recipe=``) are named sets of options; options given explicitly win:

- ``"paper"``: Adam as above, constant learning rate, fixed ``eps``, one run.
- ``"best"``: what this package recommends (see :data:`RECIPES`): Adam from lr 1e-2 on a cosine
  schedule, continuation in ``eps`` (1e-2 -> ``eps`` over the first 60 % of the iterations),
  re-initialisation of saturated units (active on >= 98 % of samples: no gradient reaches their
  boundary), ``min(4, ceil(n_lam / 2))`` extra units during Adam then pruned greedily by
  deletion or elimination (:mod:`lcs_cvx.units`: the escape from the permutation trap) with one
  Gauss--Newton step after each removal, then a Gauss--Newton refinement on batches of 500 --
  4,000 Adam iterations instead of the paper's 10,000 so that the whole fits the paper
  protocol's wall time.

With ``restarts > 1`` the runs start from different initialisations (the first from ``model``),
train on ``1 - holdout`` of the data, and the one with the lowest relative error on the held-out
part is returned.

Checkpoints (``checkpoint=path``) hold the model, the optimiser state, the RNG state, the epoch
permutation and the history; they are written atomically every ``checkpoint_every`` iterations
(and after every second-order step), and ``resume=True`` continues a killed run to exactly the
result of an uninterrupted one (wall times aside).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch

from ._checks import LCSInputError, SolverError
from .data import Dataset
from .io import atomic_write
from .losses import prediction_fast, regularizer, violation_fast
from .metrics import relative_error
from .second_order import gauss_newton_step, newton_step
from .system import LCS, PARAMETER_NAMES
from .units import grow, prune

__all__ = ["FitOptions", "FitResult", "RECIPES", "extra_units", "fit"]

LOSSES = ("violation", "prediction")
OPTIMIZERS = ("adam", "gauss-newton", "newton")
SCHEDULES = ("constant", "cosine")
REFINERS = (None, "gauss-newton", "newton")
CHECKPOINT_FORMAT = 2  # 2: the solver's active sets per sample (warm starts)


@dataclass(frozen=True)
class FitOptions:
    """Every option of :func:`fit` (frozen; unknown names are rejected).

    Attributes:
        loss: ``"violation"`` (eq. equ.contactnet) or ``"prediction"`` (eq. equ.prednet).
        optimizer: ``"adam"``, ``"gauss-newton"`` or ``"newton"``.
        recipe: the recipe these options came from (``"paper"``, ``"best"`` or None).
        gamma, eps: the violation loss's constants (Lemma 2: ``gamma < sigma_min(F + F^T)``).
        reg: ``omega`` of the regulariser ``omega ||C||_F^2``.
        iterations: optimiser iterations (Adam steps, or second-order steps).
        batch_size: minibatch size (second-order: capped at the data size).
        lr, betas, adam_eps: Adam's learning rate, betas and epsilon.
        lr_schedule: ``"constant"`` or ``"cosine"`` (from ``lr`` to ``lr * lr_floor``).
        lr_floor: the cosine schedule's final fraction of ``lr``.
        eps_start: if set, ``eps`` decays geometrically from it to ``eps`` over the first
            ``eps_fraction`` of the iterations (continuation).
        eps_fraction: see ``eps_start``.
        reinit_saturated: re-draw the hyperplane of a unit active on >= 98 % of samples, every
            ``reinit_every`` iterations during the continuation phase.
        reinit_every: see ``reinit_saturated``.
        extra_units: Adam trains ``n_lam + extra_units`` units (``"auto"``: see
            :func:`extra_units`); the extra ones are then pruned
            greedily (:func:`lcs_cvx.units.prune`: deletion or elimination of a unit, scored after
            a least-squares refit of ``(A, B, C, d)``) before the refinement -- the escape from
            the permutation trap of DESIGN.md.
        prune_repair, prune_batch: the pruning's samples (``prune_batch`` of them score the
            candidates) and its Gauss--Newton steps on them after each removal.
        damping: initial Levenberg--Marquardt damping of the second-order steps.
        refine: second-order refinement after Adam: ``None``, ``"gauss-newton"`` or ``"newton"``.
        refine_iterations, refine_batch: its steps and batch size.
        polish_iterations, polish_lr: Adam steps (minibatches of ``batch_size``, constant
            ``polish_lr``) on the prediction loss (eq. equ.prednet) after everything else -- the
            "final polish": the model is then judged by the loss it is used with. 0: none.
        restarts: independent runs; the best on the held-out split is returned.
        holdout: fraction of the data held out to score restarts (only when ``restarts > 1``).
        seed: seed of minibatches, restarts' initialisations and re-initialisations.
        eval_every: iterations between history records (loss, e_test on ``test``).
        checkpoint_every: iterations between checkpoints.
        keep_best: return the iterate with the lowest e_test (on ``test``) instead of the last.
    """

    loss: str = "violation"
    optimizer: str = "adam"
    recipe: str | None = None
    gamma: float = 1e-2
    eps: float = 1e-4
    reg: float = 1e-5
    iterations: int = 10_000
    batch_size: int = 200
    lr: float = 1e-3
    betas: tuple[float, float] = (0.9, 0.9)
    adam_eps: float = 1e-6
    lr_schedule: str = "constant"
    lr_floor: float = 0.01
    eps_start: float | None = None
    eps_fraction: float = 0.6
    reinit_saturated: bool = False
    reinit_every: int = 500
    extra_units: int | str = 0
    prune_repair: int = 1
    prune_batch: int = 1000
    damping: float = 1e-3
    refine: str | None = None
    refine_iterations: int = 20
    refine_batch: int = 5000
    polish_iterations: int = 0
    polish_lr: float = 1e-4
    restarts: int = 1
    holdout: float = 0.1
    seed: int = 0
    eval_every: int = 100
    checkpoint_every: int = 500
    keep_best: bool = False

    def __post_init__(self) -> None:
        def choice(name: str, allowed: Sequence[Any]) -> None:
            if getattr(self, name) not in allowed:
                raise LCSInputError(
                    f"{name}: expected one of {tuple(allowed)}, received {getattr(self, name)!r}"
                )

        choice("loss", LOSSES)
        choice("optimizer", OPTIMIZERS)
        choice("recipe", (None, *RECIPES))
        choice("lr_schedule", SCHEDULES)
        choice("refine", REFINERS)
        for name in ("gamma", "eps", "lr", "adam_eps", "lr_floor", "eps_fraction", "polish_lr"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < math.inf:
                raise LCSInputError(f"{name}: expected a finite number > 0, received {v!r}")
        for name in ("reg", "damping"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v < math.inf:
                raise LCSInputError(f"{name}: expected a finite number >= 0, received {v!r}")
        if self.extra_units != "auto" and (isinstance(self.extra_units, bool)
                                           or not isinstance(self.extra_units, int) or self.extra_units < 0):
            raise LCSInputError(
                f"extra_units: expected an integer >= 0 or 'auto', received {self.extra_units!r}"
            )
        if isinstance(self.prune_repair, bool) or not isinstance(self.prune_repair, int) or self.prune_repair < 0:
            raise LCSInputError(f"prune_repair: expected an integer >= 0, received {self.prune_repair!r}")
        for name in ("iterations", "batch_size", "reinit_every", "refine_iterations", "prune_batch",
                     "refine_batch", "restarts", "eval_every", "checkpoint_every", "polish_iterations"):
            v = getattr(self, name)
            low = 0 if name in ("iterations", "polish_iterations") else 1
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise LCSInputError(f"{name}: expected an integer >= {low}, received {v!r}")
        if self.eps_start is not None and not (
            isinstance(self.eps_start, (int, float)) and self.eps_start >= self.eps
        ):
            raise LCSInputError(
                f"eps_start: expected None or a number >= eps = {self.eps!r}, received {self.eps_start!r}"
            )
        if not 0 < self.holdout < 1:
            raise LCSInputError(f"holdout: expected a fraction in (0, 1), received {self.holdout!r}")
        b = self.betas
        if not (isinstance(b, (tuple, list)) and len(b) == 2 and all(0 <= x < 1 for x in b)):
            raise LCSInputError(f"betas: expected two numbers in [0, 1), received {b!r}")
        if self.extra_units != 0 and (self.optimizer != "adam" or self.refine is None):
            raise LCSInputError(
                "extra_units: the pruned model needs a refinement phase; expected optimizer='adam' "
                f"with refine set, received optimizer={self.optimizer!r}, refine={self.refine!r}"
            )
        if self.loss == "prediction" and (self.optimizer != "adam" or self.refine is not None):
            raise LCSInputError(
                "optimizer: the second-order methods are for the violation loss (Lemma 4); "
                f"received loss='prediction' with optimizer={self.optimizer!r}, refine={self.refine!r}"
            )


#: Named option sets. ``"best"`` was chosen by measurement (see the README's training section).
RECIPES: dict[str, dict[str, Any]] = {
    "paper": {"optimizer": "adam", "lr": 1e-3, "lr_schedule": "constant", "eps_start": None,
              "refine": None, "restarts": 1, "reinit_saturated": False},
    "best": {"optimizer": "adam", "lr": 1e-2, "lr_schedule": "cosine", "eps_start": 1e-2,
             "eps_fraction": 0.6, "reinit_saturated": True, "iterations": 4000, "extra_units": "auto",
             "prune_repair": 1, "refine": "gauss-newton", "refine_iterations": 10, "refine_batch": 500},
}

#: Defaults that depend on the optimiser (applied to options nobody set).
_OPTIMIZER_DEFAULTS: dict[str, dict[str, Any]] = {
    "adam": {},
    "gauss-newton": {"iterations": 50, "batch_size": 5000, "eval_every": 1, "checkpoint_every": 1},
    "newton": {"iterations": 50, "batch_size": 5000, "eval_every": 1, "checkpoint_every": 1},
}


@dataclass(frozen=True)
class FitResult:
    """What :func:`fit` returns.

    Attributes:
        model: the trained model (the same object as the ``model`` argument, updated in place,
            unless ``restarts > 1`` chose another initialisation).
        history: one dict per record: ``iteration``, ``phase`` (``"adam"`` / ``"gauss-newton"`` /
            ``"newton"`` / ``"polish"``), ``loss`` (mean regularised training loss since the last record),
            ``eps``, ``lr``, ``e_test`` (None without ``test``), ``wall_time`` (s), ``restart``.
        settings: the resolved :class:`FitOptions`.
        restart_scores: held-out relative error of each restart (empty with one run).
        wall_time: seconds, summed over resumed pieces.
    """

    model: LCS
    history: list[dict[str, Any]]
    settings: FitOptions
    restart_scores: list[float] = field(default_factory=list)
    wall_time: float = 0.0


def extra_units(option: int | str, n_lam: int) -> int:
    """The extra units Adam trains: ``option``, or for ``"auto"`` ``min(4, ceil(n_lam / 2))``.

    Measured on the training comparison (studies/configs/train_best.toml, 10 seeds each): four
    extra units took n_lam = 8 from one stuck seed in ten (2 extra) to none and n_lam = 20 from a
    mean e_test of ~3e-4 to ~1e-4; at n_lam = 4 they left one seed of ten stuck at 7e-4 after
    pruning (two of the six non-saturated units shared one boundary), which 2 extra units solve.
    """
    return min(4, math.ceil(n_lam / 2)) if option == "auto" else int(option)


def resolve_options(recipe: str | None = None, **options: Any) -> FitOptions:
    """Defaults < optimiser defaults < recipe < explicit options; unknown names are rejected."""
    valid = {f.name for f in dataclasses.fields(FitOptions)}
    unknown = sorted(set(options) - valid)
    if unknown:
        raise LCSInputError(
            f"options: unknown option(s) {unknown}; valid options are {sorted(valid)}"
        )
    if recipe is not None and recipe not in RECIPES:
        raise LCSInputError(f"recipe: expected one of {tuple(RECIPES)}, received {recipe!r}")
    explicit = {**(RECIPES[recipe] if recipe else {}), **{k: v for k, v in options.items()}}
    optimizer = explicit.get("optimizer", "adam")
    base = {k: v for k, v in _OPTIMIZER_DEFAULTS.get(optimizer, {}).items() if k not in explicit}
    return FitOptions(**{**base, **explicit, "recipe": recipe})


# -- checkpoints -------------------------------------------------------------------------------
def _atomic_save(obj: dict, path: str) -> None:
    atomic_write(path, lambda f: torch.save(obj, f), name="checkpoint")


def _load_checkpoint(path: str, opts: FitOptions) -> dict | None:
    if not os.path.exists(path):
        return None
    try:
        ckpt = torch.load(path, weights_only=True)
    except Exception as exc:  # a corrupt file must not be silently overwritten
        raise LCSInputError(f"checkpoint: could not read {path!r}: {exc}") from exc
    if ckpt.get("format") != CHECKPOINT_FORMAT:
        raise LCSInputError(f"checkpoint: {path!r} has format {ckpt.get('format')!r}, expected {CHECKPOINT_FORMAT}")
    saved = ckpt["options"]
    mine = _options_dict(opts)
    if saved != mine:
        diff = sorted(k for k in set(saved) | set(mine) if saved.get(k) != mine.get(k))
        raise LCSInputError(
            f"checkpoint: {path!r} was written with other options (differing: {diff}); "
            "resume with the same options or start afresh with resume=False"
        )
    return ckpt


def _options_dict(opts: FitOptions) -> dict:
    d = dataclasses.asdict(opts)
    d["betas"] = list(d["betas"])
    return d


# -- one run -----------------------------------------------------------------------------------
class _Run:
    """One training run: the Adam phase, then the second-order phase (if any)."""

    def __init__(self, model: LCS, train: Dataset, test: Dataset | None, opts: FitOptions,
                 restart: int) -> None:
        self.model, self.train, self.test, self.opts, self.restart = model, train, test, opts, restart
        self.gen = torch.Generator().manual_seed(opts.seed * 1_000_003 + restart)
        # the model Adam trains: the user's, or a larger one pruned back after the Adam phase
        self.extra = extra_units(opts.extra_units, model.n_lam) if opts.optimizer == "adam" else 0
        self.work = grow(model, self.extra, self.gen) if self.extra else model
        self.adam = torch.optim.Adam(
            self.work.parameters(), lr=opts.lr, betas=tuple(opts.betas), eps=opts.adam_eps
        )
        self.iteration = 0  # Adam iterations done
        self.second = 0  # second-order steps done
        self.polished = 0  # polish steps done (prediction loss, Adam on the final model)
        self.polish_adam = torch.optim.Adam(
            model.parameters(), lr=opts.polish_lr, betas=tuple(opts.betas), eps=opts.adam_eps
        )
        self.perm = torch.randperm(len(train), generator=self.gen)
        self.pos = 0
        self.history: list[dict[str, Any]] = []
        self.damping = opts.damping
        self.best: tuple[float, dict[str, torch.Tensor]] | None = None
        self.acc_loss, self.acc_n = 0.0, 0
        # the fast solver's final active sets per training sample, the warm start of its next
        # visit (from the second epoch on); the loss does not depend on them, the work does
        self.active: torch.Tensor | None = None
        self.seen = torch.zeros(len(train), dtype=torch.bool)

    # state for checkpoints (tensors and plain types only: loadable with weights_only=True)
    def state(self) -> dict:
        grown = self.work is not self.model
        return {
            "model": {k: v.detach().clone() for k, v in self.model.state_dict().items()},
            "work": {k: v.detach().clone() for k, v in self.work.state_dict().items()} if grown else None,
            "adam": self.adam.state_dict() if grown or self.extra == 0 else None,
            "gen": self.gen.get_state(),
            "iteration": self.iteration, "second": self.second, "polished": self.polished,
            "polish_adam": self.polish_adam.state_dict(),
            "perm": self.perm, "pos": self.pos, "history": self.history,
            "damping": self.damping,
            "best": None if self.best is None else {"score": self.best[0], "params": self.best[1]},
            "acc": [self.acc_loss, self.acc_n],
            "active": self.active, "seen": self.seen,
        }

    def load(self, st: dict) -> None:
        self.model.load_state_dict(st["model"])
        if st["work"] is not None:
            self.work.load_state_dict(st["work"])
        else:
            self.work = self.model  # pruned already
        if st["adam"] is not None:
            self.adam.load_state_dict(st["adam"])
        self.gen.set_state(st["gen"])
        self.iteration, self.second, self.polished = st["iteration"], st["second"], st["polished"]
        self.polish_adam.load_state_dict(st["polish_adam"])
        self.perm, self.pos, self.history = st["perm"], st["pos"], st["history"]
        self.damping = st["damping"]
        self.best = None if st["best"] is None else (st["best"]["score"], st["best"]["params"])
        self.acc_loss, self.acc_n = st["acc"]
        self.active, self.seen = st["active"], st["seen"]

    # schedules
    def eps_at(self, it: int) -> float:
        o = self.opts
        if o.eps_start is None:
            return o.eps
        frac = min(1.0, it / max(1.0, o.eps_fraction * o.iterations))
        return o.eps_start * (o.eps / o.eps_start) ** frac

    def lr_at(self, it: int) -> float:
        o = self.opts
        if o.lr_schedule == "constant":
            return o.lr
        c = 0.5 * (1.0 + math.cos(math.pi * it / max(1, o.iterations)))
        return o.lr * (o.lr_floor + (1.0 - o.lr_floor) * c)

    def next_batch(self, size: int) -> torch.Tensor:
        if self.pos + size > len(self.perm):
            self.perm = torch.randperm(len(self.train), generator=self.gen)
            self.pos = 0
        idx = self.perm[self.pos : self.pos + size]
        self.pos += size
        return idx

    def loss(self, idx: torch.Tensor, eps: float) -> torch.Tensor:
        d, m, o = self.train, self.work, self.opts
        x, u, xn = d.x[idx], d.u[idx], d.x_next[idx]
        warm = self.active[idx] if self.active is not None and bool(self.seen[idx].all()) else None
        # the losses' fast paths directly: the data were validated once, by fit
        if o.loss == "violation":
            info = violation_fast(m, x, u, xn, gamma=o.gamma, eps=eps, warm_start=warm)
        else:
            info = prediction_fast(m, x, u, xn, warm_start=warm)
        value, active = info.loss, info.active
        if self.active is None:
            self.active = torch.zeros(len(d), active.shape[1], dtype=torch.bool)
        self.active[idx] = active.to(self.active.device)
        self.seen[idx] = True
        return value + regularizer(m, o.reg)

    def record(self, phase: str, eps: float, lr: float | None, elapsed: float) -> dict:
        e_test = relative_error(self.work, self.test) if self.test is not None else None
        rec = {
            "iteration": self.iteration + self.second + self.polished, "phase": phase,
            "loss": self.acc_loss / max(1, self.acc_n), "eps": eps, "lr": lr,
            "e_test": e_test, "wall_time": elapsed, "restart": self.restart,
        }
        self.acc_loss, self.acc_n = 0.0, 0
        self.history.append(rec)
        tracked = self.work is self.model  # not while a grown model is trained
        if self.opts.keep_best and tracked and e_test is not None and (self.best is None or e_test < self.best[0]):
            self.best = (e_test, {k: getattr(self.model, k).detach().clone() for k in PARAMETER_NAMES})
        return rec

    def reinit_saturated(self) -> None:
        """Re-draw the hyperplane ``(D_i, E_i, c_i)`` and ``C[:, i]`` of units active on >= 98 %
        of a sample of the data, and zero their Adam moments."""
        m = self.work
        idx = self.perm[: min(2000, len(self.perm))]
        with torch.no_grad():
            active = (m.solve_lcp(self.train.x[idx], self.train.u[idx]).lam > 0).to(torch.float64)
            sat = (active.mean(0) >= 0.98).nonzero().squeeze(1)
            if sat.numel() == 0:
                return
            for name, rows in (("D", True), ("E", True), ("c", True), ("C", False)):
                p = getattr(m, name)
                shape = (sat.numel(),) + tuple(p.shape[1:]) if rows else (p.shape[0], sat.numel())
                new = 0.1 * torch.randn(shape, generator=self.gen, dtype=torch.float64).to(p.dtype)
                if rows:
                    p[sat] = new
                else:
                    p[:, sat] = new
                st = self.adam.state.get(p)
                if st:
                    for key in ("exp_avg", "exp_avg_sq"):
                        if rows:
                            st[key][sat] = 0.0
                        else:
                            st[key][:, sat] = 0.0


def _adam_step(run: _Run, adam: torch.optim.Adam, model: LCS, value: torch.Tensor,
               iteration: int, lr: float) -> None:
    """One Adam step on ``value``, accumulated into the run's loss record; a clear error when
    the loss or ``F`` stops being finite."""
    adam.zero_grad()
    value.backward()
    adam.step()
    loss_value = float(value.detach())
    with torch.no_grad():  # F = G G^T + ... overflows first when the parameters blow up
        finite_F = bool(torch.isfinite(model.F).all())
    if not (math.isfinite(loss_value) and finite_F):
        raise SolverError(
            f"training diverged at iteration {iteration}: loss = {loss_value}, "
            f"F {'finite' if finite_F else 'not finite'}; lower lr (now {lr:g})"
        )
    run.acc_loss += loss_value
    run.acc_n += 1


def _run(run: _Run, *, callbacks, checkpoint: str | None, ckpt_extra: Callable[[], dict],
         bar, t_offset: float) -> bool:
    """Train ``run`` to completion (or until a callback asks to stop); returns True if stopped."""
    o, t0 = run.opts, time.perf_counter()

    def elapsed() -> float:
        return t_offset + time.perf_counter() - t0

    def save() -> None:
        if checkpoint is not None:
            _atomic_save({**ckpt_extra(), "run": run.state(), "elapsed": elapsed()}, checkpoint)

    def after_record(rec: dict) -> bool:
        if bar is not None:
            bar.set_postfix(loss=f"{rec['loss']:.3e}",
                            e_test="-" if rec["e_test"] is None else f"{rec['e_test']:.2e}")
        return any(bool(cb(rec, run.model)) for cb in callbacks)

    n_adam = o.iterations if o.optimizer == "adam" else 0
    while run.iteration < n_adam:
        it = run.iteration
        eps, lr = run.eps_at(it), run.lr_at(it)
        for group in run.adam.param_groups:
            group["lr"] = lr
        if o.reinit_saturated and it > 0 and it % o.reinit_every == 0 and it < o.eps_fraction * o.iterations:
            run.reinit_saturated()
        value = run.loss(run.next_batch(min(o.batch_size, len(run.train))), eps)
        _adam_step(run, run.adam, run.work, value, run.iteration + 1, lr)
        run.iteration += 1
        if bar is not None:
            bar.update(1)
        if run.iteration % o.eval_every == 0 or run.iteration == n_adam:
            if after_record(run.record("adam", eps, lr, elapsed())):
                save()
                return True
        if run.iteration % o.checkpoint_every == 0:
            save()
    if run.work is not run.model:  # prune the grown model back to the user's size
        idx = run.next_batch(min(o.prune_batch, len(run.train)))
        d = run.train
        x, u, xn = d.x[idx], d.u[idx], d.x_next[idx]

        def repair(kept: LCS) -> None:  # a few Gauss--Newton steps after each removal
            mu = o.damping
            for _ in range(o.prune_repair):
                mu = gauss_newton_step(kept, x, u, xn, gamma=o.gamma, eps=o.eps, reg=o.reg,
                                       damping=mu).damping

        pruned = prune(run.work, run.model.n_lam, x, u, xn, reg=o.reg,
                       repair=repair if o.prune_repair else None)
        run.model.load_state_dict(pruned.state_dict())
        run.work = run.model
        save()
    method = o.optimizer if o.optimizer != "adam" else o.refine
    n_second = o.iterations if o.optimizer != "adam" else (o.refine_iterations if o.refine else 0)
    size = min(o.batch_size if o.optimizer != "adam" else o.refine_batch, len(run.train))
    step = gauss_newton_step if method == "gauss-newton" else newton_step
    while run.second < n_second:
        idx = run.next_batch(size)
        d = run.train
        res = step(run.model, d.x[idx], d.u[idx], d.x_next[idx], gamma=o.gamma, eps=o.eps,
                   reg=o.reg, damping=run.damping)
        run.damping = res.damping
        run.acc_loss += res.loss
        run.acc_n += 1
        run.second += 1
        if bar is not None:
            bar.update(1)
        if run.second % (o.eval_every if o.optimizer != "adam" else 1) == 0 or run.second == n_second:
            if after_record(run.record(method, o.eps, None, elapsed())):
                save()
                return True
        save()
    while run.polished < o.polish_iterations:
        idx = run.next_batch(min(o.batch_size, len(run.train)))
        d = run.train
        value = prediction_fast(run.model, d.x[idx], d.u[idx], d.x_next[idx]).loss
        value = value + regularizer(run.model, o.reg)
        _adam_step(run, run.polish_adam, run.model, value,
                   run.iteration + run.second + run.polished + 1, o.polish_lr)
        run.polished += 1
        if bar is not None:
            bar.update(1)
        if run.polished % o.eval_every == 0 or run.polished == o.polish_iterations:
            if after_record(run.record("polish", o.eps, o.polish_lr, elapsed())):
                save()
                return True
        if run.polished % o.checkpoint_every == 0:
            save()
    save()
    return False


def _check_data(name: str, data: Any, model: LCS) -> Dataset:
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
    if data.x.device == model.device and data.x.dtype == model.dtype:
        return data
    kw = {"device": model.device, "dtype": model.dtype}
    return Dataset(data.x.to(**kw), data.u.to(**kw), data.x_next.to(**kw),
                   None if data.lam is None else data.lam.to(**kw))


def fit(
    model: LCS,
    train: Dataset,
    *,
    test: Dataset | None = None,
    recipe: str | None = None,
    callbacks: Sequence[Callable[[dict, LCS], Any]] = (),
    checkpoint: str | os.PathLike | None = None,
    resume: bool = False,
    progress: bool = True,
    **options: Any,
) -> FitResult:
    """Learn the LCS ``model`` from ``train`` (in place); see the module docstring.

    Args:
        model: an :class:`lcs_cvx.LCS`, the initialisation (float64 recommended).
        train: :class:`lcs_cvx.Dataset` of transitions.
        test: optional dataset; its relative error (the paper's e_test) is recorded every
            ``eval_every`` iterations and drives ``keep_best``.
        recipe: ``"paper"``, ``"best"`` or None (options as given).
        callbacks: ``cb(record, model)`` after every history record; a true return value stops
            training (a checkpoint is written first).
        checkpoint: path of the checkpoint file (written atomically; not a model file -- use
            :func:`lcs_cvx.save_model` for that).
        resume: continue from ``checkpoint`` if it exists (the options must be the same).
        progress: a tqdm bar on stderr when it is a terminal.
        **options: any field of :class:`FitOptions` (``loss``, ``optimizer``, ``gamma``, ``eps``,
            ``reg``, ``iterations``, ``batch_size``, ``lr``, ``seed``, ...).

    Returns:
        :class:`FitResult`.

    Example:
        >>> import lcs_cvx
        >>> truth = lcs_cvx.random_lcs(2, 1, 2, seed=0)
        >>> data = lcs_cvx.make_dataset(truth, 500, seed=1)
        >>> model = lcs_cvx.LCS(2, 1, 2, seed=2)
        >>> result = lcs_cvx.fit(model, data, optimizer="gauss-newton", iterations=5, progress=False)
        >>> len(result.history)
        5
    """
    if not isinstance(model, LCS):
        raise LCSInputError(f"model: expected an lcs_cvx.LCS, received {type(model).__name__}")
    opts = resolve_options(recipe, **options)
    train = _check_data("train", train, model)
    test = _check_data("test", test, model) if test is not None else None
    path = os.fspath(checkpoint) if checkpoint is not None else None
    ckpt = _load_checkpoint(path, opts) if (path is not None and resume) else None

    fit_data, holdout = train, None
    if opts.restarts > 1:
        fit_data, holdout = train.split(1.0 - opts.holdout, seed=opts.seed)
    initial = copy.deepcopy(model.state_dict())
    done: list[dict] = [] if ckpt is None else ckpt["done"]
    t_offset = 0.0 if ckpt is None else ckpt["elapsed"]
    total = opts.restarts * (
        (opts.iterations if opts.optimizer == "adam" else 0)
        + (opts.iterations if opts.optimizer != "adam" else (opts.refine_iterations if opts.refine else 0))
        + opts.polish_iterations
    )
    use_bar = progress and sys.stderr.isatty()
    bar = None
    if use_bar:
        from tqdm.auto import tqdm

        bar = tqdm(total=total, desc="fit", unit="it", dynamic_ncols=True)
    t_start = time.perf_counter()
    history: list[dict] = [h for d in done for h in d["history"]]
    stopped = False
    try:
        for r in range(len(done), opts.restarts):
            if r == 0:
                model.load_state_dict(initial)
            else:
                fresh = LCS(model.n_x, model.n_u, model.n_lam, stiffness=float(model.stiffness),
                            seed=opts.seed * 7919 + r, dtype=model.dtype).to(model.device)
                model.load_state_dict(fresh.state_dict())
            run = _Run(model, fit_data, test, opts, r)
            if ckpt is not None and ckpt.get("restart") == r and ckpt.get("run") is not None:
                run.load(ckpt["run"])
                if bar is not None:
                    bar.update(run.iteration + run.second)

            def extra(r=r) -> dict:
                return {"format": CHECKPOINT_FORMAT, "options": _options_dict(opts), "restart": r,
                        "done": done}

            stopped = _run(run, callbacks=callbacks, checkpoint=path, ckpt_extra=extra, bar=bar,
                           t_offset=t_offset + time.perf_counter() - t_start)
            if opts.keep_best and run.best is not None:
                with torch.no_grad():
                    for k, v in run.best[1].items():
                        getattr(model, k).copy_(v)
            score = relative_error(model, holdout) if holdout is not None else math.nan
            done.append({"score": score, "history": run.history,
                         "params": {k: v.detach().clone() for k, v in model.state_dict().items()}})
            history.extend(run.history)
            if stopped:
                break
    finally:
        if bar is not None:
            bar.close()
    scores = [d["score"] for d in done] if opts.restarts > 1 else []
    if done:  # the chosen run (also when a resumed checkpoint had finished them all)
        best = min(range(len(done)), key=lambda i: done[i]["score"]) if opts.restarts > 1 else -1
        model.load_state_dict(done[best]["params"])
    if path is not None and not stopped:
        _atomic_save({"format": CHECKPOINT_FORMAT, "options": _options_dict(opts),
                      "restart": opts.restarts, "done": done, "run": None,
                      "elapsed": t_offset + time.perf_counter() - t_start}, path)
    return FitResult(model, history, opts, scores, t_offset + time.perf_counter() - t_start)
