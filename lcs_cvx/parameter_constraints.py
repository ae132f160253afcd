r"""Known structure of an LCS -- fixed parameters and sparsity masks -- and what training does
with it.

The user states what they know about eq. (1),

    x' = A x + B u + C lam + d,      0 <= lam  _|_  D x + E u + F lam + c >= 0,

on the model itself (:class:`lcs_cvx.LCS`): a parameter is *fixed* iff it does not require grad
(:meth:`~lcs_cvx.LCS.fix`, or ``model.A.requires_grad_(False)``), and a *mask*
(:meth:`~lcs_cvx.LCS.mask`, :attr:`~lcs_cvx.LCS.masks`: True = learned) holds chosen entries of
``A, B, C, d, D, E, c`` at exactly 0, or at given values (:meth:`~lcs_cvx.LCS.hold`). An entry
is *free* when its parameter is not fixed and its
mask (if any) is True: :func:`free_entries`, :func:`free_vector`.

This module owns how every part of training honours that, so that a fixed parameter comes back
bit-identical and a masked entry at exactly its held value:

- first order: :func:`mask_gradients_` before an optimiser step, :func:`project_` after it;
- second order: the flat free coordinates (:func:`free_vector`) to which
  :mod:`lcs_cvx.second_order` restricts its linear systems;
- least squares: :func:`row_lstsq`, each output row fitted on its free columns only
  (:func:`lcs_cvx.resizing.refit_dynamics`, the affine initialisation);
- models derived from a model (:mod:`lcs_cvx.resizing`, restarts): :func:`restrict_structure_`
  (units kept or eliminated), :func:`grow_structure_` (units added), :func:`keeps_structure`
  (whether an elimination changed a fixed value or filled a masked entry), :func:`copy_structure_`;
- extra units: :func:`growth_blocker` and :func:`allowed_extra_units`. A parameter indexed by the
  units (``C``'s columns, ``D``, ``E``, ``c``, ``G``, ``H``) that is fixed, or masked with a
  pattern that differs between units, says something about each unit that new units cannot
  share: then no units are added (``extra_units="auto"`` resolves to 0, an explicit number is
  an error). With the same pattern for every unit, grown units copy it.
"""

from __future__ import annotations

import torch

from ._checks import LCSInputError
from .system import LCS, PARAMETER_NAMES

__all__ = [
    "UNIT_AXES",
    "free_entries",
    "free_vector",
    "has_constraints",
    "check_learnable",
    "project_",
    "mask_gradients_",
    "row_lstsq",
    "copy_structure_",
    "restrict_structure_",
    "grow_structure_",
    "keeps_structure",
    "growth_blocker",
    "allowed_extra_units",
]

#: The axes of each parameter indexed by the complementarity units.
UNIT_AXES: dict[str, tuple[int, ...]] = {"C": (1,), "D": (0,), "E": (0,), "c": (0,),
                                         "G": (0, 1), "H": (0, 1)}


# -- what is free ---------------------------------------------------------------------------
def free_entries(model: LCS, name: str) -> torch.Tensor:
    """Bool tensor of parameter ``name``'s shape (on its device): False where the parameter is
    fixed or the entry masked, True where the entry is learned."""
    if name not in PARAMETER_NAMES:
        raise LCSInputError(f"name: expected one of {PARAMETER_NAMES}, received {name!r}")
    p = getattr(model, name)
    if not p.requires_grad:
        return torch.zeros(p.shape, dtype=torch.bool, device=p.device)
    mask = model.masks.get(name)
    return torch.ones(p.shape, dtype=torch.bool, device=p.device) if mask is None \
        else mask.to(p.device, copy=True)


def free_vector(model: LCS) -> torch.Tensor:
    """``(P,)`` bool: :func:`free_entries` of every parameter flattened in the order of
    :func:`lcs_cvx.hessian.flatten_parameters` (``PARAMETER_NAMES``, row-major)."""
    return torch.cat([free_entries(model, k).reshape(-1) for k in PARAMETER_NAMES])


def has_constraints(model: LCS) -> bool:
    """Whether any parameter of ``model`` is fixed or masked."""
    return bool(model.masks) or not all(getattr(model, k).requires_grad for k in PARAMETER_NAMES)


def check_learnable(model: LCS) -> None:
    """:class:`LCSInputError` when ``model`` has no free entry (nothing to learn)."""
    if not any(bool(free_entries(model, k).any()) for k in PARAMETER_NAMES):
        raise LCSInputError(
            "model: expected at least one learnable entry, received a model whose every "
            "parameter is fixed (requires_grad False) or masked; lcs_cvx.random_lcs returns such "
            "a model (a ground truth): .requires_grad_(True) makes all of it learnable"
        )


