"""The pusher-slider study (studies/physics/pusher_*.py): the MuJoCo plant (sticking, sliding
either way and separation all occur, the friction force stays in the Coulomb cone and points
against the slip, the slider's frame, reproducible by seed), the nested training sizes, the
config's errors, the PARC baseline (a piecewise-affine toy, rebuilt exactly from its stored arrays),
and the smoke config run end to end through the study runner, resumed from its store, and with a
PARC fit that fails reported in its rows."""

from __future__ import annotations

import importlib.util
import json
import os

import numpy as np
import pytest
from conftest import ROOT, needs_mujoco

import lcs_cvx
from lcs_cvx import load_model

pytestmark = needs_mujoco
needs_parc = pytest.mark.skipif(
    importlib.util.find_spec("pyparc") is None,
    reason="pyparc is not installed (the baselines extra: pip install 'lcs_cvx[baselines]')")
SMOKE = os.path.join(ROOT, "studies", "configs", "pusher_slider_smoke.toml")


@pytest.fixture(scope="module")
def transitions():
    from studies.physics.pusher_plant import sample_transitions

    return sample_transitions(1500, seed=0)


# -- the plant -----------------------------------------------------------------------------------
def test_shapes_chaining_and_every_mode_occurs(transitions):
    from studies.physics.pusher_plant import MODES

    tr = transitions
    assert tr.x.shape == (1500, 5) and tr.x_next.shape == (1500, 5) and tr.u.shape == (1500, 2)
    assert tr.force.shape == (1500, 2) and tr.contact.shape == (1500,) and tr.pose.shape == (1500, 3)
    assert all(np.isfinite(a).all() for a in (tr.x, tr.u, tr.x_next, tr.force, tr.pose))
    fractions = np.bincount(tr.contact, minlength=len(MODES)) / len(tr)
    assert len(fractions) == len(MODES) and (fractions >= 0.08).all(), fractions  # all four modes, often
    same = tr.traj[1:] == tr.traj[:-1]
    assert np.array_equal(tr.x[1:][same], tr.x_next[:-1][same])  # a trajectory chains
    assert (tr.step[1:][same] == tr.step[:-1][same] + 1).all()
    assert np.array_equal(tr.in_contact, tr.contact != 0)
    assert tr.select(tr.traj < 3).pose.shape[1] == 3  # selecting keeps the pusher's fields


def test_friction_stays_in_the_coulomb_cone_and_opposes_the_slip(transitions):
    from studies.physics.pusher_plant import Physics

    mu = Physics().mu_pusher
    f_n, f_t, mode = transitions.force[:, 0], transitions.force[:, 1], transitions.contact
    assert (f_n[mode == 0] == 0).all() and (f_t[mode == 0] == 0).all()  # separated: no force
    assert (f_n[mode != 0] > 0).all()  # the pusher pushes, never pulls
    assert (np.abs(f_t) <= mu * f_n * (1 + 1e-9) + 1e-12).all()  # the period mean of forces in the cone
    ratio = np.abs(f_t) / np.where(f_n > 0, f_n, 1.0)
    assert np.median(ratio[mode == 1]) < 0.5 * mu  # sticking: inside the cone
    # sliding: on its boundary while it slides (the mean over a period that also sticks or
    # separates for a few substeps is inside)
    assert np.median(ratio[mode >= 2]) > 0.75 * mu and np.quantile(ratio[mode >= 2], 0.75) > 0.99 * mu
    # sliding +y (the pusher slips towards +y on the face): friction drags the slider along +y
    assert np.median(f_t[mode == 2]) > 0 > np.median(f_t[mode == 3])


