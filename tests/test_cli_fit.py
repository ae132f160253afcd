"""`lcs-cvx fit` and `lcs-cvx predict`: predictions and metrics of a saved model, the plumbing
from the command line to :func:`lcs_cvx.fit` (with a stand-in trainer), one real end-to-end fit,
and bad input that exits 2 with a one-line message naming the option."""

from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

import lcs_cvx
from lcs_cvx import LCS, Dataset, load_metadata, load_model, make_dataset, random_lcs, save_model
from lcs_cvx.cli import main

F64 = torch.float64


def _facts(out: str) -> dict[str, str]:
    return dict(line.split(": ", 1) for line in out.strip().splitlines() if ": " in line)


def _error_line(capsys, command: str) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"lcs-cvx {command}: error: ")
    return lines[0]


@pytest.fixture(scope="module")
def truth() -> LCS:
    return random_lcs(2, 1, 2, seed=4)


@pytest.fixture
def files(tmp_path, truth) -> dict[str, Path]:
    """A noiseless data set of ``truth``, ``truth`` saved as a model, and a second data set."""
    paths = {"data": tmp_path / "data.npz", "model": tmp_path / "model.npz", "test": tmp_path / "test.npz"}
    make_dataset(truth, 300, seed=1).save(paths["data"])
    make_dataset(truth, 100, seed=2).save(paths["test"])
    save_model(truth, paths["model"])
    return paths


# -- predict ---------------------------------------------------------------------------------


def test_predict_with_the_true_model(files, truth, capsys):
    out = files["data"].with_name("pred.npz")
    argv = ["predict", "--model", str(files["model"]), "--data", str(files["data"]), "--out", str(out)]
    assert main(argv) == 0
    facts = _facts(capsys.readouterr().out)
    data = Dataset.load(files["data"])
    assert float(facts["e_test"]) < 1e-24  # noiseless data of this very system
    assert int(facts["modes"]) == lcs_cvx.count_modes(truth, data)
    assert int(facts["modes"]) >= 2
    assert facts["predictions"] == str(out)
    with np.load(out, allow_pickle=False) as f:
        assert sorted(f.files) == ["lam", "x_next_pred"]
        np.testing.assert_allclose(f["x_next_pred"], data.x_next.numpy(), rtol=0, atol=1e-10)
        np.testing.assert_allclose(f["lam"], data.lam.numpy(), rtol=0, atol=1e-10)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_predict_reports_the_library_metrics(files, capsys, dtype):
    model = LCS(2, 1, 3, stiffness=1.0, seed=9, init_scale=1.0, dtype=dtype)  # another system: e_test is not 0
    save_model(model, files["model"])
    assert main(["predict", "--model", str(files["model"]), "--data", str(files["test"])]) == 0
    facts = _facts(capsys.readouterr().out)
    test = Dataset.load(files["test"])
    expected = lcs_cvx.relative_error(model, test)
    assert expected > 1e-3
    assert float(facts["e_test"]) == pytest.approx(expected, rel=1e-5)
    assert int(facts["modes"]) == lcs_cvx.count_modes(model, test)
    assert facts["model"].startswith("n_x=2, n_u=1, n_lam=3 ")
    assert "predictions" not in facts


def _bad_data(path: Path, **arrays: Any) -> str:
    g = np.random.default_rng(0)
    base = {"x": g.standard_normal((20, 2)), "u": g.standard_normal((20, 1)), "x_next": g.standard_normal((20, 2))}
    base.update(arrays)
    np.savez(path, **base)
    return str(path)


def _nan(shape: tuple[int, ...]) -> np.ndarray:
    a = np.ones(shape)
    a[3, 0] = np.nan
    return a


@pytest.mark.parametrize(
    ("case", "named", "says"),
    [
        ("no-model", "--model", r"expected an existing model file .*\(not found\)"),
        ("no-data", "--data", r"expected an existing \.npz file.*\(not found\)"),
        ("data-as-model", "--model", r"a data set\?"),
        ("wrong-n-x", "--data", r"expected n_x=2, n_u=1 \(the model's, .*\), received n_x=3, n_u=1 in "),
        ("nan-x", "--data", r"x: expected finite values, received 1 NaN/inf entries \(in '.*bad\.npz'\)"),
        ("out-dir", "--out", r"expected a file in an existing directory"),
        ("no-model-option", "--model", r"expected a value \(the option is required\), received none"),
    ],
)
def test_predict_bad_input_exits_2(files, capsys, case, named, says):
    tmp = files["data"].parent
    model, data, extra = str(files["model"]), str(files["data"]), []
    if case == "no-model":
        model = str(tmp / "missing.npz")
    elif case == "no-data":
        data = str(tmp / "missing.npz")
    elif case == "data-as-model":
        model = data
    elif case == "wrong-n-x":
        data = _bad_data(tmp / "bad.npz", x=np.ones((20, 3)), x_next=np.ones((20, 3)))
    elif case == "nan-x":
        data = _bad_data(tmp / "bad.npz", x=_nan((20, 2)))
    elif case == "out-dir":
        extra = ["--out", str(tmp / "no" / "pred.npz")]
    argv = ["predict", "--model", model, "--data", data, *extra]
    if case == "no-model-option":
        argv = argv[:1] + argv[3:]
    assert main(argv) == 2
    line = _error_line(capsys, "predict")
    assert line.startswith(f"lcs-cvx predict: error: {named}: ")
    assert re.search(says, line), line


