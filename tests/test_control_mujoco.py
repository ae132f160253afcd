"""The MuJoCo closed-loop study of the controllers (studies.control.mujoco_closed_loop), smoke
variant: 2 starts, 0.8 s runs, every controller; the JSON lines, the report and the figure are
written, a rerun skips the finished runs, and the hand-written LCS of the plant is the physical one.
The learn, control, relearn study (studies.control.relearn), smoke variant."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("mujoco")

from studies.control import mujoco_closed_loop as study  # noqa: E402
from studies.control import relearn  # noqa: E402


def test_smoke_run_writes_report(tmp_path):
    out = tmp_path / "control"
    assert study.main(["--out", str(out), "--smoke"]) == 0
    lines = (out / "mujoco_closed_loop.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in lines]
    names = list(study.CONTROLLERS)
    assert len(records) == 2 * len(names)
    assert {(r["controller"], r["start"]) for r in records} == {(n, i) for n in names for i in range(2)}
    for r in records:
        assert r["steps"] == 20
        assert isinstance(r["success"], bool)
        assert np.isfinite(r["final_error"]) and r["final_error"] >= 0
        assert r["max_abs_u"] <= study.U_MAX + 1e-9
        if r["controller"] == "no input":
            assert r["max_abs_u"] == 0.0 and r["ms_per_step_median"] == 0.0
        else:
            assert r["ms_per_step_median"] > 0
        if r["controller"].startswith("C3"):
            assert np.isfinite(r["plan_violation_median"])
    # the starts are the stated box, tilted and falling towards one wall
    x0 = np.array([r["x0"] for r in records if r["controller"] == "no input"])
    np.testing.assert_allclose(x0, study.starts(2))
    assert np.all(np.abs(x0[:, 1]) >= 0.2) and np.all(np.sign(x0[:, 1]) == np.sign(x0[:, 3]))
    md = (out / "mujoco_closed_loop.md").read_text()
    for n in names:
        assert f"| {n} |" in md
    assert "2026-11-25" in md and "2-core x86-64 VM" in md and "--smoke" in md
    assert (out / "mujoco_closed_loop.png").stat().st_size > 1000
    # a rerun finds every run done and appends nothing
    assert study.main(["--out", str(out), "--smoke"]) == 0
    assert (out / "mujoco_closed_loop.jsonl").read_text().splitlines() == lines


def test_handwritten_lcs_matches_plant():
    """Upright and centred, the walls are inactive; the tip pressed 5 cm into the right wall gets a
    force pushing it back, of the size MuJoCo's wall spring gives."""
    import lcs_cvx

    m = study.handwritten_lcs()
    M = m.to_matrices()
    assert np.allclose(lcs_cvx.solve_lcp(M["F"], (M["D"] @ np.zeros(4) + M["c"])[None]).lam.numpy(), 0)
    x = np.array([0.0, (0.18 + 0.05) / 0.6, 0.0, 0.0])
    lam = lcs_cvx.solve_lcp(M["F"], (M["D"] @ x + M["c"])[None]).lam.numpy()[0]
    assert lam[0] == 0 and 0.5 < lam[1] < 2.0  # m_eff * k * 0.05 ~ 1 N
    assert (M["C"] @ lam)[3] < 0  # it pushes the pole back


def test_the_relearn_study_smoke_run_writes_its_rounds_and_resumes(tmp_path):
    """studies.control.relearn --smoke: round 0 and one refit, the random-data baseline, the
    report; a rerun finds every round done and writes the same table."""
    out = tmp_path / "control"
    assert relearn.main(["--out", str(out), "--smoke"]) == 0
    rows = [json.loads(line) for line in (out / "relearn_smoke.jsonl").read_text().splitlines()]
    rounds = [r for r in rows if r["kind"] == "round"]
    assert [r["round"] for r in rounds] == [0, 1]
    assert [r["data_size"] for r in rounds] == [500 + 75, 500 + 150]
    assert [r["kind"] for r in rows].count("baseline") == 1
    report = (out / "relearn_smoke.md").read_text()
    assert "| 1 | " in report and "Same budget of random data" in report
    assert relearn.main(["--out", str(out), "--smoke"]) == 0
    assert (out / "relearn_smoke.jsonl").read_text().count("\n") == len(rows)
