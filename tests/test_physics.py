"""The physics study (studies/physics/): the MuJoCo cart-pole data generator (plant.py), the
normalisation folded into an LCS in physical units, the contact-agreement metric, the training
jobs (jobs.py: keys, the store, a failing job), a smoke run of the whole study (study.py,
report.py, the command line of cartpole_walls.py), resumed from the store, and of the MPC, and
user data in: Dataset.load / Dataset.from_csv on good and bad files."""

from __future__ import annotations

import json
import os
import tomllib

import numpy as np
import pytest
import torch
from conftest import ROOT, needs_mujoco

import lcs_cvx
from lcs_cvx import Dataset, LCSInputError, load_model

F64 = torch.float64


# -- the generator -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def transitions():
    from studies.physics.plant import sample_transitions

    return sample_transitions(1500, seed=0)


@needs_mujoco
def test_generator_shapes_finite_and_contact_fraction(transitions):
    tr = transitions
    assert len(tr) == 1500
    assert tr.x.shape == (1500, 4) and tr.u.shape == (1500, 1) and tr.x_next.shape == (1500, 4)
    assert tr.force.shape == (1500, 2) and tr.contact.shape == (1500, 2)
    assert all(a.dtype == np.float64 for a in (tr.x, tr.u, tr.x_next, tr.force))
    assert tr.contact.dtype == bool
    assert all(np.isfinite(a).all() for a in (tr.x, tr.u, tr.x_next, tr.force))
    assert 0.05 <= tr.in_contact.mean() <= 0.60
    assert tr.contact[:, 0].any() and tr.contact[:, 1].any()  # both walls get hit
    assert not tr.contact.all(axis=1).any()  # the walls are 0.4 m apart: never both at once
    # a wall pushes (never pulls) exactly when it is in contact
    assert (tr.force >= 0).all()
    assert ((tr.force > 0) == tr.contact).all()
    # consecutive samples of a trajectory chain: x_next of one is x of the next
    same = tr.traj[1:] == tr.traj[:-1]
    assert np.array_equal(tr.x[1:][same], tr.x_next[:-1][same])
    ds = tr.dataset()
    assert isinstance(ds, Dataset) and len(ds) == 1500 and ds.lam.shape == (1500, 2)


@needs_mujoco
def test_generator_seeds_and_wide_inputs(transitions):
    from studies.physics.plant import Sampling, sample_transitions

    again = sample_transitions(1500, seed=0)
    assert np.array_equal(again.x_next, transitions.x_next)
    other = sample_transitions(300, seed=1)
    assert not np.array_equal(other.x[:10], transitions.x[:10])
    wide = sample_transitions(1500, seed=2, wide_factor=1.5)
    s = Sampling()
    w = transitions.u[:, 0] + s.kp * transitions.x[:, 0] + s.kd * transitions.x[:, 2]
    w_wide = wide.u[:, 0] + s.kp * wide.x[:, 0] + s.kd * wide.x[:, 2]
    assert np.abs(w).max() <= s.u_max + 1e-9
    assert s.u_max < np.abs(w_wide).max() <= 1.5 * s.u_max + 1e-9


@needs_mujoco
def test_wall_pushes_only_a_pole_that_touches_it():
    from studies.physics.plant import CartPoleWalls

    sim = CartPoleWalls()
    sim.reset([0.0, 0.0, 0.0, 0.0])  # upright and still: nothing touches in one period
    _, force, contact = sim.step(0.0)
    assert not contact.any() and (force == 0).all()
    sim.reset([0.0, 0.4, 0.0, 0.0])  # the tip is 3.4 cm into the right wall
    x_next, force, contact = sim.step(0.0)
    assert contact.tolist() == [False, True] and force[1] > 0
    assert x_next[3] < 0  # pushed back towards upright


@needs_mujoco
def test_windows_stay_inside_one_trajectory(transitions):
    for h in (1, 5, 20):
        starts = transitions.windows(h)
        assert len(starts) > 0
        assert (transitions.traj[starts + h - 1] == transitions.traj[starts]).all()
        assert (transitions.step[starts + h - 1] == transitions.step[starts] + h - 1).all()