def test_hand_made_pushes_stick_slide_and_separate():
    from studies.physics.pusher_plant import MODES, PusherSlider

    sim = PusherSlider()
    sim.reset(p_x=sim.physics.touching_x, p_y=0.0)
    for _ in range(4):  # a centred push: the slider follows the pusher, no turn, no slip
        x, force, mode = sim.step([10.0, 0.0])
        assert MODES[mode] == "sticking"
    assert abs(x[2] - 10.0) < 0.5 and abs(x[4]) < 1e-3 and abs(x[1]) < 0.01
    assert sim.pose[0] == pytest.approx(4 * 0.05 * 10.0, rel=0.1)  # ~2 cm forward in the world
    x, force, mode = sim.step([5.0, 12.0])  # sideways faster than friction holds
    assert MODES[mode] == "sliding +y" and x[1] > 0.3
    x, force, mode = sim.step([-5.0, 0.0])  # retreat
    assert MODES[mode] == "separated" and (force == 0).all()
    assert x[0] < sim.physics.touching_x - 0.1

    sim.reset(p_x=sim.physics.touching_x, p_y=3.0)  # off-centre: the slider turns away from the pusher
    for _ in range(10):
        x, _, _ = sim.step([10.0, 0.0])
    assert x[4] < 0 and sim.pose[2] < -0.01
    with pytest.raises(ValueError, match=r"p_x, p_y: expected finite numbers with p_x <= -6 cm"):
        sim.reset(p_x=-5.0, p_y=0.0)
    with pytest.raises(ValueError, match=r"u: expected 2 finite numbers"):
        sim.step([1.0, np.nan])


def test_the_slider_frame_makes_the_state_independent_of_the_heading():
    """After a turn, the same command from the same slider-frame state gives the same next
    state: the simulation is re-expressed in the slider's frame every period."""
    from studies.physics.pusher_plant import PusherSlider

    a, b = PusherSlider(), PusherSlider()
    a.reset(p_x=a.physics.touching_x, p_y=3.0)
    b.reset(p_x=b.physics.touching_x, p_y=3.0)
    for _ in range(12):
        a.step([10.0, 0.0])
    for _ in range(12):
        b.step([10.0, 0.0])
    assert abs(a.pose[2]) > 0.02  # it has turned ...
    xa, _, _ = a.step([6.0, -2.0])
    xb, _, _ = b.step([6.0, -2.0])
    assert np.array_equal(xa, xb)  # ... deterministic, and the world pose only accumulates


def test_reproducible_by_seed_and_wide_inputs(transitions):
    from studies.physics.pusher_plant import Sampling, sample_transitions

    again = sample_transitions(1500, seed=0)
    for name in ("x", "u", "x_next", "force", "contact", "pose"):
        assert np.array_equal(getattr(again, name), getattr(transitions, name))
    assert not np.array_equal(sample_transitions(100, seed=1).u, transitions.u[:100])
    s = Sampling()
    lo, hi = s.ux_range
    assert lo <= transitions.u[:, 0].min() and transitions.u[:, 0].max() <= hi
    wide = sample_transitions(1500, seed=2, wide_factor=1.5)
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    assert wide.u[:, 0].min() < lo or wide.u[:, 0].max() > hi
    assert (np.abs(wide.u[:, 0] - mid) <= 1.5 * half + 1e-9).all()
    w = transitions.u[:, 1] + s.uy_gain * transitions.x[:, 1]
    assert np.abs(w).max() <= s.uy_noise + 1e-9


# -- data splits and config ----------------------------------------------------------------------
def test_training_sizes_are_nested_with_interleaved_validation(transitions):
    from studies.physics.pusher_study import split_sizes

    splits = split_sizes(transitions, [200, 700, 1200], val_every=5)
    for n, (train, val) in splits.items():
        assert len(train) == n and len(val) > 0
        assert (train.traj % 5 != 4).all() and (val.traj % 5 == 4).all()
        assert val.traj.max() < train.traj.max() + 5  # interleaved with the training trajectories
    assert np.array_equal(splits[700][0].x[:200], splits[200][0].x)  # nested
    with pytest.raises(ValueError, match=r"data.sizes: the stream holds \d+ training samples, fewer than"):
        split_sizes(transitions, [5000], val_every=5)