def _trajectories(system: LCS, lengths, seed: int = 0) -> lcs_cvx.Trajectories:
    """Noiseless trajectories of ``system``, simulated with ``LCS.rollout``."""
    g = torch.Generator().manual_seed(seed)
    xs, us = [], []
    for T in lengths:
        u = torch.rand(T, system.n_u, generator=g, dtype=F64) * 10 - 5
        with torch.no_grad():
            xs.append(system.rollout(torch.rand(system.n_x, generator=g, dtype=F64) * 20 - 10, u))
        us.append(u)
    return lcs_cvx.Trajectories(xs, us)


@pytest.mark.parametrize("kind", ["npz", "csv"])
def test_predict_on_a_trajectory_file(files, truth, capsys, kind):
    trajs = _trajectories(truth, [8, 30, 12])
    path = files["data"].with_name(f"trajs.{kind}")
    if kind == "npz":
        trajs.save(path)
    else:
        rows = ["trajectory,x_0,x_1,u_0"]
        for i, (x, u) in enumerate(zip(trajs.xs, trajs.us, strict=True)):
            rows += [f"{i},{x[t, 0].item()!r},{x[t, 1].item()!r},{u[t, 0].item() if t < len(u) else ''}"
                     for t in range(len(x))]
        path.write_text("\n".join(rows) + "\n")
    model = LCS(2, 1, 3, stiffness=1.0, seed=9, init_scale=1.0, dtype=F64)  # not the truth: errors > 0
    save_model(model, files["model"])
    assert main(["predict", "--model", str(files["model"]), "--data", str(path)]) == 0
    facts = _facts(capsys.readouterr().out)
    assert facts["data"] == f"50 samples in 3 trajectories ({path})"
    assert float(facts["e_test"]) == pytest.approx(lcs_cvx.relative_error(model, trajs.to_transitions()), rel=1e-5)
    expected = lcs_cvx.rollout_error(model, trajs, (1, 5, 20))
    printed = [float(v) for v in facts["rollout error (H=1, 5, 20)"].split(", ")]
    assert printed == pytest.approx([expected[1], expected[5], expected[20]], rel=1e-5)
    assert min(printed) > 1e-3

    # --horizons; one longer than every trajectory is left out
    assert main(["predict", "--model", str(files["model"]), "--data", str(path), "--horizons", "2,31,30"]) == 0
    facts = _facts(capsys.readouterr().out)
    expected = lcs_cvx.rollout_error(model, trajs, (2, 30))
    printed = [float(v) for v in facts["rollout error (H=2, 30)"].split(", ")]
    assert printed == pytest.approx([expected[2], expected[30]], rel=1e-5)
    assert not any(k.startswith("rollout error (H=2, 31") for k in facts)

    # the true system: zero rollout error; every horizon too long: said so
    save_model(truth, files["model"])
    assert main(["predict", "--model", str(files["model"]), "--data", str(path), "--horizons", "1,30"]) == 0
    facts = _facts(capsys.readouterr().out)
    assert all(float(v) < 1e-24 for v in facts["rollout error (H=1, 30)"].split(", "))
    assert main(["predict", "--model", str(files["model"]), "--data", str(path), "--horizons", "40"]) == 0
    assert "longer than the longest trajectory, 30 steps" in _facts(capsys.readouterr().out)["rollout error"]


def test_predict_on_transitions_prints_no_rollout_and_refuses_horizons(files, capsys):
    assert main(["predict", "--model", str(files["model"]), "--data", str(files["test"])]) == 0
    assert "rollout" not in capsys.readouterr().out
    assert main(["predict", "--model", str(files["model"]), "--data", str(files["test"]), "--horizons", "1,5"]) == 2
    assert "error: --horizons: only for trajectory files" in _error_line(capsys, "predict")


@pytest.mark.parametrize(
    "text, says",
    [
        ("trajectory,x_0,x_1,u_0\na,1,2,3\n", r"--data: trajectory 'a' of '.*bad\.csv' \(line 2\): expected at least 2 rows"),
        ("trajectory,x_0,x_1,u_0\na,1,2,x\na,1,2,\n", r"--data: line 2 of '.*bad\.csv', column 'u_0': expected a finite number"),
    ],
)
def test_predict_bad_trajectory_file_exits_2(files, capsys, text, says):
    path = files["data"].with_name("bad.csv")
    path.write_text(text)
    assert main(["predict", "--model", str(files["model"]), "--data", str(path)]) == 2
    line = _error_line(capsys, "predict")
    assert re.search(says, line), line


def test_predict_bad_horizons_exits_2(files, capsys):
    assert main(["predict", "--model", str(files["model"]), "--data", str(files["test"]), "--horizons", "1,0"]) == 2
    assert "expected comma-separated integers >= 1" in capsys.readouterr().err