# -- models and metrics --------------------------------------------------------------------------
def test_contact_agreement_best_assignment():
    from studies.physics.evaluation import contact_agreement

    g = np.random.default_rng(0)
    contact = np.zeros((400, 2), dtype=bool)
    contact[:100, 0] = True
    contact[100:180, 1] = True
    # unit 2 = right wall, units 0 and 3 = left wall (split), unit 1 always active
    active = np.stack([contact[:, 0] & (np.arange(400) % 2 == 0), np.ones(400, bool),
                       contact[:, 1], contact[:, 0] & (np.arange(400) % 2 == 1)], axis=1)
    res = contact_agreement(active, contact)
    assert res["agreement"] == 1.0
    # either sign uses one unit per wall: the split left wall is half covered by unit 0 or 3
    assert res["either_sign"] == pytest.approx(0.5 * (1 - 50 / 400) + 0.5) and res["either_sign_units"][1] == 2
    assert res["assignment"] == ["left", None, "right", "left"]
    assert res["trivial"] == pytest.approx(1 - 180 / 800)
    # permutation invariance and a noisy copy
    perm = g.permutation(4)
    assert contact_agreement(active[:, perm], contact)["agreement"] == 1.0
    flipped = active.copy()
    flipped[:40, 0] = ~flipped[:40, 0]
    assert contact_agreement(flipped, contact)["agreement"] == pytest.approx(1 - 20 / 800)
    # a unit active exactly off contact: no credit as "active", full credit with either sign
    off = np.stack([~contact[:, 0], ~contact[:, 1]], axis=1)
    assert contact_agreement(off, contact)["agreement"] < 0.8
    assert contact_agreement(off, contact)["either_sign"] == 1.0


@needs_mujoco
def test_one_step_and_rollout_errors_of_a_perfect_model(transitions):
    from studies.physics import evaluation as ev

    class Replay:  # returns the recorded next state: exact one step, exact along windows
        def predict(self, x, u, contact=None):
            idx = np.array([np.flatnonzero((transitions.x == xi).all(axis=1))[0] for xi in x])
            return transitions.x_next[idx]

    errs = ev.one_step_errors(Replay(), transitions)
    assert errs == {"free": 0.0, "contact": 0.0, "all": 0.0}
    assert (ev.rollout_errors(Replay(), transitions, 5) == 0).all()


# -- the study, end to end -----------------------------------------------------------------------
def _smoke_config() -> dict:
    with open(os.path.join(ROOT, "studies", "configs", "physics_cartpole_smoke.toml"), "rb") as f:
        return tomllib.load(f)


def _without_timing(metrics: dict) -> dict:
    """metrics.json less what a second run may change: times, the jobs run, the code state."""
    out = {k: v for k, v in metrics.items() if k not in ("timing_s", "jobs", "code")}
    out["metrics"] = {s: [{k: v for k, v in r.items() if k != "train_s"} for r in rows]
                      for s, rows in metrics["metrics"].items()}
    return out


@needs_mujoco
def test_smoke_study_runs_end_to_end_and_resumes_from_the_store(tmp_path):
    from studies.physics.study import run_study

    config = _smoke_config()
    assert config["kind"] == "module" and config["module"] == "studies.physics.cartpole_walls"
    run_study(config, str(tmp_path), workers=1)
    for name in ("report.md", "metrics.json", "rollouts.png", "error_vs_horizon.png", "studies.sqlite"):
        assert (tmp_path / name).stat().st_size > 0
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    rows = metrics["metrics"]["test"]
    names = [r["name"] for r in rows]
    assert names == ["LCS violation n_λ=2", "LCS prediction n_λ=2", "affine (least squares)", "MLP",
                     "affine per true mode (oracle)"]
    for r in rows:
        assert np.isfinite([r["one_step"]["free"], r["one_step"]["contact"], r["rollout"]["1"]]).all()
    report = (tmp_path / "report.md").read_text()
    assert "| LCS violation n_λ=2 |" in report and "rollout H=20" in report
    # the exported model maps physical units: it reproduces the study's one-step error
    model = load_model(tmp_path / "models" / "lcs_violation_nlam2.npz")
    assert model.n_x == 4 and model.n_u == 1 and model.n_lam == 2
    assert metrics["jobs"] == {"total": 3, "run_now": 3}
    # a second run reads the three training jobs from the store: the same numbers, nothing trained
    first = (tmp_path / "models" / "lcs_violation_nlam2.npz").read_bytes()
    run_study(config, str(tmp_path), workers=1)
    again = json.loads((tmp_path / "metrics.json").read_text())
    assert again["jobs"] == {"total": 3, "run_now": 0}
    assert _without_timing(again) == _without_timing(metrics)
    assert [r["train_s"] for r in again["metrics"]["test"][:2]] == [r["train_s"] for r in rows[:2]]
    assert (tmp_path / "models" / "lcs_violation_nlam2.npz").read_bytes() == first
    assert "3 of 3 jobs read from the study database" in (tmp_path / "report.md").read_text()


