"""The LCP-algorithms study (studies/solvers): each algorithm against enumeration, and the
smoke run's files and resumption."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from lcs_cvx.lcp import solve_lcp_brute
from studies.solvers import lcp_algorithms as study
from studies.solvers import lcp_algos as algos


def _problem(n: int, seed: int, batch: int = 30) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    G = rng.uniform(-1, 1, (n, n))
    H = rng.uniform(-1, 1, (n, n))
    F = G @ G.T + H - H.T + np.eye(n)
    return F, rng.uniform(-1, 1, (batch, n))


def _brute(F: np.ndarray, q: np.ndarray) -> np.ndarray:
    return solve_lcp_brute(torch.from_numpy(F), torch.from_numpy(q)).lam.numpy()


@pytest.mark.parametrize("name", ["lemke", "fb_newton", "osqp_direct", "osqp_cvxpy",
                                  "pivoting"])
@pytest.mark.parametrize("n", [3, 5])
def test_agrees_with_brute_force(name: str, n: int) -> None:
    for seed in range(3):
        F, q = _problem(n, seed)
        if name == "pivoting":
            lam, ok, _ = study.METHODS["pivoting"][0](F, q)
        else:
            lam, ok = getattr(algos, name)(F, q)
        assert ok.all()
        np.testing.assert_allclose(lam, _brute(F, q), atol=1e-8, rtol=0)


@pytest.mark.parametrize("n", [3, 5])
def test_pgs_converges_on_spd(n: int) -> None:
    for seed in range(3):
        rng = np.random.default_rng(seed)
        G = rng.uniform(-1, 1, (n, n))
        F = G @ G.T + 0.5 * np.eye(n)
        q = rng.uniform(-1, 1, (30, n))
        lam, ok = algos.pgs(F, q, max_sweeps=5000)
        assert ok.all()
        np.testing.assert_allclose(lam, _brute(F, q), atol=1e-8, rtol=0)


def test_fb_newton_residual() -> None:
    for problem in ("random", "degenerate", "scaled"):
        F, q, _ = study.make_problem(problem, 5, 50, seed=1)
        lam, ok = algos.fb_newton(F, q)
        assert ok.all()
        assert algos.natural_residual(F, q, lam).max() < 1e-10


def test_lemke_degenerate_matches_construction() -> None:
    F, q, lam_star = study.make_problem("degenerate", 5, 50, seed=2)
    lam, ok = algos.lemke(F, q)
    assert ok.all()
    np.testing.assert_allclose(lam, lam_star, atol=1e-8, rtol=0)


def test_smoke_run_and_resume(tmp_path, monkeypatch) -> None:
    done = study.run(tmp_path, smoke=True, log=lambda s: None)
    stem = tmp_path / "lcp_algorithms_smoke"
    for ext in (".jsonl", ".md", ".png"):
        assert stem.with_suffix(ext).exists()
    lines = stem.with_suffix(".jsonl").read_text().splitlines()
    cells, _, _ = study.plan(smoke=True)
    assert len(lines) == len(cells) == len(done)
    assert {json.loads(line)["method"] for line in lines} == set(study.METHODS)
    assert "## Which to use" in stem.with_suffix(".md").read_text()

    def boom(*args, **kwargs):
        raise AssertionError("a finished cell was run again")

    monkeypatch.setattr(study, "run_cell", boom)
    study.run(tmp_path, smoke=True, log=lambda s: None)
    assert len(stem.with_suffix(".jsonl").read_text().splitlines()) == len(lines)