# -- fit: the plumbing, with a stand-in for lcs_cvx.fit -------------------------------------


@dataclass(frozen=True)
class _Settings:
    loss: str = "violation"
    lr: float = 1e-3
    betas: tuple[float, float] = (0.9, 0.9)
    max_time: float = math.inf
    dtype: torch.dtype = F64
    extra: dict = field(default_factory=lambda: {"polish": True})

    def flat(self) -> dict:  # FitOptions.flat(): the settings as fit's keywords
        return asdict(self)


@dataclass
class _Result:
    model: LCS
    history: list
    settings: _Settings
    n_fallback: int = 0
    fallback_residual: float = 0.0
    beats_affine: bool | None = None
    verdict: str = ""


class _FakeFit:
    """Records its call; "learns" by copying ``truth``'s parameters into the model."""

    def __init__(self, truth: LCS) -> None:
        self.truth = truth
        self.calls: list[tuple[LCS, Dataset, dict]] = []

    def __call__(self, model, train, **kwargs):
        self.calls.append((model, train, kwargs))
        init = {k: v.detach().clone() for k, v in model.state_dict().items()}
        model.load_state_dict({k: v.clone() for k, v in self.truth.state_dict().items()})
        self.init = init
        return _Result(model, [{"iteration": 1, "loss": 0.5}], _Settings())


@pytest.fixture
def fake_fit(monkeypatch, truth):
    fake = _FakeFit(truth)
    monkeypatch.setattr(lcs_cvx, "fit", fake, raising=False)  # run_fit looks up lcs_cvx.fit
    return fake


def test_fit_passes_only_the_given_options(files, fake_fit, capsys, truth):
    out = files["data"].with_name("learned.npz")
    argv = ["fit", "--data", str(files["data"]), "--n-lam", "2", "--out", str(out)]
    assert main(argv) == 0
    facts = _facts(capsys.readouterr().out)

    (model, train, kwargs), = fake_fit.calls
    assert kwargs == {"test": None, "progress": True}  # fit's own defaults decide the rest
    assert len(train) == 300 and torch.equal(train.x, Dataset.load(files["data"]).x)
    assert (model.n_x, model.n_u, model.n_lam) == (2, 1, 2)
    fresh = LCS(2, 1, 2, stiffness=1.0, seed=0)  # documented defaults of the initialisation
    assert all(torch.equal(fake_fit.init[k], v) for k, v in fresh.state_dict().items())

    loaded = load_model(out)
    assert all(torch.equal(getattr(loaded, k), getattr(truth, k)) for k in ("A", "C", "G", "H", "c"))
    meta = load_metadata(out)["metadata"]
    assert meta["fit"] == {
        "loss": "violation", "lr": 1e-3, "betas": [0.9, 0.9], "max_time": "inf",
        "dtype": "torch.float64", "extra": {"polish": True},
    }
    assert meta["init"] == {"n_lam": 2, "stiffness": 1.0, "seed": 0}
    assert "e_test" not in facts
    assert float(facts["train relative error"]) < 1e-24  # the stand-in returned the truth
    assert float(facts["wall time"].split()[0]) >= 0
    assert facts["saved"] == str(out)


def test_rollout_horizon_none_turns_the_phase_off(files, fake_fit, tmp_path):
    out = tmp_path / "m.npz"
    assert main(["fit", "--data", str(files["data"]), "--n-lam", "2", "--rollout-horizon", "none", "--out", str(out)]) == 0
    assert fake_fit.calls[-1][2]["rollout_horizon"] is None
    assert main(["fit", "--data", str(files["data"]), "--n-lam", "2", "--out", str(out)]) == 0
    assert "rollout_horizon" not in fake_fit.calls[-1][2]  # not given: fit's default ("auto")


def test_fit_passes_every_option(files, fake_fit, capsys, tmp_path):
    out, ckpt = tmp_path / "learned.npz", tmp_path / "ckpt.pt"
    argv = [
        "fit", "--data", str(files["data"]), "--test", str(files["test"]), "--n-lam", "3",
        "--loss", "prediction", "--optimizer", "gauss-newton", "--recipe", "best",
        "--iterations", "7", "--lr", "0.5", "--batch-size", "11", "--gamma", "0.02",
        "--eps", "1e-3", "--seed", "5", "--stiffness", "0.25", "--checkpoint", str(ckpt),
        "--resume", "--threads", "2", "--rollout-horizon", "3", "--rollout-iterations", "4",
        "--holdout-horizon", "2", "--affine-if-better", "--out", str(out),
    ]
    fake_fit.truth = LCS(2, 1, 3, stiffness=1.0, seed=1)
    assert main(argv) == 0
    facts = _facts(capsys.readouterr().out)

    (model, _, kwargs), = fake_fit.calls
    test = kwargs.pop("test")
    assert kwargs == {
        "loss": "prediction", "optimizer": "gauss-newton", "recipe": "best", "iterations": 7,
        "lr": 0.5, "batch_size": 11, "gamma": 0.02, "eps": 1e-3, "seed": 5,
        "checkpoint": str(ckpt), "resume": True, "progress": True, "rollout_horizon": 3,
        "rollout_iterations": 4, "holdout_horizon": 2, "affine_if_better": True,
    }
    assert isinstance(test, Dataset) and len(test) == 100
    fresh = LCS(2, 1, 3, stiffness=0.25, seed=5)
    assert all(torch.equal(fake_fit.init[k], v) for k, v in fresh.state_dict().items())
    assert float(facts["e_test"]) == pytest.approx(lcs_cvx.relative_error(model, test), rel=1e-5)
    assert float(facts["train relative error"]) == pytest.approx(
        lcs_cvx.relative_error(model, Dataset.load(files["data"])), rel=1e-5
    )
    assert load_metadata(out)["metadata"]["init"] == {"n_lam": 3, "stiffness": 0.25, "seed": 5}