def test_the_command_line_module_re_exports_the_split_modules():
    from studies.physics import cartpole_walls, plant, study

    assert cartpole_walls.run_study is study.run_study
    assert cartpole_walls.parse_config is study.parse_config
    for name in ("Physics", "Sampling", "Transitions", "CartPoleWalls", "mjcf", "sample_transitions"):
        assert getattr(cartpole_walls, name) is getattr(plant, name)
    with pytest.raises(SystemExit):
        cartpole_walls.main(["--config", "c.toml"])  # --out is required


def test_config_errors_name_the_section_and_the_key():
    from studies.physics.study import parse_config

    cfg = parse_config(_smoke_config())
    assert cfg["lcs"]["violation"]["iterations"] == 20 and cfg["lcs"]["violation"]["recipe"] == "best"
    assert cfg["data"]["n_test"] == 200 and cfg["data"]["val_every"] == 10  # given and default
    for bad, match in (({"physics": {"mass": 1.0}}, r"\[physics\]: unknown key 'mass'"),
                       ({"lcs": {"losses": ["hinge"]}}, r"lcs\.losses: expected 'violation'"),
                       ({"lcs": {"seeds": [0, 0]}}, r"lcs\.seeds: expected a non-empty list of distinct"),
                       ({"mlp": {"depth": 2}}, r"mlp\.depth: unknown key"),
                       ({"plots": {}}, r"plots: unknown key")):
        with pytest.raises(ValueError, match=match):
            parse_config({**_smoke_config(), **bad})


# -- the training jobs ---------------------------------------------------------------------------
def _tiny_mlp_args(seed: int = 0) -> dict:
    g = np.random.default_rng(seed)
    z, v, y = g.normal(size=(40, 2)), g.normal(size=(40, 1)), g.normal(size=(40, 2))
    return {"z": z, "v": v, "y": y, "z_val": z, "v_val": v, "y_val": y, "hidden": [4],
            "iterations": 3, "batch_size": 8, "lr": 1e-2, "weight_decay": 0.0, "seed": seed}


def test_job_keys_follow_the_function_and_every_argument():
    from studies.physics.jobs import job_key, make_job

    args = _tiny_mlp_args()
    key = make_job("fit_mlp", args)["key"]
    assert key == job_key("fit_mlp", {**args})  # reproducible
    assert key == job_key("fit_mlp", {**args, "hidden": (4,)})  # a tuple is its list
    assert key != job_key("fit_lcs", args)
    assert key != job_key("fit_mlp", {**args, "seed": 1})
    changed = args["z"].copy()
    changed[3, 1] += 1e-12
    assert key != job_key("fit_mlp", {**args, "z": changed})  # arrays by their bytes
    assert key != job_key("fit_mlp", {**args, "z": args["z"].astype(np.float32)})
    with pytest.raises(ValueError, match=r"function: expected one of \('fit_lcs', 'fit_mlp', 'fit_parc'\), received 'fit_svm'"):
        make_job("fit_svm", args)


def test_a_failing_job_stops_the_run_and_keeps_the_finished_ones(tmp_path):
    from lcs_cvx.study import Store
    from studies.physics.jobs import JobError, make_job, run_jobs

    good = make_job("fit_mlp", _tiny_mlp_args())
    bad = make_job("fit_mlp", {k: v for k, v in _tiny_mlp_args(1).items() if k != "lr"})
    with pytest.raises(JobError, match=r"(?s)job fit_mlp failed; 1 finished jobs are in .*KeyError: 'lr'"):
        run_jobs([good, bad], str(tmp_path), "t", workers=1)
    with Store(tmp_path) as store:
        assert list(store.jobs([good["key"], bad["key"]])) == [good["key"]]
    results, run_now = run_jobs([good], str(tmp_path), "t", workers=1)
    assert run_now == 0 and results[0]["hidden"] == [4]