def test_the_full_config_spells_out_the_defaults():
    """pusher_slider.toml says its values are the code's defaults: parsing it gives the same
    study as parsing an empty config."""
    import dataclasses
    import tomllib

    from studies.physics.pusher_study import parse_config

    with open(os.path.join(ROOT, "studies", "configs", "pusher_slider.toml"), "rb") as f:
        full = parse_config(tomllib.load(f))
    empty = parse_config({"name": "pusher_slider"})
    plain = lambda c: {k: dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v for k, v in c.items()}  # noqa: E731
    assert plain(full) == plain(empty)


def test_config_errors_name_the_section_and_the_key():
    from studies.physics.pusher_study import parse_config

    cfg = parse_config({"name": "p"})
    assert cfg["data"]["sizes"] == [500, 2000, 10000, 20000] and cfg["lcs"]["tolerance"] == 0.1
    assert cfg["parc"]["K"] == 4 and cfg["parc"]["sigma"] == 1.0 and cfg["parc"]["seed"] == 0
    assert cfg["lcs"]["prediction"]["normalize"] is True
    for bad, match in (({"data": {"sizes": [500, 500]}}, r"data\.sizes: expected a non-empty list of distinct integers"),
                       ({"data": {"sizes": [0.5]}}, r"data\.sizes"),
                       ({"mlp": {"hidden": [64, 64]}}, r"mlp\.hidden: expected a list of layer-width lists"),
                       ({"mlp": {"weight_decay": [-1.0]}}, r"mlp\.weight_decay"),
                       ({"physics": {"mu": 0.3}}, r"\[physics\]: unknown key 'mu'"),
                       ({"lcs": {"losses": ["hinge"]}}, r"lcs\.losses: expected 'violation' or 'prediction'"),
                       ({"parc": {"sigma": -1.0}}, r"parc\.sigma: expected a finite number >= 0"),
                       ({"parc": {"K": 0}}, r"parc\.K: expected"),
                       ({"parc": {"seed": -1}}, r"parc\.seed: expected an integer >= 0"),
                       ({"parc": {"pieces": 4}}, r"parc\.pieces: unknown key"),
                       ({"plots": {}}, r"plots: unknown key")):
        with pytest.raises(ValueError, match=match):
            parse_config({"name": "p", **bad})


# -- PARC ----------------------------------------------------------------------------------------
@needs_parc
def test_parc_job_finds_the_pieces_of_a_piecewise_affine_map_and_is_rebuilt_exactly():
    """On x' = x + B u + (a_left or a_right)(x) with the switch at x_1 = 0, PARC (K = 2) fits
    the training data far better than one affine map, its partition is the switch, and the model
    rebuilt from the job's stored arrays predicts what pyparc's own predictor does."""
    from lcs_cvx.study.baselines import baseline_options
    from lcs_cvx.study.baselines.parc import fit
    from lcs_cvx.study.store import Store
    from studies.physics.evaluation import relative_error
    from studies.physics.models import AffineModel, fit_parc, parc_from_result

    rng = np.random.default_rng(0)
    x, u = rng.uniform(-1, 1, (600, 2)), rng.uniform(-1, 1, (600, 1))
    left = x[:, 0] < 0
    x_next = x + 0.1 * u @ np.array([[1.0, 0.5]]) + np.where(
        left[:, None], [0.3, -0.2] - 0.5 * x[:, 1:2], [-0.3, 0.2] + 0.5 * x[:, 1:2])
    options = baseline_options("parc", {"K": 2})
    res = fit_parc({"x": x, "u": u, "x_next": x_next, "options": options, "modes": 2, "seed": 0})
    assert res["error"] is None and res["info"]["K_final"] == 2
    model = parc_from_result(res)
    pred = model.predict(x, u)
    assert pred.shape == x_next.shape
    parc_err = relative_error(pred, x_next)
    affine_err = relative_error(AffineModel.fit(x, u, x_next).predict(x, u), x_next)
    assert parc_err < 0.5 * affine_err, (parc_err, affine_err)
    piece = model.piece(x, u)
    assert max((piece == left).mean(), (piece != left).mean()) > 0.85  # the partition is the switch
    # the arrays survive the study database, and the rebuilt model is pyparc's predictor
    import tempfile

    with tempfile.TemporaryDirectory() as d, Store(d) as store:
        store.add_job("k", "toy", "fit_parc", res)
        stored = parc_from_result(store.jobs(["k"])["k"])
    own, _ = fit(lcs_cvx.Dataset.from_arrays(x, u, x_next), options, seed=0, modes=2)
    xt, ut = rng.uniform(-2, 2, (50, 2)), rng.uniform(-2, 2, (50, 1))
    assert np.array_equal(stored.predict(xt, ut), own.predictor.predict(np.hstack([xt, ut]))[0])


