"""The forward-solves study (studies/solvers): the smoke run's files, resumption, Clarabel on
(P) against enumeration, and the constructed degenerate samples against enumeration."""

from __future__ import annotations

import json

import numpy as np
import torch

import lcs_cvx
from studies.solvers import forward_solves as study


def test_smoke_run_writes_and_resumes(tmp_path) -> None:
    torch.set_num_threads(1)
    logs: list[str] = []
    study.run(tmp_path, smoke=True, log=logs.append)
    jpath = tmp_path / "forward_solves_smoke.jsonl"
    rows = [json.loads(line) for line in jpath.read_text().splitlines()]
    installed = study.solvers()
    assert "CLARABEL" in installed
    for problem in study.PROBLEMS:
        got = {r["solver"] for r in rows if r["problem"] == problem}
        assert got == set(installed)
    for r in rows:
        assert sum(r["statuses"].values()) == r["samples"]  # every sample counted
        assert r["failures"] >= r["samples"] - r["statuses"].get("optimal", 0)
        assert r["cold_wall_s"] > 0
        assert r["form"] in ("QP", "SOCP")
        assert (r["warm_start"] is not None) == (r["solver"] in study.WARM_START)
    md = (tmp_path / "forward_solves_smoke.md").read_text()
    assert "| CLARABEL |" in md and rows[0]["date"] in md
    for s, why in study.not_run().items():
        assert s in md and why in md
    for s in ("GLPK", "SCIPY"):
        if s in study.skipped():
            assert s in md
    n_logs = len(logs)
    assert n_logs == len(rows)
    study.run(tmp_path, smoke=True, log=logs.append)  # every cell finished: nothing re-run
    assert len(logs) == n_logs
    assert len(jpath.read_text().splitlines()) == len(rows)


def test_clarabel_p_agrees_with_brute_force() -> None:
    setting = study.SMOKE_SETTINGS["smoke"]
    data = study.make_data(setting, 10)
    out = study.solve_all("P", data, "CLARABEL")
    assert all(s == "optimal" for s in out["status"])
    ref = lcs_cvx.solve_lcp(data["F"], data["q"], method="brute").lam.numpy()
    np.testing.assert_allclose(out["lam"], ref, atol=1e-6, rtol=0)


def test_degenerate_samples_are_exact_and_degenerate() -> None:
    setting = study.SMOKE_SETTINGS["smoke_degenerate"]
    data = study.make_data(setting, 20)
    lam_p = data["lam_P"]
    w = data["q"] + lam_p @ data["F"].mT
    assert ((lam_p == 0) & (w.abs() < 1e-12)).any(1).all()  # a weakly active index per sample
    ref = lcs_cvx.solve_lcp(data["F"], data["q"], method="brute").lam
    torch.testing.assert_close(ref, lam_p, atol=1e-10, rtol=0)
    vals = {k: data[k] for k in ("L", "b", "K", "h")}
    ref_v = study.solve_violation_brute(vals).lam
    torch.testing.assert_close(ref_v, data["lam_V"], atol=1e-9, rtol=0)
    assert float(study.violation_kkt_residual(vals, data["lam_V"]).max()) < 1e-12
