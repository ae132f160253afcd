r"""Textbook LCP algorithms for ``0 <= lam _|_ w = F lam + q >= 0``, in NumPy, for comparison
with the package's block principal pivoting (:func:`lcs_cvx.solve_lcp`).

One ``F`` ``(n, n)`` and a batch ``q`` ``(B, n)``, as an LCS poses them. Every solver returns
``(lam, ok)``: ``lam`` ``(B, n)`` and ``ok`` ``(B,)`` bool, False where the method stopped
without meeting its own test (iteration cap, line-search failure, ray termination). A
non-converged sample keeps its last iterate; the study counts it as a failure.

- :func:`lemke`: complementary pivoting with the covering vector ``e = 1`` and a
  lexicographic minimum-ratio test (no cycling on degenerate ``q``). A Python loop over the
  samples, one dense tableau each.
- :func:`pgs`: projected Gauss--Seidel, vectorised over the batch (the loop is over the
  coordinates within a sweep).
- :func:`fb_newton`: semismooth Newton on the Fischer--Burmeister reformulation with an Armijo
  line search on ``0.5 ||Phi||^2``, vectorised over the batch (batched LU).
- :func:`osqp_cvxpy`: the package's declared convex problem (P),
  :func:`lcs_cvx.problems.convex_lcp_problem` (valid for nonsymmetric ``F``), solved by OSQP
  through CVXPY, one sample at a time.
- :func:`osqp_direct`: the same (P) handed to OSQP directly, set up once and updated per
  sample (no CVXPY in the loop).
"""

from __future__ import annotations

import numpy as np

__all__ = ["natural_residual", "lemke", "pgs", "fb_newton", "osqp_cvxpy", "osqp_direct"]


