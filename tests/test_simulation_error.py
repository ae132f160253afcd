"""The simulation error (lcs_cvx.simulation_error): windows of trajectories, the multi-step loss
against a plain rollout loop and in normalised coordinates, its gradient against finite
differences and against a closed form in a single mode, the affine baseline's rollout error
against the affine map as an LCS, and the growth of diverging rollouts."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import simulated_runs

import lcs_cvx
from lcs_cvx.metrics import affine_lstsq
from lcs_cvx.scaling import Scaling
from lcs_cvx.simulation_error import Windows, affine_rollout_error, rollout_growth, simulation_error
from lcs_cvx.train.holdout import affine_lcs


def trajectories(truth, lengths, seed=0):
    return simulated_runs(truth, lengths, seed=seed)


@pytest.fixture(scope="module")
def truth():
    return lcs_cvx.random_lcs(3, 1, 2, seed=0)


def test_windows_index_every_window_of_every_trajectory(truth):
    tr = trajectories(truth, [6, 3, 9])
    with pytest.warns(UserWarning, match="shorter than 4 steps"):
        w = Windows(tr, 4)
    assert len(w) == (6 - 4 + 1) + 0 + (9 - 4 + 1)
    x0, us, xs = w.batch(torch.arange(len(w)))
    # window 3 is the third trajectory's first: x_0 of that trajectory, its first 4 inputs and states 1..4
    np.testing.assert_array_equal(x0[3], tr.xs[2][0])
    np.testing.assert_array_equal(us[3], tr.us[2][:4])
    np.testing.assert_array_equal(xs[3], tr.xs[2][1:5])
    np.testing.assert_array_equal(xs[2], tr.xs[0][3:7])  # the first trajectory's last window


def test_windows_name_bad_horizons(truth):
    tr = trajectories(truth, [5, 3])
    with pytest.raises(lcs_cvx.LCSInputError, match=r"rollout_horizon: expected at most 5 steps .* received 6"):
        Windows(tr, 6)
    with pytest.raises(lcs_cvx.LCSInputError, match=r"rollout_horizon: expected an integer >= 1, received 0"):
        Windows(tr, 0)
    with pytest.warns(UserWarning, match=r"1 of 2 trajectories are shorter than 4 steps \(the first: index 1, 3 steps\)"):
        Windows(tr, 4)


def test_simulation_error_is_the_mean_squared_rollout_error(truth):
    """Against a plain loop over model.step, in the user's units and in normalised coordinates
    (the normalised model with the scaling gives the physical model's error over S_y^2)."""
    tr = trajectories(truth, [8, 7], seed=1)
    model = lcs_cvx.random_lcs(3, 1, 2, seed=5)
    w = Windows(tr, 5)
    x0, us, xs = w.batch(torch.arange(len(w)))
    x, want, want_scaled = x0, 0.0, 0.0
    scaling = Scaling.fit(tr.to_transitions())
    with torch.no_grad():
        for h in range(5):
            x = model.step(x, us[:, h])
            want += float(((x - xs[:, h]) ** 2).mean()) / 5
            want_scaled += float((((x - xs[:, h]) / scaling.sy) ** 2).mean()) / 5
        got = float(simulation_error(model, x0, us, xs))
        got_scaled = float(simulation_error(scaling.to_normalised(model), x0, us, xs, scaling))
    assert got == pytest.approx(want, rel=1e-12)
    assert got_scaled == pytest.approx(want_scaled, rel=1e-9)


def test_gradient_matches_finite_differences(truth):
    """Autograd through the rollout (the implicit function of each step's LCP) against central
    differences of every parameter entry, in the normalised coordinates training uses."""
    tr = trajectories(truth, [6], seed=2)
    scaling = Scaling.fit(tr.to_transitions())
    model = scaling.to_normalised(lcs_cvx.random_lcs(3, 1, 2, seed=7))
    for p in model.parameters():
        p.requires_grad_(True)
    x0, us, xs = Windows(tr, 3).batch(torch.arange(4))
    with torch.no_grad():
        lam = model.solve_lcp((x0 - scaling.mx) / scaling.sx, (us[:, 0] - scaling.mu) / scaling.su).lam
    assert float(lam.max()) > 0  # a unit is active: the LCP's implicit gradient is exercised
    loss = simulation_error(model, x0, us, xs, scaling)
    grads = torch.autograd.grad(loss, [p for p in model.parameters() if p.requires_grad])
    for (name, p), g in zip([(n, p) for n, p in model.named_parameters() if p.requires_grad], grads, strict=True):
        flat = p.detach().reshape(-1)
        for i in range(flat.numel()):
            if name == "H" and i % (p.shape[-1] + 1) == 0:  # F holds H - H^T: no H_ii at all
                assert float(g.reshape(-1)[i]) == 0.0  # (a difference quotient is round-off)
                continue
            old = float(flat[i])
            vals = []
            for step in (1e-6, -1e-6):
                with torch.no_grad():
                    p.view(-1)[i] = old + step
                    vals.append(float(simulation_error(model, x0, us, xs, scaling)))
            with torch.no_grad():
                p.view(-1)[i] = old
            fd = (vals[0] - vals[1]) / 2e-6
            assert float(g.reshape(-1)[i]) == pytest.approx(fd, rel=1e-5, abs=1e-9 * max(1.0, float(loss.detach()))), (name, i)


def test_gradient_in_one_mode_is_the_linear_rollouts():
    """With no unit ever active (c large), a rollout is x_h = A^h x0 + sum A^j (B u + d): the
    gradient with respect to d has a closed form, 2/(H n B) sum_h sum_{j<h} (A^j)^T e_h."""
    model = lcs_cvx.LCS(2, 1, 1, seed=0)
    with torch.no_grad():
        model.c.fill_(1e3)
        model.D.zero_()
        model.E.zero_()
        model.A.copy_(torch.tensor([[0.9, 0.1], [-0.2, 0.8]], dtype=torch.float64))
    rng = np.random.default_rng(0)
    x0 = torch.tensor(rng.standard_normal((3, 2)))
    us = torch.tensor(rng.standard_normal((3, 4, 1)))
    xs = torch.tensor(rng.standard_normal((3, 4, 2)))
    loss = simulation_error(model, x0, us, xs)
    (g,) = torch.autograd.grad(loss, [model.d])
    A, B, d = model.A.detach(), model.B.detach(), model.d.detach()
    x, want, H = x0, torch.zeros(2, dtype=torch.float64), 4
    errs = []
    for h in range(H):
        x = x @ A.T + us[:, h] @ B.T + d
        errs.append(x - xs[:, h])
    for h in range(H):
        for j in range(h + 1):
            want += 2 * (torch.linalg.matrix_power(A, j).T @ errs[h].sum(0)) / (H * errs[h].numel())
    torch.testing.assert_close(g, want, rtol=1e-12, atol=1e-14)


def test_affine_rollout_error_equals_the_affine_map_as_an_lcs(truth):
    tr = trajectories(truth, [12, 9, 15], seed=3)
    affine = affine_lstsq(tr.to_transitions())
    as_lcs = affine_lcs(affine, lcs_cvx.LCS(3, 1, 2, seed=1))
    for H in (1, 4, 9):
        assert affine_rollout_error(affine, tr, H) == pytest.approx(lcs_cvx.rollout_error(as_lcs, tr, H)[H], rel=1e-10)


def test_rollout_growth_tells_a_stable_model_from_a_diverging_one(truth):
    tr = trajectories(truth, [30, 20], seed=4)
    assert rollout_growth(truth, tr) == pytest.approx(1.0, rel=1e-9)  # the data's own system
    unstable = lcs_cvx.LCS.from_matrices(A=1.5 * np.eye(3), B=np.zeros((3, 1)), C=np.zeros((3, 2)), d=np.zeros(3),
                                         D=np.zeros((2, 3)), E=np.zeros((2, 1)), F=np.eye(2), c=np.ones(2))
    assert rollout_growth(unstable, tr) > 1e3


def test_change_error_against_a_hand_loop_and_its_reference_points(truth):
    """``change_error``: every window rolled out by hand; a model that predicts no motion scores
    exactly 1 and the truth 0; each coordinate counts by its own scale (a coordinate's units
    changed together with its scale leave the score unchanged); the affine map is scored too."""
    from lcs_cvx.simulation_error import change_error

    runs = trajectories(truth, [12, 9, 4], seed=3)
    model = lcs_cvx.LCS(3, 1, 2, seed=5)
    scale = torch.tensor([0.3, 2.0, 1.0], dtype=torch.float64)
    H = 4
    num = den = 0.0
    with torch.no_grad():
        for xs, us in zip(runs.xs, runs.us, strict=True):
            for s in range(len(us) - H + 1):
                x = xs[s:s + 1]
                for h in range(H):
                    x = model.step(x, us[s + h:s + h + 1])
                num += float((((x[0] - xs[s + H]) / scale) ** 2).sum())
                den += float((((xs[s + H] - xs[s]) / scale) ** 2).sum())
    assert change_error(model, runs, H, scale) == pytest.approx(num / den, rel=1e-12)
    assert change_error(truth, runs, H, scale) <= 1e-24
    still = lcs_cvx.LCS.from_matrices(A=np.eye(3), B=np.zeros((3, 1)), C=np.zeros((3, 2)), d=np.zeros(3),
                                      D=np.zeros((2, 3)), E=np.zeros((2, 1)), F=np.eye(2), c=np.ones(2))
    assert change_error(still, runs, H, scale) == pytest.approx(1.0, rel=1e-12)
    # units: position in mm (x 1000) and its scale in mm leave the score as it was
    mm = torch.tensor([1000.0, 1.0, 1.0], dtype=torch.float64)
    runs_mm = lcs_cvx.Trajectories([x * mm for x in runs.xs], list(runs.us))
    affine = affine_lstsq(runs.to_transitions())
    affine_mm = affine_lstsq(runs_mm.to_transitions())
    assert change_error(affine_mm, runs_mm, H, scale * mm) == pytest.approx(
        change_error(affine, runs, H, scale), rel=1e-8)
