"""Known kinematics (lcs_cvx.kinematics): the integration against a hand loop (positions,
quaternions in the body and the world frame), the quaternion's norm over long rollouts, gradients
by central differences (through the integration and the LCP, in the coordinates training uses),
the held configuration rows through training, the export as one LCS (exact for positions, a
linearisation for quaternions) and in C3, model files, select_n_lam and the CLI's spec."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from helpers import simulated_runs

import lcs_cvx
from lcs_cvx import Kinematics, LCSInputError
from lcs_cvx.kinematics import quaternion_exp, quaternion_product
from lcs_cvx.scaling import Scaling
from lcs_cvx.simulation_error import Windows, simulation_error

POS = Kinematics(0.1, positions={0: 2, 1: 3})


def _qmul(a, b):  # Hamilton product, scalar first, written out independently
    w1, v1, w2, v2 = a[0], np.asarray(a[1:]), b[0], np.asarray(b[1:])
    return np.concatenate([[w1 * w2 - v1 @ v2], w1 * v2 + w2 * v1 + np.cross(v1, v2)])


def _qexp(phi):
    angle = np.linalg.norm(phi)
    if angle == 0:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * phi / angle])


def _quat_truth(frame="body", seed=0):
    truth = lcs_cvx.random_lcs(7, 1, 2, seed=seed)
    with torch.no_grad():  # a contracting angular velocity: rollouts stay bounded
        truth.A[4:, 4:] *= 0.3
    return truth.with_kinematics(Kinematics(0.05, quaternions=[(0, 4)], frame=frame))


def _unit_quat_states(n, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 1, (n, 7))
    x[:, :4] /= np.linalg.norm(x[:, :4], axis=1, keepdims=True)
    return torch.tensor(x)


def test_positions_integrate_the_predicted_velocity_as_a_hand_loop():
    truth = lcs_cvx.random_lcs(4, 1, 3, seed=0).with_kinematics(POS)
    x0, us = torch.randn(4, dtype=torch.float64), torch.randn(6, 1, dtype=torch.float64)
    xs = truth.rollout(x0, us).detach()
    x = x0.clone()
    with torch.no_grad():
        for t in range(6):
            lam = truth.solve_lcp(x, us[t]).lam[0]
            v = truth.A[2:] @ x + truth.B[2:] @ us[t] + truth.C[2:] @ lam + truth.d[2:]
            x = torch.cat([x[:2] + 0.1 * v, v])
            np.testing.assert_allclose(xs[t + 1], x, rtol=0, atol=1e-13)


@pytest.mark.parametrize("frame", ["body", "world"])
def test_quaternion_integrates_as_a_hand_loop_and_keeps_unit_norm(frame):
    truth = _quat_truth(frame)
    x0 = _unit_quat_states(1)[0]
    us = torch.randn(200, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    xs = truth.rollout(x0, us).detach().numpy()
    x = x0.numpy().copy()
    with torch.no_grad():
        for t in range(5):
            raw = truth.A.numpy() @ x + truth.B.numpy() @ us[t].numpy() + truth.d.numpy() \
                + truth.C.numpy() @ truth.solve_lcp(torch.tensor(x), us[t]).lam[0].numpy()
            delta = _qexp(0.05 * raw[4:])
            q = _qmul(x[:4], delta) if frame == "body" else _qmul(delta, x[:4])
            x = np.concatenate([q / np.linalg.norm(q), raw[4:]])
            np.testing.assert_allclose(xs[t + 1], x, rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.linalg.norm(xs[:, :4], axis=1), 1.0, rtol=0, atol=1e-14)


def test_quaternion_exp_is_smooth_at_zero_and_a_rotation():
    phi = torch.tensor([[0.0, 0.0, 0.0], [1e-7, -2e-7, 0.0], [0.3, -1.2, 0.5]], dtype=torch.float64,
                       requires_grad=True)
    assert torch.autograd.gradcheck(quaternion_exp, (phi,))
    q = quaternion_exp(phi.detach())
    np.testing.assert_allclose(q.norm(dim=-1), 1.0, rtol=0, atol=1e-15)
    # exp(phi) ⊗ exp(-phi) = identity
    back = quaternion_product(q, quaternion_exp(-phi.detach()))
    np.testing.assert_allclose(back, [[1.0, 0, 0, 0]] * 3, rtol=0, atol=1e-15)


def test_simulation_error_gradient_through_the_integration_by_central_differences():
    """The normalised model (training's coordinates) stepped, decoded and integrated
    (quaternion), against central differences of every learned entry."""
    truth = _quat_truth()
    x0s = _unit_quat_states(3, seed=2)
    us = torch.randn(3, 4, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    runs = [truth.rollout(x0s[i], us[i]).detach() for i in range(3)]
    tr = lcs_cvx.Trajectories(runs, list(us))
    learner = lcs_cvx.random_lcs(7, 1, 2, seed=9).requires_grad_(True)
    learner.with_kinematics(truth.kinematics)
    scaling = Scaling.fit(tr.to_transitions(), learner)
    model = scaling.to_normalised(learner)
    assert model.kinematics is None  # integrated after decoding, in the user's units
    x0, u, xs = Windows(tr, 3).batch(torch.arange(4))
    loss = simulation_error(model, x0, u, xs, scaling, truth.kinematics)
    params = [(n, p) for n, p in model.named_parameters() if p.requires_grad]
    grads = torch.autograd.grad(loss, [p for _, p in params])
    loss = loss.detach()
    checked = 0
    for (name, p), g in zip(params, grads, strict=True):
        free = lcs_cvx.parameter_constraints.free_entries(model, name).reshape(-1)
        flat = p.detach().reshape(-1)
        for i in range(0, flat.numel(), 2):
            if not bool(free[i]) or (name == "H" and i % (p.shape[-1] + 1) == 0):
                continue
            old, vals = float(flat[i]), []
            for step in (1e-6, -1e-6):
                with torch.no_grad():
                    p.view(-1)[i] = old + step
                    vals.append(float(simulation_error(model, x0, u, xs, scaling, truth.kinematics)))
            with torch.no_grad():
                p.view(-1)[i] = old
            fd = (vals[0] - vals[1]) / 2e-6
            assert float(g.reshape(-1)[i]) == pytest.approx(fd, rel=1e-5, abs=1e-9 * max(1.0, float(loss))), (name, i)
            checked += 1
    assert checked > 20
    # and the scaled path is the physical model's rollout error over S_y^2
    with torch.no_grad():
        x, want = x0, 0.0
        for h in range(3):
            x = learner.step(x, u[:, h])
            want += float((((x - xs[:, h]) / scaling.sy) ** 2).mean()) / 3
    assert float(loss) == pytest.approx(want, rel=1e-9)


@pytest.mark.parametrize("loss", ["violation", "prediction"])
def test_fit_keeps_the_configuration_rows_and_learns_the_velocities(loss):
    truth = lcs_cvx.random_lcs(4, 1, 2, seed=0).with_kinematics(POS)
    data = lcs_cvx.make_dataset(truth, 400, seed=1)
    test = lcs_cvx.make_dataset(truth, 200, seed=2)
    np.testing.assert_allclose(data.x_next[:, :2], data.x[:, :2] + 0.1 * data.x_next[:, 2:], rtol=0, atol=1e-14)
    model = lcs_cvx.LCS(4, 1, 2, seed=3, kinematics=POS)
    start = lcs_cvx.relative_error(model, test)
    lcs_cvx.fit(model, data, recipe="plain", loss=loss, iterations=300, restarts=1, progress=False)
    with torch.no_grad():
        np.testing.assert_array_equal(model.A[:2], [[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
        for name in ("B", "C", "d"):
            assert not getattr(model, name)[:2].any()
    assert model.kinematics == POS
    assert lcs_cvx.relative_error(model, test) < 0.1 * start


def test_fit_on_trajectories_with_the_simulation_error_phase():
    truth = lcs_cvx.random_lcs(4, 1, 2, seed=0)
    with torch.no_grad():
        truth.A[2:] *= 0.5
    truth.with_kinematics(POS)
    tr = simulated_runs(truth, [20] * 8, seed=1)
    model = lcs_cvx.LCS(4, 1, 2, seed=3, kinematics=POS)
    result = lcs_cvx.fit(model, tr, recipe="plain", iterations=200, restarts=1, rollout_horizon=5, rollout_iterations=20,
                         progress=False)
    assert any(h["phase"] == "rollout" for h in result.history)
    assert model.kinematics == POS and math.isfinite(result.heldout_error)
    with torch.no_grad():
        np.testing.assert_array_equal(model.A[:2, :2], torch.eye(2, dtype=torch.float64))


def test_scaling_centres_a_model_whose_held_rows_are_whole():
    """The configuration rows (A - K, B, C, d held whole) let x and u be centred; a held d
    entry in a row with learned A does not."""
    truth = lcs_cvx.random_lcs(4, 1, 2, seed=0).with_kinematics(POS)
    data = lcs_cvx.make_dataset(truth, 300, seed=1)
    s = Scaling.fit(data, lcs_cvx.LCS(4, 1, 2, kinematics=POS))
    assert bool((s.mx != 0).all()) and s.k.tolist() == [1.0] * 4
    assert s.my[:2].tolist() == [0.0, 0.0] and bool((s.my[2:] != 0).all())
    held = lcs_cvx.LCS(4, 1, 2).hold(d=[math.nan, math.nan, math.nan, -0.98])
    assert not bool(Scaling.fit(data, held).mx.any())


def test_as_lcs_is_the_step_for_positions_and_a_linearisation_for_quaternions():
    truth = lcs_cvx.random_lcs(4, 1, 3, seed=0).with_kinematics(POS)
    x, u = torch.randn(50, 4, dtype=torch.float64), torch.randn(50, 1, dtype=torch.float64)
    plain = truth.as_lcs()
    assert plain.kinematics is None and not plain.masks
    np.testing.assert_allclose(plain.step(x, u).detach(), truth.step(x, u).detach(), rtol=0, atol=1e-13)
    q = _quat_truth()
    with pytest.raises(LCSInputError, match=r"^about: expected a state"):
        q.as_lcs()
    about = _unit_quat_states(1, seed=4)[0]
    lin = q.as_lcs(about=about)
    u0 = torch.zeros(1, 1, dtype=torch.float64)
    errors = []
    np.testing.assert_allclose(lin.step(about[None], u0).detach(), q.step(about[None], u0).detach(), rtol=0, atol=1e-14)
    for r in (1e-2, 1e-3):  # second order in the distance from ``about`` (fixed mode)
        xr = about + r * torch.tensor([0.3, -0.2, 0.1, 0.4, 0.5, -0.3, 0.2], dtype=torch.float64)
        errors.append(float((lin.step(xr[None], u0) - q.step(xr[None], u0)).abs().max()))
    assert errors[1] < 0.03 * errors[0]  # ~0.01: second order


def test_c3_plans_with_the_positional_model_as_with_its_lcs():
    truth = lcs_cvx.random_lcs(4, 1, 2, seed=0).with_kinematics(POS)
    kw = {"Q": np.eye(4), "R": np.eye(1), "x_des": np.zeros(4)}
    x0 = np.array([0.5, -0.2, 0.1, 0.0])
    a = lcs_cvx.control.C3(truth, 5, **kw).solve(x0)
    b = lcs_cvx.control.C3(truth.as_lcs(), 5, **kw).solve(x0)
    np.testing.assert_allclose(a.u, b.u, rtol=1e-9, atol=1e-12)
    with pytest.raises(LCSInputError, match=r"as_lcs\(about=x\)"):
        lcs_cvx.control.C3(_quat_truth(), 5, Q=np.eye(7), R=np.eye(1))


def test_model_files_keep_the_kinematics(tmp_path):
    model = _quat_truth("world")
    lcs_cvx.save_model(model, tmp_path / "k.npz")
    back = lcs_cvx.load_model(tmp_path / "k.npz")
    assert back.kinematics == model.kinematics
    x, u = _unit_quat_states(5), torch.randn(5, 1, dtype=torch.float64)
    np.testing.assert_array_equal(back.step(x, u).detach(), model.step(x, u).detach())
    assert lcs_cvx.load_metadata(tmp_path / "k.npz")["format_version"] == 4


def test_select_n_lam_attaches_the_kinematics():
    truth = lcs_cvx.random_lcs(4, 1, 2, seed=0).with_kinematics(POS)
    data = lcs_cvx.make_dataset(truth, 300, seed=1)
    sel = lcs_cvx.select_n_lam(data, [1, 2], kinematics=POS, recipe="plain", iterations=50, restarts=1,
                               progress=False)
    assert sel.model.kinematics == POS


def test_spec_parses_and_prints_back():
    k = Kinematics.parse("dt=0.01 positions=0:3,1:4 quaternions=5:9 frame=world")
    assert k == Kinematics(0.01, [(0, 3), (1, 4)], [(5, 9)], "world")
    assert Kinematics.parse(str(k)) == k and Kinematics.from_dict(k.to_dict()) == k


@pytest.mark.parametrize("make, match", [
    (lambda: Kinematics(0.0, positions={0: 1}), r"^dt: expected a finite number > 0, received 0\.0"),
    (lambda: Kinematics(0.1), r"^positions, quaternions: expected at least one"),
    (lambda: Kinematics(0.1, positions={0: 1, 1: 2}), r"received \[1\] as both"),
    (lambda: Kinematics(0.1, positions=[(0, 2), (0, 3)]), r"each configuration index once"),
    (lambda: Kinematics(0.1, positions={-1: 2}), r"^positions: expected a state index"),
    (lambda: Kinematics(0.1, quaternions=[(0, 4)], frame="local"), r"^frame: expected one of"),
    (lambda: lcs_cvx.LCS(3, 1, 1, kinematics=POS), r"^kinematics: expected state indices below n_x = 3, received 3"),
    (lambda: lcs_cvx.LCS(4, 1, 1, kinematics={"dt": 0.1}), r"^kinematics: expected an lcs_cvx.Kinematics"),
    (lambda: Kinematics.parse("dt=0.1 positions=0-2"), r"positions as index:index pairs"),
    (lambda: Kinematics.parse("positions=0:2"), r"expected dt="),
])
def test_bad_declarations_are_named(make, match):
    with pytest.raises(LCSInputError, match=match):
        make()


def test_cli_fit_takes_the_kinematics(tmp_path, capsys):
    from lcs_cvx.cli import main

    truth = lcs_cvx.random_lcs(4, 1, 2, seed=0).with_kinematics(POS)
    lcs_cvx.make_dataset(truth, 300, seed=1).save(tmp_path / "train.npz")
    out = tmp_path / "m.npz"
    argv = ["fit", "--data", str(tmp_path / "train.npz"), "--n-lam", "2", "--iterations", "30",
            "--kinematics", "dt=0.1 positions=0:2,1:3", "--out", str(out)]
    assert main(argv) == 0
    assert "kinematics dt=0.1 positions=0:2,1:3" in capsys.readouterr().out
    assert lcs_cvx.load_model(out).kinematics == POS
    assert lcs_cvx.load_metadata(out)["metadata"]["init"]["kinematics"] == "dt=0.1 positions=0:2,1:3"
    assert main(argv[:-4] + ["--kinematics", "dt=0.1 positions=0-2", "--out", str(out)]) == 2
    assert "positions as index:index pairs" in capsys.readouterr().err


def test_up_coordinates_follow_the_integrated_quaternion_and_make_heights_linear():
    k = Kinematics(0.05, quaternions=[(0, 4)], up=[(7, 0)])
    truth = lcs_cvx.random_lcs(10, 1, 2, seed=0)
    with torch.no_grad():
        truth.A[4:7] *= 0.3
    truth.with_kinematics(k)
    x0 = torch.cat([_unit_quat_states(1, seed=5)[0], torch.zeros(3, dtype=torch.float64)])
    x0[7:] = lcs_cvx.kinematics.up_in_body(x0[:4])
    xs = truth.rollout(x0, torch.randn(30, 1, dtype=torch.float64)).detach()
    q = xs[:, :4].numpy()
    # R(q)^T e_z written out: the third row of the rotation matrix
    w, a, b, c = q.T
    want = np.stack([2 * (a * c - w * b), 2 * (b * c + w * a), 1 - 2 * (a * a + b * b)], axis=1)
    np.testing.assert_allclose(xs[:, 7:], want, rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(xs[:, 7:], axis=1), 1.0, rtol=0, atol=1e-13)
    lin = truth.as_lcs(about=xs[3])  # the up rows linearised with the quaternion's
    u0 = torch.zeros(1, 1, dtype=torch.float64)
    np.testing.assert_allclose(lin.step(xs[3:4], u0).detach(), truth.step(xs[3:4], u0).detach(), rtol=0, atol=1e-13)
    assert Kinematics.parse(str(k)) == k and Kinematics.from_dict(k.to_dict()) == k
    with pytest.raises(LCSInputError, match=r"^up: expected \(g0, q0\) pairs whose q0 starts a declared quaternion"):
        Kinematics(0.05, quaternions=[(0, 4)], up=[(7, 1)])


def test_an_ensemble_names_the_kinematics_it_cannot_train():
    from lcs_cvx.stacked import StackedLCS

    models = [lcs_cvx.LCS(4, 1, 2, seed=s, kinematics=POS) for s in (0, 1)]
    with pytest.raises(LCSInputError, match=r"kinematics hold the configuration rows\); fit them one at a time"):
        StackedLCS(models)


def test_a_later_hold_keeps_the_configuration_rows_held():
    """hold adds to what is held (a held entry is replaced only where a value is given again)."""
    model = lcs_cvx.LCS(4, 1, 2, kinematics=POS).hold(d=[math.nan, math.nan, math.nan, -0.98])
    assert model.held["d"].tolist()[:2] == [0.0, 0.0] and model.held["d"][3].item() == -0.98
    assert torch.isnan(model.held["d"][2])
    values = torch.tensor([0.5, math.nan, math.nan, math.nan], dtype=torch.float64)
    again = model.hold(d=values)  # given again: replaced
    assert again.held["d"][0].item() == 0.5 and again.held["d"][3].item() == -0.98
    assert torch.isnan(values[1:]).all()  # the caller's array is left as it was
