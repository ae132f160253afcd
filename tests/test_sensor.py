"""Measured data for the physics studies (studies/physics/sensor.py and the ``sensor`` argument of
both plants' generators): the exact sensor reproduces the plain generators bit for bit (checked
against a copy of their loops), a differencing sensor logs velocities as backward differences of
its readings, one noise draw per logged state (the same in the transition it ends and the one it
starts), the encoder's counts and the motion capture's jitter at their stated levels, the study
configs' ``data.sensor`` key, and the measured-with-noise comparison (studies/physics/noisy.py)
run end to end on its smoke configs."""

from __future__ import annotations

import json
import math
import os
import tomllib

import numpy as np
import pytest
from conftest import ROOT, needs_mujoco

pytestmark = needs_mujoco

CART_DT = 0.04  # the plants' control periods (s)
PUSH_DT = 0.05


def _arrays(tr) -> dict[str, np.ndarray]:
    import dataclasses

    return {f.name: getattr(tr, f.name) for f in dataclasses.fields(tr)}


def _same_bits(a, b) -> None:
    A, B = _arrays(a), _arrays(b)
    assert list(A) == list(B)
    for k in A:
        assert A[k].dtype == B[k].dtype and A[k].shape == B[k].shape, k
        assert A[k].tobytes() == B[k].tobytes(), k


# -- the exact sensor: the old data, bit for bit ------------------------------------------------
def _old_cartpole(n: int, seed: int, wide_factor: float = 1.0):
    """The cart-pole generator's loop as it was before sensors (a copy)."""
    from studies.physics.plant import CartPoleWalls, Physics, Sampling, Transitions

    physics, sampling = Physics(), Sampling()
    sim = CartPoleWalls(physics)
    rng = np.random.default_rng(seed)
    high = np.asarray(sampling.x0_high, dtype=np.float64)
    inner = physics.wall_distance - physics.tip_radius
    w_max = sampling.u_max * wide_factor
    cols: dict[str, list] = {k: [] for k in ("x", "u", "x_next", "force", "contact", "traj", "step")}
    traj = 0
    while len(cols["x"]) < n:
        while True:
            x0 = rng.uniform(-high, high)
            if abs(sim.tip_x(x0)) < inner:
                break
        sim.reset(x0)
        x = x0
        for t in range(sampling.traj_len):
            u = -sampling.kp * x[0] - sampling.kd * x[2] + rng.uniform(-w_max, w_max)
            x_next, force, contact = sim.step(u)
            for k, v in (("x", x), ("u", [u]), ("x_next", x_next), ("force", force),
                         ("contact", contact), ("traj", traj), ("step", t)):
                cols[k].append(v)
            x = x_next
            if len(cols["x"]) >= n or abs(x[0]) > sampling.x_limit or abs(x[1]) > sampling.theta_limit:
                break
        traj += 1
    return Transitions.from_lists(cols)


def _old_pusher(n: int, seed: int, wide_factor: float = 1.0):
    """The pusher-slider generator's loop as it was before sensors (a copy)."""
    from studies.physics.pusher_plant import Physics, PusherSlider, PusherTransitions, Sampling

    physics, s = Physics(), Sampling()
    sim = PusherSlider(physics)
    rng = np.random.default_rng(seed)
    ux_mid, ux_half = 0.5 * (s.ux_range[0] + s.ux_range[1]), 0.5 * (s.ux_range[1] - s.ux_range[0]) * wide_factor
    wy = s.uy_noise * wide_factor
    touching = physics.touching_x
    rows: dict[str, list] = {k: [] for k in ("x", "u", "x_next", "force", "contact", "traj", "step", "pose")}
    traj = 0
    while len(rows["x"]) < n:
        sim.reset(touching - rng.uniform(0.0, s.gap0_max), rng.uniform(-s.offset0_max, s.offset0_max))
        x = sim.state
        for t in range(s.traj_len):
            u = np.array([ux_mid + rng.uniform(-ux_half, ux_half), -s.uy_gain * x[1] + rng.uniform(-wy, wy)])
            pose = sim.pose.copy()
            x_next, force, mode = sim.step(u)
            for k, v in zip(rows, (x, u, x_next, force, mode, traj, t, pose), strict=True):
                rows[k].append(v)
            x = x_next
            if len(rows["x"]) >= n or abs(x[1]) > s.face_limit or x[0] < touching - s.gap_limit:
                break
        traj += 1
    return PusherTransitions.from_lists(rows)


