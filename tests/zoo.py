"""The problem zoo: LCPs ``0 <= lam _|_ F lam + q >= 0`` (eq. (2)) with known answers, and
random P-matrix families, each a :class:`Problem`; and the solver paths that must all solve them
(:data:`SOLVERS`). ``tests/test_zoo.py`` runs every solver on every problem.

Known answers: a contact-free system (``q >= 0``: ``lam = 0``), a 1-D spring against a wall
(:func:`spring_wall`, ``lam`` by hand), decoupled units (``F`` diagonal), and LCPs built from
their solution (strictly complementary, degenerate). Without a known answer, enumeration of the
``2^n`` free sets is the reference (Assumption 1 makes the solution unique). The families:
random P-matrices of several sizes and scales of ``q``, ill-conditioned ones (``sigma_min(F + F^T)`` down to 1e-5,
with a weak or strong skew part) and a nearly skew-symmetric ``F`` (Fig. 1(c)'s stiffest truth,
``G = 0``), on which pivoting needs Murty's rule and many sweeps.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from conftest import random_p_matrix, random_q, strictly_complementary_lcp

import lcs_cvx
from lcs_cvx.lcp import LCPSolution, solve_lcp, solve_lcp_brute, solve_lcp_fast

F64 = torch.float64


@dataclass(frozen=True)
class Problem:
    """One batch of LCPs of size ``n`` sharing ``F``.

    Attributes:
        F: ``(n, n)`` with ``F + F^T`` positive definite; q: ``(B, n)``.
        lam: ``(B, n)`` the known solution, or None (then enumeration's answer is the reference).
        smin: ``sigma_min(F + F^T)`` (the a-posteriori bound on the Clarabel reference).
        atol, rtol: the exact solvers (pivoting, enumeration) agree with the answer to
            ``atol + rtol |lam|_inf`` per sample.
        kkt_tol: their ``lam`` meets the LCP conditions to this, relative to ``1 + |q|``.
        residual_tol: the fast solver's largest :func:`lcs_cvx.lcp.lcp_residual`.
        n_reference: samples given to the Clarabel reference (one CVXPY solve each).
        margin: the reference must agree to 1e-8 absolute on samples whose complementarity
            margin ``min_i max(lam_i, w_i)`` is at least this (inf: the bound only) ...
        min_sharp: ... and there must be at least this many of them.
        degenerate: some ``lam_i = w_i = 0``: the free set there is a matter of round-off.
        arrays_tol: the fast solver in NumPy and in torch agree to this, relative to
            ``1 + |lam|_inf`` (round-off of two BLAS libraries, times the conditioning).
        reference_atol: the reference agrees with the answer to this absolute on every sample.
    """

    F: torch.Tensor
    q: torch.Tensor
    lam: torch.Tensor | None
    smin: float
    atol: float = 1e-8
    rtol: float = 0.0
    kkt_tol: float = 1e-10
    residual_tol: float = 1e-12
    n_reference: int = 16
    margin: float = 1e-2
    min_sharp: int = 0
    degenerate: bool = False
    arrays_tol: float = 1e-12
    reference_atol: float = float("inf")


# -- known answers ---------------------------------------------------------------------------

H_STEP, K_WALL = 0.1, 50.0


def spring_wall() -> lcs_cvx.LCS:
    """Mass at position p, velocity v, unit mass, input force u, time step h. The wall at p = 0
    pushes with impulse-force lam >= 0 and is a spring of stiffness k: the next position may
    penetrate by lam / k, i.e. 0 <= lam _|_ p' + lam / k >= 0 with p' = p + h v + h^2 (u + lam).

        x = (p, v),  A = [[1, h], [0, 1]],  B = C = [[h^2], [h]],  d = 0
        D = [1, h],  E = [h^2],  F = [h^2 + 1/k],  c = 0
    """
    h = H_STEP
    return lcs_cvx.LCS.from_matrices(
        A=[[1.0, h], [0.0, 1.0]], B=[[h * h], [h]], C=[[h * h], [h]], d=[0.0, 0.0],
        D=[[1.0, h]], E=[[h * h]], F=[[h * h + 1.0 / K_WALL]], c=[0.0],
    )


#: (p, v, u) of the spring wall, each a different situation (the first five by hand).
SPRING_POINTS = [
    (1.0, 0.0, 0.0),     # far from the wall, at rest: no contact
    (0.05, -1.0, 0.0),   # would cross the wall: contact
    (0.0, 0.0, -2.0),    # pushed into the wall from rest
    (-0.01, 0.5, 0.0),   # already inside, moving out fast enough: no force
    (0.2, -3.0, 1.0),
]


def spring_wall_by_hand(points) -> tuple[torch.Tensor, torch.Tensor]:
    """``(lam, x')`` of the spring wall at ``points`` ``[(p, v, u), ...]``, by hand: the free
    next position ``p_free = p + h v + h^2 u``, ``lam = max(0, -p_free / (h^2 + 1/k))``."""
    h, k = H_STEP, K_WALL
    lam, xn = [], []
    for p, v, uu in points:
        p_free = p + h * v + h * h * uu
        f = max(0.0, -p_free / (h * h + 1.0 / k))
        lam.append([f])
        xn.append([p_free + h * h * f, v + h * (uu + f)])
    return torch.tensor(lam, dtype=F64), torch.tensor(xn, dtype=F64)


def decoupled(n_lam: int) -> lcs_cvx.LCS:
    """x' = x + lam, 0 <= lam _|_ x + diag(1..n) lam >= 0: lam_i = max(0, -x_i / i), so unit i
    is active exactly when x_i < 0."""
    n = n_lam
    return lcs_cvx.LCS.from_matrices(
        A=np.eye(n), B=np.zeros((n, 0)), C=np.eye(n), d=np.zeros(n),
        D=np.eye(n), E=np.zeros((n, 0)), F=np.diag(np.arange(1.0, n + 1)), c=np.zeros(n),
    ).requires_grad_(False)


def degenerate_lcp(F: torch.Tensor, batch: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(q, lam*)`` where each index is, at random, free, inactive or degenerate (both 0);
    every sample has at least one degenerate index."""
    n = F.shape[0]
    g = np.random.default_rng(seed)
    kind = g.integers(0, 3, (batch, n))  # 0: lam > 0, 1: w > 0, 2: lam = w = 0
    kind[np.arange(batch), g.integers(0, n, batch)] = 2
    lam = np.where(kind == 0, 0.2 + g.random((batch, n)), 0.0)
    w = np.where(kind == 1, 0.2 + g.random((batch, n)), 0.0)
    lam_t = torch.tensor(lam, dtype=F64)
    return torch.tensor(w, dtype=F64) - lam_t @ F.mT, lam_t


def nearly_skew_F(n: int = 8, s: float = 1e-5, seed: int = 5) -> tuple[torch.Tensor, torch.Generator]:
    """``F = s I + H - H^T`` with ``H`` uniform in [-1, 1]: Fig. 1(c)'s stiffest truth (``G = 0``),
    ``sigma_min(F + F^T) = 2 s``; and the generator, to draw ``q`` from."""
    gen = torch.Generator().manual_seed(seed)
    H = torch.rand(n, n, generator=gen, dtype=F64) * 2 - 1
    return s * torch.eye(n, dtype=F64) + H - H.mT, gen


def _sym_min(F: torch.Tensor) -> float:
    return float(torch.linalg.eigvalsh(F + F.mT)[0])


# -- the problems ----------------------------------------------------------------------------


def _contact_free() -> Problem:
    F = random_p_matrix(4, seed=0)
    q = random_q(50, 4, seed=1).abs()
    return Problem(F, q, torch.zeros_like(q), _sym_min(F), atol=0.0, min_sharp=8)


def _spring_wall() -> Problem:
    g = np.random.default_rng(0)
    extra = [(p, v, uu) for p, v, uu in zip(g.uniform(-0.2, 1.0, 45), g.uniform(-3, 3, 45),
                                            g.uniform(-2, 2, 45), strict=True)]
    points = SPRING_POINTS + extra
    sys = spring_wall()
    x = torch.tensor([[p, v] for p, v, _ in points], dtype=F64)
    u = torch.tensor([[uu] for *_, uu in points], dtype=F64)
    with torch.no_grad():
        F, q = sys.F, sys.lcp_offset(x, u)
    return Problem(F, q, spring_wall_by_hand(points)[0], _sym_min(F), atol=1e-12, min_sharp=8)


def _decoupled() -> Problem:
    x = torch.tensor(np.random.default_rng(0).uniform(-1, 1, (300, 3)), dtype=F64)
    F = torch.diag(torch.arange(1.0, 4.0, dtype=F64))
    return Problem(F, x, (-x).clamp(min=0.0) / torch.arange(1.0, 4.0, dtype=F64), 2.0, atol=1e-15,
                   min_sharp=8)


def _strictly_complementary(n: int) -> Problem:
    F = random_p_matrix(n, smin=1.0, seed=60 + n)
    q, lam = strictly_complementary_lcp(F, 50, seed=n)
    return Problem(F, q, lam, 1.0, atol=1e-12, min_sharp=16)


def _random_p(n: int) -> Problem:
    F = random_p_matrix(n, smin=0.5, seed=n)
    return Problem(F, random_q(300, n, seed=10 + n, scale=3.0), None, 0.5, min_sharp=8)


def _degenerate(n: int) -> Problem:
    F = random_p_matrix(n, smin=0.5, seed=20 + n)
    q, lam = degenerate_lcp(F, 100, seed=n)
    # An interior-point method meets a degenerate index (lam_i = w_i = 0) at the analytic
    # centre, lam_i ~ w_i ~ sqrt(gap tolerance) ~ 1e-5 (measured 4e-6..1.1e-5): Clarabel cannot
    # give 1e-8 there, only its residual-based bound.
    return Problem(F, q, lam, 0.5, atol=1e-12, kkt_tol=1e-12, n_reference=10, margin=float("inf"),
                   degenerate=True, reference_atol=1e-4)


def _ill_conditioned(n: int, smin: float, skew: float) -> Problem:
    F = random_p_matrix(n, smin=smin, seed=30 + n, skew=skew)
    return Problem(F, random_q(400, n, seed=n), None, smin, rtol=1e-8, residual_tol=1e-10,
                   margin=float("inf"))


def _wide_q(n: int, smin: float) -> Problem:
    F = random_p_matrix(n, smin=smin, seed=n)
    return Problem(F, random_q(500, n, seed=n, scale=10.0), None, smin, atol=1e-9, rtol=1e-9,
                   margin=float("inf"))


def _nearly_skew() -> Problem:
    F, gen = nearly_skew_F()
    q = 10 * (torch.rand(3000, 8, generator=gen, dtype=F64) * 2 - 1)
    # |lam| reaches 1.3e6 here: NumPy and torch measured 2.9e-12 apart
    return Problem(F, q, None, 2e-5, rtol=1e-8, residual_tol=1e-10, margin=float("inf"),
                   arrays_tol=1e-10)


#: name -> builder of every problem of the zoo.
BUILDERS: dict[str, Callable[[], Problem]] = {
    "contact-free": _contact_free,
    "spring-wall": _spring_wall,
    "decoupled-3": _decoupled,
    **{f"strictly-complementary-{n}": functools.partial(_strictly_complementary, n) for n in (1, 3, 6)},
    **{f"random-P-{n}": functools.partial(_random_p, n) for n in range(1, 9)},
    **{f"degenerate-{n}": functools.partial(_degenerate, n) for n in (1, 2, 3, 5, 8)},
    **{f"ill-conditioned-{n}-{smin:g}-{skew:g}": functools.partial(_ill_conditioned, n, smin, skew)
       for n in (2, 4, 8) for smin in (1e-3, 1e-4, 1e-5) for skew in (1.0, 1e-3)},
    **{f"wide-q-{n}-{smin:g}": functools.partial(_wide_q, n, smin)
       for n, smin in ((3, 0.5), (6, 0.1), (8, 1e-5))},
    "nearly-skew-8": _nearly_skew,
}


@functools.cache
def problem(name: str) -> Problem:
    """The zoo's problem ``name`` (built once)."""
    return BUILDERS[name]()


@functools.cache
def answer(name: str) -> torch.Tensor:
    """The known solution of problem ``name``, else enumeration's."""
    p = problem(name)
    return p.lam if p.lam is not None else solve_lcp_brute(p.F, p.q).lam


# -- checks of an answer ---------------------------------------------------------------------

ATOL = 1e-8  # absolute agreement on lam of the Clarabel reference on well-posed samples


def max_abs(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max())


def assert_lcp_conditions(F, q, lam, tol=1e-10):
    """lam >= 0, w = F lam + q >= 0 and lam_i w_i = 0, to ``tol`` relative to ``1 + |q|``."""
    w = lam @ F.mT + q
    scale = 1.0 + q.abs().amax(-1, keepdim=True) + lam.abs().amax(-1, keepdim=True)
    assert bool((lam >= 0).all())
    assert bool((w >= -tol * scale).all()), float(w.min())
    assert bool(((lam * w).abs() <= tol * scale * scale).all()), float((lam * w).abs().max())


def check_against_reference(F, q, lam, ref_lam, smin, margin=1e-2):
    """Compare the exact ``lam`` with Clarabel's ``ref_lam``.

    An interior-point answer is accurate in its residual, not in ``lam``: its error is about
    ``residual * |F_II^{-1}| / (complementarity margin)``. Two checks:

    - every sample: the a-posteriori bound for strongly monotone LCPs (Pang 1987;
      Facchinei & Pang 2003, Prop. 6.3.1) with modulus ``mu = smin / 2`` (``lam^T F lam =
      lam^T (F + F^T) lam / 2``): ``|ref - lam*|_2 <= (1 + |F|_2) / mu * |min(ref, F ref + q)|_2``
      (plus round-off of ``lam`` itself);
    - samples whose margin ``min_i max(lam_i, w_i)`` is at least ``margin``: the full 1e-8
      absolute agreement.

    Returns the number of samples that got the 1e-8 check.
    """
    err2 = (lam - ref_lam).norm(dim=-1)
    r = torch.minimum(ref_lam, ref_lam @ F.mT + q).norm(dim=-1)
    bound = (1.0 + torch.linalg.matrix_norm(F, 2)) / (smin / 2.0) * r
    slack = 1e-12 * (1.0 + lam.abs().amax(-1))
    assert bool((err2 <= bound + slack).all()), float((err2 - bound - slack).max())
    w = lam @ F.mT + q
    sharp = torch.maximum(lam, w).amin(-1) >= margin
    err = (lam - ref_lam).abs().amax(-1)
    if bool(sharp.any()):
        assert float(err[sharp].max()) <= ATOL, float(err[sharp].max())
    return int(sharp.sum())


# -- the solvers -----------------------------------------------------------------------------

#: name -> ``solve(F, q) -> LCPSolution``: the fast pivoting in each array library, enumeration
#: of the 2^n free sets, and the declared problem (P) solved by Clarabel (the reference).
SOLVERS: dict[str, Callable[[torch.Tensor, torch.Tensor], LCPSolution]] = {
    "fast-numpy": functools.partial(solve_lcp_fast, arrays="numpy"),
    "fast-torch": functools.partial(solve_lcp_fast, arrays="torch"),
    "brute": solve_lcp_brute,
    "cvxpy": functools.partial(solve_lcp, method="cvxpy"),
}
FAST = ("fast-numpy", "fast-torch")
