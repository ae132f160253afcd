"""The cells of the differentiable-paths comparison (:mod:`studies.solvers.differentiable_paths`):
the data, the QPs of (P) and (V), every path's loss, solution and gradient, and one row timed."""

from __future__ import annotations

import contextlib
import functools
import math
import os
import statistics
import sys
import time
import warnings
from collections.abc import Callable

import numpy as np
import torch

import lcs_cvx
from lcs_cvx.bench import median_time, perturbed
from lcs_cvx.layers import lcp_layer, violation_layer
from lcs_cvx.lcp import active_set_solve
from lcs_cvx.losses import prediction_fast, violation_fast
from lcs_cvx.problems import convex_lcp_problem, violation_problem
from lcs_cvx.system import LCS, PARAMETER_NAMES

DATE = time.strftime("%Y-%m-%d")
MACHINE = "x86_64 2-core VM, one torch thread, the other core busy with other work"
GAMMA, EPS = 1e-2, 1e-4
PERTURB = 0.05
N_DATA = 50_000
SIZES = ((10, 4, 4), (10, 4, 20))
BATCHES = (1, 200, 50_000)
SMOKE_SIZES = ((4, 2, 3),)
SMOKE_BATCHES = (1, 20)
LOSSES = ("violation", "prediction")
PATHS = ("fast", "cvxpylayers", "cvxpylayers-scs", "cvxpylayers-ecos", "qpth", "qplayer",
         "qpoases")
#: paths that solve the whole batch in one batched computation (the rest loop over samples)
BATCHED = ("fast", "qpth")
#: a call estimated to take longer than this at the largest batch is not run
SKIP_SECONDS = 60.0
#: calls longer than this are timed as one warm-up call and REPEATS timed calls
SLOW_CALL_S = 1.0
REPEATS = 5
#: qpOASES: an index is free (lam_i > 0) above this, relative to 1 + |q|_inf
FREE_TOL = 1e-9

PATH_NOTES = {
    "fast": "package kernels (`solver=\"fast\"`, as a training step runs them): exact pivoting "
            "(compiled, each sample on its own), closed-form gradients",
    "cvxpylayers": "package `solver=\"cvxpylayers\"`: diffcp + Clarabel (tolerances 1e-10), dense "
                   "mode; includes the package's KKT-residual check",
    "cvxpylayers-scs": "package `solver=\"cvxpylayers-scs\"`: diffcp + SCS (eps 1e-10, 1e5 "
                       "iterations); includes the KKT-residual check",
    "cvxpylayers-ecos": "the package's layers with diffcp + ECOS (abstol = reltol = feastol = "
                        "1e-10), dense mode",
    "qpth": "`qpth.qp.QPFunction(eps=1e-12, maxIter=50)`, batched PDIPM",
    "qplayer": "`proxsuite.torch.qplayer.QPFunction(eps=1e-10, eps_backward=1e-9, "
               "rho_backward=mu_backward=1e-9)`, serial",
    "qpoases": "CasADi `conic('qpoases')` mapped over the batch (forward), gradient written "
               "here: envelope theorem (V) / implicit function on the active set (P)",
}


# -- data -----------------------------------------------------------------------------------------
@functools.cache
def setup(size: tuple[int, int, int], n_data: int) -> tuple[LCS, lcs_cvx.Dataset]:
    n_x, n_u, n_lam = size
    truth = lcs_cvx.random_lcs(n_x, n_u, n_lam, stiffness=0.5, seed=0)
    data = lcs_cvx.make_dataset(truth, n_data, noise=1e-2, seed=1)
    return perturbed(truth, PERTURB, 2), data


# -- the QPs of (P) and (V) -----------------------------------------------------------------------
def terms(model: LCS, x: torch.Tensor, u: torch.Tensor, xn: torch.Tensor):
    """``F``, ``C``, ``q = D x + E u + c``, ``r = A x + B u + d - x'`` (differentiable)."""
    q = x @ model.D.mT + u @ model.E.mT + model.c
    r = x @ model.A.mT + u @ model.B.mT + model.d - xn
    return model.F, model.C, q, r