def test_exact_sensor_is_the_old_cartpole_data_bit_for_bit():
    from studies.physics.plant import sample_measured, sample_transitions

    for seed, wide in ((0, 1.0), (2, 1.5)):
        old = _old_cartpole(400, seed, wide)
        _same_bits(sample_transitions(400, seed, wide_factor=wide), old)
        _same_bits(sample_transitions(400, seed, wide_factor=wide, sensor="exact"), old)
        measured, true = sample_measured(400, seed, wide_factor=wide)
        _same_bits(measured, old)
        _same_bits(true, old)


def test_exact_sensor_is_the_old_pusher_data_bit_for_bit():
    from studies.physics.pusher_plant import sample_measured, sample_transitions

    for seed, wide in ((0, 1.0), (2, 1.5)):
        old = _old_pusher(300, seed, wide)
        _same_bits(sample_transitions(300, seed, wide_factor=wide), old)
        _same_bits(sample_transitions(300, seed, wide_factor=wide, sensor="exact"), old)
        measured, true = sample_measured(300, seed, wide_factor=wide)
        _same_bits(measured, old)
        _same_bits(true, old)


# -- the cart-pole's encoders ---------------------------------------------------------------------
@pytest.fixture(scope="module")
def encoder():
    from studies.physics.plant import sample_measured, sample_transitions

    measured, true = sample_measured(1200, 0, sensor="encoder")
    return measured, true, sample_transitions(2000, 0)


def test_encoder_velocities_are_backward_differences_of_the_logged_positions(encoder):
    m, _, _ = encoder
    assert len(m) == 1200 and m.x.shape == (1200, 4) and m.x_next.shape == (1200, 4)
    # the velocity logged at t + 1 is (position logged at t + 1 - position logged at t) / dt
    assert np.array_equal(m.x_next[:, 2:], (m.x_next[:, :2] - m.x[:, :2]) / CART_DT)
    # and the one logged at t is the difference of the two readings before it
    same = m.traj[1:] == m.traj[:-1]
    assert np.array_equal(m.x[1:][same, 2:], ((m.x[1:, :2] - m.x[:-1, :2]) / CART_DT)[same])


def test_encoder_noise_is_one_draw_per_logged_state(encoder):
    m, true, _ = encoder
    same = m.traj[1:] == m.traj[:-1]
    assert same.sum() > 1000
    # x_{t+1} of one transition is x_t of the next, bit for bit: one reading per instant
    assert np.array_equal(m.x_next[:-1][same], m.x[1:][same])
    assert (m.step[1:][same] == m.step[:-1][same] + 1).all()


def test_encoder_counts_are_the_stated_resolutions(encoder):
    m, true, _ = encoder
    res = np.array([1e-4, 2 * math.pi / 4096])
    for logged, exact in ((m.x, true.x), (m.x_next, true.x_next)):
        counts = logged[:, :2] / res
        assert np.abs(counts - np.round(counts)).max() < 1e-6  # whole counts
        # the nearest count: within half a count of the simulator's position
        assert (np.abs(logged[:, :2] - exact[:, :2]) <= res / 2 + 1e-12).all()
        assert np.array_equal(logged[:, :2], np.round(exact[:, :2] / res) * res)
    # a count is 0.1 mm and 2π/4096 rad: the cart position has many distinct values, all counts
    assert len(np.unique(m.x[:, 0])) > 100


def test_encoder_data_are_the_exact_trajectories_without_their_first_transition(encoder):
    m, true, exact = encoder
    assert (m.step >= 1).all() and (true.step >= 1).all()
    keep = exact.step >= 1
    n = len(m)
    for name in ("x", "u", "x_next", "force", "contact", "traj", "step"):
        assert np.array_equal(getattr(true, name), getattr(exact, name)[keep][:n]), name
    for name in ("u", "force", "contact", "traj", "step"):
        assert np.array_equal(getattr(m, name), getattr(true, name)), name
    # differencing without noise: exact positions, velocities the differences of exact positions
    from studies.physics.plant import sample_measured

    d, _ = sample_measured(300, 0, sensor="differenced")
    assert np.array_equal(d.x[:, :2], true.x[:300, :2])
    assert np.allclose(d.x_next[:, 2:], (true.x_next[:300, :2] - true.x[:300, :2]) / CART_DT, rtol=0, atol=1e-12)


# -- the pusher-slider's motion capture -------------------------------------------------------------
@pytest.fixture(scope="module")
def mocap():
    from studies.physics.pusher_plant import sample_measured

    return sample_measured(1500, 0, sensor="mocap")


def _rot(theta: np.ndarray, v: np.ndarray) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1]], axis=1)


