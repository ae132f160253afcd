"""The C3 cart-pole closed-loop study (studies/control/cartpole_c3.py), its --smoke variant: every
unit's record, C3 settling from C3's published x0, the cost gap to the exact optimum (a lower
bound, so never negative), the exact optimum itself, the batched run, the report and resuming."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

pytest.importorskip("pyscipopt", reason="the exact optimum and the miqp projection need SCIP (the control extra)")
pytest.importorskip("matplotlib")

from studies.control import cartpole_c3  # noqa: E402

RUN_KEYS = {"date", "machine", "load", "kind", "controller", "state", "steps", "x0", "success", "settled",
            "simulated", "wall", "final_error", "max_abs", "contact_steps", "contact_last100", "solve_us",
            "solve_ms_median", "solve_ms_p95", "plan_cost", "plan_u", "qp_failures", "warnings"}
EXACT_KEYS = {"date", "machine", "kind", "controller", "state", "steps", "x0", "cost", "objective", "modes",
              "complementarity", "max_lam", "max_gap", "big_m_active", "scip_time", "u"}


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("control"))
    assert cartpole_c3.main(["--out", out, "--smoke"]) == 0
    path = os.path.join(out, "cartpole_c3.jsonl")
    with open(path) as f:
        lines = f.read().splitlines()
    return out, [json.loads(line) for line in lines]


def by(records, kind, controller=None):
    return {str(r["state"]): r for r in records if r["kind"] == kind and (controller is None or r["controller"] == controller)}


def test_every_unit_is_recorded_once_with_its_keys(smoke):
    _, records = smoke
    st = cartpole_c3.Settings.smoke()
    states = {"x0"} | {str(i) for i in range(st.states)}
    expected = {"c3+": states, "lqr": states, "qp": states, "c3+ cvxpy": {"x0"}, "miqp": {"x0"},
                "miqp enum": states}
    keys = [cartpole_c3.unit_key(r) for r in records]
    assert len(keys) == len(set(keys))
    for name, want in expected.items():
        runs = by(records, "run", name)
        assert set(runs) == want, name
        for r in runs.values():
            assert RUN_KEYS <= set(r), (name, RUN_KEYS - set(r))
            assert "error" not in r and "plan_error" not in r
            assert len(r["solve_us"]) == r["simulated"] and r["simulated"] <= r["steps"]
            assert np.isfinite(r["final_error"]) and r["final_error"] >= 0
            assert (r["settled"] >= 0) == r["success"]
    exact = by(records, "exact")
    assert set(exact) == states
    for e in exact.values():
        assert EXACT_KEYS <= set(e), EXACT_KEYS - set(e)
    batch = [r for r in records if r["kind"] == "batch"]
    assert len(batch) == 1 and batch[0]["rollouts"] == st.batch and len(batch[0]["settled"]) == st.batch


def test_c3_plus_settles_from_c3s_x0(smoke):
    _, records = smoke
    r = by(records, "run", "c3+")["x0"]
    np.testing.assert_allclose(r["x0"], [0.1, -0.5, 0.5, -0.4])
    assert r["success"] and 0 <= r["settled"] <= r["steps"] - cartpole_c3.HOLD
    assert r["final_error"] <= cartpole_c3.TOL
    assert r["traj"][0] == pytest.approx([0.1, -0.5])


def test_exact_optimum_is_a_feasible_lower_bound(smoke):
    _, records = smoke
    exact = by(records, "exact")
    for e in exact.values():
        assert not e["big_m_active"] and max(e["max_lam"], e["max_gap"]) < 100  # far from M = 1000
        assert e["complementarity"] < 1e-8
        assert e["cost"] == pytest.approx(e["objective"], rel=1e-8)  # the rollout matches the plan
        if "enumerated_cost" in e:  # every mode sequence tried: SCIP's modes are optimal
            assert e["scip_matches"] and e["cost"] == pytest.approx(e["enumerated_cost"], rel=1e-9)
            assert e["scip_cost"] == pytest.approx(e["cost"], rel=1e-9)
    assert sum("enumerated_cost" in e for e in exact.values()) == 2  # x0 and the first random state
    gaps = []
    for name in ("c3+", "qp", "miqp", "miqp enum", "lqr", "c3+ cvxpy"):
        for s, r in by(records, "run", name).items():
            gap = (r["plan_cost"] - exact[s]["cost"]) / exact[s]["cost"]
            assert gap >= -1e-6, (name, s, gap)
            gaps.append(gap)
    assert len(gaps) == 4 * (cartpole_c3.Settings.smoke().states + 1) + 2
    # SCIP's first plan and the active sets' are the same plan (the same exact projection)
    assert by(records, "run", "miqp")["x0"]["plan_cost"] == pytest.approx(
        by(records, "run", "miqp enum")["x0"]["plan_cost"], rel=1e-6)
    # C3's first plans are near the optimum here
    c3 = by(records, "run", "c3+")
    assert all((c3[s]["plan_cost"] - exact[s]["cost"]) / exact[s]["cost"] < 0.5 for s in c3)


def test_the_two_qp_paths_plan_alike_and_the_batch_matches_single_runs(smoke):
    _, records = smoke
    fast, slow = by(records, "run", "c3+")["x0"], by(records, "run", "c3+ cvxpy")["x0"]
    np.testing.assert_allclose(fast["plan_u"], slow["plan_u"], atol=1e-6)
    batch = next(r for r in records if r["kind"] == "batch")
    single = by(records, "run", "c3+")
    shared = [s for s in single if s != "x0"]
    assert shared and all(single[s]["settled"] == batch["settled"][int(s)] for s in shared)
    assert batch["success_rate"] == pytest.approx(np.mean(np.array(batch["settled"]) >= 0))
    assert 0 < batch["success_rate"] < 1  # the box is neither trivial nor hopeless
    assert batch["wall"] > 0 and batch["per_step_ms"] == pytest.approx(1e3 * batch["wall"] / batch["steps"])
    # the fast path is far quicker than the CVXPY paths
    assert fast["solve_ms_median"] < slow["solve_ms_median"]
    assert fast["solve_ms_median"] < by(records, "run", "qp")["x0"]["solve_ms_median"]


def test_report_figure_and_resume(smoke):
    out, records = smoke
    with open(os.path.join(out, "cartpole_c3.md")) as f:
        md = f.read()
    for heading in ("## Closed-loop success", "## Cost gap", "## Time per solve", "## The batched fast path"):
        assert heading in md
    assert "python -m studies.control.cartpole_c3" in md and "--smoke" in md
    assert cartpole_c3.MACHINE in md and "LQR ignoring contact" in md
    assert "session" not in md.lower()
    assert os.path.getsize(os.path.join(out, "cartpole_c3.png")) > 10_000
    # a re-run finds every unit done and appends nothing
    assert cartpole_c3.main(["--out", out, "--smoke"]) == 0
    assert len(cartpole_c3.load_records(os.path.join(out, "cartpole_c3.jsonl"))) == len(records)


def test_initial_states_are_nested_and_in_the_box():
    a, b = cartpole_c3.initial_states(5), cartpole_c3.initial_states(50)
    np.testing.assert_array_equal(a, b[:5])
    assert (np.abs(b) <= cartpole_c3.BOX).all()
