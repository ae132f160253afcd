"""The differentiable-paths and learning-effect studies (studies/solvers): the QP forms of (V)
and (P), each path's loss and gradient against the fast path, and the study's training loop
against lcs_cvx.fit."""

from __future__ import annotations

import pytest
import torch

import lcs_cvx
from lcs_cvx.problems import violation_problem
from studies.solvers import differentiable_paths as dp
from studies.solvers import learning_effect as le


@pytest.fixture(scope="module")
def small():
    torch.set_num_threads(1)
    model, data = dp.setup((4, 2, 3), 40)
    return model, data.x[:12], data.u[:12], data.x_next[:12]


def test_violation_qp_is_eps_times_the_objective(small) -> None:
    """1/2 z^T Q z + p^T z + eps const = eps * (V)'s objective at every z = (lam, phi)."""
    model, x, u, xn = small
    with torch.no_grad():
        F, C, q, r = dp.terms(model, x, u, xn)
        Q, p = dp.violation_qp(C, F, q, r, dp.GAMMA, dp.EPS)
        z = torch.rand(len(x), 6, generator=torch.Generator().manual_seed(0), dtype=q.dtype)
        quad = 0.5 * torch.einsum("bi,ij,bj->b", z, Q, z) + (p * z).sum(1)
        const = dp.EPS * (0.5 * (r * r).sum(1) + (q * q).sum(1) / (2 * dp.GAMMA * dp.EPS))
        obj = violation_problem(3).objective(z[:, :3], z[:, 3:], C, F, q, r, dp.GAMMA, dp.EPS)
    torch.testing.assert_close(quad + const, dp.EPS * obj, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("loss", dp.LOSSES)
@pytest.mark.parametrize("path,tol_lam,tol_loss,tol_grad", [
    ("qpoases", 1e-10, 1e-12, 1e-7), ("qplayer", 1e-6, 1e-6, 1e-5), ("qpth", 1e-8, 1e-8, None),
])
def test_paths_agree_with_fast(small, loss, path, tol_lam, tol_loss, tol_grad) -> None:
    model, x, u, xn = small
    ref = dp.call(loss, "fast", model, x, u, xn)
    got = dp.agreement(dp.call(loss, path, model, x, u, xn), ref)
    assert got["max_dlam"] < tol_lam
    assert got["rel_dloss"] < tol_loss
    # qpth's violation gradient is off by ~1e-4 (its interior point leaves active constraints
    # slightly inactive, and (V)'s multipliers are large); its prediction gradient agrees
    tol = tol_grad if tol_grad is not None else (1e-6 if loss == "prediction" else 1e-2)
    assert got["rel_dgrad"] < tol


def test_qpth_averages_the_gradient_of_a_shared_input() -> None:
    """Why the study passes qpth every input with the batch dimension: for an input without
    one, qpth returns the batch mean of the per-sample gradients instead of their sum."""
    from qpth.qp import QPFunction

    gen = torch.Generator().manual_seed(0)
    M = torch.rand(3, 3, generator=gen, dtype=torch.float64)
    Q0 = M @ M.T + torch.eye(3, dtype=torch.float64)
    p = torch.randn(5, 3, generator=gen, dtype=torch.float64)
    G, h, e = -torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), torch.empty(0)
    grads = []
    for batched in (False, True):
        Q = Q0.clone().requires_grad_(True)
        args = (Q.expand(5, 3, 3), p, G.expand(5, 3, 3), h.expand(5, 3)) if batched else (Q, p, G, h)
        QPFunction(verbose=-1)(*args, e.double(), e.double()).square().sum().backward()
        grads.append(Q.grad)
    torch.testing.assert_close(5 * grads[0], grads[1], rtol=1e-6, atol=1e-9)


def test_learning_loop_is_fit() -> None:
    """The study's Adam loop on the fast path gives lcs_cvx.fit's model (paper recipe)."""
    torch.set_num_threads(1)
    (cell,) = [c for c in le.cells((4,), 1, 300, 8) if c["method"] == "violation"]
    rows = {p: le.run_one(cell, p, rate=1e9) for p in ("fit", "fast")}
    assert rows["fit"]["status"] == rows["fast"]["status"] == "ok"
    assert rows["fast"]["e_test"] == pytest.approx(rows["fit"]["e_test"], rel=1e-9)
    assert rows["fast"]["e_test"] < lcs_cvx.relative_error(le.setup_cell(cell)[3], le.setup_cell(cell)[2])