# -- first-order optimisers -----------------------------------------------------------------
def project_(model: LCS) -> None:
    """Set the masked entries of ``model``'s parameters to their held values (0 for a mask,
    :meth:`lcs_cvx.LCS.hold`'s otherwise; in place)."""
    with torch.no_grad():
        for name, mask in model.masks.items():
            p = getattr(model, name)
            p.copy_(torch.where(mask.to(p.device), p, model._held[name].to(p)))


def mask_gradients_(model: LCS) -> None:
    """Zero the gradients (``.grad``) of the masked entries (in place): an optimiser's moments
    then stay 0 there and its steps leave them unchanged."""
    for name, mask in model.masks.items():
        g = getattr(model, name).grad
        if g is not None:
            g.masked_fill_(~mask.to(g.device), 0.0)


# -- constrained least squares --------------------------------------------------------------
def row_lstsq(phi: torch.Tensor, target: torch.Tensor, free: torch.Tensor, fixed: torch.Tensor,
              ridge: torch.Tensor) -> torch.Tensor:
    r"""Row-wise least squares ``target ~ phi @ W.T`` with some entries of ``W`` known.

    Each row ``i`` of ``W`` ``(R, K)`` keeps ``W[i, k] = fixed[i, k]`` where ``free[i, k]`` is
    False and takes its free entries ``S_i`` as the minimiser of

        1/(2 N) ||target[:, i] - phi @ W[i]||^2 + 1/2 sum_{k in S_i} ridge_k W[i, k]^2,

    i.e. ``(G_SS + diag(ridge_S)) W[i, S] = (phi^T target[:, i] / N)_S - G_{S, ~S} W[i, ~S]``
    with ``G = phi^T phi / N`` (normal equations: the columns of ``phi`` should be of comparable
    scale). Rows with the same free pattern are solved together; with every entry free this is
    one solve ``(G + diag(ridge)) W^T = phi^T target / N``.

    Args:
        phi: ``(N, K)`` regressors.
        target: ``(N, R)`` targets, one column per row of ``W``.
        free: ``(R, K)`` bool, True where ``W`` is fitted.
        fixed: ``(R, K)`` the known values (read where ``free`` is False, copied exactly).
        ridge: ``(K,)`` per-column ridge ``>= 0`` (``G_SS + diag(ridge_S)`` must be invertible).

    Returns:
        ``W`` ``(R, K)``.
    """
    N, K = phi.shape
    R = target.shape[1]
    if target.shape[0] != N or free.shape != (R, K) or fixed.shape != (R, K) or ridge.shape != (K,):
        raise LCSInputError(
            f"row_lstsq: expected phi (N, K), target (N, R), free and fixed (R, K), ridge (K,), "
            f"received phi {tuple(phi.shape)}, target {tuple(target.shape)}, free "
            f"{tuple(free.shape)}, fixed {tuple(fixed.shape)}, ridge {tuple(ridge.shape)}"
        )
    gram = phi.mT @ phi / N
    rhs = phi.mT @ target / N  # (K, R)
    if bool(free.all()):
        return torch.linalg.solve(gram + torch.diag(ridge), rhs).mT
    free = free.to(phi.device)
    W = torch.where(free, torch.zeros((), dtype=phi.dtype, device=phi.device), fixed)
    patterns, which = torch.unique(free, dim=0, return_inverse=True)
    for p, f in enumerate(patterns):
        if not bool(f.any()):
            continue
        rows = (which == p).nonzero().squeeze(1)
        cols, known = f.nonzero().squeeze(1), (~f).nonzero().squeeze(1)
        b = rhs[cols][:, rows] - gram[cols][:, known] @ W[rows][:, known].mT
        sol = torch.linalg.solve(gram[cols][:, cols] + torch.diag(ridge[cols]), b)
        W[rows[:, None], cols[None, :]] = sol.mT
    return W