def violation_qp(C: torch.Tensor, F: torch.Tensor, q: torch.Tensor, r: torch.Tensor,
                 gamma: float, eps: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(Q (2n, 2n), p (B, 2n))`` of (V) in ``z = (lam, phi)`` times ``eps`` (module docstring)."""
    n = F.shape[0]
    eye = torch.eye(n, dtype=F.dtype)
    Q = torch.cat([
        torch.cat([eps * C.mT @ C + F.mT @ F / gamma, eye - F.mT / gamma], 1),
        torch.cat([eye - F / gamma, eye / gamma], 1),
    ], 0)
    p = torch.cat([eps * r @ C + q @ F / gamma, -q / gamma], 1)
    return Q, p


def prediction_from_lam(model: LCS, x, u, xn, lam) -> torch.Tensor:
    pred = x @ model.A.mT + u @ model.B.mT + lam @ model.C.mT + model.d
    return 0.5 * ((pred - xn) ** 2).sum(-1).mean()


# -- qpOASES through CasADi -----------------------------------------------------------------------
@functools.cache
def _qpoases(kind: str, n: int, batch: int):
    """A CasADi conic function (qpOASES) for (V) (``2n`` variables, bounds only) or (P)
    (``n`` variables, ``F lam + q >= 0``), mapped over ``batch`` samples."""
    import casadi as ca

    opts = {"printLevel": "none", "error_on_fail": False}
    if kind == "V":
        S = ca.conic("S", "qpoases", {"h": ca.Sparsity.dense(2 * n, 2 * n),
                                       "a": ca.Sparsity(0, 2 * n)}, opts)
    else:
        S = ca.conic("S", "qpoases", {"h": ca.Sparsity.dense(n, n),
                                       "a": ca.Sparsity.dense(n, n)}, opts)
    return S if batch == 1 else S.map(batch)


@contextlib.contextmanager
def _quiet_stdout():
    """qpOASES prints its licence banner from C on first use: send file descriptor 1 to
    /dev/null meanwhile (two system calls, negligible against a solve)."""
    sys.stdout.flush()
    saved = os.dup(1)
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 1)
    try:
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(null)


def qpoases_violation(Q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(V)'s ``z = (lam, phi)`` ``(B, 2n)`` by qpOASES, from ``Q`` ``(2n, 2n)``, ``p`` ``(B, 2n)``."""
    B, m = p.shape
    with _quiet_stdout():
        S = _qpoases("V", m // 2, B)
        out = S(h=Q, g=p.T, lbx=0.0, ubx=np.inf)
    return np.asarray(out["x"]).T.reshape(B, m)


def qpoases_lcp(F: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The LCP's ``lam`` ``(B, n)`` by qpOASES on (P), from ``F`` ``(n, n)``, ``q`` ``(B, n)``."""
    B, n = q.shape
    with _quiet_stdout():
        S = _qpoases("P", n, B)
        out = S(h=F + F.T, g=q.T, a=F, lba=-q.T, uba=np.inf, lbx=0.0, ubx=np.inf)
    return np.asarray(out["x"]).T.reshape(B, n)


# -- the paths ------------------------------------------------------------------------------------
_ECOS = {"solve_method": "ECOS", "n_jobs_forward": 1, "n_jobs_backward": 1, "mode": "dense",
         "abstol": 1e-10, "reltol": 1e-10, "feastol": 1e-10}


def _qpth(Q, p, G, h):
    from qpth.qp import QPFunction

    # every input with the batch dimension: qpth averages the gradient of an input without one
    # over the batch (instead of summing it), which scales those gradients by 1/B
    B = p.shape[0]
    Q = Q.expand(B, *Q.shape[-2:])
    G = G.expand(B, *G.shape[-2:])
    h = h.expand(B, G.shape[-2])
    e = torch.empty(0, dtype=Q.dtype)
    return QPFunction(verbose=-1, eps=1e-12, maxIter=50)(Q, p, G, h, e, e)


def _qplayer(Q, p, G, lo, hi):
    from proxsuite.torch.qplayer import QPFunction

    e = torch.empty(0, dtype=Q.dtype)
    z, _, _ = QPFunction(eps=1e-10, maxIter=1000, eps_backward=1e-9, rho_backward=1e-9,
                         mu_backward=1e-9)(Q, p, e, e, G, lo, hi)
    return z


def loss_and_lam(loss: str, path: str, model: LCS, x, u, xn, gamma: float = GAMMA,
                 eps: float = EPS) -> tuple[torch.Tensor, torch.Tensor]:
    """The differentiable loss and the (detached) ``lam`` of one call of ``path``; ``gamma``,
    ``eps``: the violation loss's."""
    if path == "fast":  # what a training step runs (no diagnostics: the residual is not formed)
        if loss == "violation":
            info = violation_fast(model, x, u, xn, gamma=gamma, eps=eps)
        else:
            info = prediction_fast(model, x, u, xn)
        return info.loss, info.lam
    if path in ("cvxpylayers", "cvxpylayers-scs"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", lcs_cvx.LayerAccuracyWarning)
            if loss == "violation":
                info = lcs_cvx.violation_loss_info(model, x, u, xn, gamma=gamma, eps=eps, solver=path)
            else:
                info = lcs_cvx.prediction_loss_info(model, x, u, xn, solver=path)
        return info.loss, info.lam
    n = model.n_lam
    F, C, q, r = terms(model, x, u, xn)
    decl = violation_problem(n)
    if loss == "violation":
        if path == "cvxpylayers-ecos":
            vals = decl.parameter_values(C, F, q, r, gamma, eps)
            (lam,) = violation_layer(n)(*(vals[k] for k in decl.parameter_order), solver_args=_ECOS)
            lam = lam.clamp(min=0.0)
            phi = decl.phi(lam, F, q, gamma)
        else:
            Q, p = violation_qp(C, F, q, r, gamma, eps)
            m = 2 * n
            if path == "qpth":
                z = _qpth(Q, p, -torch.eye(m, dtype=Q.dtype), torch.zeros(m, dtype=Q.dtype))
            elif path == "qplayer":
                z = _qplayer(Q, p, torch.eye(m, dtype=Q.dtype), torch.zeros(m, dtype=Q.dtype),
                             torch.full((m,), 1e20, dtype=Q.dtype))
            elif path == "qpoases":  # forward by qpOASES; the envelope theorem: z detached
                z = torch.from_numpy(qpoases_violation(Q.detach().numpy(), p.detach().numpy()))
            else:
                raise ValueError(path)
            lam, phi = z[:, :n], z[:, n:]
        value = decl.objective(lam, phi, C, F, q, r, gamma, eps).mean()
        return value, lam.detach()
    if path == "cvxpylayers-ecos":
        pdecl = convex_lcp_problem(n)
        vals = pdecl.parameter_values(F, q)
        (lam,) = lcp_layer(n)(*(vals[k] for k in pdecl.parameter_order), solver_args=_ECOS)
    elif path == "qpth":
        G = torch.cat([-torch.eye(n, dtype=F.dtype), -F], 0)
        h = torch.cat([torch.zeros_like(q), q], 1)
        lam = _qpth(F + F.mT, q, G, h)
    elif path == "qplayer":
        G = torch.cat([torch.eye(n, dtype=F.dtype), F], 0)
        lo = torch.cat([torch.zeros_like(q), -q], 1)
        lam = _qplayer(F + F.mT, q, G, lo, torch.full_like(lo, 1e20))
    elif path == "qpoases":  # forward by qpOASES; Lemma 1 on its active set
        lam0 = torch.from_numpy(qpoases_lcp(F.detach().numpy(), q.detach().numpy()))
        tol = FREE_TOL * (1.0 + q.detach().abs().amax(1, keepdim=True))
        lam = active_set_solve(F, q, lam0 > tol)
    else:
        raise ValueError(path)
    return prediction_from_lam(model, x, u, xn, lam), lam.detach()


def grads(model: LCS) -> list[torch.Tensor]:
    return [getattr(model, k).grad.detach().clone() if getattr(model, k).grad is not None
            else torch.zeros_like(getattr(model, k)) for k in PARAMETER_NAMES]


def call(loss: str, path: str, model: LCS, x, u, xn) -> tuple[float, torch.Tensor, list[torch.Tensor]]:
    """One timed unit: the loss and its backward; returns (loss, lam, gradients)."""
    model.zero_grad()
    if path == "qplayer":  # its backward allocates in the default dtype: make it float64
        old = torch.get_default_dtype()
        torch.set_default_dtype(torch.float64)
        try:
            value, lam = loss_and_lam(loss, path, model, x, u, xn)
            value.backward()
        finally:
            torch.set_default_dtype(old)
    else:
        value, lam = loss_and_lam(loss, path, model, x, u, xn)
        value.backward()
    return float(value.detach()), lam, grads(model)


# -- timing ---------------------------------------------------------------------------------------
class TooSlow(Exception):
    """The warm-up call took longer than the limit (seconds in ``args[0]``)."""


def timed(fn: Callable[[], object], limit: float = math.inf) -> tuple[float, str, object]:
    """(median seconds per call, how, the last call's result); :class:`TooSlow` when the
    warm-up call takes longer than ``limit`` seconds."""
    box: dict[str, object] = {}

    def run() -> None:
        box["out"] = fn()

    t0 = time.perf_counter()
    run()
    first = time.perf_counter() - t0
    if first > limit:
        raise TooSlow(first)
    if first < SLOW_CALL_S:
        med = median_time(run, REPEATS)
        return med, f"median_time ({REPEATS}+ repeats)", box["out"]
    times = []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), f"1 warm-up + {REPEATS} calls", box["out"]


# -- one row --------------------------------------------------------------------------------------
def agreement(out, ref) -> dict[str, float]:
    value, lam, g = out
    rvalue, rlam, rg = ref
    dg = max(float((a - b).abs().max()) for a, b in zip(g, rg, strict=True))
    gmax = max(float(b.abs().max()) for b in rg)
    return {
        "max_dlam": float((lam - rlam).abs().max()),
        "rel_dloss": abs(value - rvalue) / (1.0 + abs(rvalue)),
        "rel_dgrad": dg / (1.0 + gmax),
    }


def run_row(loss: str, size: tuple[int, int, int], path: str, batch: int, n_data: int,
            rate_200: float | None, big: int) -> dict:
    model, data = setup(size, n_data)
    x, u, xn = data.x[:batch], data.u[:batch], data.x_next[:batch]
    row = {"loss": loss, "n_x": size[0], "n_u": size[1], "n_lam": size[2], "path": path,
           "batch": batch, "date": DATE, "machine": MACHINE, "status": "ok"}
    t_start = time.perf_counter()
    try:
        if batch == big and rate_200 is not None:
            est = big / rate_200
            how = "rate at batch 200"
            if est > SKIP_SECONDS and path in BATCHED and est < 10 * SKIP_SECONDS:
                probe = min(5_000, big)
                t0 = time.perf_counter()
                call(loss, path, model, data.x[:probe], data.u[:probe], data.x_next[:probe])
                est = (time.perf_counter() - t0) * big / probe
                how = f"one call at batch {probe}"
            if est > SKIP_SECONDS:
                row.update(status="skipped", estimated_s=est, estimated_from=how,
                           rate_at_200=rate_200,
                           note=f"skipped: > {SKIP_SECONDS:.0f} s per call (estimated "
                                f"{est:,.0f} s from the {how}; {rate_200:,.0f} samples/s at 200)")
                row["row_seconds"] = time.perf_counter() - t_start
                return row
        ref = call(loss, "fast", model, x, u, xn)
        try:
            med, how, out = timed(lambda: call(loss, path, model, x, u, xn),
                                  SKIP_SECONDS if batch == big else math.inf)
        except TooSlow as slow:
            row.update(status="skipped", measured_s=slow.args[0], rate_at_200=rate_200,
                       note=f"skipped: > {SKIP_SECONDS:.0f} s per call (the warm-up call took "
                            f"{slow.args[0]:,.0f} s; {rate_200:,.0f} samples/s at 200)")
            row["row_seconds"] = time.perf_counter() - t_start
            return row
        row.update(median_s=med, samples_per_s=batch / med, timing=how, **agreement(out, ref),
                   loss_value=ref[0])
    except Exception as exc:  # a failed path is a result
        row.update(status="error", error=f"{type(exc).__name__}: {str(exc)[:300]}")
    row["row_seconds"] = time.perf_counter() - t_start
    return row