@needs_mujoco
def test_mpc_closes_the_loop_in_mujoco():
    from studies.physics.mpc_example import LCSMPC, MPCSettings, simulate

    # a hand-made LCS: the free dynamics of a linear inverted pendulum on a cart and one unit
    # per wall (lam_0 = max(0, tip - 0.18), lam_1 = max(0, -tip - 0.18) push theta' back)
    dt = 0.04
    A = np.eye(4) + dt * np.array([[0, 0, 1, 0], [0, 0, 0, 1], [0, -2.0, 0, 0], [0, 30.0, 0, 0]])
    B = dt * np.array([[0.0], [0.0], [0.9], [-2.5]])
    C = dt * np.array([[0.0, 0.0], [0.0, 0.0], [5.0, -5.0], [-100.0, 100.0]])
    D = np.array([[-1.0, -0.6, 0, 0], [1.0, 0.6, 0, 0]])
    matrices = {"A": A, "B": B, "C": C, "d": np.zeros(4), "D": D, "E": np.zeros((2, 1)),
                "F": np.eye(2), "c": np.array([0.18, 0.18])}
    ctrl = LCSMPC(matrices, MPCSettings(horizon=5, u_max=4.0))
    run = simulate(ctrl, np.array([0.0, 0.1, 0.0, 0.0]), steps=10)
    assert run["x"].shape == (11, 4) and np.isfinite(run["x"]).all()
    assert (np.abs(run["u"]) <= 4.0 + 1e-9).all() and ctrl.qp_solves >= 10


# -- user data in: npz and CSV ------------------------------------------------------------------
def _write(path, text: str):
    path.write_text(text)
    return path


def test_csv_round_trip_default_and_named_columns(tmp_path):
    g = np.random.default_rng(0)
    x, u, xn, lam = g.normal(size=(5, 2)), g.normal(size=(5, 1)), g.normal(size=(5, 2)), g.random((5, 3))
    header = "t,x_0,x_1,u_0,x_next_0,x_next_1,lam_0,lam_1,lam_2"
    rows = [",".join(repr(float(v)) for v in [i, *x[i], *u[i], *xn[i], *lam[i]]) for i in range(5)]
    path = _write(tmp_path / "data.CSV", "# my robot\n" + header + "\n" + "\n".join(rows) + "\n")
    ds = Dataset.load(path)
    assert ds.n_x == 2 and ds.n_u == 1 and len(ds) == 5
    for got, want in ((ds.x, x), (ds.u, u), (ds.x_next, xn), (ds.lam, lam)):
        assert got.dtype == F64 and np.array_equal(got.numpy(), want)  # repr round-trips exactly
    named = Dataset.from_csv(path, columns={"x": ["x_1", "x_0"], "u": ["t"], "x_next": ["x_next_0", "x_next_1"]})
    assert np.array_equal(named.x.numpy(), x[:, ::-1]) and named.lam is None
    assert np.array_equal(named.u.numpy()[:, 0], np.arange(5.0))


@pytest.mark.parametrize(
    "name, text, match",
    [
        ("empty.csv", "", r"^path: expected a CSV file with a header row, '.*empty\.csv' is empty$"),
        ("header.csv", "x_0,u_0,x_next_0\n", r"expected at least one data row in '.*', found only the header"),
        ("dup.csv", "x_0,x_0,u_0,x_next_0\n1,2,3,4\n", r"duplicate column 'x_0' in the header"),
        ("noname.csv", "x_0,,u_0,x_next_0\n1,2,3,4\n", r"line 1 of '.*' \(the header\) has an empty column name"),
        ("missing.csv", "x_0,u_0\n1,2\n", r"missing \['x_next_0\.\.'\] \(found \['x_0', 'u_0'\]\)"),
        ("gap.csv", "x_0,x_2,u_0,x_next_0,x_next_1,x_next_2\n1,2,3,4,5,6\n", r"expected columns x_0 \.\. x_2 in '.*', missing \['x_1'\]"),
        ("ragged.csv", "x_0,u_0,x_next_0\n1,2,3\n\n4,5\n", r"line 4 of '.*' has 2 fields, expected 3 \(the header's\)"),
        ("text.csv", "x_0,u_0,x_next_0\n1,abc,3\n", r"line 2 of '.*', column 'u_0': expected a finite number, received 'abc'"),
        ("nan.csv", "x_0,u_0,x_next_0\n1,2,nan\n", r"column 'x_next_0': expected a finite number, received 'nan'"),
        ("blank.csv", "x_0,u_0,x_next_0\n1,,3\n", r"column 'u_0': expected a finite number, received ''"),
        ("sizes.csv", "x_0,x_1,u_0,x_next_0\n1,2,3,4\n", r"expected as many next-state columns as state columns"),
    ],
)
def test_csv_rejects_malformed_files(tmp_path, name, text, match):
    with pytest.raises(LCSInputError, match=match):
        Dataset.load(_write(tmp_path / name, text))