def test_mocap_velocities_are_backward_differences_of_the_measured_pose(mocap):
    m, _ = mocap
    same = m.traj[1:] == m.traj[:-1]
    pose0, pose1 = m.pose[:-1][same], m.pose[1:][same]  # measured pose at t and t + 1
    nxt = m.x_next[:-1][same]
    # omega_{t+1} = (Theta~_{t+1} - Theta~_t) / dt, v_{t+1} = R(-Theta~_{t+1}) (S~_{t+1} - S~_t) / dt
    assert np.allclose(nxt[:, 4], (pose1[:, 2] - pose0[:, 2]) / PUSH_DT, rtol=0, atol=1e-9)
    assert np.allclose(nxt[:, 2:4], _rot(-pose1[:, 2], (pose1[:, :2] - pose0[:, :2]) / PUSH_DT), rtol=0, atol=1e-9)


def test_mocap_noise_is_one_draw_per_logged_state_and_at_the_stated_level(mocap):
    m, true = mocap
    same = m.traj[1:] == m.traj[:-1]
    assert np.array_equal(m.x_next[:-1][same], m.x[1:][same])
    # the simulated trajectories are the exact data's (the jitter has its own random stream)
    from studies.physics.pusher_plant import sample_transitions

    _same_bits(true, sample_transitions(1500, 0))
    for name in ("u", "force", "contact", "traj", "step"):
        assert np.array_equal(getattr(m, name), getattr(true, name)), name
    # pose jitter: 0.05 cm on X, Y and 0.005 rad on Theta, zero mean, independent between readings
    e = m.pose - true.pose
    assert e[:, :2].std() == pytest.approx(0.05, rel=0.08) and e[:, 2].std() == pytest.approx(0.005, rel=0.08)
    assert (np.abs(e.mean(axis=0)) < 4 * np.array([0.05, 0.05, 0.005]) / math.sqrt(len(e))).all()
    assert abs(np.corrcoef(e[:-1][same, 0], e[1:][same, 0])[0, 1]) < 0.1
    # the differenced angular velocity carries sqrt(2) 0.005 / dt of noise (~0.14 rad/s)
    d = m.x[:, 4] - true.x[:, 4]
    assert d.std() == pytest.approx(math.sqrt(2) * 0.005 / PUSH_DT, rel=0.15)
    # at rest before the first push: the first logged velocity is jitter only
    first = m.step == 0
    assert np.abs(true.x[first, 2:]).max() < 1e-9
    assert m.x[first, 2:4].std() == pytest.approx(math.sqrt(2) * 0.05 / PUSH_DT, rel=0.25)
    # another seed, other jitter and other trajectories
    from studies.physics.pusher_plant import sample_measured

    assert not np.array_equal(sample_measured(50, 1, sensor="mocap")[0].x, m.x[:50])


def test_differenced_pusher_positions_are_exact(mocap):
    from studies.physics.pusher_plant import sample_measured

    d, true = sample_measured(400, 0, sensor="differenced")
    assert np.allclose(d.x[:, :2], true.x[:, :2], rtol=0, atol=1e-10)
    assert np.array_equal(d.pose, true.pose)
    same = d.traj[1:] == d.traj[:-1]
    assert np.allclose(d.x_next[:-1][same, 4], ((true.pose[1:, 2] - true.pose[:-1, 2]) / PUSH_DT)[same],
                       rtol=0, atol=1e-9)


def test_sensor_names_and_levels():
    from studies.physics.sensor import SENSORS, sensor

    enc = sensor("cartpole", "encoder")
    assert enc.resolution == (1e-4, 2 * math.pi / 4096) and enc.noise == (0.0, 0.0) and enc.differenced
    mc = sensor("pusher", "mocap")
    assert mc.noise == (0.05, 0.05, 0.005, 0.05, 0.05) and mc.resolution == (0.0,) * 5
    assert sensor("pusher", "exact").exact and not sensor("pusher", "differenced").exact
    assert set(SENSORS["cartpole"]) == {"exact", "differenced", "encoder"}
    with pytest.raises(ValueError, match=r"sensor: expected one of \['differenced', 'encoder', 'exact'\]"):
        sensor("cartpole", "mocap")
    # quantisation rounds to the nearest count; jitter needs a generator
    q = enc.read(np.array([[0.00014, 0.0], [-0.00016, 0.002]]), None)
    assert np.allclose(q[:, 0], [1e-4, -2e-4]) and q[1, 1] == pytest.approx(2 * math.pi / 4096)
    with pytest.raises(ValueError, match="needs a random generator"):
        mc.read(np.zeros((2, 5)), None)


