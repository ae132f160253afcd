"""lcs_cvx.rigid_body: the time-stepping LCS of a rigid body's state -- free flight, resting, the
LCS of one state, files and bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import lcs_cvx
from lcs_cvx.kinematics import quaternion_product, rotation_matrix
from lcs_cvx.per_sample import solve_sample_lcp
from lcs_cvx.rigid_body import box_vertices

F64 = torch.float64
DT, MASS, HALF = 0.01, 0.4, 0.05


def cube(**kw) -> lcs_cvx.RigidBodyContact:
    args = {"half_sizes": [HALF, HALF, HALF], "mass": MASS, "dt": DT}
    args.update(kw)
    return lcs_cvx.RigidBodyContact(**args)


def state(q=(1.0, 0, 0, 0), p=(0, 0, 0.3), w=(0, 0, 0), v=(0, 0, 0)) -> torch.Tensor:
    q = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return torch.tensor(np.concatenate([q, p, w, v])[None], dtype=F64)


NO_U = torch.zeros(1, 0, dtype=F64)


@pytest.fixture(autouse=True)
def _no_grad():
    """These tests check values, not gradients (tests/test_per_sample.py has those)."""
    with torch.no_grad():
        yield


def test_rotation_matrix_is_the_quaternion_rotation():
    q = torch.tensor([[0.3, -0.5, 0.7, 0.2]], dtype=F64)
    q = q / q.norm()
    r = torch.tensor([0.1, -0.4, 0.25], dtype=F64)
    rotated = quaternion_product(quaternion_product(q[0], torch.cat([torch.zeros(1, dtype=F64), r])),
                                 q[0] * torch.tensor([1.0, -1, -1, -1], dtype=F64))
    assert torch.allclose(rotation_matrix(q)[0] @ r, rotated[1:], atol=1e-15)


def test_in_free_flight_no_impulse_gravity_and_an_isotropic_body_keeps_its_spin():
    m = cube(inertia=0.001)
    x = state(q=(0.9, 0.1, -0.3, 0.2), p=(0.1, -0.2, 1.0), w=(3.0, -1.0, 2.0), v=(0.5, 0.2, 1.0))
    assert float(m.solve_lcp(x, NO_U).abs().max()) == 0.0
    x1 = m.step(x, NO_U)
    assert torch.allclose(x1[0, 10:], torch.tensor([0.5, 0.2, 1.0 - 9.81 * DT], dtype=F64), atol=1e-14)
    assert torch.allclose(x1[0, 7:10], x[0, 7:10], atol=1e-13)  # omega x I omega = 0 for I = 0.001 * 1
    assert torch.allclose(x1[0, 4:7], x[0, 4:7] + DT * x1[0, 10:], atol=1e-15)
    assert abs(float(x1[0, :4].norm()) - 1.0) < 1e-15


def test_a_body_resting_on_a_face_stays_and_the_floor_carries_its_weight():
    m = cube(ground=0.02)
    x = state(p=(0.0, 0.0, 0.02 + HALF))
    lcs = m.sample_lcs(x, NO_U)
    lam = solve_sample_lcp(lcs)
    x1 = m.step(x, NO_U)
    # at rest up to the compliance: w = J~ nu' + kappa lam = 0 lets it sink at kappa lam per step
    assert float(x1[0, 7:12].abs().max()) < 1e-14
    assert 0 < -float(x1[0, 12]) <= float(m.compliance.max() * lam.max()) * (1 + 1e-9)
    # the normal impulses (each edge's lam pushes along n + mu d_j) balance gravity over the step
    assert abs(float(lam.sum()) - MASS * (9.81 * DT + float(x1[0, 12]))) < 1e-15
    w = lam @ lcs.F[0].mT + lcs.q
    assert float(lam.min()) >= 0 and float(w.min()) > -1e-12 and float((lam * w).abs().max()) < 1e-14


def test_a_sliding_body_slows_down_and_gains_no_energy():
    m = cube(mu=0.4)
    x = state(p=(0.0, 0.0, HALF), v=(1.0, 0.0, 0.0))
    xs = m.rollout(x[0], torch.zeros(30, 0, dtype=F64))
    vx = xs[:, 10]
    # Anitescu's cone lets a sliding body hop (w = 0 on the edge opposite the motion asks for
    # v_z' = mu v_x'), so it slows in steps; it stops within the 30 steps (mu g t > 1 m/s)
    assert bool((vx[1:] <= vx[:-1] + 1e-4).all()) and abs(float(vx[-1])) < 1e-3
    spin = 0.5 * (xs[:, 7:10] @ m.inertia * xs[:, 7:10]).sum(-1)
    energy = 0.5 * MASS * xs[:, 10:].pow(2).sum(-1) + MASS * 9.81 * xs[:, 6] + spin
    assert bool((energy[1:] <= energy[:-1] + 1e-6).all())  # 1e-6 J: the compliance settling at rest


def test_a_ball_that_slides_starts_rolling_at_five_sevenths_of_its_speed():
    # one rounded corner at the centre is a ball: friction at its lowest point (lever -rho e_z)
    # spins it up until it rolls, v = omega r, at 5/7 of the start's speed (I = 2/5 m r^2)
    r = 0.05
    ball = lcs_cvx.RigidBodyContact(vertices=[[0.0, 0.0, 0.0]], corner_radius=r, mass=MASS, dt=0.005, mu=0.3,
                                    inertia=0.4 * MASS * r**2, compliance=1e-3)
    assert np.allclose(ball.physical()["half_sizes"], [r] * 3, atol=1e-15) and abs(ball.physical()["corner_radius"] - r) < 1e-16
    xs = ball.rollout(state(p=(0, 0, r), v=(2.0, 0, 0))[0], torch.zeros(400, 0, dtype=F64))
    assert abs(float(xs[-1, 10]) - 2.0 * 5 / 7) < 1e-9 and abs(float(xs[-1, 8]) - 2.0 * 5 / 7 / r) < 1e-7
    # the same point without its radius (rho = 0, the centre on the floor) has no lever: it slides
    # to a stop without spinning
    point = lcs_cvx.RigidBodyContact(vertices=[[0.0, 0.0, 0.0]], mass=MASS, dt=0.005, mu=0.3, inertia=0.4 * MASS * r**2,
                                     compliance=1e-3)
    xs = point.rollout(state(p=(0, 0, 0), v=(2.0, 0, 0))[0], torch.zeros(400, 0, dtype=F64))
    assert abs(float(xs[-1, 10])) < 1e-9 and float(xs[:, 7:10].abs().max()) < 1e-12


def test_a_rounded_box_rests_on_a_face_at_its_half_size_and_on_an_edge_lower_than_a_sharp_one():
    rho = 0.01
    m = cube(corner_radius=rho, ground=0.02)
    assert torch.allclose(m.vertices.abs(), torch.full((8, 3), HALF - rho, dtype=F64), atol=1e-15)
    flat = m.dynamics(state(p=(0, 0, 0.02 + HALF)))[3][0]
    assert torch.allclose(flat.sort().values[:4], torch.zeros(4, dtype=F64), atol=1e-15)
    # on an edge, 45 degrees about x: the rounded edge's centre is (h - rho) sqrt 2 + rho above the floor
    s = math.sin(math.pi / 8)
    height = 0.02 + (HALF - rho) * math.sqrt(2) + rho
    edge = m.dynamics(state(q=(math.cos(math.pi / 8), s, 0, 0), p=(0, 0, height)))[3][0]
    assert torch.allclose(edge.sort().values[:2], torch.zeros(2, dtype=F64), atol=1e-15)
    assert height < 0.02 + HALF * math.sqrt(2)


def test_the_lcs_of_a_state_steps_as_the_model_there():
    m = cube(mu=0.3, com=(0.002, -0.001, 0.003), inertia=[0.001, 0.0012, 0.0009])
    x = state(q=(0.95, 0.2, -0.1, 0.05), p=(0.0, 0.0, HALF + 0.001), w=(2.0, -1.0, 0.5), v=(0.3, -0.2, -0.4))
    lcs = m.lcs_at(x[0])
    assert isinstance(lcs, lcs_cvx.LCS) and (lcs.n_x, lcs.n_u, lcs.n_lam) == (13, 0, 32)
    assert float(m.solve_lcp(x, NO_U).max()) > 0  # in contact: the test is not of free flight
    assert torch.allclose(lcs.step(x, NO_U), m.step(x, NO_U), atol=1e-12)
    assert m.step(x[0], NO_U[0]).shape == (13,) and torch.allclose(m.step(x[0], NO_U[0]), m.step(x, NO_U)[0],
                                                                   rtol=0, atol=1e-15)
    assert set(lcs.to_c3()) == {"A", "B", "D", "d", "E", "F", "H", "c"}


def test_a_wrench_input_accelerates_the_body_by_its_mass_matrix():
    m = cube(n_u=6, inertia=0.002)
    x = state(p=(0, 0, 1.0))
    u = torch.tensor([[0.01, 0.0, 0.0, 0.0, 0.0, 4.0]], dtype=F64)
    x1 = m.step(x, u)
    assert abs(float(x1[0, 7]) - 0.01 / 0.002 * DT) < 1e-14
    assert abs(float(x1[0, 12]) - (4.0 / MASS - 9.81) * DT) < 1e-14
    lcs = m.lcs_at(x[0], u[0])
    assert torch.allclose(lcs.step(x, u), x1, atol=1e-12)


def test_box_vertices_and_the_physical_quantities():
    v = box_vertices(torch.tensor([1.0, 2.0, 3.0], dtype=F64))
    assert v.shape == (8, 3) and sorted(v[:, 2].tolist()) == [-3.0] * 4 + [3.0] * 4
    m = cube(mu=0.3, inertia=[0.001, 0.002, 0.003], com=(0.001, 0.0, -0.002), ground=0.05)
    p = m.physical()
    assert np.allclose(p["half_sizes"], [HALF] * 3, atol=1e-15) and abs(p["mu"] - 0.3) < 1e-12
    assert np.allclose(np.diag(p["inertia"]), [0.001, 0.002, 0.003], atol=1e-15)
    assert np.allclose(p["com"], [0.001, 0.0, -0.002], atol=1e-15) and abs(p["ground"] - 0.05) < 1e-15
    assert np.allclose(p["compliance"], 0.02, atol=1e-15)
    free = lcs_cvx.RigidBodyContact(vertices=[[0.1, 0, 0], [0, 0.1, 0], [0, 0, -0.1]], mass=1.0, dt=0.01)
    assert free.n_lam == 12 and torch.allclose(free.vertices[2], torch.tensor([0, 0, -0.1], dtype=F64))


def test_learn_fixes_the_quantities_not_named():
    m = cube(learn=("mu", "inertia"))
    learned = {k for k, p in m.named_parameters() if p.requires_grad}
    assert learned == {"mu_raw", "inertia_factor"}


def test_save_and_load_are_bit_exact(tmp_path):
    m = cube(mu=0.27, com=(0.001, 0.002, 0.0), learn=("mu", "vertices", "ground"))
    with torch.no_grad():
        m.log_half_sizes.add_(torch.tensor([0.01, -0.02, 0.03], dtype=F64))
    path = tmp_path / "body.npz"
    lcs_cvx.save_model(m, path, metadata={"note": "test"})
    back = lcs_cvx.load_model(path)
    assert isinstance(back, lcs_cvx.RigidBodyContact)
    for (k, a), (_, b) in zip(m.state_dict().items(), back.state_dict().items(), strict=True):
        assert torch.equal(a, b), k
    assert {k for k, p in back.named_parameters() if p.requires_grad} == {"mu_raw", "log_half_sizes", "ground_scaled"}
    x = state(q=(0.9, 0.3, 0.1, 0.0), p=(0, 0, 0.04), w=(1, 2, 3), v=(0.1, 0, -1))
    assert torch.equal(back.step(x, NO_U), m.step(x, NO_U))


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"vertices": [[0.0, 0.0]]}, "vertices: expected a finite .K, 3."),
    ({"half_sizes": [0.1, -0.1, 0.1]}, "half_sizes: expected 3 finite numbers > 0"),
    ({"mu": -0.1}, "mu: expected a finite number >= 0"),
    ({"dt": 0.0}, "dt"),
    ({"mass": -1.0}, "mass"),
    ({"inertia": [[1.0, 2.0, 0], [2.0, 1.0, 0], [0, 0, 1.0]]}, "inertia: expected"),
    ({"formulation": "lemke"}, "formulation: expected one of"),
    ({"friction_directions": 2}, "friction_directions: expected an integer >= 3"),
    ({"n_u": 3}, "n_u: expected 0 .no input. or 6"),
    ({"learn": ("mass",)}, "learn: expected names among"),
    ({"compliance": 0.0}, "compliance"),
    ({"corner_radius": -0.01}, "corner_radius: expected a finite number >= 0"),
    ({"corner_radius": HALF}, "half_sizes: expected 3 finite numbers > 0.05 .the corner radius."),
])
def test_bad_construction_is_named(kwargs, match):
    args = {"half_sizes": [HALF] * 3, "mass": MASS, "dt": DT}
    if "vertices" in kwargs:
        args.pop("half_sizes")
    args.update(kwargs)
    with pytest.raises(lcs_cvx.LCSInputError, match=match):
        lcs_cvx.RigidBodyContact(**args)


def test_neither_or_both_geometries_are_refused():
    with pytest.raises(lcs_cvx.LCSInputError, match="vertices, half_sizes: expected exactly one"):
        lcs_cvx.RigidBodyContact(mass=1.0, dt=0.01)
    with pytest.raises(lcs_cvx.LCSInputError, match="received both"):
        lcs_cvx.RigidBodyContact([[0, 0, 0]], half_sizes=[1, 1, 1], mass=1.0, dt=0.01)


def test_states_of_the_wrong_width_and_far_from_unit_quaternions_are_refused():
    m = cube()
    with pytest.raises(lcs_cvx.LCSInputError, match="x: expected"):
        m.step(torch.zeros(2, 12, dtype=F64), torch.zeros(2, 0, dtype=F64))
    x = state()
    x[0, 0] = 1.5
    with pytest.raises(lcs_cvx.LCSInputError, match="x: expected unit quaternions"):
        m.step(x, NO_U)
    near = state()
    near[0, :4] *= 1 + 1e-4
    with pytest.warns(UserWarning, match="normalised"):
        out = m.step(near, NO_U)
    assert torch.allclose(out, m.step(state(), NO_U), atol=1e-15)


def test_angles_of_a_tumbling_rollout_stay_unit_quaternions():
    m = cube(mu=0.5)
    x = state(q=(0.8, 0.4, 0.3, 0.2), p=(0, 0, 0.12), w=(5.0, -3.0, 1.0), v=(0.5, 0.0, -1.0))
    xs = m.rollout(x, torch.zeros(1, 80, 0, dtype=F64))[0]
    assert bool(torch.isfinite(xs).all())
    assert float((xs[:, :4].norm(dim=-1) - 1).abs().max()) < 1e-13
    # it lands: the lowest corner ends near the floor (within the compliance's and a step's slack)
    R = rotation_matrix(xs[-1:, :4])[0]
    lowest = float((xs[-1, 4:7] + m.vertices.detach() @ R.mT)[:, 2].min())
    assert -2e-3 < lowest < 2e-3


def test_a_residual_starts_at_the_rigid_body_and_its_lcs_at_a_state_includes_it(tmp_path):
    plain, with_res = cube(mu=0.3), cube(mu=0.3, residual=True)
    x = state(q=(0.95, 0.2, -0.1, 0.05), p=(0.0, 0.0, HALF + 0.001), w=(2.0, -1.0, 0.5), v=(0.3, -0.2, -0.4))
    assert torch.equal(with_res.step(x, NO_U), plain.step(x, NO_U))
    assert with_res.residual_map.requires_grad and with_res.residual_map.shape == (6, 14)
    with torch.no_grad():
        with_res.residual_map.copy_(0.01 * torch.randn(6, 14, generator=torch.Generator().manual_seed(0), dtype=F64))
    assert not torch.allclose(with_res.step(x, NO_U), plain.step(x, NO_U))
    assert torch.allclose(with_res.lcs_at(x[0]).step(x, NO_U), with_res.step(x, NO_U), atol=1e-12)
    lcs_cvx.save_model(with_res, tmp_path / "res.npz")
    assert torch.equal(lcs_cvx.load_model(tmp_path / "res.npz").step(x, NO_U), with_res.step(x, NO_U))
