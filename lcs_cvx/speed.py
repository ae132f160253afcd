"""Speed on the paths users take, side by side in one process: a :func:`lcs_cvx.fit` step on a
large batch against the one-call loss and gradient of the same batch, and C3's defaults against
a plain dense C3+ on C3's cart-pole (``lcs-cvx bench --fit-step``, ``--c3``; the thread scaling
of the compiled kernels is :func:`lcs_cvx.bench.run_throughput`).

Both time two things interleaved, round by round, and keep medians: a shared machine's slow
phases then fall on both sides.
"""

from __future__ import annotations

import contextlib
import statistics
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import numpy as np
import torch

from .bench import perturbed
from .data import make_dataset, random_lcs

__all__ = ["DenseC3Plus", "run_c3_bench", "run_fit_step"]


def run_fit_step(batches: Iterable[int] = (200_000, 1_000_000), size: tuple[int, int, int] = (10, 4, 4),
                 loss: str = "violation", threads: int = 2, repeats: int = 5, seed: int = 0,
                 progress: Callable[[str], None] | None = None) -> str:
    """The time of one :func:`lcs_cvx.fit` step at full batch (``recipe="paper"``,
    ``batch_size`` the data's size, on ``threads`` threads) against one call of the loss and its
    gradient on the same data (:func:`lcs_cvx.violation_value_and_grad` or
    :func:`lcs_cvx.prediction_value_and_grad`). A step's time is the difference of a fit of 8
    and a fit of 2 iterations over 6 (what a fit pays once cancels: its checks, the first step,
    which creates Adam's state); each repeat times both fits and then the loss and gradient
    three times (their median), after a warm-up fit. Returns a markdown table of the medians."""
    n_x, n_u, n_lam = size
    truth = random_lcs(n_x, n_u, n_lam, stiffness=0.5, seed=seed)
    lines = ["| (n_x, n_u, n_λ) | loss | threads | batch | `fit` step (ms) | loss + gradient (ms) | ratio |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for batch in batches:
        data = make_dataset(truth, batch, noise=1e-2, seed=seed + 1)
        step, call = _fit_step_times(perturbed(truth, 0.05, seed + 2), data, loss, threads, repeats)
        lines.append(f"| ({n_x}, {n_u}, {n_lam}) | {loss} | {threads} | {batch:,} | {1e3 * step:.1f} | "
                     f"{1e3 * call:.1f} | {step / call:.2f} |")
        if progress is not None:
            progress(lines[-1])
    return "\n".join(lines)


def _fit_step_times(model: Any, data: Any, loss: str, threads: int, repeats: int) -> tuple[float, float]:
    """:func:`run_fit_step`'s medians for one batch: ``(fit step, loss and gradient)`` in s."""
    from .train import fit
    from .value_and_grad import prediction_value_and_grad, violation_value_and_grad

    value_and_grad = violation_value_and_grad if loss == "violation" else prediction_value_and_grad

    def run(k: int) -> float:
        t0 = time.perf_counter()
        fit(model, data, recipe="paper", loss=loss, batch_size=len(data), iterations=k, eval_every=10**9,
            progress=False, threads=threads)
        return time.perf_counter() - t0

    def once() -> float:
        t0 = time.perf_counter()
        value_and_grad(model, data.x, data.u, data.x_next, threads=threads)
        return time.perf_counter() - t0

    run(3)
    once()
    steps, calls = [], []
    for _ in range(repeats):
        steps.append((run(8) - run(2)) / 6)
        calls.append(statistics.median([once() for _ in range(3)]))
    return statistics.median(steps), statistics.median(calls)


class DenseC3Plus:
    """C3 with the "c3+" projection written plainly, the reference a structured solve must beat:
    at every QP step the dense KKT system of the whole horizon (C3's QP step: the cost plus
    ``(z - delta + w)^T G (z - delta + w)`` under the dynamics, ``eta = D x + E u + F lam + c``,
    ``x_0 = x0`` and, where C3 fixes it, ``lam_0``) is assembled and solved by
    ``np.linalg.solve``; the projection is C3+'s closed form per coordinate. ``ctrl``: a
    :class:`lcs_cvx.control.C3` with ``projection="c3+"`` (its horizon, weights and ADMM
    settings are taken)."""

    def __init__(self, ctrl: Any):
        self.c = ctrl
        hz, lay = ctrl.horizon, ctrl.layout
        self.N, self.nz, self.nx = hz.N, lay.n_z, hz.n_x
        N, nz, nx, nl = self.N, self.nz, self.nx, hz.n_lam
        self.n_y = N * nz + nx
        m = nx + N * nx + N * nl + (nl if ctrl.fix_lam0 else 0)  # x0, dynamics, eta, lam0 rows
        A, b0 = np.zeros((m, self.n_y)), np.zeros(m)

        def xi(k: int) -> np.ndarray:
            return np.arange(nx) + (k * nz if k < N else N * nz)

        def part(k: int, s: slice) -> np.ndarray:
            return np.arange(s.start, s.stop) + k * nz

        A[:nx, xi(0)] = np.eye(nx)
        r = nx
        for k in range(N):
            A[r:r + nx, xi(k + 1)] = np.eye(nx)
            A[r:r + nx, xi(k)] -= hz.A[k]
            A[r:r + nx, part(k, lay.u)] -= hz.B[k]
            A[r:r + nx, part(k, lay.lam)] -= hz.C[k]
            b0[r:r + nx] = hz.d[k]
            r += nx
        for k in range(N):
            A[r:r + nl, part(k, lay.eta)] = np.eye(nl)
            A[r:r + nl, xi(k)] -= hz.D[k]
            A[r:r + nl, part(k, lay.u)] -= hz.E[k]
            A[r:r + nl, part(k, lay.lam)] -= hz.F[k]
            b0[r:r + nl] = hz.c[k]
            r += nl
        self.lam0_rows = slice(r, r + nl) if ctrl.fix_lam0 else None
        if ctrl.fix_lam0:
            A[r:r + nl, part(0, lay.lam)] = np.eye(nl)
        self.Aeq, self.b0, self.m = A, b0, m
        H0 = np.zeros((self.n_y, self.n_y))
        for k in range(N + 1):
            H0[np.ix_(xi(k), xi(k))] += 2 * (ctrl.Q[k] if k < N else ctrl.QN)
            if k < N:
                H0[np.ix_(part(k, lay.u), part(k, lay.u))] += 2 * ctrl.R[k]
        self.H0 = H0
        self.Gbig = np.zeros((self.n_y, self.n_y))
        for k in range(N):
            z = np.arange(k * nz, (k + 1) * nz)
            self.Gbig[np.ix_(z, z)] = ctrl.G[k]
        U = ctrl.U[0]
        self.w_lam, self.w_eta = np.diag(U)[lay.lam], np.diag(U)[lay.eta]
        self.lay = lay

    def solve(self, x0: np.ndarray) -> np.ndarray:
        """The first input ``u_0`` ``(n_u,)`` of the plan from ``x0`` ``(n_x,)``."""
        c, lay, N, nz = self.c, self.lay, self.N, self.nz
        hz = c.horizon
        b = self.b0.copy()
        b[: self.nx] = x0
        if self.lam0_rows is not None:
            q = hz.D[0] @ x0 + hz.c[0]
            b[self.lam0_rows] = (c.model.solve_lcp(x0, np.zeros(hz.n_u)).lam[0].detach().numpy()
                                 if q.min() < 0 else 0.0)
        delta, w = np.zeros((N, nz)), np.zeros((N, nz))
        rho = 1.0
        for i in range(c.admm_iterations + 1):
            target = delta - w if i < c.admm_iterations else delta
            H = self.H0 + 2 * rho * self.Gbig
            f = np.zeros(self.n_y)
            f[: N * nz] = -2 * rho * (self.Gbig[: N * nz, : N * nz] @ target.reshape(-1))
            K = np.block([[H, self.Aeq.T], [self.Aeq, np.zeros((self.m, self.m))]])
            y = np.linalg.solve(K, np.concatenate([-f, b]))[: self.n_y]
            z = y[: N * nz].reshape(N, nz)
            if i == c.admm_iterations:
                return z[0, lay.u]
            p = z + w
            lam, eta = p[:, lay.lam], p[:, lay.eta]
            keep = eta * np.sqrt(self.w_eta) > lam * np.sqrt(self.w_lam)
            new = p.copy()
            new[:, lay.lam] = np.maximum(np.where(keep, 0.0, lam), 0.0)
            new[:, lay.eta] = np.maximum(np.where(keep, eta, 0.0), 0.0)
            w = (w + z - new) / c.rho_scale
            delta = new
            rho *= c.rho_scale
        raise AssertionError  # pragma: no cover - the loop returns


def run_c3_bench(solves: int = 50, repeats: int = 7, seed: int = 0,
                 progress: Callable[[str], None] | None = None) -> str:
    """Time per solve on C3's cart-pole (:func:`lcs_cvx.control.c3_cartpole`, its ``"c3+"``
    weights) of C3 with its defaults (projection ``"auto"`` and the polish), unbounded and with
    ``|u|`` bounded at 60 % of the peak of the unbounded c3+ plan from C3's ``x0``, and of the
    ``"c3+"`` projection alone, against :class:`DenseC3Plus` (checked to plan the same first
    input as C3's "c3+" to 1e-6), on ``solves`` initial states drawn around the upright (one
    torch thread); each of ``repeats`` rounds times every controller on every state in turn.
    Returns a markdown table of the medians over rounds of the mean time per solve."""
    from .control import C3, c3_cartpole

    P = c3_cartpole()
    G, U = P.weights["c3+"]
    states = np.random.default_rng(seed).uniform([-0.3, -0.6, -0.6, -0.6], [0.3, 0.6, 0.6, 0.6], (solves, 4))
    plus = C3(P.model, P.horizon, Q=P.Q, R=P.R, G=G, U=U, projection="c3+", gap_tol=None, polish=0)
    bound = 0.6 * float(plus.solve(P.x0).u.abs().max())
    ctrls: dict[str, Any] = {
        "C3 defaults (auto + polish)": C3(P.model, P.horizon, Q=P.Q, R=P.R, G=G, U=U, gap_tol=None),
        f"C3 defaults, u in ±{bound:.2f}": C3(P.model, P.horizon, Q=P.Q, R=P.R, G=G, U=U, gap_tol=None,
                                              u_bounds=(-bound, bound)),
        "c3+ projection, no polish": plus,
    }
    dense = DenseC3Plus(plus)
    for x0 in states[:5]:
        if not np.allclose(dense.solve(x0), plus.solve(x0).u[0].numpy(), atol=1e-6):
            raise AssertionError("the dense C3+ does not plan what C3's c3+ plans")  # pragma: no cover
    times: dict[str, list[float]] = {name: [] for name in (*ctrls, "dense C3+ (NumPy)")}
    with _one_torch_thread():
        for _ in range(repeats):
            for name, fn in (*((k, c.solve) for k, c in ctrls.items()), ("dense C3+ (NumPy)", dense.solve)):
                t0 = time.perf_counter()
                for x0 in states:
                    fn(x0)
                times[name].append((time.perf_counter() - t0) / solves)
    ref = statistics.median(times["dense C3+ (NumPy)"])
    lines = ["| controller | ms per solve | × dense C3+ |", "|---|---:|---:|"]
    for name, ts in times.items():
        med = statistics.median(ts)
        lines.append(f"| {name} | {1e3 * med:.3f} | {med / ref:.2f} |")
        if progress is not None:
            progress(lines[-1])
    return "\n".join(lines)


@contextlib.contextmanager
def _one_torch_thread() -> Iterator[None]:
    """torch on one thread inside, the count before restored after."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)