# -- the studies' configs --------------------------------------------------------------------------
def test_the_studies_take_a_sensor_and_refuse_an_unknown_one():
    from studies.physics import pusher_study, study

    assert study.parse_config({"name": "p"})["data"]["sensor"] == "exact"
    assert pusher_study.parse_config({"name": "p"})["data"]["sensor"] == "exact"
    cfg = study.parse_config({"name": "p", "data": {"sensor": "encoder", "n_train": 300, "n_test": 100,
                                                    "n_wide": 100}})
    data = study._data(cfg)
    for d in data.values():
        assert (d.step >= 1).all()  # logged by the encoders: the first transitions are dropped
        assert np.array_equal(d.x_next[:, 2:], (d.x_next[:, :2] - d.x[:, :2]) / CART_DT)
    with pytest.raises(ValueError, match=r"data\.sensor: expected one of \['differenced', 'encoder', 'exact'\]"):
        study.parse_config({"name": "p", "data": {"sensor": "mocap"}})
    with pytest.raises(ValueError, match=r"data\.sensor: expected one of \['differenced', 'exact', 'mocap'\]"):
        pusher_study.parse_config({"name": "p", "data": {"sensor": "encoder"}})
    with open(os.path.join(ROOT, "studies", "configs", "physics_cartpole.toml"), "rb") as f:
        assert study.parse_config(tomllib.load(f))["data"]["sensor"] == "exact"


# -- the measured-with-noise comparison, end to end -----------------------------------------------
@pytest.mark.parametrize("name", ["physics_cartpole_noisy_smoke", "pusher_slider_noisy_smoke"])
def test_noisy_comparison_smoke_run(tmp_path, name):
    from studies.physics.noisy import main

    config = os.path.join(ROOT, "studies", "configs", f"{name}.toml")
    assert main(["--config", config, "--out", str(tmp_path)]) == 0
    s = json.loads((tmp_path / "noisy.json").read_text())
    sensors = s["config"]["data"]["sensors"]
    assert sensors[0] == "exact" and len(sensors) == 2
    for sensor in sensors:
        r = s["results"][sensor]
        assert [(f["seed"], f["rollout_horizon"]) for f in r["fits"]] == [(0, None), (0, 5)]
        # the MLP baseline, scored as the affine map is
        assert set(r["mlp"]["scores"]) == set(r["affine"]["scores"] if "scores" in r["affine"] else r["affine"])
        assert math.isfinite(r["mlp"]["scores"]["validation"]["20"]) and r["mlp"]["hidden"] == [16]
        for f in r["fits"]:
            assert f["error"] is None
            # the library's affine map is the one the table shows, on the same held-out trajectories
            assert f["affine_heldout_error"] == pytest.approx(r["affine"]["validation"]["20"], rel=1e-9)
            assert f["beats_affine"] == (f["heldout_error"] < f["affine_heldout_error"] and not f["grows_more"])
            assert f["heldout_error"] == pytest.approx(f["scores"]["validation"]["20"], rel=1e-9)
            assert set(f["scores"]["test"]) == {"1", "5", "20"}
            assert all(math.isfinite(v) for v in f["scores"]["test"].values())
        # the exact sensor's noise-free test set is its test set; a noisy sensor's is not
        same = r["fits"][0]["scores"]["test"] == r["fits"][0]["scores"]["test_clean"]
        assert same == (sensor == "exact")
    report = (tmp_path / "noisy.md").read_text()
    assert "## Measured with noise" in report and f"### Sensor `{sensors[1]}`" in report
    assert report.count("| affine (least squares) |") == 2
    # the report is rewritten from noisy.json alone
    (tmp_path / "noisy.md").unlink()
    assert main(["--config", config, "--out", str(tmp_path), "--report-only"]) == 0
    assert (tmp_path / "noisy.md").read_text() == report
    # a second run takes every fit from noisy.partial.json
    mtime = os.path.getmtime(tmp_path / "noisy.partial.json")
    assert main(["--config", config, "--out", str(tmp_path)]) == 0
    assert os.path.getmtime(tmp_path / "noisy.partial.json") == mtime
    again = json.loads((tmp_path / "noisy.json").read_text())["results"]
    for sensor in sensors:  # the fits read back (NaN-safe comparison); the affine map refitted
        assert json.dumps(again[sensor]["fits"], sort_keys=True) == json.dumps(s["results"][sensor]["fits"], sort_keys=True)
        assert again[sensor]["affine"]["test"]["20"] == pytest.approx(s["results"][sensor]["affine"]["test"]["20"], rel=1e-9)
