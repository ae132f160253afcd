r"""Adding and removing complementarity units (the coordinates of ``lam``) of an LCS.

Learning an LCS is prone to a permutation trap: two units settle on the same mode boundary while
another boundary of the data is left unmodelled, and no local method leaves that basin
(DESIGN.md). Over-parameterising -- training with ``n_lam + k`` units -- and then removing the
``k`` least useful ones avoids it: :func:`add_units` embeds a model in a larger one and :func:`prune_units`
removes units greedily.

A unit can leave in two ways, each exact in one limit (eq. (2), ``w = D x + E u + F lam + c``):

- :func:`keep_units` *deletes* it (``lam_j = 0``): the principal submatrix of ``F`` is kept and
  ``C[:, j]``, ``D[j]``, ``E[j]``, ``c[j]`` dropped. Exact for a unit that is never active.
- :func:`eliminate_unit` *eliminates* it on ``w_j = 0``: ``lam_j = -(D_j x + E_j u + c_j + F_{j,r}
  lam_r) / F_jj`` is substituted into the other units and the dynamics, so ``F`` becomes its
  Schur complement and the unit's affine effect moves into ``A, B, d`` and the other units'
  ``D, E, c``. Exact for a unit that is always active -- the units Adam leaves saturated.

:func:`prune_units` tries both for every unit, refits ``(A, B, C, d)`` by least squares on each
candidate (:func:`refit_dynamics`, exact for the prediction loss at fixed ``lam``) and keeps the
best; ``repair`` (a few Gauss--Newton steps in :func:`lcs_cvx.fit`) then adjusts the survivor.

Known structure (:mod:`lcs_cvx.parameter_constraints`) carries over: the new models keep the fixed flags and
masks (restricted to the kept units, or copied to the grown ones), :func:`refit_dynamics` fits only
the free entries, and :func:`prune_units` drops an elimination that would change a fixed parameter or
fill a masked entry.
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Sequence

import torch

from ._checks import LCSInputError
from .lcp import solve_lcp_fast
from .parameter_constraints import (
    free_entries,
    grow_structure_,
    keeps_structure,
    restrict_structure_,
    row_lstsq,
)
from .parameters import split_F
from .system import LCS

__all__ = ["keep_units", "eliminate_unit", "add_units", "prune_units", "refit_dynamics"]


def _check_keep(model: LCS, keep: Sequence[int]) -> list[int]:
    """``keep`` as a list of distinct ints in ``[0, n_lam)``, or a clear error."""
    try:
        out = [operator.index(k) for k in keep]
    except TypeError:
        out = None
    if not out or len(set(out)) != len(out) or not all(0 <= k < model.n_lam for k in out):
        raise LCSInputError(
            f"keep: expected distinct unit indices in [0, {model.n_lam}), received {list(keep)}"
        )
    return out


def _build(model: LCS, keep: list[int], F: torch.Tensor, **matrices: torch.Tensor) -> LCS:
    """A new LCS of the units ``keep`` of ``model`` with these matrices and its structure."""
    G, H = split_F(F, float(model.stiffness))
    new = LCS(model.n_x, model.n_u, F.shape[0], stiffness=float(model.stiffness),
              init_scale=0.0, dtype=model.dtype).to(model.device)
    with torch.no_grad():
        for name, value in (*matrices.items(), ("G", G), ("H", H)):
            getattr(new, name).copy_(value)
    restrict_structure_(model, new, keep)
    return new


def keep_units(model: LCS, keep: Sequence[int]) -> LCS:
    """A new LCS with only the units ``keep`` (in that order) of ``model`` (the others deleted:
    ``lam_j = 0``); fixed flags and masks carried over (restricted to ``keep``)."""
    keep = _check_keep(model, keep)
    idx = torch.tensor(keep, device=model.device)
    with torch.no_grad():
        return _build(model, keep, model.F[idx][:, idx], A=model.A, B=model.B, d=model.d,
                      C=model.C[:, idx], D=model.D[idx], E=model.E[idx], c=model.c[idx])


def eliminate_unit(model: LCS, j: int) -> LCS:
    r"""A new LCS without unit ``j``, eliminated on ``w_j = 0`` (the unit always active).

    With ``r`` the other units and ``f = F_{r,j} / F_jj``::

        F' = F_rr - f F_{j,r}          D' = D_r - f D_j      E' = E_r - f E_j      c' = c_r - f c_j
        C' = C_r - C_j F_{j,r} / F_jj  A' = A - C_j D_j / F_jj   B' = B - C_j E_j / F_jj   d' = d - C_j c_j / F_jj

    On samples where the unit is active the result predicts exactly what ``model`` does. ``F'``
    stays in the model's set: with ``x = (y, -f^T y)``, ``F x = (F' y, 0)``, so
    ``y^T F' y = x^T F x >= s |x|^2 >= s |y|^2`` (Assumption 1 carries over).

    The result carries ``model``'s fixed flags and masks (restricted to the other units);
    :func:`lcs_cvx.parameter_constraints.keeps_structure` says whether it also kept their values.
    """
    if isinstance(j, bool) or not isinstance(j, int) or not 0 <= j < model.n_lam or model.n_lam < 2:
        raise LCSInputError(
            f"j: expected a unit index in [0, {model.n_lam}) of a model with n_lam >= 2, "
            f"received {j!r} (n_lam = {model.n_lam})"
        )
    rest = [i for i in range(model.n_lam) if i != j]
    r = torch.tensor(rest, device=model.device)
    with torch.no_grad():
        F = model.F
        fjj = F[j, j]
        f = F[r, j] / fjj
        cj = model.C[:, j] / fjj
        return _build(
            model, rest, F[r][:, r] - torch.outer(f, F[j, r]),
            A=model.A - torch.outer(cj, model.D[j]), B=model.B - torch.outer(cj, model.E[j]),
            d=model.d - cj * model.c[j], C=model.C[:, r] - torch.outer(cj, F[j, r]),
            D=model.D[r] - torch.outer(f, model.D[j]), E=model.E[r] - torch.outer(f, model.E[j]),
            c=model.c[r] - f * model.c[j],
        )


def refit_dynamics(model: LCS, x: torch.Tensor, u: torch.Tensor, x_next: torch.Tensor,
                 reg: float = 0.0, warm_start: torch.Tensor | None = None) -> float:
    r"""Refit ``(A, B, C, d)`` in place by least squares with ``lam = LCP(F, D x + E u + c)`` fixed.

    The prediction loss (eq. (6)) plus ``reg ||C||_F^2`` is quadratic in ``(A, B, C, d)``
    at fixed ``lam``; this is its exact minimiser (normal equations with a ``1e-12`` relative
    ridge so that units inactive on every sample stay well posed). Returns the loss after the
    refit. ``warm_start``: a first guess of the LCP's free sets (:func:`lcs_cvx.lcp.solve_lcp_fast`).

    Only the free entries are fitted (:func:`lcs_cvx.parameter_constraints.row_lstsq`): fixed parameters
    and masked entries keep their values, each row of ``[A B C d]`` is the least-squares fit of
    its free columns.
    """
    with torch.no_grad():
        lam = solve_lcp_fast(model.F, model.lcp_offset(x, u), warm_start=warm_start, residual=False).lam
        n = x.shape[0]
        phi = torch.cat([x, u, lam, torch.ones(n, 1, dtype=x.dtype, device=x.device)], 1)
        ridge = torch.zeros(phi.shape[1], dtype=x.dtype, device=x.device)
        c0 = model.n_x + model.n_u
        ridge[c0:c0 + model.n_lam] = 2.0 * reg
        ridge += 1e-12 * (phi * phi).sum(0).max() / n  # phi^T phi / n's largest diagonal entry
        names = ("A", "B", "C", "d")
        free = torch.cat([free_entries(model, k).reshape(model.n_x, -1) for k in names], 1)
        fixed = torch.cat([getattr(model, k).detach().reshape(model.n_x, -1) for k in names], 1)
        W = row_lstsq(phi, x_next, free, fixed, ridge)
        for name, value in (("A", W[:, :model.n_x]), ("B", W[:, model.n_x:c0]),
                            ("C", W[:, c0:c0 + model.n_lam]), ("d", W[:, -1])):
            if getattr(model, name).requires_grad:  # a fixed one: W holds its value already
                getattr(model, name).copy_(value)
        fit_err = 0.5 * ((phi @ W.mT - x_next) ** 2).sum(-1).mean() + reg * (model.C ** 2).sum()
        return float(fit_err)


def add_units(model: LCS, extra: int, generator: torch.Generator, scale: float = 0.1) -> LCS:
    """``model`` with ``extra`` new units appended, their parameters ``scale * N(0, 1)``.

    The original units' ``F`` block is kept exactly; the new rows and columns of ``F`` come from
    new rows of ``G`` and ``H`` (so ``F`` stays in the model's set). Fixed flags and masks carry
    over, the new units copying the units' common mask pattern; a fixed unit-indexed parameter
    or a pattern that differs between units is an error when ``extra > 0``
    (:func:`lcs_cvx.parameter_constraints.grow_structure_`).
    """
    n, k = model.n_lam, int(extra)
    if k < 0:
        raise LCSInputError(f"extra: expected an integer >= 0, received {extra!r}")
    new = LCS(model.n_x, model.n_u, n + k, stiffness=float(model.stiffness), init_scale=0.0,
              dtype=model.dtype).to(model.device)

    def draw(*shape: int) -> torch.Tensor:
        return (scale * torch.randn(shape, generator=generator, dtype=torch.float64)).to(
            model.dtype).to(model.device)

    with torch.no_grad():
        for name in ("A", "B", "d"):
            getattr(new, name).copy_(getattr(model, name))
        new.C.copy_(torch.cat([model.C, draw(model.n_x, k)], dim=1))
        new.D.copy_(torch.cat([model.D, draw(k, model.n_x)], dim=0))
        new.E.copy_(torch.cat([model.E, draw(k, model.n_u)], dim=0))
        new.c.copy_(torch.cat([model.c, draw(k)], dim=0))
        # G: block-triangular so that the old block of G G^T is unchanged
        G = torch.zeros(n + k, n + k, dtype=model.dtype, device=model.device)
        G[:n, :n] = model.G
        G[n:, :] = draw(k, n + k)
        H = torch.zeros_like(G)
        H[:n, :n] = model.H
        H[n:, :] = draw(k, n + k)
        new.G.copy_(G)
        new.H.copy_(H)
    if k:
        grow_structure_(model, new)
    else:
        restrict_structure_(model, new, list(range(n)))
    return new


def prune_units(
    model: LCS,
    n_lam: int,
    x: torch.Tensor,
    u: torch.Tensor,
    x_next: torch.Tensor,
    repair: Callable[[LCS], None] | None = None,
    reg: float = 0.0,
    lookahead: int = 1,
) -> LCS:
    """Remove units one at a time until ``n_lam`` remain; returns a new model.

    Each removal tries, for every unit, deleting it (:func:`keep_units`) and eliminating it
    (:func:`eliminate_unit`), refits ``(A, B, C, d)`` on each candidate (:func:`refit_dynamics`) and keeps
    the one with the lowest prediction loss (plus ``reg ||C||^2``) on ``(x, u, x_next)`` (an
    elimination that would change a fixed parameter or fill a masked entry is not a candidate);
    ``repair(model)``, if given, then improves the kept one in place (e.g. a Gauss--Newton step)
    before the next removal.

    With ``lookahead = k > 1`` and a ``repair``, the ``k`` candidates of lowest loss are each
    repaired, refitted again (:func:`refit_dynamics`) and kept if their loss is the lowest: two
    units that settled on one boundary cost much when one of them is deleted, until a repair
    step lets the other take its part, while eliminating a unit that is active on most samples
    costs less at first and stays lossy. ``lookahead = 1`` repairs the best candidate only.

    Both reductions are tried because most removals in practice are of units Adam left
    saturated, which elimination removes exactly and deletion does not; scoring every candidate
    after a cheap least-squares refit, rather than after Gauss--Newton steps, keeps a removal
    affordable at large ``n_lam`` (the docs' benchmarks page has the measurements).
    """
    if isinstance(n_lam, bool) or not isinstance(n_lam, int) or not 1 <= n_lam <= model.n_lam:
        raise LCSInputError(f"n_lam: expected an integer in [1, {model.n_lam}], received {n_lam!r}")
    if isinstance(lookahead, bool) or not isinstance(lookahead, int) or lookahead < 1:
        raise LCSInputError(f"lookahead: expected an integer >= 1, received {lookahead!r}")
    current = keep_units(model, range(model.n_lam))
    while current.n_lam > n_lam:
        scored: list[tuple[float, int, LCS]] = []  # (loss, order of trial, candidate)
        with torch.no_grad():  # the candidates' active sets are mostly the current model's
            free = solve_lcp_fast(current.F, current.lcp_offset(x, u), residual=False).free
        for j in range(current.n_lam):
            rest = [i for i in range(current.n_lam) if i != j]
            eliminated = eliminate_unit(current, j)
            if keeps_structure(eliminated, current, rest):
                cands: tuple[LCS, ...] = (keep_units(current, rest), eliminated)
            else:  # it would change a fixed parameter or fill a masked entry
                cands = (keep_units(current, rest),)
            for cand in cands:
                value = refit_dynamics(cand, x, u, x_next, reg=reg, warm_start=free[:, rest])
                scored.append((value, len(scored), cand))
        scored.sort(key=operator.itemgetter(0, 1))  # the first of equal losses, as tried
        if repair is None:
            current = scored[0][2]
            continue
        shortlist = [cand for _, _, cand in scored[:lookahead]]
        for cand in shortlist:
            repair(cand)
        if len(shortlist) == 1:
            current = shortlist[0]
            continue
        after = [refit_dynamics(c, x, u, x_next, reg=reg) for c in shortlist]
        current = shortlist[min(range(len(shortlist)), key=after.__getitem__)]
    return current
