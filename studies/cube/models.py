r"""The models of the cube study (:mod:`studies.cube.study`), each fitted on the training tosses of
one size and chosen on the validation tosses.

A model spec (:class:`Spec`) has a name, a ``fit(train, validation, budget, path)`` that returns a
*stepper* (``x (N, 13) -> x'``, :data:`studies.cube.metrics.Stepper`) and a dict of what was chosen
and how long it took, and a ``load(path)`` that rebuilds the stepper from the cached file. The
specs, in the order of the tables (:func:`specs`):

- ``affine LS``: ``x' = W [x; 1]``, least squares (:func:`lcs_cvx.metrics.affine_lstsq`);
- ``MLP``: ``x' = x + s * MLP((x - mu) / sigma)`` (:class:`ResidualMLP`; ``mu``, ``sigma`` the
  training states' mean and spread, ``s`` the spread of the training increments), trained with
  AdamW on the mean squared normalised increment error, early stopping on the validation tosses'
  one-step error; one fit per point of the grid :data:`MLP_GRID`, the one with the lowest
  validation rollout error (:func:`validation_score`) kept;
- ``constant increment``: ``x' = x + m``, ``m`` the mean training increment (where
  :func:`lcs_cvx.fit` starts; no dynamics at all);
- ``LCS``: :func:`lcs_cvx.select_n_lam` over ``n_lam`` in :data:`N_LAMS` on the training tosses as
  :class:`lcs_cvx.Trajectories`, the validation tosses as ``validation`` with the rollout score
  at :data:`VALIDATION_HORIZON` steps (``holdout_horizon``), and the library's defaults otherwise:
  the simulation-error phase and the best iterate by that score, both ``fit``'s defaults on
  trajectories with a held-out part;
- ``LCS, known structure``: the same with the structure a user knows of a tossed cube
  (:func:`structured_lcs`);
- ``LCS, one-step losses only``: ``LCS`` without the simulation-error phase
  (``rollout_horizon=None``), at the ``n_lam`` ``LCS`` chose at the same size (one fit instead
  of one per candidate; all of :data:`N_LAMS` when that cell has no record): what the phase buys;
- ``LCS, known kinematics``: ``LCS`` with ``p`` and ``q`` integrated exactly and gravity held
  (:func:`studies.cube.kinematic.kinematic_lcs`);
- ``LCS, contact coordinates``: the same on the state with the up coordinates, its first units
  started at the corner heights, ``n_lam`` among
  :data:`studies.cube.kinematic.CONTACT_N_LAMS` (:func:`studies.cube.kinematic.contact_lcs`);
- ``LCS, cube symmetry``: the contact LCS stepped in the body frame whose ``+z`` face points most
  upwards (one of the cube's symmetries per state), fitted on the tosses cut where that frame
  changes, the contact rows seeing the orientation only through the up coordinates
  (:mod:`studies.cube.symmetry`).
"""

from __future__ import annotations

import json
import math
import os
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

import lcs_cvx
from lcs_cvx.datasets import CUBE_DT
from lcs_cvx.metrics import AffineMap, affine_lstsq

from . import kinematic, rigid, symmetry
from .metrics import Stepper

__all__ = ["Spec", "specs", "structured_lcs", "ResidualMLP", "validation_score",
           "N_LAMS", "MLP_GRID", "GRAVITY", "VALIDATION_HORIZON", "Budget"]

#: Candidates for ``n_lam``.
N_LAMS = (2, 4, 8)
#: The MLP grid: hidden layer widths and AdamW weight decay.
MLP_GRID = tuple({"hidden": h, "weight_decay": wd} for h in ((64, 64), (128, 128, 128)) for wd in (0.0, 1e-4))
#: Standard gravity (m/s^2): the known offset of the structured LCS.
GRAVITY = 9.81
#: The validation rollout horizon every model is chosen by (steps).
VALIDATION_HORIZON = 30
EMPTY_U = torch.zeros(0, 0, dtype=torch.float64)


