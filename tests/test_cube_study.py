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
    assert study.main(["--out", str(out), "--smoke"]) == 0
    return out


def _lines(path):
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def test_smoke_writes_a_row_per_model_and_size(smoke):
    for name in ("cube_smoke.jsonl", "report_smoke.md", "learning_curve_smoke.png", "rollouts_smoke.png"):
        assert os.path.getsize(smoke / name) > 0, name
    rows = _lines(smoke / "cube_smoke.jsonl")
    names = [s.name for s in M.specs()]
    assert len(names) >= 4
    assert sorted((r["size"], r["model"]) for r in rows) == sorted((n, m) for n in (2, 4) for m in names)
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
    records = study.run(str(smoke), [2, 4], smoke=True)
    assert (smoke / "cube_smoke.jsonl").read_text() == before
    assert len(records) == len(before.strip().splitlines())


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
