"""Learn, control, relearn (lcs_cvx.control.relearn): the rounds' records, the data growing by
the closed-loop transitions, the warm-started refits, resuming after a saved round, and the
named errors. The plant is C3's cart-pole LCS itself, the model learned from a little data."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import lcs_cvx
from lcs_cvx.control import C3, Relearning, c3_cartpole, relearn


@pytest.fixture(scope="module")
def setup():
    P = c3_cartpole()
    rng = np.random.default_rng(0)
    x = rng.uniform(-np.array([0.3, 0.5, 1.0, 2.0]), np.array([0.3, 0.5, 1.0, 2.0]), (300, 4))
    u = rng.uniform(-10, 10, (300, 1))
    with torch.no_grad():
        xn = P.model.step(torch.as_tensor(x), torch.as_tensor(u)).numpy()
    data = lcs_cvx.Dataset.from_arrays(x, u, xn)

    def plant(x, u):
        with torch.no_grad():
            return P.model.step(torch.as_tensor(x)[None], torch.as_tensor(u)[None])[0].numpy()

    def success(xs, us):
        return bool(np.abs(xs[-1]).max() <= 0.1)

    def controller(model):
        return C3(model, P.horizon, Q=P.Q, R=P.R, u_bounds=(-20.0, 20.0), gap_tol=None)

    starts = np.array([[0.1, -0.2, 0.2, -0.1], [-0.1, 0.1, 0.0, 0.3]])
    return P, data, plant, success, controller, starts


FIT = {"iterations": 150, "recipe": "paper", "gamma": 1e-3}


def model():
    return lcs_cvx.LCS(4, 1, 2, stiffness=0.001, init_scale=0.1, seed=0)


def test_the_rounds_grow_the_data_by_the_closed_loop_transitions_and_refit(setup):
    P, data, plant, success, controller, starts = setup
    seen = []
    m = model()
    lcs_cvx.fit(m, data, progress=False, **FIT)
    A_fitted = m.A.detach().clone()
    out = relearn(m, data, plant, controller, starts, success, rounds=1, steps=40, fit_options=FIT, fit_first=False,
                  on_round=lambda rec, mod, dat: seen.append((rec.round, len(dat), mod.A.detach().clone())))
    assert isinstance(out, Relearning) and out.model is m
    assert [r.round for r in out.rounds] == [0, 1]
    for r in out.rounds:
        assert r.runs == 2 and r.transitions == 2 * 40 and 0 <= r.successes <= 2
        assert r.successes == sum(r.success) and r.ms_per_step > 0
    assert out.rounds[0].data_size == len(data) + 80 and out.rounds[1].data_size == len(data) + 160
    assert len(out.data) == len(data) + 160
    assert out.rounds[0].fit_s > 0 and out.rounds[1].fit_s == 0  # the last round is not refitted
    assert [s[:2] for s in seen] == [(0, len(data) + 80), (1, len(data) + 160)]
    assert not torch.equal(seen[0][2], A_fitted)  # round 0's refit moved the model (in place)
    assert torch.equal(seen[1][2], seen[0][2])  # the last round is not refitted
    # the data added are the plant's own transitions
    x, u, xn = out.data.x[len(data):], out.data.u[len(data):], out.data.x_next[len(data):]
    with torch.no_grad():
        assert torch.allclose(P.model.step(x, u), xn, rtol=0, atol=1e-12)
    assert "| round | success |" in out.table()


def test_a_resumed_loop_starts_after_the_saved_round(setup, tmp_path):
    P, data, plant, success, controller, starts = setup
    m = model()
    saved = {}

    def save(rec, mod, dat):
        lcs_cvx.save_model(mod, tmp_path / f"m{rec.round}.npz")
        dat.save(tmp_path / f"d{rec.round}.npz")
        saved[rec.round] = rec

    relearn(m, data, plant, controller, starts, success, rounds=0, steps=20, fit_options=FIT, on_round=save)
    resumed = relearn(lcs_cvx.load_model(tmp_path / "m0.npz"), lcs_cvx.Dataset.load(tmp_path / "d0.npz"), plant,
                      controller, starts, success, rounds=1, steps=20, fit_options=FIT, fit_first=False,
                      first_round=1)
    assert [r.round for r in resumed.rounds] == [1]
    assert resumed.rounds[0].data_size == saved[0].data_size + 40


def test_bad_input_is_named(setup):
    P, data, plant, success, controller, starts = setup
    with pytest.raises(lcs_cvx.LCSInputError, match=r"starts: expected finite initial states of shape \(S, 4\)"):
        relearn(model(), data, plant, controller, np.zeros((2, 3)), success, fit_first=False)
    with pytest.raises(lcs_cvx.LCSInputError, match="rounds: expected an integer >= 0"):
        relearn(model(), data, plant, controller, starts, success, rounds=-1, fit_first=False)
    with pytest.raises(lcs_cvx.LCSInputError, match="data: expected n_x = 4, n_u = 1"):
        relearn(model(), lcs_cvx.Dataset.from_arrays(np.zeros((3, 2)), np.zeros((3, 1)), np.zeros((3, 2))),
                plant, controller, starts, success, fit_first=False)
    with pytest.raises(lcs_cvx.LCSInputError, match="plant: expected a finite next state of shape"):
        relearn(model(), data, lambda x, u: np.zeros(3), controller, starts, success, fit_first=False, steps=2)