@pytest.mark.parametrize(
    ("case", "named", "says"),
    [
        ("no-data", "--data", r"expected an existing \.npz file.*\(not found\)"),
        ("no-test", "--test", r"expected an existing \.npz file.*\(not found\)"),
        ("test-n-u", "--test", r"expected n_x=2, n_u=1 \(as in '.*data\.npz'\), received n_x=2, n_u=2 in "),
        ("nan-x-next", "--data", r"x_next: expected finite values, received 1 NaN/inf entries"),
        ("model-as-data", "--data", r"expected arrays 'x', 'u', 'x_next' in .* missing"),
        ("out-dir", "--out", r"expected a file in an existing directory"),
        ("checkpoint-dir", "--checkpoint", r"expected a file in an existing directory"),
        ("resume", "--resume", r"expected --checkpoint PATH to resume from, received none"),
        ("n-lam", "--n-lam", r"expected an integer >= 1 or 'auto', received '0'"),
        ("no-n-lam", "--n-lam", r"expected a value \(the option is required\), received none"),
        ("no-out", "--out", r"expected a value \(the option is required\), received none"),
        ("lr", "--lr", r"expected a finite number > 0, received '-1'"),
        ("loss", "--loss", r"invalid choice: 'hinge'"),
    ],
)
def test_fit_bad_input_exits_2_before_training(files, fake_fit, capsys, case, named, says):
    tmp = files["data"].parent
    data, opts = str(files["data"]), {"--n-lam": "2", "--out": str(tmp / "learned.npz")}
    if case == "no-data":
        data = str(tmp / "missing.npz")
    elif case == "no-test":
        opts["--test"] = str(tmp / "missing.npz")
    elif case == "test-n-u":
        opts["--test"] = _bad_data(tmp / "bad.npz", u=np.ones((20, 2)))
    elif case == "nan-x-next":
        data = _bad_data(tmp / "bad.npz", x_next=_nan((20, 2)))
    elif case == "model-as-data":
        data = str(files["model"])
    elif case == "out-dir":
        opts["--out"] = str(tmp / "no" / "learned.npz")
    elif case == "checkpoint-dir":
        opts["--checkpoint"] = str(tmp / "no" / "ckpt.pt")
    elif case == "resume":
        opts["--resume"] = None
    elif case in ("no-n-lam", "no-out"):
        del opts[case.replace("no", "-")]
    elif case == "n-lam":
        opts["--n-lam"] = "0"
    elif case == "lr":
        opts["--lr"] = "-1"
    elif case == "loss":
        opts["--loss"] = "hinge"
    argv = ["fit", "--data", data, *[t for kv in opts.items() for t in kv if t is not None]]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    line = err.strip().splitlines()[-1]
    assert line.startswith("lcs-cvx fit: error: ")
    assert named in line and re.search(says, line), line
    assert fake_fit.calls == []  # nothing was trained
    assert not (tmp / "learned.npz").exists()


def test_fit_library_errors_name_the_option(files, monkeypatch, capsys):
    def rejecting_fit(model, train, **kwargs):
        raise lcs_cvx.LCSInputError("gamma: expected 0 < gamma < sigma_min(F + F^T) = 2, received 3.0")

    monkeypatch.setattr(lcs_cvx, "fit", rejecting_fit, raising=False)
    out = files["data"].with_name("learned.npz")
    argv = ["fit", "--data", str(files["data"]), "--n-lam", "2", "--gamma", "3", "--out", str(out)]
    assert main(argv) == 2
    assert _error_line(capsys, "fit") == (
        "lcs-cvx fit: error: --gamma: expected 0 < gamma < sigma_min(F + F^T) = 2, received 3.0"
    )
    assert not out.exists()


# -- fit: end to end with the real trainer ---------------------------------------------------