@needs_parc
def test_parc_job_reports_a_failed_fit(monkeypatch):
    from lcs_cvx.study.baselines import BaselineFailed, baseline_options
    from lcs_cvx.study.baselines import parc as parc_baseline
    from studies.physics.models import fit_parc, parc_from_result

    def broken(*args, **kwargs):  # as the wrapper raises when pyparc's fit fails
        raise BaselineFailed("PARC failed: LinAlgError: Singular matrix") from np.linalg.LinAlgError(
            "Singular matrix")

    monkeypatch.setattr(parc_baseline, "fit", broken)
    x = np.zeros((20, 2))
    res = fit_parc({"x": x, "u": x[:, :1], "x_next": x, "options": baseline_options("parc", {}), "modes": 2, "seed": 0})
    assert res["error"] == "LinAlgError: Singular matrix" and res["omega"] is None
    with pytest.raises(ValueError, match=r"result: expected a PARC fit that succeeded, received the error"):
        parc_from_result(res)


@needs_parc
def test_parc_job_names_pyparcs_own_error_when_its_fit_fails():
    """30 pieces on 30 samples: pyparc merges every cluster away and raises; the job's error
    names pyparc's exception, not the BaselineFailed that wraps it."""
    from lcs_cvx.study.baselines import baseline_options
    from studies.physics.models import fit_parc

    x = np.random.default_rng(0).uniform(-1, 1, (30, 2))
    res = fit_parc({"x": x, "u": x[:, :1], "x_next": x, "options": baseline_options("parc", {"K": 30}),
                    "modes": 2, "seed": 0})
    assert res["error"] == "ValueError: attempt to get argmax of an empty sequence" and res["omega"] is None