def test_csv_bad_columns_argument_and_unreadable_files(tmp_path):
    good = _write(tmp_path / "good.csv", "x_0,u_0,x_next_0\n1,2,3\n")
    with pytest.raises(LCSInputError, match=r"columns: 'u' names \['force'\] not in the header"):
        Dataset.from_csv(good, columns={"x": ["x_0"], "u": ["force"], "x_next": ["x_next_0"]})
    with pytest.raises(LCSInputError, match=r"columns: expected keys 'x', 'u', 'x_next'"):
        Dataset.from_csv(good, columns={"x": ["x_0"]})
    with pytest.raises(LCSInputError, match=r"expected a non-empty list of column names for 'x'"):
        Dataset.from_csv(good, columns={"x": "x_0", "u": ["u_0"], "x_next": ["x_next_0"]})
    with pytest.raises(LCSInputError, match=r"^path: expected an existing \.csv file, received '.*nope\.csv' \(not found\)$"):
        Dataset.load(tmp_path / "nope.csv")
    binary = tmp_path / "binary.csv"
    binary.write_bytes(b"\xff\xfe\x00\x01")
    with pytest.raises(LCSInputError, match=r"expected a CSV text file, could not read"):
        Dataset.load(binary)
    with pytest.raises(LCSInputError, match=r"columns: only for \.csv files"):
        Dataset.load(tmp_path / "data.npz", columns={"x": ["a"]})


def test_npz_from_a_user_and_its_errors(tmp_path):
    g = np.random.default_rng(1)
    path = tmp_path / "mine.npz"
    np.savez(path, x=g.normal(size=(7, 3)), u=g.normal(size=7), x_next=g.normal(size=(7, 3)))
    ds = Dataset.load(path)  # a 1-D u is one input
    assert ds.n_x == 3 and ds.n_u == 1 and len(ds) == 7
    bad = tmp_path / "nan.npz"
    np.savez(bad, x=np.full((3, 2), np.nan), u=np.zeros((3, 1)), x_next=np.zeros((3, 2)))
    with pytest.raises(LCSInputError, match=r"^x: expected finite values, received 6 NaN/inf entries$"):
        Dataset.load(bad)
    wrong = tmp_path / "wrong.npz"
    np.savez(wrong, x=np.zeros((3, 2)), u=np.zeros((3, 1)), x_next=np.zeros((3, 3)))
    with pytest.raises(LCSInputError, match=r"^x_next: expected shape \(N, 2\) or \(2,\), received shape \(3, 3\)$"):
        Dataset.load(wrong)


def test_a_diverged_restart_is_reported_not_selected(monkeypatch):
    from studies.physics import models

    def diverge(*args, **kwargs):
        raise lcs_cvx.SolverError("fit: the loss became NaN at iteration 7")

    monkeypatch.setattr(lcs_cvx, "fit", diverge)
    g = np.random.default_rng(0)
    x, u, xn = g.normal(size=(50, 2)), g.normal(size=(50, 1)), g.normal(size=(50, 2))
    out = models.fit_lcs({"x": x, "u": u, "x_next": xn, "x_val": x, "u_val": u, "x_next_val": xn,
                          "n_lam": 2, "loss": "violation", "recipe": "best", "options": {},
                          "stiffness": 1.0, "init_scale": 0.1, "init": "affine", "seed": 0})
    assert out["matrices"] is None and out["val_error"] == float("inf")
    assert "iteration 7" in out["error"]