def natural_residual(F: np.ndarray, q: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """``|min(lam, F lam + q)|_inf / (1 + |q|_inf)`` per sample -- the same measure as
    :func:`lcs_cvx.lcp.lcp_residual`."""
    w = lam @ F.T + q
    return np.abs(np.minimum(lam, w)).max(-1) / (1.0 + np.abs(q).max(-1))


# ---------------------------------------------------------------------------------------------
# Lemke


def _lemke_one(F: np.ndarray, q: np.ndarray, max_pivots: int) -> tuple[np.ndarray, bool]:
    """One LCP by Lemke's method. Tableau columns: ``w`` (0..n-1), ``z`` (n..2n-1), ``z0`` (2n),
    right-hand side (2n+1); rows ``w - F z - e z0 = q``."""
    n = q.shape[0]
    if np.all(q >= 0.0):
        return np.zeros(n), True
    T = np.zeros((n, 2 * n + 2))
    T[:, :n] = np.eye(n)
    T[:, n:2 * n] = -F
    T[:, 2 * n] = -1.0
    T[:, 2 * n + 1] = q
    basis = np.arange(n)  # variable index basic in each row
    z0 = 2 * n

    def lexmin(rows: np.ndarray, col: np.ndarray) -> int:
        # lexicographic minimum of (rhs_i, B^{-1}_i) / col_i over candidate rows
        cand = rows
        keys = np.concatenate([T[cand, 2 * n + 1:2 * n + 2], T[cand, :n]], axis=1) / col[cand, None]
        for k in range(keys.shape[1]):
            v = keys[:, k]
            m = v.min()
            keep = v <= m + 1e-12 * max(1.0, abs(m))
            cand, keys = cand[keep], keys[keep]
            if cand.size == 1:
                break
        return int(cand[0])

    # first pivot: z0 enters, the row of the most negative q leaves (lexicographically: the
    # minimum of (q_i, B^{-1}_i) / (-1) over all rows, i.e. of -q_i first)
    col = -T[:, z0]
    r = lexmin(np.arange(n), col)
    entering = z0
    for _ in range(max_pivots):
        T[r] /= T[r, entering]
        others = np.arange(n) != r
        T[others] -= np.outer(T[others, entering], T[r])
        leaving = int(basis[r])
        basis[r] = entering
        if leaving == z0:
            lam = np.zeros(n)
            zb = basis >= n
            zb &= basis < 2 * n
            lam[basis[zb] - n] = T[zb, 2 * n + 1]
            return np.maximum(lam, 0.0), True
        entering = leaving + n if leaving < n else leaving - n
        d = T[:, entering]
        rows = np.flatnonzero(d > 1e-12)
        if rows.size == 0:  # ray termination (cannot happen for a P-matrix in exact arithmetic)
            break
        r = lexmin(rows, d)
    lam = np.zeros(n)
    zb = (basis >= n) & (basis < 2 * n)
    lam[basis[zb] - n] = T[zb, 2 * n + 1]
    return np.maximum(lam, 0.0), False


def lemke(F: np.ndarray, q: np.ndarray, max_pivots: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Lemke's method per sample (a Python loop over the batch). ``max_pivots`` defaults to
    ``50 n`` (Lemke ends in finitely many pivots on a P-matrix, in practice O(n))."""
    B, n = q.shape
    cap = 50 * n if max_pivots is None else max_pivots
    lam = np.zeros((B, n))
    ok = np.zeros(B, dtype=bool)
    for b in range(B):
        lam[b], ok[b] = _lemke_one(F, q[b], cap)
    return lam, ok


# ---------------------------------------------------------------------------------------------
# projected Gauss-Seidel


def pgs(F: np.ndarray, q: np.ndarray, tol: float = 1e-12, max_sweeps: int = 1000,
        check_every: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Projected Gauss--Seidel from ``lam = 0``: ``lam_i <- max(0, lam_i - w_i / F_ii)`` in
    coordinate order, the whole batch at once. Stops when the natural residual
    (:func:`natural_residual`) of every sample is below ``tol`` (tested every ``check_every``
    sweeps; converged samples keep sweeping, which does not move them) or after ``max_sweeps``.
    Converges for symmetric positive definite ``F``; not guaranteed otherwise."""
    B, n = q.shape
    lam = np.zeros((B, n))
    Ft = np.ascontiguousarray(F.T)
    diag = np.diag(F).copy()
    ok = np.zeros(B, dtype=bool)
    for sweep in range(1, max_sweeps + 1):
        for i in range(n):
            wi = lam @ Ft[:, i] + q[:, i]
            np.maximum(lam[:, i] - wi / diag[i], 0.0, out=lam[:, i])
        if sweep % check_every == 0 or sweep == max_sweeps:
            res = natural_residual(F, q, lam)
            ok = res <= tol
            if ok.all() or not np.isfinite(lam).all():
                break
    ok &= np.isfinite(lam).all(-1)
    return lam, ok


# ---------------------------------------------------------------------------------------------
# semismooth Newton on Fischer-Burmeister


def _fb(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a + b - np.sqrt(a * a + b * b)


def fb_newton(F: np.ndarray, q: np.ndarray, tol: float = 1e-13, accept: float = 1e-10,
              max_iter: int = 100, sigma: float = 1e-4, beta: float = 0.5,
              max_halvings: int = 40, rho: float = 0.0, p: float = 2.1) -> tuple[np.ndarray, np.ndarray]:
    """Semismooth Newton on ``Phi(lam)_i = phi(lam_i, w_i)``,
    ``phi(a, b) = a + b - sqrt(a^2 + b^2)``, batched.

    Generalised Jacobian ``J = D_a + D_b F`` with ``D_a = 1 - a / r``, ``D_b = 1 - b / r``
    (``r = sqrt(a^2 + b^2)``); at ``a = b = 0`` the element along ``(1, 1)``:
    ``D_a = D_b = 1 - 1/sqrt(2)``. Newton direction ``J d = -Phi``; where it is not a
    descent direction of ``Psi = 0.5 ||Phi||^2`` (``grad . d > -rho ||d||^p``; ``rho = 0``
    by default -- the usual ``rho = 1e-8``, ``p = 2.1`` of De Luca--Facchinei--Kanzow switched
    to steepest descent so often on the stiff problems, whose solutions reach ~1e5, that half
    of them stalled) or the solve fails, the steepest descent ``-J^T Phi``.
    Armijo backtracking ``Psi(lam + t d) <= Psi + sigma t grad . d``, per sample. A sample
    stops when its natural residual is below ``tol`` or its line search fails (then frozen);
    it is reported converged when its residual is below ``accept`` (the stopping target
    ``tol`` is below the rounding floor of solutions of size ~1e5). Start
    ``lam = max(0, -q)``."""
    B, n = q.shape
    lam = np.maximum(-q, 0.0)
    active = np.ones(B, dtype=bool)
    ok = np.zeros(B, dtype=bool)
    eye = np.eye(n)
    c = 1.0 - 1.0 / np.sqrt(2.0)
    for _ in range(max_iter):
        res = natural_residual(F, q, lam)
        ok = res <= tol
        active &= ~ok
        if not active.any():
            break
        idx = np.flatnonzero(active)
        L, Q = lam[idx], q[idx]
        W = L @ F.T + Q
        r = np.sqrt(L * L + W * W)
        zero = r <= 1e-300
        rs = np.where(zero, 1.0, r)
        Da = np.where(zero, c, 1.0 - L / rs)
        Db = np.where(zero, c, 1.0 - W / rs)
        Phi = L + W - r
        J = Da[:, :, None] * eye + Db[:, :, None] * F
        grad = np.einsum("bij,bi->bj", J, Phi)
        try:
            d = np.linalg.solve(J, -Phi[..., None])[..., 0]
            bad_solve = ~np.isfinite(d).all(-1)
        except np.linalg.LinAlgError:
            d = np.zeros_like(L)
            bad_solve = np.ones(len(idx), dtype=bool)
            for k in range(len(idx)):
                try:
                    d[k] = np.linalg.solve(J[k], -Phi[k])
                    bad_solve[k] = not np.isfinite(d[k]).all()
                except np.linalg.LinAlgError:
                    pass
        slope = (grad * d).sum(-1)
        dn = np.linalg.norm(d, axis=-1)
        steep = bad_solve | (slope > -rho * dn ** p)
        d = np.where(steep[:, None], -grad, d)
        slope = np.where(steep, -(grad * grad).sum(-1), slope)
        psi = 0.5 * (Phi * Phi).sum(-1)
        t = np.ones(len(idx))
        done = np.zeros(len(idx), dtype=bool)
        new = L.copy()
        for _h in range(max_halvings):
            cand = L + t[:, None] * d
            Wc = cand @ F.T + Q
            pc = _fb(cand, Wc)
            good = ~done & (0.5 * (pc * pc).sum(-1) <= psi + sigma * t * slope)
            new[good] = cand[good]
            done |= good
            if done.all():
                break
            t = np.where(done, t, beta * t)
        lam[idx] = new
        stuck = ~done
        if stuck.any():  # line search failed: no further progress possible for these samples
            active[idx[stuck]] = False
    res = natural_residual(F, q, lam)
    ok = (res <= accept) & np.isfinite(lam).all(-1)
    return lam, ok


# ---------------------------------------------------------------------------------------------
# convex QP (P) with OSQP

#: OSQP settings for both routes: tight tolerances and solution polishing.
OSQP_OPTIONS = {"eps_abs": 1e-10, "eps_rel": 1e-10, "max_iter": 20000, "polishing": True}


def osqp_cvxpy(F: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P), eq. (5) of the paper -- ``min 1/2 lam^T (F + F^T) lam + q^T lam`` s.t.
    ``lam >= 0``, ``F lam + q >= 0`` -- the package's declaration
    (:func:`lcs_cvx.problems.convex_lcp_problem`), solved with OSQP through CVXPY, one sample at
    a time. Valid for nonsymmetric ``F`` (its optimum is 0 at the LCP solution)."""
    import cvxpy as cp

    from lcs_cvx.problems import convex_lcp_problem

    B, n = q.shape
    decl = convex_lcp_problem(n)
    S = F + F.T
    decl.parameters["R"].value = np.linalg.cholesky(S).T
    decl.parameters["F"].value = F
    lam = np.zeros((B, n))
    ok = np.zeros(B, dtype=bool)
    for b in range(B):
        decl.parameters["q"].value = q[b]
        try:
            decl.problem.solve(solver=cp.OSQP, **OSQP_OPTIONS)
        except cp.error.SolverError:
            continue
        v = decl.variables["lam"].value
        if v is not None and decl.problem.status == cp.OPTIMAL:
            lam[b] = np.maximum(v, 0.0)
            ok[b] = True
        elif v is not None:
            lam[b] = np.maximum(v, 0.0)
    return lam, ok


def osqp_direct(F: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same (P) given to OSQP without CVXPY: ``P = F + F^T``, constraints
    ``[I; F] lam >= [0; -q]``; one setup, then per sample an update of the linear term and the
    lower bounds (the factorisation is reused)."""
    import osqp
    import scipy.sparse as sp

    B, n = q.shape
    P = sp.csc_matrix(np.triu(F + F.T))
    A = sp.csc_matrix(np.vstack([np.eye(n), F]))
    inf = np.full(2 * n, np.inf)
    solver = osqp.OSQP()
    solver.setup(P, q[0], A, np.concatenate([np.zeros(n), -q[0]]), inf, verbose=False,
                 **OSQP_OPTIONS)
    lam = np.zeros((B, n))
    ok = np.zeros(B, dtype=bool)
    for b in range(B):
        if b:
            solver.update(q=q[b], l=np.concatenate([np.zeros(n), -q[b]]))
        res = solver.solve(raise_error=False)
        if res.x is not None and res.x[0] is not None:
            lam[b] = np.maximum(res.x, 0.0)
        ok[b] = res.info.status_val in (1,)  # OSQP_SOLVED
    return lam, ok