@dataclass(frozen=True)
class Budget:
    """How long each model trains: LCS Adam iterations per candidate, the simulation-error phase's
    steps and window (None: :func:`lcs_cvx.fit`'s defaults; the window is 10 steps, the one the
    study's records were fitted with, where ``fit``'s ``"auto"`` would now take the
    ``holdout_horizon`` of 30), MLP steps and evaluation interval, the validation rollout's
    window stride."""

    lcs_iterations: int = 10_000
    rollout_iterations: int | None = None
    rollout_horizon: int | None = 10
    mlp_steps: int = 8000
    mlp_eval_every: int = 100
    mlp_patience: int = 15
    mlp_batch: int = 256
    n_lams: tuple[int, ...] = N_LAMS
    mlp_grid: tuple[dict[str, Any], ...] = MLP_GRID
    val_stride: int = 2
    rigid_iterations: int = 300
    rigid_rollout_iterations: int = 400
    rigid_lr: float = 3e-3
    rigid_eval_every: int = 100
    rigid_val_tosses: int = 20
    rigid_friction_directions: int = 8


#: The smoke run's budgets (a check in about a minute).
SMOKE_BUDGET = Budget(lcs_iterations=60, rollout_iterations=10, rollout_horizon=5, mlp_steps=100,
                      mlp_eval_every=50, n_lams=(2, 4), mlp_grid=(MLP_GRID[0],), val_stride=1,
                      rigid_iterations=10, rigid_rollout_iterations=4, rigid_eval_every=5, rigid_val_tosses=4,
                      rigid_friction_directions=4)


@dataclass(frozen=True)
class Spec:
    """A model of the study: ``fit(train, validation, budget, path) -> (stepper, info)`` writes
    the fitted model to ``path`` (its file, extension included); ``load(path) -> stepper``."""

    name: str
    key: str
    ext: str
    fit: Callable[..., tuple[Stepper, dict[str, Any]]]
    load: Callable[[str], Stepper]
    #: the key of the spec whose chosen ``n_lam`` this one reuses at the same size, if any
    twin: str | None = None


# ----------------------------------------------------------------------------- shared
class _Wrapped:
    """A stepper as a model :func:`lcs_cvx.rollout_error` accepts (``step(x, u)``, ``n_x``, ...)."""

    n_x, n_u, dtype, device = 13, 0, torch.float64, torch.device("cpu")

    def __init__(self, step: Stepper) -> None:
        self._step = step

    def step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return self._step(x)


def validation_score(step: Stepper, val: lcs_cvx.Trajectories, stride: int = 1) -> float:
    """The validation rollout error by which every model is chosen: :func:`lcs_cvx.rollout_error`
    at :data:`VALIDATION_HORIZON` steps on the validation tosses (every ``stride``-th toss); inf
    when the rollouts produce NaN/inf or the stepper raises."""
    if stride > 1:
        idx = range(0, len(val), stride)
        val = lcs_cvx.Trajectories([val.xs[i] for i in idx], [val.us[i] for i in idx])
    try:
        with torch.no_grad():
            e = lcs_cvx.rollout_error(_Wrapped(step), val, VALIDATION_HORIZON)[VALIDATION_HORIZON]
    except Exception:  # noqa: BLE001 - a model whose rollout fails is never chosen
        return math.inf
    return e if math.isfinite(e) else math.inf


# ----------------------------------------------------------------------------- affine
def _fit_affine(train: lcs_cvx.Trajectories, val: lcs_cvx.Trajectories, budget: Budget, path: str
                ) -> tuple[Stepper, dict[str, Any]]:
    t0 = time.perf_counter()
    W = affine_lstsq(train.to_transitions()).W
    np.savez(path, W=W.numpy())
    step = _affine_step(W)
    return step, {"wall": time.perf_counter() - t0, "val_rollout": validation_score(step, val, budget.val_stride)}


def _affine_step(W: torch.Tensor) -> Stepper:
    amap = AffineMap(W)
    return lambda x: amap.step(x, x.new_zeros(x.shape[0], 0))


def _load_affine(path: str) -> Stepper:
    with np.load(path) as f:
        return _affine_step(torch.from_numpy(f["W"]))