@pytest.mark.skipif(not hasattr(lcs_cvx, "fit"), reason="lcs_cvx.fit is not available yet")
def test_fit_end_to_end(tmp_path, capsys):
    truth = random_lcs(2, 1, 2, stiffness=0.5, seed=4)
    train, test = tmp_path / "train.npz", tmp_path / "test.npz"
    make_dataset(truth, 400, noise=1e-2, seed=1).save(train)
    make_dataset(truth, 200, seed=2).save(test)
    out = tmp_path / "learned.npz"
    argv = ["fit", "--data", str(train), "--test", str(test), "--n-lam", "2",
            "--iterations", "300", "--seed", "3", "--out", str(out)]
    assert main(argv) == 0
    facts = _facts(capsys.readouterr().out)

    learned = load_model(out)
    assert (learned.n_x, learned.n_u, learned.n_lam) == (2, 1, 2)
    test_set = Dataset.load(test)
    e_test = float(facts["e_test"])
    assert e_test == pytest.approx(lcs_cvx.relative_error(learned, test_set), rel=1e-5)
    initial = lcs_cvx.relative_error(LCS(2, 1, 2, stiffness=1.0, seed=3), test_set)
    assert e_test < 0.5 * initial  # training improved on the initialisation
    assert math.isfinite(float(facts["train relative error"]))
    meta = load_metadata(out)["metadata"]
    assert meta["fit"] and meta["init"] == {"n_lam": 2, "stiffness": 1.0, "seed": 3}
    assert meta["fit"]["iterations"] == 300 and meta["fit"]["seed"] == 3
    assert main(["predict", "--model", str(out), "--data", str(test)]) == 0
    assert float(_facts(capsys.readouterr().out)["e_test"]) == pytest.approx(e_test, rel=1e-5)


def test_fit_reports_fallbacks_in_one_line(files, tmp_path, capsys, monkeypatch):
    """A training run whose solver handed samples to the reference says so in its output (the
    solver is told it fell back on every step); a clean run prints no such line."""
    import dataclasses

    from lcs_cvx.train import phases

    argv = ["fit", "--data", str(files["data"]), "--n-lam", "2", "--out", str(tmp_path / "m.npz"),
            "--iterations", "20", "--recipe", "plain"]
    assert main(argv) == 0
    assert "fallbacks" not in _facts(capsys.readouterr().out)
    real = phases.violation_fast
    monkeypatch.setattr(phases, "adam_steps", lambda *a, **k: None)  # every step through violation_fast
    monkeypatch.setattr(phases, "adam_step", lambda *a, **k: None)
    monkeypatch.setattr(phases, "violation_fast", lambda *a, **k: dataclasses.replace(
        real(*a, **k), n_fallback=1, fallback_residual=2e-8))
    assert main(argv) == 0
    facts = _facts(capsys.readouterr().out)
    assert facts["fallbacks"] == ("20 training samples were solved by the reference solver "
                                  "(worst relative KKT residual 2.00e-08)")


# -- fit --n-lam auto --------------------------------------------------------------------------


def _table(out: str) -> list[list[str]]:
    """The rows of the selection table printed by ``fit --n-lam auto`` (the chosen one marked)."""
    return [line.split() for line in out.splitlines() if re.match(r"^\s+\d+ [ *]\s", line)]


def test_fit_n_lam_auto_end_to_end(files, capsys):
    out = files["data"].with_name("auto.npz")
    argv = ["fit", "--data", str(files["data"]), "--validation", str(files["test"]), "--n-lam", "auto",
            "--candidates", "3,1,2", "--optimizer", "gauss-newton", "--iterations", "30", "--out", str(out)]
    assert main(argv) == 0
    text = capsys.readouterr().out
    facts = _facts(text)
    meta = load_metadata(out)["metadata"]
    sel = meta["selection"]
    assert sel["candidates"] == [1, 2, 3] and sel["tolerance"] == 0.1 and sel["holdout"] is None
    assert [row["n_lam"] for row in sel["table"]] == [1, 2, 3]
    errors = {row["n_lam"]: row["validation_error"] for row in sel["table"]}
    assert sel["n_lam"] == lcs_cvx.selection.choose(errors) == int(facts["chosen n_lam"].split()[0])
    assert facts["chosen n_lam"].endswith(f"lowest relative error on --validation '{files['test']}')")
    assert meta["init"]["n_lam"] == sel["n_lam"] and meta["data"]["validation"] == str(files["test"])
    assert meta["fit"]["iterations"] == 30 and meta["fit"]["seed"] == 0

    learned = load_model(out)
    assert learned.n_lam == sel["n_lam"]
    # the saved model is the one whose validation error is in the table: recomputed
    assert lcs_cvx.relative_error(learned, Dataset.load(files["test"])) == errors[learned.n_lam]
    rows = _table(text)
    assert [int(r[0]) for r in rows] == [1, 2, 3]
    assert [r[1] == "*" for r in rows] == [n == sel["n_lam"] for n in (1, 2, 3)]
    assert [float(r[-4]) for r in rows] == pytest.approx([errors[n] for n in (1, 2, 3)], rel=1e-4)
    assert errors[1] > 10 * min(errors.values())  # one unit cannot hold the truth's two


class _TruthFit(_FakeFit):
    """A stand-in that only "learns" a model of the truth's size (other sizes stay as built)."""

    def __call__(self, model, train, **kwargs):
        if model.n_lam == self.truth.n_lam:
            return super().__call__(model, train, **kwargs)
        self.calls.append((model, train, kwargs))
        return _Result(model, [], _Settings())


