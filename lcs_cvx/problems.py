r"""The two per-sample convex problems of the paper, each declared once.

(P) -- the convex reformulation of the LCP, eq. (5)::

    lam*(q) = argmin_lam  1/2 lam^T (F + F^T) lam + q^T lam   s.t.  lam >= 0,  F lam + q >= 0

  DPP form: parameters ``R`` (with ``R^T R = F + F^T``), ``F`` and ``q``; objective
  ``1/2 ||R lam||^2 + q^T lam``.

(V) -- the violation-based per-sample problem, eq. (9b)::

    l_eps = min_{lam >= 0, phi >= 0}  1/2 ||C lam + r||^2
                                     + (1/eps) (lam^T phi + ||F lam + q - phi||^2 / (2 gamma))

  with ``r = A x + B u + d - x'`` and ``q = D x + E u + c``. ``lam^T phi`` is bilinear, so (V)
  is not DCP as written. For fixed ``lam`` the minimiser over ``phi`` is
  ``phi* = max(0, w - gamma lam)`` (``w = F lam + q``), and eliminating it gives the exact,
  DPP, n_lam-dimensional problem -- (V) times ``eps``, constant terms dropped::

    min_{lam >= 0}  1/2 ||L lam + b||^2 + 1/2 ||pos(K lam - h)||^2

    L^T L = eps C^T C + F + F^T - gamma I     (Cholesky; needs gamma < sigma_min(F + F^T))
    L^T b = eps C^T r + q
    K = (gamma I - F) / sqrt(gamma),          h = q / sqrt(gamma)

  A completed square rather than ``1/2 lam^T H lam + g^T lam`` (see DESIGN.md on cancellation),
  scaled by ``eps`` so that its optimal value is ~|q|^2 rather than ~|q|^2/eps (through diffcp's
  second-order-cone form this took the layer's |d lam| from ~1e-4 to ~1e-7 at eps = 1e-4), and
  independent of ``n_x``.

Each declaration object carries the CVXPY problem, its parameters and variables by name, and
builds the parameter values from torch tensors, differentiably. The CVXPY problem is what the
``cvxpylayers`` layers and the Clarabel reference solve; the fast batched kernels consume the
same data (:mod:`lcs_cvx.lcp`; :mod:`lcs_cvx.violation`, which takes (V) before the
factorisation, :meth:`ViolationProblem.normal_equations`, the one formula the fast loss also
evaluates in its arrays). The value of (V) in the original (lam, phi) variables, from which
gradients are taken, is :meth:`ViolationProblem.objective`; a test checks it against the CVXPY
objective.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import cvxpy as cp
import numpy as np
import torch

from ._checks import LCSInputError, SolverError, check_positive
from ._kernels import violation as kernel
from ._kernels.arrays import TORCH

__all__ = [
    "ConvexLCPProblem",
    "ViolationProblem",
    "convex_lcp_problem",
    "violation_problem",
    "sym_min_eig",
    "check_gamma",
]

#: Clarabel settings for the reference solves (tighter than the defaults: the reference
#: is what the fast kernels are tested against).
CLARABEL_OPTIONS: Mapping[str, float | int] = MappingProxyType({
    "tol_gap_abs": 1e-10,
    "tol_gap_rel": 1e-10,
    "tol_feas": 1e-10,
})


def sym_min_eig(F: torch.Tensor) -> torch.Tensor:
    """sigma_min(F + F^T) -- the smallest eigenvalue of the symmetric part times two.

    Assumption 1 of the paper is ``sym_min_eig(F) > 0``. ``F`` is ``(n, n)`` or ``(B, n, n)``.
    """
    return torch.linalg.eigvalsh(F + F.mT)[..., 0]


def _rows_solve_transposed(U: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Rows ``b_t`` of ``U^T b_t = g_t`` for an upper triangular ``U`` and ``g`` ``(B, n)``:
    ``b = g U^{-1}``, one solve from the right (no transposed copies)."""
    return torch.linalg.solve_triangular(U, g, upper=True, left=False)


def _upper_cholesky(name: str, S: torch.Tensor) -> torch.Tensor:
    """``U`` with ``U^T U = S`` for a symmetric positive definite ``S`` ``(n, n)`` or a stack
    ``(N, n, n)`` (one per sample); a clear error otherwise."""
    Lc, info = torch.linalg.cholesky_ex(S)
    if bool((info != 0).any()):
        raise LCSInputError(
            f"{name}: expected a positive definite matrix, received one with smallest "
            f"eigenvalue {float(torch.linalg.eigvalsh(S).min()):.3e}"
        )
    return Lc.mT


