"""``cvxpylayers`` layers over the two declared problems -- the reference solver paths.

The layers wrap exactly the CVXPY problems of :mod:`lcs_cvx.problems` (no second copy) and
solve them with diffcp, whose cone solver is Clarabel (default) or SCS. Gradients come from
diffcp's implicit differentiation of the cone program; ``mode="dense"`` is set on every call
that needs gradients because diffcp's default ``mode="lsqr"`` returns wrong gradients on (V)
(DESIGN.md), and only on those: diffcp hands unknown options of a solve-only call to the solver.
The layers run on CPU; tensors on another device are moved there and back.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

import torch
from cvxpylayers.torch import CvxpyLayer

from ._checks import LCSInputError
from .problems import convex_lcp_problem, violation_problem

__all__ = ["LAYER_SOLVERS", "lcp_layer", "violation_layer", "solve_layer"]

#: diffcp options per cone solver (read-only). n_jobs=1: one process, one thread.
LAYER_SOLVERS: Mapping[str, Mapping[str, Any]] = MappingProxyType({
    "clarabel": MappingProxyType({
        "solve_method": "Clarabel",
        "n_jobs_forward": 1,
        # passed on to Clarabel's settings (its defaults, 1e-8, leave |dlam| ~ 1e-6 on (V))
        "tol_gap_abs": 1e-10,
        "tol_gap_rel": 1e-10,
        "tol_feas": 1e-10,
    }),
    "scs": MappingProxyType({
        "solve_method": "SCS",
        "n_jobs_forward": 1,
        "eps_abs": 1e-10,
        "eps_rel": 1e-10,
        "max_iters": 100_000,
    }),
})


def _check_cone_solver(cone_solver: str) -> dict[str, Any]:
    if cone_solver not in LAYER_SOLVERS:
        raise LCSInputError(
            f"cone_solver: expected one of {sorted(LAYER_SOLVERS)}, received {cone_solver!r}"
        )
    return dict(LAYER_SOLVERS[cone_solver])


@functools.cache
def lcp_layer(n_lam: int) -> CvxpyLayer:
    """CvxpyLayer over (P), :func:`lcs_cvx.problems.convex_lcp_problem`; inputs ``R, F, q``."""
    decl = convex_lcp_problem(n_lam)
    params = [decl.parameters[k] for k in decl.parameter_order]
    return CvxpyLayer(decl.problem, parameters=params, variables=[decl.variables["lam"]])


@functools.cache
def violation_layer(n_lam: int) -> CvxpyLayer:
    """CvxpyLayer over (V), :func:`lcs_cvx.problems.violation_problem`; inputs ``L, b, K, h``."""
    decl = violation_problem(n_lam)
    params = [decl.parameters[k] for k in decl.parameter_order]
    return CvxpyLayer(decl.problem, parameters=params, variables=[decl.variables["lam"]])


def solve_layer(layer: CvxpyLayer, values: list[torch.Tensor], cone_solver: str = "clarabel") -> torch.Tensor:
    """Run ``layer`` on parameter tensors (batched ones first dimension ``B``); returns ``lam``.

    Differentiable (diffcp, dense mode). ``cone_solver``: diffcp's cone solver, ``"clarabel"``
    or ``"scs"`` (:data:`LAYER_SOLVERS`). The result is on the device and of the dtype of
    ``values[0]`` (diffcp computes in float64).
    """
    args = dict(_check_cone_solver(cone_solver))
    if torch.is_grad_enabled() and any(v.requires_grad for v in values):
        # only with gradients: a solve-only call hands unknown options to the cone solver
        args.update(mode="dense", n_jobs_backward=1)
    device = values[0].device
    (lam,) = layer(*(v.cpu() for v in values), solver_args=args)
    return lam.to(device=device, dtype=values[0].dtype)
