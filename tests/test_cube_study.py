"""The cube-toss study (studies/cube): its smoke run, resume, metrics and split."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest
import torch

import lcs_cvx
from studies.cube import models as M
from studies.cube import study
from studies.cube.metrics import geodesic_angle, rollouts


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    out = tmp_path_factory.mktemp("cube")
    # one training size (every model at its smoke budget); a second size is added by the resume
    # test, for the fast models alone
    assert study.main(["--out", str(out), "--smoke", "--sizes", "2"]) == 0
    return out


def _lines(path):
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def test_smoke_writes_a_row_per_model_and_size(smoke):
    for name in ("cube_smoke.jsonl", "report_smoke.md", "learning_curve_smoke.png", "rollouts_smoke.png"):
        assert os.path.getsize(smoke / name) > 0, name
    rows = [r for r in _lines(smoke / "cube_smoke.jsonl") if r["size"] == 2]  # (the resume test adds size 4)
    names = [s.name for s in M.specs()]
    assert len(names) >= 4
    assert sorted((r["size"], r["model"]) for r in rows) == sorted((2, m) for m in names)
    for r in rows:
        assert os.path.exists(smoke / r["model_file"])
        for h in ("H10", "H30", "end"):
            ro = r["rollout"][h]
            assert ro["rollouts"] > 0 and 0 <= ro["diverged"] <= ro["rollouts"]
            # a diverged rollout makes the mean infinite instead of vanishing from it
            assert (ro["diverged"] > 0) == (ro["pos"] == "inf")
        assert set(r["one_step"]) >= {"quaternion rel", "position rms", "angular velocity rel", "linear velocity rms"}
    report = (smoke / "report_smoke.md").read_text()
    assert study.DATE in report and study.MACHINE in report
    assert "## Target check" in report
    for name in names:
        assert name in report


def test_resume_skips_finished_cells(smoke, monkeypatch):
    before = (smoke / "cube_smoke.jsonl").read_text()

    def refuse(*args, **kwargs):
        raise AssertionError("a finished cell was fitted again")

    monkeypatch.setattr(M, "specs", lambda _s=M.specs: [
        M.Spec(s.name, s.key, s.ext, refuse, s.load, s.twin) for s in _s()])
    records = study.run(str(smoke), [2], smoke=True)
    assert (smoke / "cube_smoke.jsonl").read_text() == before
    assert len(records) == len(before.strip().splitlines())
    # a larger size for two models: their cells appended, the finished ones kept as they were
    monkeypatch.undo()
    records = study.run(str(smoke), [2, 4], smoke=True, only=["affine", "increment"])
    after = (smoke / "cube_smoke.jsonl").read_text()
    assert after.startswith(before)
    added = _lines(smoke / "cube_smoke.jsonl")[len(before.strip().splitlines()):]
    assert sorted((r["size"], r["key"]) for r in added) == [(4, "affine"), (4, "increment")]
    assert len(records) == len(before.strip().splitlines()) + 2


def test_structured_lcs_keeps_its_fixed_entries(smoke):
    rows = [r for r in _lines(smoke / "cube_smoke.jsonl") if r["key"] == "lcs_structured"]
    assert rows
    reference = M.structured_lcs(2)
    for r in rows:
        model = lcs_cvx.load_model(smoke / r["model_file"])
        assert torch.equal(model.d.detach(), reference.d.detach())  # bit-identical gravity
        assert float(model.d.detach().reshape(-1)[12]) == pytest.approx(-9.81 / 148.0)
        free = reference.masks["A"]
        assert bool((model.A.detach()[~free] == 0).all())
        assert bool((model.A.detach()[free] != 0).any())  # the rest was learned


def test_geodesic_angle_on_a_known_rotation():
    theta = 0.7
    q = np.array([1.0, 0.0, 0.0, 0.0])
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    q_hat = np.concatenate([[math.cos(theta / 2)], math.sin(theta / 2) * axis])
    assert geodesic_angle(q, q_hat) == pytest.approx(theta, abs=1e-12)
    assert geodesic_angle(q, -3.0 * q_hat) == pytest.approx(theta, abs=1e-12)  # sign and scale
    assert geodesic_angle(q_hat, q_hat) == pytest.approx(0.0, abs=1e-6)
    assert math.isnan(float(geodesic_angle(q, [np.nan, 0, 0, 0])))


def test_a_diverging_rollout_is_counted():
    xs = [torch.tensor([[1.0] * 13, [1.0] * 13, [1.0] * 13, [1.0] * 13], dtype=torch.float64)] * 2
    stats = rollouts(lambda x: 100.0 * x, xs, horizons=(2,))
    assert stats["end"]["diverged"] == 2 and stats["end"]["pos"] == math.inf
    assert stats["H2"]["diverged"] == stats["H2"]["rollouts"] == 4
    ok = rollouts(lambda x: x, xs, horizons=(2,))
    assert ok["end"]["diverged"] == 0 and ok["end"]["pos"] == 0.0 and ok["end"]["rot"] == pytest.approx(0.0, abs=1e-6)


def test_split_is_by_toss_and_disjoint():
    parts = study.split(550)
    sets = {k: set(v) for k, v in parts.items()}
    assert [len(parts[k]) for k in ("train", "validation", "test")] == [275, 138, 137]
    assert sets["train"].isdisjoint(sets["validation"]) and sets["train"].isdisjoint(sets["test"])
    assert sets["validation"].isdisjoint(sets["test"])
    assert sets["train"] | sets["validation"] | sets["test"] == set(range(550))
    assert study.split(550) == parts  # fixed
    data = lcs_cvx.datasets.cube_tosses()
    train = study.subset(data, parts["train"])
    small, large = (study.subset(train, list(range(n))) for n in (4, 8))
    for a, b in zip(small.xs, large.xs, strict=False):  # nested: a larger size extends a smaller one
        assert torch.equal(a, b)
    assert torch.equal(train.xs[0], data.xs[parts["train"][0]])


def test_a_saved_mlp_loads_back_the_same_stepper(tmp_path):
    """Its normalisation buffers load back as saved (they once shared one tensor on load)."""
    mu, sigma, s = torch.linspace(0, 1, 13), torch.linspace(1, 2, 13), torch.linspace(2, 3, 13)
    model = M.ResidualMLP(mu, sigma, s, (8,))
    torch.save({"hidden": [8], "state": model.state_dict()}, tmp_path / "m.pt")
    x = torch.randn(5, 13, dtype=torch.float64)
    loaded = M._load_mlp(str(tmp_path / "m.pt"))
    with torch.no_grad():
        assert torch.equal(loaded(x), model.eval()(x))


def _rotate(q, v):
    """``v`` rotated by the unit quaternion ``q`` (``q ⊗ (0, v) ⊗ q*``)."""
    from lcs_cvx.kinematics import quaternion_product
    qv = torch.cat([torch.zeros(v.shape[0], 1, dtype=v.dtype), v], dim=1)
    conj = q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)
    return quaternion_product(quaternion_product(q, qv), conj)[:, 1:]


def test_the_cube_frames_are_its_rotations_and_their_quaternions_agree():
    from studies.cube import symmetry as Y
    rotations = Y._rotations()
    assert len(rotations) == 24 and len({tuple(S.flatten().tolist()) for S in rotations}) == 24
    for S in rotations:
        assert torch.allclose(S @ S.T, torch.eye(3, dtype=torch.float64)) and torch.linalg.det(S) > 0
        q = Y._quaternion(S).expand(3, 4)
        assert torch.allclose(_rotate(q, torch.eye(3, dtype=torch.float64)), S.T, atol=1e-15)  # q e_j = S e_j
    assert Y.FRAMES.shape == (6, 3, 3)
    assert sorted(tuple(S[2].tolist()) for S in Y.FRAMES) == sorted(
        tuple(v) for v in (torch.eye(3).tolist() + (-torch.eye(3)).tolist()))  # each face to +z once


def test_a_state_in_its_frame_has_its_top_face_up_and_maps_back():
    from lcs_cvx.kinematics import up_in_body
    from studies.cube import symmetry as Y
    x = torch.cat(lcs_cvx.datasets.cube_tosses().xs[:20])
    k = Y.frame_of(x)
    assert len(set(k.tolist())) > 1  # the tosses visit several frames
    xs = Y.to_frame(x, k)
    g, gs = up_in_body(x[:, :4]), up_in_body(xs[:, :4])
    assert torch.allclose(gs, torch.einsum("nij,nj->ni", Y.FRAMES[k], g), atol=1e-12)  # g_S = S g
    assert bool((gs[:, 2] >= gs[:, :2].abs().max(dim=1).values - 1e-12).all())
    # the same rigid motion: the world position of a body point and the world angular velocity agree
    r = torch.randn(x.shape[0], 3, dtype=torch.float64)
    r_s = torch.einsum("nij,nj->ni", Y.FRAMES[k], r)
    assert torch.allclose(_rotate(xs[:, :4], r_s), _rotate(x[:, :4], r), atol=1e-12)
    assert torch.allclose(_rotate(xs[:, :4], xs[:, 7:10]), _rotate(x[:, :4], x[:, 7:10]), atol=1e-12)
    assert torch.allclose(Y.from_frame(xs, k), x, atol=1e-12)
    assert torch.equal(Y.frame_of(xs), torch.zeros_like(k) + Y.frame_of(xs)[0])  # all in the +z frame
    assert bool((Y.FRAMES[Y.frame_of(xs)] == torch.eye(3, dtype=torch.float64)).all())


def test_segments_keep_every_transition_once_in_the_frame_of_its_first_state():
    from studies.cube import symmetry as Y
    data = lcs_cvx.datasets.cube_tosses()
    tosses = lcs_cvx.Trajectories(data.xs[:10], data.us[:10])
    pieces = Y.segments(tosses)
    assert len(pieces.xs) > len(tosses.xs) and sum(pieces.lengths) == sum(tosses.lengths)
    x = torch.cat([t[:-1] for t in tosses.xs])
    x_next = torch.cat([t[1:] for t in tosses.xs])
    k = Y.frame_of(x)
    ours = torch.cat([p[:-1] for p in pieces.xs]), torch.cat([p[1:] for p in pieces.xs])
    assert torch.allclose(ours[0], Y.to_frame(x, k), atol=1e-14)
    assert torch.allclose(ours[1], Y.to_frame(x_next, k), atol=1e-14)


def test_the_symmetric_stepper_flies_a_cube_like_the_kinematics():
    """In flight (every corner far above the floor, no unit active) the step is free flight in
    any frame: ``v' = v - g dt e_z``, ``w' = w``, ``p`` and ``q`` integrated from them."""
    from studies.cube import kinematic
    from studies.cube import symmetry as Y
    model = Y.symmetric_lcs(8)
    assert bool((model.masks["D"][:, :6] == False).all()) and bool((model.D.detach()[:, :6] == 0).all())  # noqa: E712
    assert bool((model.C.detach() == 0).all())  # it starts at free flight
    with torch.no_grad():  # forces that would show: a unit active in flight would change the velocities
        model.C.copy_(torch.randn(model.C.shape, dtype=model.dtype, generator=torch.Generator().manual_seed(0)))
    x = torch.cat(lcs_cvx.datasets.cube_tosses().xs[:20])
    x = x[Y.frame_of(x) != Y.frame_of(x)[0]][:50].clone()  # states in frames other than the first's
    x[:, 6] = 1.0  # high above the floor
    plain = kinematic.stepper(model)
    with torch.no_grad():
        assert torch.allclose(Y.stepper(model)(x), plain(x), atol=1e-12)
        assert torch.allclose(plain(x)[:, 7:10], x[:, 7:10], atol=1e-12)


def test_the_physics_reference_lets_a_flat_cube_fall_to_rest():
    pytest.importorskip("mujoco")
    from studies.cube import physics
    x0 = torch.zeros(1, 13, dtype=torch.float64)
    x0[0, 0], x0[0, 6], x0[0, 10] = 1.0, 0.2, 0.3  # level, 20 cm up, sliding along x
    (traj,) = physics.simulate(physics.NOMINAL, [x0.expand(120, 13)])
    assert traj.shape == (120, 13) and torch.equal(traj[0], x0[0])
    end = traj[-1]
    assert end[6].item() == pytest.approx(physics.NOMINAL.side / 2, abs=2e-3)  # resting on its face
    assert float(end[7:13].abs().max()) < 1e-2 and end[4].item() > 0.0  # stopped, after sliding forward
    assert float(geodesic_angle(x0[0, :4].numpy(), end[:4].numpy())) < 0.02
    err = physics.errors(physics.NOMINAL, [traj])
    assert err["pos"] == pytest.approx(0.0, abs=1e-12) and err["rot"] == pytest.approx(0.0, abs=1e-6)


def test_drake_flies_as_mujoco_and_lets_a_dropped_cube_come_to_rest():
    pytest.importorskip("mujoco")
    pytest.importorskip("pydrake")
    from studies.cube import physics
    # a tumbling toss in flight: both engines take the state as the tosses record it (body
    # angular velocity, world linear velocity, w < 0 kept) and agree to their integrators
    q = torch.tensor([-0.6, 0.3, -0.5, 0.55], dtype=torch.float64)
    x0 = torch.cat([q / q.norm(), torch.tensor([0.1, -0.2, 0.8, 4.0, -2.0, 7.0, 0.5, 0.2, 1.0], dtype=torch.float64)])
    (mj,) = physics.simulate(physics.NOMINAL, [x0.expand(20, 13)])
    (dk,) = physics.simulate(physics.NOMINAL_DRAKE, [x0.expand(20, 13)])
    assert float((dk[:, 4:6] - mj[:, 4:6]).abs().max()) < 1e-12
    # the height: Drake takes one semi-implicit Euler step per period, MuJoCo ten, which differ
    # by g dt^2 / 2 per step in free fall (19 steps: 4 mm)
    assert float((dk[:, 6] - mj[:, 6]).abs().max()) < 19 * 9.81 * (1 / 148) ** 2 / 2 * 1.05
    assert float(geodesic_angle(dk[:, :4].numpy(), mj[:, :4].numpy()).max()) < 1e-2
    assert float((dk[:, :4] * mj[:, :4]).sum(-1).min()) > 0  # one hemisphere: the sign is continuous
    assert float((dk[:, 7:] - mj[:, 7:]).abs().max()) < 1e-2
    drop = torch.zeros(150, 13, dtype=torch.float64)
    drop[:, 0], drop[:, 6] = 1.0, 0.2
    (traj,) = physics.simulate(physics.NOMINAL_DRAKE, [drop])
    assert traj[-1, 6].item() == pytest.approx(physics.NOMINAL_DRAKE.side / 2, abs=2e-3)
    assert float(traj[-1, 7:].abs().max()) < 1e-2


def test_the_seed_table_reports_every_fit_and_the_range(tmp_path):
    from studies.cube import seeds

    def rec(seed, rot):
        roll = {h: {"pos": 0.01 * (seed + 1), "rot": rot, "diverged": 0} for h in ("H10", "H30", "end")}
        return {"key": "lcs_symmetry", "model": "LCS, cube symmetry", "seed": seed, "size": 275, "n_lam": 16,
                "heldout_error": 0.2, "rollout": roll, "dair_pll": {"pos": 0.03, "rot": rot}}
    text = seeds.write(str(tmp_path), [rec(0, 0.5), rec(1, 0.7)], "cmd")
    assert (tmp_path / "seeds.md").read_text() == text
    assert text.count("| LCS, cube symmetry | 0 |") == 1 and text.count("| LCS, cube symmetry | 1 |") == 1
    assert "| LCS, cube symmetry | 2 | 0.015 (0.01–0.02) | 0.6 (0.5–0.7) |" in text
    assert f"{math.degrees(0.6):.4g} ({math.degrees(0.5):.4g}–{math.degrees(0.7):.4g})" in text


def test_the_simulated_box_tosses_end_at_rest_on_a_face():
    pytest.importorskip("mujoco")
    from studies.cube import simulated_box as B

    runs = B.tosses(4, seed=0)
    assert len(runs) == 4 and all(x.shape == (B.STEPS + 1, 13) for x in runs.xs)
    for x in runs.xs:
        assert float((x[:, :4].norm(dim=1) - 1).abs().max()) < 1e-9
        # at rest on one of its faces: the centre at one of the half sizes above the floor
        assert min(abs(float(x[-1, 6]) - h) for h in B.TRUTH["half_sizes"]) < 3e-3
        assert float(x[-1, 10:13].abs().max()) < 0.05


def test_dair_pll_angle_is_the_shorter_one_within_a_hemisphere_and_its_complement_across():
    from studies.cube.metrics import atan2_angle

    q = np.array([0.9, 0.1, 0.3, -0.2])
    q /= np.linalg.norm(q)
    p = np.array([0.8, 0.2, 0.3, -0.1])
    p /= np.linalg.norm(p)
    short = float(geodesic_angle(q, p))
    assert float(atan2_angle(q, p)) == pytest.approx(short, abs=1e-12)
    assert float(atan2_angle(q, -p)) == pytest.approx(2 * math.pi - short, abs=1e-12)