@dataclass(frozen=True, eq=False)
class ConvexLCPProblem:
    """Declaration of (P), eq. (5), for ``n_lam`` complementarity variables.

    Attributes:
        n_lam: dimension of ``lam``.
        problem: the DPP ``cvxpy.Problem``.
        parameters: ``{"R": (n, n), "F": (n, n), "q": (n,)}`` CVXPY parameters.
        variables: ``{"lam": (n,)}``.
    """

    n_lam: int
    problem: cp.Problem = field(repr=False)
    parameters: dict[str, cp.Parameter] = field(repr=False)
    variables: dict[str, cp.Variable] = field(repr=False)

    @property
    def parameter_order(self) -> list[str]:
        return ["R", "F", "q"]

    def parameter_values(self, F: torch.Tensor, q: torch.Tensor) -> dict[str, torch.Tensor]:
        """Parameter values (differentiable) from ``F`` ``(n, n)`` and ``q`` ``(B, n)``."""
        return {"R": _upper_cholesky("F + F^T", F + F.mT), "F": F, "q": q}

    def solve(self, F: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """Solve (P) for each row of ``q`` ``(B, n)`` with Clarabel; returns ``lam`` ``(B, n)``
        of ``q``'s dtype and device (not clamped: Clarabel's interior point may leave
        ``-1e-10``-small entries).

        This is the reference path: one CVXPY solve per sample.
        """
        F_c = F.detach().cpu().to(torch.float64)
        self.parameters["R"].value = _upper_cholesky("F + F^T", F_c + F_c.mT).numpy()
        self.parameters["F"].value = F_c.numpy()
        q_c = q.detach().cpu().to(torch.float64).reshape(-1, self.n_lam).numpy()
        out = np.empty_like(q_c)
        for i, qi in enumerate(q_c):
            self.parameters["q"].value = qi
            _solve_reference(self.problem, f"(P) sample {i}")
            out[i] = self.variables["lam"].value
        return torch.from_numpy(out).to(dtype=q.dtype, device=q.device)


@dataclass(frozen=True, eq=False)
class ViolationProblem:
    """Declaration of (V), eq. (9b), in the DPP form of the module docstring.

    Attributes:
        n_lam: dimension of ``lam``.
        problem: the DPP ``cvxpy.Problem`` in ``lam`` (``phi`` eliminated exactly).
        parameters: ``{"L": (n, n), "b": (n,), "K": (n, n), "h": (n,)}``.
        variables: ``{"lam": (n,)}``.
    """

    n_lam: int
    problem: cp.Problem = field(repr=False)
    parameters: dict[str, cp.Parameter] = field(repr=False)
    variables: dict[str, cp.Variable] = field(repr=False)

    @property
    def parameter_order(self) -> list[str]:
        return ["L", "b", "K", "h"]

    def normal_equations(self, C: torch.Tensor, F: torch.Tensor, q: torch.Tensor, r: torch.Tensor,
                         gamma: float, eps: float, sigma_min_bound: float = 0.0) -> dict[str, torch.Tensor]:
        """(V)'s data before the factorisation: the form the fast kernel consumes.

        ``{"LtL": L^T L = eps C^T C + F + F^T - gamma I, "Ltb": rows of L^T b = eps C^T r + q,
        "K", "h"}``, the quantities of the module docstring that define the parameter values
        (:meth:`parameter_values` factors them), differentiable in every input. The formula is
        :func:`lcs_cvx._kernels.violation.normal_equations`, which the fast violation loss
        evaluates in its own arrays. Arguments as in :meth:`parameter_values`; ``gamma`` is
        checked here.
        """
        check_gamma(F, gamma, sigma_min_bound)
        return kernel.normal_equations(TORCH, C, F, q, r, gamma, eps)

    @staticmethod
    def factor(normal: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """The parameter values ``{"L", "b", "K", "h"}`` from :meth:`normal_equations`: ``L``
        the upper Cholesky factor of ``L^T L`` (a clear error if it is not positive definite),
        ``b`` the rows of ``L^{-T} (L^T b)``."""
        L = _upper_cholesky("eps C^T C + F + F^T - gamma I", normal["LtL"])
        if L.dim() == 3:  # a stack of one problem per sample (lcs_cvx.per_sample): b_t = L_t^-T (L^T b)_t
            b = torch.linalg.solve_triangular(L, normal["Ltb"].unsqueeze(-2), upper=True, left=False).squeeze(-2)
        else:
            b = _rows_solve_transposed(L, normal["Ltb"])
        return {"L": L, "b": b, "K": normal["K"], "h": normal["h"]}

    def parameter_values(
        self,
        C: torch.Tensor,
        F: torch.Tensor,
        q: torch.Tensor,
        r: torch.Tensor,
        gamma: float,
        eps: float,
        sigma_min_bound: float = 0.0,
    ) -> dict[str, torch.Tensor]:
        """Parameter values of (V), differentiable in every input.

        Args:
            C: ``(n_x, n)``; F: ``(n, n)``; q: ``(B, n)`` the LCP offset ``D x + E u + c``;
            r: ``(B, n_x)`` the dynamics residual ``A x + B u + d - x'``;
            gamma, eps: the paper's ``gamma`` (``0 < gamma < sigma_min(F + F^T)``, checked) and
                ``eps``.
            sigma_min_bound: a known lower bound of ``sigma_min(F + F^T)`` (an
                :class:`lcs_cvx.LCS` has ``2 s``): a ``gamma`` below it needs no factorisation
                to be checked (:func:`check_gamma`).

        Returns:
            ``{"L": (n, n), "b": (B, n), "K": (n, n), "h": (B, n)}``.
        """
        return self.factor(self.normal_equations(C, F, q, r, gamma, eps, sigma_min_bound))

    @staticmethod
    def phi(lam: torch.Tensor, F: torch.Tensor, q: torch.Tensor, gamma: float) -> torch.Tensor:
        """The exact minimiser over ``phi`` for fixed ``lam``: ``max(0, F lam + q - gamma lam)``
        (:func:`lcs_cvx._kernels.violation.phi`)."""
        return kernel.phi(TORCH, lam, F, q, gamma)

    @staticmethod
    def hessian_zz(C: torch.Tensor, F: torch.Tensor, gamma: float, eps: float) -> torch.Tensor:
        """``J_zz`` of :meth:`objective` in ``z = (lam, phi)``: ``(2 n, 2 n)`` for one model's
        ``C`` ``(n_x, n)``, ``F`` ``(n, n)``, or ``(B, 2 n, 2 n)`` for one per sample::

            [[C^T C + F^T F / (eps gamma),  (I - F^T / gamma) / eps],
             [(I - F / gamma) / eps,        I / (eps gamma)        ]]
        """
        eye = torch.eye(F.shape[-1], dtype=F.dtype, device=F.device).expand_as(F)
        top = torch.cat([C.mT @ C + F.mT @ F / (eps * gamma), (eye - F.mT / gamma) / eps], dim=-1)
        bottom = torch.cat([(eye - F / gamma) / eps, eye / (eps * gamma)], dim=-1)
        return torch.cat([top, bottom], dim=-2)

    @staticmethod
    def objective(
        lam: torch.Tensor,
        phi: torch.Tensor,
        C: torch.Tensor,
        F: torch.Tensor,
        q: torch.Tensor,
        r: torch.Tensor,
        gamma: float,
        eps: float,
    ) -> torch.Tensor:
        """Per-sample value of eq. (9b) at ``(lam, phi)``, shape ``(B,)``; ``C``, ``F`` one model's
        or one per sample (``(B, n_x, n)``, ``(B, n, n)``).

        ``1/2 ||C lam + r||^2 + (1/eps) (lam^T phi + ||F lam + q - phi||^2 / (2 gamma))``.
        At the detached optimum, autograd of this expression gives Lemma 3's envelope gradients.
        """
        if C.dim() == 3:  # per-sample matrices (lcs_cvx.per_sample): C (B, n_x, n), F (B, n, n)
            e_dyn = (C @ lam.unsqueeze(-1)).squeeze(-1) + r
            w_res = (F @ lam.unsqueeze(-1)).squeeze(-1) + q - phi
        else:
            e_dyn = lam @ C.mT + r
            w_res = lam @ F.mT + q - phi
        return 0.5 * (e_dyn * e_dyn).sum(-1) + (
            (lam * phi).sum(-1) + (w_res * w_res).sum(-1) / (2.0 * gamma)
        ) / eps

    def solve(self, values: dict[str, torch.Tensor]) -> torch.Tensor:
        """Solve (V) for every row of ``values["b"]`` with Clarabel; returns ``lam`` ``(B, n)``
        (clamped at 0) of ``values["b"]``'s dtype and device."""
        self.parameters["L"].value = values["L"].detach().cpu().to(torch.float64).numpy()
        self.parameters["K"].value = values["K"].detach().cpu().to(torch.float64).numpy()
        b = values["b"].detach().cpu().to(torch.float64).numpy()
        h = values["h"].detach().cpu().to(torch.float64).numpy()
        out = np.empty_like(b)
        for i in range(b.shape[0]):
            self.parameters["b"].value = b[i]
            self.parameters["h"].value = h[i]
            _solve_reference(self.problem, f"(V) sample {i}")
            out[i] = self.variables["lam"].value
        lam = torch.from_numpy(np.maximum(out, 0.0))
        return lam.to(dtype=values["b"].dtype, device=values["b"].device)


def check_gamma(F: torch.Tensor, gamma: float, sigma_min_bound: float = 0.0) -> None:
    """Lemma 2's condition ``0 < gamma < sigma_min(F + F^T)``; raise naming both numbers.

    ``gamma < sigma_min(F + F^T)`` iff ``F + F^T - gamma I`` is positive definite, so the check
    is one Cholesky factorisation (of that matrix less a round-off margin, ``1e-12`` relative,
    so that ``gamma`` equal to ``sigma_min`` to working precision is refused); the eigenvalue
    is computed only for the error message. A ``gamma`` below ``sigma_min_bound``, a known lower
    bound of ``sigma_min(F + F^T)``, passes without it.
    """
    check_positive("gamma", gamma)
    if gamma < sigma_min_bound:
        return
    Fd = F.detach()
    S = Fd + Fd.mT
    S.diagonal().sub_(gamma + 1e-12 * max(gamma, float(S.abs().amax())))
    if int(torch.linalg.cholesky_ex(S)[1]) != 0:
        smin = float(sym_min_eig(Fd))
        raise LCSInputError(
            f"gamma: expected 0 < gamma < sigma_min(F + F^T) = {smin:.6g} (Lemma 2), "
            f"received {gamma!r}; lower gamma or raise the model's stiffness"
        )


def _solve_reference(problem: cp.Problem, what: str) -> None:
    """Clarabel with tight tolerances; on failure once more with its defaults, then raise.

    ``warm_start=False``: with CVXPY's default warm start, Clarabel's cached solver is updated
    in place, keeping the equilibration of the first data it saw and the settings of the
    previous call, so the answer (and failure) depended on earlier solves of the declaration.
    """
    status = "no solve"
    for options in (CLARABEL_OPTIONS, {}):
        try:
            problem.solve(solver=cp.CLARABEL, warm_start=False, **dict(options))
        except cp.error.SolverError as exc:
            status = f"solver error ({exc})"
            continue
        status = f"status {problem.status}"
        if problem.status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
            return
    raise SolverError(f"Clarabel failed on {what}: {status}")


@functools.cache
def convex_lcp_problem(n_lam: int) -> ConvexLCPProblem:
    """The DPP declaration of (P), eq. (5), for ``n_lam`` variables (cached)."""
    n = check_positive("n_lam", n_lam, integer=True)
    lam = cp.Variable(n, name="lam")
    R = cp.Parameter((n, n), name="R")
    F = cp.Parameter((n, n), name="F")
    q = cp.Parameter(n, name="q")
    objective = cp.Minimize(0.5 * cp.sum_squares(R @ lam) + q @ lam)
    problem = cp.Problem(objective, [lam >= 0, F @ lam + q >= 0])
    assert problem.is_dpp()
    return ConvexLCPProblem(n, problem, {"R": R, "F": F, "q": q}, {"lam": lam})


@functools.cache
def violation_problem(n_lam: int) -> ViolationProblem:
    """The DPP declaration of (V), eq. (9b), for ``n_lam`` variables (cached)."""
    n = check_positive("n_lam", n_lam, integer=True)
    lam = cp.Variable(n, name="lam")
    L = cp.Parameter((n, n), name="L")
    b = cp.Parameter(n, name="b")
    K = cp.Parameter((n, n), name="K")
    h = cp.Parameter(n, name="h")
    objective = cp.Minimize(
        0.5 * cp.sum_squares(L @ lam + b) + 0.5 * cp.sum_squares(cp.pos(K @ lam - h))
    )
    problem = cp.Problem(objective, [lam >= 0])
    assert problem.is_dpp()
    return ViolationProblem(n, problem, {"L": L, "b": b, "K": K, "h": h}, {"lam": lam})