def test_fit_n_lam_auto_passes_options_and_holds_out(files, monkeypatch, truth, capsys):
    fake_fit = _TruthFit(truth)
    monkeypatch.setattr(lcs_cvx.selection, "fit", fake_fit)  # select_n_lam's trainer
    out = files["data"].with_name("auto.npz")
    argv = ["fit", "--data", str(files["data"]), "--test", str(files["test"]), "--n-lam", "auto",
            "--holdout", "0.25", "--tolerance", "0", "--iterations", "7", "--seed", "4",
            "--stiffness", "0.5", "--out", str(out)]
    assert main(argv) == 0
    facts = _facts(capsys.readouterr().out)
    assert [c[0].n_lam for c in fake_fit.calls] == [1, 2, 4, 8]  # the default candidates
    part, _ = Dataset.load(files["data"]).split(0.75, seed=4)
    for model, train, kwargs in fake_fit.calls:
        assert torch.equal(train.x, part.x)
        assert kwargs.pop("test").x.shape == (100, 2)
        assert kwargs == {"progress": False, "seed": 4, "iterations": 7}
        assert float(model.stiffness) == 0.5
    meta = load_metadata(out)["metadata"]
    assert meta["selection"]["n_lam"] == 2 and load_model(out).n_lam == 2  # the one "learned"
    assert meta["selection"]["holdout"] == 0.25 and meta["selection"]["tolerance"] == 0.0
    assert facts["chosen n_lam"].endswith("(the smallest within 0% of the lowest relative error on 25% of --data held out)")


@pytest.mark.parametrize(
    ("extra", "named", "says"),
    [
        (["--n-lam", "2", "--candidates", "1,2"], "--candidates", r"only with --n-lam auto, received --n-lam 2"),
        (["--n-lam", "2", "--validation", "V"], "--validation", r"only with --n-lam auto, received --n-lam 2 \(use --test"),
        (["--n-lam", "2", "--tolerance", "0.5"], "--tolerance", r"only with --n-lam auto"),
        (["--n-lam", "auto", "--checkpoint", "C"], "--checkpoint", r"expected none with --n-lam auto"),
        (["--n-lam", "auto", "--validation", "V", "--holdout", "0.3"], "--holdout", r"expected none with --validation"),
        (["--n-lam", "auto", "--validation", "BAD"], "--validation", r"expected n_x=2, n_u=1 \(as in '.*data\.npz'\), received n_x=2, n_u=2"),
        (["--n-lam", "auto", "--candidates", "1,1"], "--candidates", r"expected distinct comma-separated integers >= 1"),
        (["--n-lam", "auto", "--candidates", "0,2"], "--candidates", r"expected distinct comma-separated integers >= 1"),
        (["--n-lam", "auto", "--holdout", "1"], "--holdout", r"expected a fraction in \(0, 1\), received '1'"),
        (["--n-lam", "auto", "--tolerance", "-1"], "--tolerance", r"expected a finite number >= 0, received '-1'"),
        (["--n-lam", "many"], "--n-lam", r"expected an integer >= 1 or 'auto', received 'many'"),
    ],
)
def test_fit_n_lam_auto_bad_input(files, fake_fit, capsys, extra, named, says):
    tmp = files["data"].parent
    subst = {"V": str(files["test"]), "C": str(tmp / "c.pt"), "BAD": _bad_data(tmp / "bad.npz", u=np.ones((20, 2)))}
    argv = ["fit", "--data", str(files["data"]), "--out", str(tmp / "m.npz"), *[subst.get(a, a) for a in extra]]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    line = err.strip().splitlines()[-1]
    assert line.startswith("lcs-cvx fit: error: ") and named in line and re.search(says, line), line
    assert fake_fit.calls == []


# -- CSV files with the user's column names; trajectory files -----------------------------------