# ----------------------------------------------------------------------------- MLP
class ResidualMLP(nn.Module):
    """``x' = x + s * net((x - mu) / sigma)`` with a tanh MLP ``net`` (float32 inside)."""

    def __init__(self, mu: torch.Tensor, sigma: torch.Tensor, s: torch.Tensor, hidden: tuple[int, ...]) -> None:
        super().__init__()
        # copies: ``.float()`` of a float32 tensor is the tensor itself, and buffers sharing one
        # tensor would each load the last one's values
        self.register_buffer("mu", mu.float().clone())
        self.register_buffer("sigma", sigma.float().clone())
        self.register_buffer("s", s.float().clone())
        dims = (13, *hidden)
        layers: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:], strict=True):
            layers += [nn.Linear(a, b), nn.Tanh()]
        layers.append(nn.Linear(dims[-1], 13))
        self.net = nn.Sequential(*layers)
        self.hidden = tuple(hidden)

    def increment(self, x: torch.Tensor) -> torch.Tensor:
        """The normalised increment ``(x' - x) / s``."""
        return self.net((x.float() - self.mu) / self.sigma)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + (self.s * self.increment(x)).to(x.dtype)


def _train_mlp(train: lcs_cvx.Dataset, val: lcs_cvx.Dataset, hidden: tuple[int, ...], weight_decay: float,
               budget: Budget, seed: int = 0) -> tuple[ResidualMLP, dict[str, Any]]:
    torch.manual_seed(seed)
    x, y = train.x, train.x_next
    mu, sigma = x.mean(0), x.std(0).clamp_min(1e-6)
    s = (y - x).std(0).clamp_min(1e-6)
    model = ResidualMLP(mu, sigma, s, hidden)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=weight_decay)
    target = ((y - x) / s).float()
    vx, vt = val.x, ((val.x_next - val.x) / s).float()
    gen = torch.Generator().manual_seed(seed)
    best, best_state, best_step, bad = math.inf, None, 0, 0
    n = x.shape[0]
    for it in range(1, budget.mlp_steps + 1):
        idx = torch.randint(0, n, (min(budget.mlp_batch, n),), generator=gen)
        loss = ((model.increment(x[idx]) - target[idx]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if it % budget.mlp_eval_every == 0 or it == budget.mlp_steps:
            with torch.no_grad():
                v = float(((model.increment(vx) - vt) ** 2).mean())
            if v < best:
                best, best_step, bad = v, it, 0
                best_state = {k: t.clone() for k, t in model.state_dict().items()}
            else:
                bad += 1
                if bad >= budget.mlp_patience:
                    break
    if best_state is not None:
        model.load_state_dict(best_state)
    return model, {"val_one_step_mse": best, "best_step": best_step, "steps": it}


def _fit_mlp(train: lcs_cvx.Trajectories, val: lcs_cvx.Trajectories, budget: Budget, path: str
             ) -> tuple[Stepper, dict[str, Any]]:
    t0 = time.perf_counter()
    tr, va = train.to_transitions(), val.to_transitions()
    grid = []
    best: tuple[float, ResidualMLP | None] = (math.inf, None)
    for point in budget.mlp_grid:
        model, info = _train_mlp(tr, va, tuple(point["hidden"]), float(point["weight_decay"]), budget)
        score = validation_score(_mlp_step(model), val, budget.val_stride)
        grid.append({**point, "hidden": list(point["hidden"]), **info, "val_rollout": score})
        if score < best[0] or best[1] is None:
            best = (score, model)
    model = best[1]
    assert model is not None
    torch.save({"hidden": list(model.hidden), "state": model.state_dict()}, path)
    chosen = next(g for g in grid if g["val_rollout"] == best[0])
    return _mlp_step(model), {"wall": time.perf_counter() - t0, "grid": grid, "val_rollout": best[0],
                              "chosen": {"hidden": chosen["hidden"], "weight_decay": chosen["weight_decay"],
                                         "best_step": chosen["best_step"]}}


def _mlp_step(model: ResidualMLP) -> Stepper:
    model.eval()

    def step(x: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return model(x)
    return step


def _load_mlp(path: str) -> Stepper:
    blob = torch.load(path, weights_only=True)
    z = torch.zeros(13)
    model = ResidualMLP(z, z, z, tuple(blob["hidden"]))
    model.load_state_dict(blob["state"])
    return _mlp_step(model)


# ----------------------------------------------------------------------------- LCS
def structured_lcs(n_lam: int, seed: int = 0) -> lcs_cvx.LCS:
    r"""An LCS with what a user knows of a tossed cube (state ``q, p, w, v``, semi-implicit Euler
    ``p' = p + dt v'`` -- what the recorded positions and velocities satisfy):

    - ``d`` fixed: in free flight only gravity offsets the step, ``v_z' = v_z - g dt`` and
      ``p_z' = p_z - g dt^2``; every other entry 0;
    - ``A`` masked to the free-flight pattern: ``p_i'`` from ``p_i`` and ``v_i``, ``w_i'`` from
      ``w_i``, ``v_i'`` from ``v_i`` (the values of these entries are learned: the library fixes
      whole parameters, not entries), ``q'`` from ``q`` and ``w`` (the quaternion kinematics
      ``q' = q + dt/2 q (x) (0, w)`` is bilinear, so its linearisation is learned);
    - ``C``, ``D``, ``c``, ``F`` learned (contact and friction).
    """
    mask = np.zeros((13, 13), dtype=bool)
    mask[0:4, 0:4] = True
    mask[0:4, 7:10] = True
    for i in range(3):
        mask[4 + i, 4 + i] = mask[4 + i, 10 + i] = True
        mask[7 + i, 7 + i] = True
        mask[10 + i, 10 + i] = True
    d = np.zeros((13,))
    d[6] = -GRAVITY * CUBE_DT**2
    d[12] = -GRAVITY * CUBE_DT
    model = lcs_cvx.LCS(13, 0, n_lam, seed=seed).mask(A=mask)
    return model.fix(d=d.reshape(tuple(model.d.shape)))


def _num(v: Any) -> Any:
    """A JSON-safe float (None for None; inf/NaN as strings)."""
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else str(v)


def _plain_lcs(n: int, seed: int = 0) -> lcs_cvx.LCS:
    return lcs_cvx.LCS(13, 0, n, seed=seed)


def _fit_lcs(make: Callable[[int], lcs_cvx.LCS], rollout: bool,
             prepare: Callable[[lcs_cvx.Trajectories], lcs_cvx.Trajectories] | None = None,
             candidates: tuple[int, ...] | None = None,
             stepper: Callable[[lcs_cvx.LCS], Stepper] = kinematic.stepper,
             ) -> Callable[..., tuple[Stepper, dict[str, Any]]]:
    """The LCS of a user: :func:`lcs_cvx.select_n_lam` on the training tosses as
    :class:`lcs_cvx.Trajectories`, the validation tosses as ``validation`` with the rollout score
    at :data:`VALIDATION_HORIZON` (by which ``n_lam`` is chosen and, by ``fit``'s default on
    trajectories, the best iterate kept) and otherwise the library's defaults: with ``rollout``
    the simulation-error phase runs (its default on trajectories), without it the one-step losses
    only (``rollout_horizon=None``). ``make(n)`` builds each candidate; ``prepare``: what the
    model is fitted on, made of the tosses (e.g. :func:`studies.cube.kinematic.augment`: the state
    with the up coordinates); ``candidates``: the ``n_lam`` tried instead of the budget's;
    ``stepper(model)``: the model's step on the study's 13-states; ``seed``: of the
    initialisations (``make(n, seed=seed)``) and of ``select_n_lam``'s batches."""
    def fit(train: lcs_cvx.Trajectories, val: lcs_cvx.Trajectories, budget: Budget, path: str,
            n_lams: tuple[int, ...] | None = None, seed: int = 0) -> tuple[Stepper, dict[str, Any]]:
        t0 = time.perf_counter()
        val13 = val
        if prepare is not None:
            train, val = prepare(train), prepare(val)
        phase = {"rollout_iterations": budget.rollout_iterations, "rollout_horizon": budget.rollout_horizon}
        extra = {k: v for k, v in phase.items() if v is not None} if rollout else {"rollout_horizon": None}
        with warnings.catch_warnings():
            if prepare is not None:  # pieces of tosses (the symmetric model's) may be shorter than a window:
                # they train the one-step losses and have no window in the rollout scores, as the report says
                warnings.filterwarnings("ignore", message="rollout_horizon: .* shorter than", category=UserWarning)
            sel = lcs_cvx.select_n_lam(train, list(n_lams or candidates or budget.n_lams), validation=val,
                                       make_model=lambda n: make(n, seed=seed),
                                       iterations=budget.lcs_iterations, holdout_horizon=VALIDATION_HORIZON,
                                       progress=False, seed=seed, recipe="plain", **extra)
        table: list[dict[str, Any]] = []
        for row in sel.table:
            n = row["n_lam"]
            res = sel.results[n]
            scored = [(h["iteration"], h["e_test"]) for h in res.history if h.get("e_test") is not None]
            best = min(scored, key=lambda t: t[1]) if scored else None
            table.append({"n_lam": n, "heldout_error": _num(res.heldout_error),
                          "affine_heldout_error": _num(res.affine_heldout_error),
                          "beats_affine": res.beats_affine, "heldout_growth": _num(res.heldout_growth),
                          "refinement_kept": res.refinement_kept, "keep_best": res.settings.run.keep_best,
                          "best_iteration": None if best is None else best[0],
                          "val_one_step": lcs_cvx.relative_error(res.model, val.to_transitions()),
                          "val_rollout": validation_score(stepper(res.model), val13, budget.val_stride),
                          "wall": row["wall_time"]})
        model = sel.model
        lcs_cvx.save_model(model, path, metadata={"n_lam": sel.n_lam, "rollout": rollout})
        chosen = next(r for r in table if r["n_lam"] == sel.n_lam)
        info = {"wall": time.perf_counter() - t0, "n_lam": sel.n_lam, "candidates": table,
                "val_rollout": chosen["val_rollout"], "beats_affine": chosen["beats_affine"],
                "verdict": sel.results[sel.n_lam].verdict}
        for row in table:
            for k, v in list(row.items()):
                if isinstance(v, float):
                    row[k] = _num(v)
        return stepper(model), info
    return fit


# ----------------------------------------------------------------------------- constant increment
def _fit_increment(train: lcs_cvx.Trajectories, val: lcs_cvx.Trajectories, budget: Budget, path: str
                   ) -> tuple[Stepper, dict[str, Any]]:
    """``x' = x + m``, ``m`` the mean training increment (``fit``'s starting ``(A, B, d)``)."""
    t0 = time.perf_counter()
    tr = train.to_transitions()
    m = (tr.x_next - tr.x).mean(0)
    np.savez(path, m=m.numpy())
    step = _increment_step(m)
    return step, {"wall": time.perf_counter() - t0, "val_rollout": validation_score(step, val, budget.val_stride)}


def _increment_step(m: torch.Tensor) -> Stepper:
    return lambda x: x + m


def _load_increment(path: str) -> Stepper:
    with np.load(path) as f:
        return _increment_step(torch.from_numpy(f["m"]))


def _load_lcs(path: str) -> Stepper:
    return kinematic.stepper(lcs_cvx.load_model(path))


def _load_symmetric(path: str) -> Stepper:
    return symmetry.stepper(lcs_cvx.load_model(path))


def specs() -> list[Spec]:
    """The model specs in table order."""
    return [
        Spec("affine LS", "affine", "npz", _fit_affine, _load_affine),
        Spec("constant increment", "increment", "npz", _fit_increment, _load_increment),
        Spec("MLP", "mlp", "pt", _fit_mlp, _load_mlp),
        Spec("LCS", "lcs", "npz", _fit_lcs(_plain_lcs, True), _load_lcs),
        Spec("LCS, known structure", "lcs_structured", "npz", _fit_lcs(structured_lcs, True), _load_lcs),
        Spec("LCS, one-step losses only", "lcs_one_step", "npz", _fit_lcs(_plain_lcs, False), _load_lcs, twin="lcs"),
        Spec("LCS, known kinematics", "lcs_kinematics", "npz", _fit_lcs(kinematic.kinematic_lcs, True), _load_lcs),
        Spec("LCS, contact coordinates", "lcs_contact", "npz",
             _fit_lcs(kinematic.contact_lcs, True, prepare=kinematic.augment, candidates=kinematic.CONTACT_N_LAMS),
             _load_lcs),
        Spec("LCS, cube symmetry", "lcs_symmetry", "npz",
             _fit_lcs(symmetry.symmetric_lcs, True, prepare=symmetry.prepare, candidates=kinematic.CONTACT_N_LAMS,
                      stepper=symmetry.stepper), _load_symmetric),
        Spec("rigid body", "rigid_body", "npz", rigid.fit, rigid.load),
        Spec("rigid body, rounded corners", "rigid_body_rounded", "npz", rigid.fit_rounded, rigid.load),
    ]


def to_json(obj: Any) -> str:
    """One JSON line with inf/NaN written as strings."""
    def clean(v: Any) -> Any:
        if isinstance(v, float):
            return _num(v)
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        return v
    return json.dumps(clean(obj))


def model_path(out: str, size: int, spec: Spec) -> str:
    return os.path.join(out, "models", f"n{size:03d}_{spec.key}.{spec.ext}")
