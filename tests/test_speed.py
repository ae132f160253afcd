"""The speed checks of lcs_cvx/speed.py (a fit step against its loss and gradient, C3's defaults
against a dense C3+): the tables they write, the dense reference planning C3's plan, the CLI."""

from __future__ import annotations

import numpy as np
import pytest

from lcs_cvx.cli import main
from lcs_cvx.control import C3, c3_cartpole
from lcs_cvx.speed import DenseC3Plus, run_c3_bench, run_fit_step


def _rows(table: str) -> list[list[str]]:
    return [[c.strip() for c in line.strip("|").split("|")] for line in table.splitlines()[2:]]


@pytest.mark.parametrize("loss", ["violation", "prediction"])
def test_fit_step_table(loss):
    rows = _rows(run_fit_step(batches=(300, 500), size=(3, 1, 2), loss=loss, threads=1, repeats=1))
    assert [r[3] for r in rows] == ["300", "500"] and all(r[1] == loss for r in rows)
    for r in rows:
        step, call, ratio = float(r[4]), float(r[5]), float(r[6])  # (a step: a difference of two fits' times,
        assert call > 0 and np.isfinite(step) and np.isfinite(ratio)  # noisy at this size, maybe below 0)


def test_the_dense_reference_plans_c3s_plan():
    P = c3_cartpole()
    G, U = P.weights["c3+"]
    plus = C3(P.model, P.horizon, Q=P.Q, R=P.R, G=G, U=U, projection="c3+", gap_tol=None, polish=0)
    dense = DenseC3Plus(plus)
    for x0 in np.random.default_rng(3).uniform(-0.4, 0.4, (4, 4)):
        assert np.abs(dense.solve(x0) - plus.solve(x0).u[0].numpy()).max() <= 1e-6


def test_c3_bench_table():
    rows = _rows(run_c3_bench(solves=2, repeats=1))
    names = [r[0] for r in rows]
    assert names[0] == "C3 defaults (auto + polish)" and names[-1] == "dense C3+ (NumPy)" and len(rows) == 4
    assert float(rows[-1][2]) == 1.0 and all(float(r[1]) > 0 for r in rows)


def test_cli_fit_step(capsys):
    assert main(["bench", "--fit-step", "--batches", "300", "--sizes", "3,1,2", "--repeats", "1",
                 "--losses", "violation"]) == 0
    out = capsys.readouterr().out
    assert "| (3, 1, 2) | violation | 1 | 300 |" in out