def _write_csv(path: Path, header: list[str], rows: np.ndarray | list) -> Path:
    lines = [",".join(header)] + [",".join(repr(float(v)) if not isinstance(v, str) else v for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture
def user_csv(files) -> tuple[Path, Dataset]:
    """``files["data"]`` as a robot log: a time column and the user's own names."""
    data = Dataset.load(files["data"])
    table = np.column_stack([np.arange(len(data)) * 0.01, data.x, data.u, data.x_next])
    path = _write_csv(files["data"].with_name("log.csv"), ["t", "z", "vz", "fz", "z_next", "vz_next"], table)
    return path, data


def test_fit_and_predict_on_a_csv_with_the_users_names(files, user_csv, fake_fit, truth, capsys):
    path, data = user_csv
    out = path.with_name("m.npz")
    names = ["--state", "z,vz", "--input", "fz"]
    test = _write_csv(path.with_name("test.csv"), ["z", "vz", "fz", "z_next", "vz_next"],
                      np.column_stack([data.x, data.u, data.x_next])[:40])
    assert main(["fit", "--data", str(path), "--test", str(test), "--n-lam", "2", "--out", str(out), *names]) == 0
    (_, train, kwargs), = fake_fit.calls
    assert torch.equal(train.x, data.x) and torch.equal(train.u, data.u) and torch.equal(train.x_next, data.x_next)
    assert torch.equal(kwargs["test"].x, data.x[:40])
    capsys.readouterr()

    # the default names are refused with a hint that names the command-line options
    assert main(["fit", "--data", str(path), "--n-lam", "2", "--out", str(out)]) == 2
    line = _error_line(capsys, "fit")
    assert "--data: expected columns x_0.., u_0.., x_next_0.." in line
    assert "(found ['t', 'z', 'vz', 'fz', 'z_next', 'vz_next']); or name them with --state and --input" in line
    assert "columns=" not in line

    # predict reads the same file the same way: the truth predicts it exactly
    assert main(["predict", "--model", str(files["model"]), "--data", str(path), *names]) == 0
    facts = _facts(capsys.readouterr().out)
    assert float(facts["e_test"]) < 1e-24 and facts["data"] == f"300 samples ({path})"

    # other next-state names, by suffix
    renamed = path.with_name("log2.csv")
    renamed.write_text(path.read_text().replace("z_next,vz_next", "z+,vz+", 1))
    assert main(["predict", "--model", str(files["model"]), "--data", str(renamed), *names, "--next-suffix", "+"]) == 0
    assert float(_facts(capsys.readouterr().out)["e_test"]) < 1e-24


def test_a_system_without_inputs(tmp_path, capsys):
    system = random_lcs(2, 0, 2, seed=1)
    data = make_dataset(system, 50, seed=0)
    path = _write_csv(tmp_path / "free.csv", ["p", "v", "p_next", "v_next"], np.column_stack([data.x, data.x_next]))
    save_model(system, tmp_path / "m.npz")
    assert main(["predict", "--model", str(tmp_path / "m.npz"), "--data", str(path), "--state", "p,v", "--input", ""]) == 0
    facts = _facts(capsys.readouterr().out)
    assert float(facts["e_test"]) < 1e-24 and facts["model"].startswith("n_x=2, n_u=0, n_lam=2 ")


def _trajectory_csv(path: Path, trajs: lcs_cvx.Trajectories, header: list[str], id_column: str = "run",
                    extra: bool = False) -> Path:
    rows = []
    for i, (x, u) in enumerate(zip(trajs.xs, trajs.us, strict=True)):
        for t in range(len(x)):
            ut = [repr(v) for v in u[t].tolist()] if t < len(u) else [""] * u.shape[1]
            nxt = [repr(v) for v in x[t + 1].tolist()] if t + 1 < len(x) else ["0"] * x.shape[1]
            if extra and t == len(u):  # a transitions file: every row complete
                ut = ["0"] * u.shape[1]
            rows.append(",".join([f"run{i}", *map(repr, x[t].tolist()), *ut, *(nxt if extra else [])]))
    path.write_text(",".join([id_column, *header]) + "\n" + "\n".join(rows) + "\n")
    return path


def test_fit_and_predict_on_trajectory_rows(files, truth, fake_fit, capsys):
    trajs = _trajectories(truth, [6, 11, 4])
    path = _trajectory_csv(files["data"].with_name("runs.csv"), trajs, ["z", "vz", "fz"])
    names = ["--state", "z,vz", "--input", "fz", "--trajectory-column", "run"]
    out = path.with_name("m.npz")
    assert main(["fit", "--data", str(path), "--n-lam", "2", "--out", str(out), *names]) == 0
    (_, runs, _), = fake_fit.calls
    assert isinstance(runs, lcs_cvx.Trajectories) and runs.lengths == (6, 11, 4)  # passed whole: held out by run
    train = runs.to_transitions()
    expected = trajs.to_transitions()  # the next state: the next row of the same run
    assert len(train) == 21 and torch.equal(train.x, expected.x) and torch.equal(train.x_next, expected.x_next)
    assert torch.equal(train.u, expected.u)
    assert _facts(capsys.readouterr().out)["data"] == "21 samples (n_x=2, n_u=1)"

    assert main(["predict", "--model", str(files["model"]), "--data", str(path), *names]) == 0
    facts = _facts(capsys.readouterr().out)
    assert facts["data"] == f"21 samples in 3 trajectories ({path})"
    assert float(facts["e_test"]) < 1e-24 and "rollout error (H=1, 5)" in facts

    # the trajectory column not in the file: named, with the file's columns
    assert main(["predict", "--model", str(files["model"]), "--data", str(path), "--state", "z,vz",
                 "--input", "fz", "--trajectory-column", "episode"]) == 2
    line = _error_line(capsys, "predict")
    assert re.search(r"--trajectory-column: expected a column 'episode' \(the trajectory id\) in --data "
                     r"file '.*runs\.csv', received columns \['run', 'z', 'vz', 'fz'\]", line), line


def test_a_trajectory_label_beside_next_state_columns_is_a_label(files, truth, fake_fit, capsys):
    """A transitions file that also has a ``trajectory`` column is read row by row (the column
    is a label), unless --trajectory-column names it."""
    trajs = _trajectories(truth, [3, 5])
    path = _trajectory_csv(files["data"].with_name("both.csv"), trajs, ["x_0", "x_1", "u_0", "x_next_0", "x_next_1"],
                           id_column="trajectory", extra=True)
    out = path.with_name("m.npz")
    assert main(["fit", "--data", str(path), "--n-lam", "2", "--out", str(out)]) == 0
    assert len(fake_fit.calls[-1][1]) == 10  # every row, the last of each run included
    assert main(["fit", "--data", str(path), "--n-lam", "2", "--out", str(out), "--trajectory-column", "trajectory"]) == 0
    assert sum(fake_fit.calls[-1][1].lengths) == 8  # the next rows of each run
    capsys.readouterr()


@pytest.mark.parametrize(
    ("names", "named", "says"),
    [
        (["--state", "z,vy", "--input", "fz"], "--state",
         r"expected columns \['z', 'vy'\] in --data file '.*log\.csv', missing \['vy'\] \(its columns: \['t', 'z', 'vz', 'fz', 'z_next', 'vz_next'\]\)"),
        (["--state", "z,vz", "--input", "fz"], "--input",
         r"expected columns \['fz'\] in --test file '.*test\.csv', missing \['fz'\] \(its columns: \['z', 'vz', 'force', 'z_next', 'vz_next'\]\)"),
        (["--state", "z,vz", "--input", "fz", "--next-suffix", "_n"], "--next-suffix",
         r"expected next-state columns \['z_n', 'vz_n'\] \(--state \+ '_n'\) in --data file .* missing \['z_n', 'vz_n'\]"),
        (["--state", "z,vz"], "--input", r"expected the input columns with --state \(--input '' for a system without inputs\)"),
        (["--input", "fz"], "--input", r"expected --state too"),
        (["--next-suffix", "_n"], "--next-suffix", r"expected --state too"),
        (["--state", "", "--input", "fz"], "--state", r"expected at least one state column"),
        (["--state", "z,z", "--input", "fz"], "--state", r"expected distinct comma-separated column names"),
        (["--state", "z,vz", "--input", "vz"], "--input", r"expected columns other than --state's, received \['vz'\] in both"),
    ],
)
def test_column_options_bad_input(files, user_csv, fake_fit, capsys, names, named, says):
    path, data = user_csv
    test = path.with_name("test.csv")
    test.write_text("z,vz,force,z_next,vz_next\n1,2,3,4,5\n")
    argv = ["fit", "--data", str(path), "--test", str(test), "--n-lam", "2", "--out", str(path.with_name("m.npz")), *names]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    line = err.strip().splitlines()[-1]
    assert line.startswith(f"lcs-cvx fit: error: {named}") or f"argument {named}" in line, line
    assert re.search(says, line), line
    assert fake_fit.calls == []


# -- damaged files --------------------------------------------------------------------------------


@pytest.mark.parametrize("what", ["data-npz", "data-csv", "test-npz", "model", "checkpoint", "trajectory-npz"])
def test_damaged_files_exit_2_in_one_line(files, truth, fake_fit, monkeypatch, capsys, what):
    tmp = files["data"].parent
    bad = tmp / ("bad.csv" if what == "data-csv" else "bad.npz")
    if what == "data-csv":  # a CSV cut in the middle of a row
        bad.write_text("x_0,x_1,u_0,x_next_0,x_next_1\n1,2,3,4,5\n1,2,3,4,5\n1,2")
    elif what == "trajectory-npz":
        _trajectories(truth, [4, 4]).save(tmp / "t.npz")
        bad.write_bytes((tmp / "t.npz").read_bytes()[:200])
    else:
        source = files["model"] if what in ("model", "checkpoint") else files["data"]
        bad.write_bytes(source.read_bytes()[:-60])  # the end of the zip directory lost
    out = str(tmp / "m.npz")
    argv = {
        "data-npz": ["fit", "--data", str(bad), "--n-lam", "2", "--out", out],
        "data-csv": ["fit", "--data", str(bad), "--n-lam", "2", "--out", out],
        "test-npz": ["fit", "--data", str(files["data"]), "--test", str(bad), "--n-lam", "2", "--out", out],
        "model": ["predict", "--model", str(bad), "--data", str(files["data"])],
        "checkpoint": ["fit", "--data", str(files["data"]), "--n-lam", "2", "--out", out,
                       "--checkpoint", str(bad), "--resume", "--iterations", "2"],
        "trajectory-npz": ["predict", "--model", str(files["model"]), "--data", str(bad)],
    }[what]
    if what == "checkpoint":
        monkeypatch.setattr(lcs_cvx, "fit", lcs_cvx.train.fit)  # the real trainer reads it
    assert main(argv) == 2
    line = _error_line(capsys, argv[0])
    option = {"data-npz": "--data", "data-csv": "--data", "test-npz": "--test", "model": "--model",
              "checkpoint": "--checkpoint", "trajectory-npz": "--data"}[what]
    assert line.startswith(f"lcs-cvx {argv[0]}: error: {option}: "), line
    assert str(bad) in line
    if what == "data-csv":
        assert "line 4 of" in line and "has 2 fields, expected 5" in line
    elif what != "checkpoint":
        assert "could not read it" in line