# -- models derived from a model --------------------------------------------------------------
def _restrict(name: str, t: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
    for axis in UNIT_AXES.get(name, ()):
        t = t.index_select(axis, keep.to(t.device))
    return t


def copy_structure_(src: LCS, dst: LCS) -> LCS:
    """Give ``dst`` (same sizes as ``src``) ``src``'s fixed parameters -- values and flags --
    masks and kinematics, its masked entries set to ``src``'s held values; returns ``dst``. A fresh
    restart keeps what the user stated this way."""
    with torch.no_grad():
        for name in PARAMETER_NAMES:
            p = getattr(src, name)
            if not p.requires_grad:
                getattr(dst, name).copy_(p).requires_grad_(False)
    dst.replace_masks(src.masks, held=src._held)
    dst._kinematics = src.kinematics
    return dst


def restrict_structure_(src: LCS, dst: LCS, keep: list[int]) -> None:
    """Give ``dst``, built from the units ``keep`` of ``src`` (:func:`lcs_cvx.resizing.keep_units`,
    :func:`~lcs_cvx.resizing.eliminate_unit`), ``src``'s fixed flags and its masks restricted to those
    units. Values are not touched (:func:`keeps_structure` checks them)."""
    idx = torch.tensor(keep, dtype=torch.long)
    for name in PARAMETER_NAMES:
        if not getattr(src, name).requires_grad:
            getattr(dst, name).requires_grad_(False)
    dst.replace_masks({k: _restrict(k, m, idx) for k, m in src.masks.items()}, zero=False)
    dst._kinematics = src.kinematics


def keeps_structure(candidate: LCS, model: LCS, keep: list[int]) -> bool:
    """Whether ``candidate``, built from the units ``keep`` of ``model``, holds ``model``'s
    fixed values (restricted to those units; bit-identical) and its held values at its masked
    entries. A
    fixed ``G`` or ``H`` asks for the restriction of ``F`` (to round-off: ``F`` is re-factored)."""
    idx = torch.tensor(keep, dtype=torch.long)
    for name in PARAMETER_NAMES:
        if getattr(model, name).requires_grad:
            continue
        if name in ("G", "H"):
            F0 = _restrict("G", model.F.detach(), idx)
            if not torch.allclose(candidate.F.detach(), F0, rtol=1e-12, atol=1e-12):
                return False
        elif not torch.equal(getattr(candidate, name).detach(),
                             _restrict(name, getattr(model, name).detach(), idx)):
            return False
    for name, mask in candidate.masks.items():
        p = getattr(candidate, name).detach()
        held = _restrict(name, model._held[name], idx).to(p)
        off = ~mask.to(p.device)
        if not torch.equal(p[off], held[off]):
            return False
    return True


def growth_blocker(model: LCS) -> str | None:
    """Why units cannot be added to ``model`` (a unit-indexed parameter fixed, or masked with a
    pattern that differs between units), or None."""
    for name, axes in UNIT_AXES.items():
        if not getattr(model, name).requires_grad:
            return f"{name} is fixed"
        mask = model.masks.get(name)
        if mask is not None:
            first = mask.narrow(axes[0], 0, 1)
            if not bool((mask == first).all()):
                return f"the mask of {name} differs between units"
            if bool((model._held[name] != 0).any()):
                return f"entries of {name} are held at values other than 0"
    return None


def grow_structure_(src: LCS, dst: LCS) -> None:
    """Give ``dst``, ``src`` with units appended (:func:`lcs_cvx.resizing.add_units`), ``src``'s fixed
    flags and masks, the new units copying the (common) pattern of the old ones; masked entries
    of ``dst`` held at ``src``'s values (0 on the unit-indexed parameters). :class:`LCSInputError` when :func:`growth_blocker` objects."""
    why = growth_blocker(src)
    if why is not None:
        raise LCSInputError(
            f"extra: expected 0 for a model on which {why} (new units could not share it), "
            f"received {dst.n_lam - src.n_lam}"
        )
    for name in PARAMETER_NAMES:
        if not getattr(src, name).requires_grad:
            getattr(dst, name).requires_grad_(False)
    masks = {}
    for name, mask in src.masks.items():
        axes = UNIT_AXES.get(name, ())
        if axes:
            size = list(mask.shape)
            size[axes[0]] = dst.n_lam
            mask = mask.narrow(axes[0], 0, 1).expand(size).clone()
        masks[name] = mask.clone()
    # held values: 0 on the unit-indexed parameters (growth_blocker), the source's elsewhere
    dst.replace_masks(masks, held={k: v for k, v in src._held.items() if k not in UNIT_AXES})
    dst._kinematics = src.kinematics


def allowed_extra_units(model: LCS, option: int | str, n_extra: int) -> int:
    """The extra units a run of :func:`lcs_cvx.fit` trains: ``n_extra`` (resolved from
    ``option``), unless :func:`growth_blocker` objects -- then 0 for ``option="auto"`` and an
    :class:`LCSInputError` for an explicit number > 0."""
    why = growth_blocker(model) if n_extra else None
    if why is None:
        return n_extra
    if option == "auto":
        return 0
    raise LCSInputError(
        f"extra_units: expected 0 or 'auto' for a model on which {why} (new units could not "
        f"share it), received {option!r}"
    )