# -- the study, end to end -------------------------------------------------------------------------
@needs_parc
def test_smoke_study_runs_through_the_runner_and_resumes(tmp_path, monkeypatch):
    from lcs_cvx.study.runner import run_config

    run_config(SMOKE, out=tmp_path, workers=1, progress=False)
    for name in ("report.md", "metrics.json", "learning_curve.png", "error_vs_horizon.png", "rollouts.png"):
        assert (tmp_path / name).stat().st_size > 0
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert list(m["sizes"]) == ["200", "400"] and m["jobs"] == {"total": 14, "run_now": 14}
    rows = m["sizes"]["400"]["sets"]["test"]
    assert [r["name"] for r in rows] == ["LCS, violation loss", "LCS, prediction loss", "affine (least squares)",
                                         "MLP", "affine per true mode (oracle)", "PARC (piecewise-affine regression)"]
    for r in rows:
        assert set(r["one_step"]) == {"separated", "sticking", "sliding +y", "sliding -y", "contact", "all"}
        assert np.isfinite(list(r["one_step"].values())).all() and set(r["rollout"]) == {"1", "5", "20"}
        assert np.isfinite(list(r["rollout"].values())).all() and r["error"] is None
    parc = m["sizes"]["400"]["selection"]["parc"]  # a real PARC fit: 4 pieces, fitted in the job
    assert parc["error"] is None and parc["info"]["K"] == 4 and 1 <= parc["info"]["K_final"] <= 4
    assert parc["wall_time"] > 0 and np.isfinite(parc["val_error"])
    # every (size, set, loss) has a target row, computed from the rows
    assert len(m["target"]) == 2 * 2 * 2
    t = next(t for t in m["target"] if t["size"] == 400 and t["set"] == "test" and t["loss"] == "violation")
    assert t["contact_ratio"] == pytest.approx(rows[3]["one_step"]["contact"] / rows[0]["one_step"]["contact"])
    # the chosen n_lam is the selection rule's on the recorded validation errors
    from lcs_cvx.selection import choose

    sel = m["sizes"]["400"]["selection"]["n_lam"]["violation"]
    assert sel["chosen"] == choose({int(k): v for k, v in sel["val_error"].items()}, 0.1)
    model = load_model(tmp_path / "models" / "lcs_violation_n400.npz")
    assert (model.n_x, model.n_u, model.n_lam) == (5, 2, sel["chosen"])
    # the study's rollout error is the library's (lcs_cvx.rollout_error) at the longest horizon
    from studies.physics.pusher_plant import sample_transitions

    test = sample_transitions(300, seed=1)  # the smoke config's test set
    library = lcs_cvx.rollout_error(model, test.to_trajectories(), [20])[20]
    assert library == pytest.approx(rows[0]["rollout"]["20"], rel=1e-9)
    report = (tmp_path / "report.md").read_text()
    assert "## Target: the LCS 1.5× below the MLP" in report
    parc_rows = [line for line in report.splitlines() if line.startswith("| PARC (piecewise-affine regression) | ")]
    assert len(parc_rows) == 4 and not any("–" in r or "failed" in r for r in parc_rows)  # 2 curves, 2 per mode
    assert "K = 4 (told how many modes there are" in report and "N = 400: " in report
    # a second run reads every job from the store: the same numbers, nothing trained
    run_config(SMOKE, out=tmp_path, workers=1, progress=False)
    again = json.loads((tmp_path / "metrics.json").read_text())
    assert again["jobs"] == {"total": 14, "run_now": 0}
    assert again["sizes"] == m["sizes"] and again["target"] == m["target"]
    # another PARC seed runs the two PARC jobs only; where pyparc raises, the rows say so
    from lcs_cvx.study.baselines import BaselineFailed
    from lcs_cvx.study.baselines import parc as parc_baseline

    def broken(*args, **kwargs):  # as the wrapper raises when pyparc's fit fails
        raise BaselineFailed("PARC failed: LinAlgError: Singular matrix") from np.linalg.LinAlgError(
            "Singular matrix")

    monkeypatch.setattr(parc_baseline, "fit", broken)
    other = tmp_path / "other_seed.toml"
    other.write_text(f'name = "pusher_slider_smoke"\nextends = {json.dumps(SMOKE)}\n[parc]\nseed = 1\n')
    run_config(other, out=tmp_path, workers=1, progress=False)
    failed = json.loads((tmp_path / "metrics.json").read_text())
    assert failed["jobs"] == {"total": 14, "run_now": 2}
    for n in ("200", "400"):
        row = failed["sizes"][n]["sets"]["test"][-1]
        assert row["name"] == "PARC (piecewise-affine regression)" and row["one_step"] is None
        assert row["error"] == "LinAlgError: Singular matrix"
        assert failed["sizes"][n]["sets"]["test"][:-1] == m["sizes"][n]["sets"]["test"][:-1]
    report = (tmp_path / "report.md").read_text()
    assert "| PARC (piecewise-affine regression) | fit failed: LinAlgError: Singular matrix | – |" in report
    assert "| PARC (piecewise-affine regression) | failed (see Models) | failed (see Models) |" in report
    assert "N = 200: **failed** after" in report and (tmp_path / "learning_curve.png").stat().st_size > 0
