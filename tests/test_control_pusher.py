"""The MuJoCo pusher-slider closed-loop study (studies.control.pusher_closed_loop), smoke variant:
2 starts, 0.5 s runs, every controller; the JSON lines, the report and the figure are written, a
rerun skips the finished runs, and the pose augmentation of the planning model is the rotation
of the slider-frame displacement."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

pytest.importorskip("mujoco")

from studies.control import pusher_closed_loop as study  # noqa: E402


def test_smoke_run_writes_report(tmp_path):
    out = tmp_path / "control"
    assert study.main(["--out", str(out), "--smoke"]) == 0
    lines = (out / "pusher_closed_loop.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in lines]
    names = list(study.CONTROLLERS)
    assert len(records) == 2 * len(names)
    assert {(r["controller"], r["start"]) for r in records} == {(n, i) for n in names for i in range(2)}
    for r in records:
        assert r["steps"] == 10
        assert isinstance(r["success"], bool)
        assert np.isfinite(r["final_position_error"]) and r["final_position_error"] >= 0
        assert 0 <= r["final_heading_error"] <= math.pi
        assert r["max_abs_u"] <= study.U_MAX + 1e-9
        assert len(r["path"]) == 6  # every other of the 11 poses
        np.testing.assert_allclose(r["start_params"], study.starts(2)[r["start"]])
        if r["controller"] == "no input":
            assert r["max_abs_u"] == 0.0 and r["ms_per_step_median"] == 0.0
            # nothing pushes the box: it stays at the origin with its start heading
            np.testing.assert_allclose(r["path"][-1], [0.0, 0.0, round(r["start_params"][2], 4)], atol=1e-3)
        else:
            assert r["ms_per_step_median"] > 0
        if r["controller"].startswith("C3"):
            assert np.isfinite(r["plan_violation_median"])
    md = (out / "pusher_closed_loop.md").read_text()
    for n in names:
        assert f"| {n} |" in md
    assert "2026-11-25" in md and "2-core x86-64 VM" in md and "--smoke" in md
    assert (out / "pusher_closed_loop.png").stat().st_size > 1000
    assert (out / "pusher_closed_loop_cache_smoke" / "affine_1000.npz").exists()
    # a rerun finds every run done and appends nothing
    assert study.main(["--out", str(out), "--smoke"]) == 0
    assert (out / "pusher_closed_loop.jsonl").read_text().splitlines() == lines


def _learned() -> dict[str, np.ndarray]:
    import os

    import lcs_cvx

    m = lcs_cvx.load_model(os.path.join(study.MODELS, "lcs_violation_n20000.npz")).to_matrices()
    return {k: np.asarray(v, dtype=np.float64) for k, v in m.items()}


@pytest.mark.parametrize("theta", [0.0, 0.7, -2.3])
def test_augmented_model_rotates_the_slider_frame_displacement(theta):
    """One step of the augmented LCS (the learned one and the hand-written one): the slider-frame
    rows are the LCS's own, and the pose moves by R(theta) times the kinematic displacement
    (dt u - (p' - p), dt omega') of that step, to 1e-12."""
    import lcs_cvx

    rng = np.random.default_rng(1)
    for m in (_learned(), study.handwritten_lcs(1.0)):
        aug = study.augment(m, theta=theta)
        x = np.array([-6.2, 1.0, 3.0, -0.5, 0.1])
        pose = np.array([3.0, -2.0, theta])
        u = rng.uniform(-5, 10, 2)
        z = np.concatenate([x, pose])
        lam = lcs_cvx.solve_lcp(aug["F"], (aug["D"] @ z + aug["E"] @ u + aug["c"])[None]).lam.numpy()[0]
        lam_small = lcs_cvx.solve_lcp(m["F"], (m["D"] @ x + m["E"] @ u + m["c"])[None]).lam.numpy()[0]
        np.testing.assert_allclose(lam, lam_small, atol=1e-12)
        z_next = aug["A"] @ z + aug["B"] @ u + aug["C"] @ lam + aug["d"]
        x_next = m["A"] @ x + m["B"] @ u + m["C"] @ lam + m["d"]
        np.testing.assert_allclose(z_next[:5], x_next, rtol=0, atol=1e-12)
        delta = study.displacement(x, u, x_next)
        c, s = math.cos(theta), math.sin(theta)
        expected = pose + np.array([c * delta[0] - s * delta[1], s * delta[0] + c * delta[1], delta[2]])
        np.testing.assert_allclose(z_next[5:], expected, rtol=0, atol=1e-12)
        np.testing.assert_allclose(study.compose(pose, delta), expected, rtol=0, atol=1e-12)
        # the LCS built from the matrices (what C3 plans with) reproduces them
        M = study.as_lcs(aug).to_matrices()
        np.testing.assert_allclose(np.asarray(M["F"]), aug["F"], atol=1e-10)


def test_displacement_matches_the_plant():
    """The kinematic displacement reproduces the plant's tracked world pose over a few pushes."""
    from studies.physics.pusher_plant import PusherSlider

    sim = PusherSlider()
    sim.reset(-6.3, 0.5)
    pose = np.zeros(3)
    for u in ([8.0, 0.0], [8.0, 1.0], [6.0, -2.0], [6.0, 0.0], [-2.0, 0.0]):
        x = sim.state
        x_next, _, _ = sim.step(np.array(u))
        pose = study.compose(pose, study.displacement(x, np.array(u), x_next))
    assert np.linalg.norm(pose[:2] - sim.pose[:2]) < 0.1  # cm, after ~1.5 cm of pushing
    assert np.linalg.norm(sim.pose[:2]) > 1.0
    assert abs(pose[2] - sim.pose[2]) < 0.02


def test_goal_in_local_frame():
    pose = np.array([2.0, 1.0, 0.5])
    goal = np.array([10.0, -3.0, 0.1])
    local = study.to_local(pose, goal)
    back = study.compose(pose, local)
    np.testing.assert_allclose(back[:2], goal[:2], atol=1e-12)
    assert abs(local[2] - (0.1 - 0.5)) < 1e-12


def test_handwritten_lcs_pushes():
    """Pushing straight at the face's centre: both cone edges carry the force, the slider moves with
    the pusher and does not turn; pulling away: no force."""
    import lcs_cvx

    m = study.handwritten_lcs(0.0)
    x = np.array([study.TOUCH, 0.0, 0.0, 0.0, 0.0])
    for u, pushes in (([5.0, 0.0], True), ([-2.0, 0.0], False)):
        lam = lcs_cvx.solve_lcp(m["F"], (m["D"] @ x + m["E"] @ np.array(u) + m["c"])[None]).lam.numpy()[0]
        x_next = m["A"] @ x + m["B"] @ np.array(u) + m["C"] @ lam
        if pushes:
            assert lam[0] > 0 and abs(lam[0] - lam[1]) < 1e-9
            assert abs(x_next[2] - 5.0) < 0.05 and abs(x_next[4]) < 1e-12  # eps I in F: 0.5 %
        else:
            assert np.all(lam == 0) and x_next[0] < study.TOUCH
