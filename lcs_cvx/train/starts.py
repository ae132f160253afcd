r"""Where a run of :func:`lcs_cvx.fit` starts (``RunOptions.init``), in the coordinates of learning.

- ``"model"``: the user's model, mapped exactly into the coordinates of learning.
- ``"increment"``: ``x' = x`` plus the mean increment (``A = I``, ``B = 0``, ``d`` the mean of
  ``x' - x``; in normalised coordinates ``Â = B̂ = d̂ = 0``), and the other learnable parameters'
  values taken as a draw in the coordinates of learning (a fresh :class:`lcs_cvx.LCS`'s
  ``init_scale * N(0, 1)``: hyperplanes of the data's scale whatever its units).
- ``"affine"``: as ``"increment"``, then ``(A, B, d)`` from the least-squares affine fit
  ``x' ~ A x + B u + d`` (eq. (1) with ``C lam`` dropped) of the training data, entry by entry
  where they are learnable (fixed entries and masked zeros are held; each row of ``[A B d]`` is
  its own least-squares problem on its learnable columns).

Fixed parameters keep their values in every case (mapped exactly). ``"increment"`` is the
default: it does not depend on the data's units, and it reached the noise floor as reliably as any
start where the starts were compared. ``"affine"`` often stalls: the affine fit already
explains part of what the complementarity units should, so their boundaries get little
gradient. ``"model"`` (the user's random ``LCS`` mapped as is) learns as well on data at the
paper's scale, but where it starts depends on the data's units. The documentation's Benchmarks
page ("Measurements behind the training defaults") has the runs that compared them.
"""

from __future__ import annotations

import copy
from typing import Any

import torch

from ..data import Dataset
from ..parameter_constraints import copy_structure_, free_entries, row_lstsq
from ..scaling import Scaling
from ..system import LCS, PARAMETER_NAMES

__all__ = ["start", "fresh_like", "affine_start_", "jittered"]


def affine_start_(model: LCS, data: Dataset) -> None:
    """Set the learnable entries of ``A``, ``B``, ``d`` of ``model`` in place to the least-squares
    affine fit of ``data``: row ``i`` of ``W = [A B d]`` minimises
    ``sum_t (x'_ti - phi_t W_i)^2`` over its learnable entries, ``phi_t = [x_t, u_t, 1]``."""
    with torch.no_grad():
        x, u, xn = data.x.to(model.dtype), data.u.to(model.dtype), data.x_next.to(model.dtype)
        phi = torch.cat([x, u, torch.ones(x.shape[0], 1, dtype=x.dtype, device=x.device)], 1)
        # the normal equations want columns of one scale: solve for W * scale on phi / scale
        scale = phi.abs().amax(0).clamp(min=torch.finfo(phi.dtype).tiny)
        names = ("A", "B", "d")
        W = torch.cat([model.A, model.B, model.d[:, None]], 1).detach()
        free = torch.cat([free_entries(model, "A"), free_entries(model, "B"),
                          free_entries(model, "d")[:, None]], 1)
        phi_s = phi / scale
        ridge = 1e-12 * (phi_s * phi_s).mean(0).max() * torch.ones_like(scale)
        W = row_lstsq(phi_s, xn, free, W * scale, ridge) / scale
        n_x, n_u = model.n_x, model.n_u
        for name, value in zip(names, (W[:, :n_x], W[:, n_x:n_x + n_u], W[:, -1]), strict=True):
            p = getattr(model, name)
            if p.requires_grad:
                p.copy_(torch.where(free_entries(model, name), value, p))


def _increment_start_(model: LCS, data: Dataset, normalised: bool) -> None:
    """Learnable entries of ``A``, ``B``, ``d`` to ``x' = x + mean(x' - x)`` (normalised
    coordinates: ``Â = B̂ = d̂ = 0``, the increment's mean being 0 there)."""
    if normalised:
        target = {"A": torch.zeros_like(model.A), "B": torch.zeros_like(model.B),
                  "d": torch.zeros_like(model.d)}
    else:
        target = {"A": torch.eye(model.n_x, dtype=model.dtype, device=model.device),
                  "B": torch.zeros_like(model.B),
                  "d": (data.x_next - data.x).mean(0).to(model.dtype)}
    for name, value in target.items():
        p = getattr(model, name)
        if p.requires_grad:
            p.copy_(torch.where(free_entries(model, name), value, p))


def fresh_like(model: LCS, seed: int) -> LCS:
    """A fresh random LCS of ``model``'s sizes, stiffness, dtype and device (``LCS(...,
    seed=seed)``) with ``model``'s fixed parameters (their values) and masks."""
    new = LCS(model.n_x, model.n_u, model.n_lam, stiffness=float(model.stiffness), seed=seed,
              dtype=model.dtype).to(model.device)
    return copy_structure_(model, new)


def start(base: LCS, init: str, scaling: Scaling | None, train: Dataset,
          exact: bool) -> LCS:
    """The start of a run in the coordinates of learning.

    Args:
        base: the model in the user's units (the user's model, or :func:`fresh_like` it).
        init: ``"model"``, ``"increment"`` or ``"affine"`` (module docstring).
        scaling: the change of coordinates, or None (learning in the user's units).
        train: the training data in the coordinates of learning.
        exact: whether ``base`` is the user's model (``init="model"`` maps it exactly; a restart's
            fresh model is a draw).
    """
    learner = scaling.to_normalised(base) if scaling is not None else base
    if init == "model" and exact:
        return learner
    with torch.no_grad():
        if scaling is not None:  # the draw, taken in normalised coordinates
            for name in PARAMETER_NAMES:
                p = getattr(learner, name)
                if p.requires_grad:
                    p.copy_(getattr(base, name))
        if init in ("increment", "affine"):
            _increment_start_(learner, train, normalised=scaling is not None)
    if init == "affine":
        affine_start_(learner, train)
    return learner


def jittered(model: Any, seed: int, scale: float = 0.1) -> Any:
    """A copy of a model of per-sample matrices (:class:`lcs_cvx.RigidBodyContact`) with each
    learnable parameter moved by ``scale * N(0, 1)`` (its parameters are in the body's own units:
    log sizes, lengths relative to its size): a restart's start."""
    new = copy.deepcopy(model)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in new.parameters():
            if p.requires_grad:
                p.add_((scale * torch.randn(p.shape, generator=gen, dtype=torch.float64)).to(p))
    return new
