"""The report of C3's cart-pole study (:mod:`studies.control.cartpole_c3`): success rates with
their Wilson intervals, cost gaps to the exact optimum, times per solve, the batch run, as
``OUT/cartpole_c3.md`` and ``OUT/cartpole_c3.png``, from the units in ``OUT``
(:mod:`studies.control.cartpole_c3_records`)."""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np

from .cartpole_c3_records import (
    BOX,
    COLORS,
    CONTROLLERS,
    FILE,
    LABELS,
    MACHINE,
    SEED,
    TRAJ_STATES,
    Settings,
    load_records,
    today,
)

__all__ = ["wilson", "summarize", "write_report", "plot"]

def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The 95 % Wilson interval of a success rate ``k / n``."""
    if n == 0:
        return math.nan, math.nan
    p = k / n
    den = 1 + z * z / n
    mid = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return max(0.0, mid - half), min(1.0, mid + half)


def _fmt(v: float, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return f"{v:.{digits}g}"


def summarize(records: list[dict[str, Any]], settings: Settings) -> dict[str, Any]:
    """The numbers of the report, from the units finished so far."""
    steps_of = {"c3+": settings.steps, "lqr": settings.steps, "c3+ cvxpy": settings.qp_steps,
                "qp": settings.qp_steps, "miqp": settings.miqp_steps, "miqp enum": settings.steps,
                "lcp": settings.steps, "auto": settings.steps, "defaults": settings.steps,
                "defaults, penalize_input_change": settings.steps}
    runs: dict[str, dict[str, dict[str, Any]]] = {k: {} for k in CONTROLLERS}
    exact: dict[str, dict[str, Any]] = {}
    batch = None
    for r in records:
        if r.get("kind") == "run" and r["controller"] in runs and r["steps"] == steps_of[r["controller"]]:
            runs[r["controller"]][str(r["state"])] = r
        elif r.get("kind") == "exact":
            exact[str(r["state"])] = r
        elif r.get("kind") == "batch" and r["rollouts"] == settings.batch and r["steps"] == settings.steps:
            batch = r
    out: dict[str, Any] = {"controllers": {}, "exact": {}, "batch": batch, "runs": runs}
    for name, by_state in runs.items():
        rand = [r for s, r in by_state.items() if s != "x0"]
        if not rand and "x0" not in by_state:
            continue
        succ = [r for r in rand if r.get("success")]
        k, n = len(succ), len(rand)
        fails = [r for r in rand if not r.get("success") and "final_error" in r]
        finals = np.array([r["final_error"] for r in rand if "final_error" in r])
        times = np.concatenate([np.asarray(r["solve_us"], dtype=float) / 1e3 for r in by_state.values()
                                if r.get("solve_us")] or [np.zeros(0)])
        gaps, contact = [], []
        for s, r in by_state.items():
            e = exact.get(s)
            if e is not None and "cost" in e and "plan_cost" in r and s != "x0":
                gaps.append((r["plan_cost"] - e["cost"]) / e["cost"])
                contact.append(any(any(row) for row in e["modes"]))
        gaps_a, contact_a = np.array(gaps), np.array(contact, dtype=bool)
        phases = [r["phase_ms_median"] for r in by_state.values() if "phase_ms_median" in r]
        x0r = by_state.get("x0")
        x0_gap = None
        if x0r is not None and "x0" in exact and "plan_cost" in x0r and "cost" in exact["x0"]:
            x0_gap = (x0r["plan_cost"] - exact["x0"]["cost"]) / exact["x0"]["cost"]
        out["controllers"][name] = {
            "n": n, "k": k, "rate": k / n if n else math.nan, "ci": wilson(k, n),
            "errors": sum("error" in r for r in by_state.values()),
            "settle_median": float(np.median([r["settled"] for r in succ])) if succ else math.nan,
            "final_median": float(np.median(finals)) if finals.size else math.nan,
            "final_p95": float(np.percentile(finals, 95)) if finals.size else math.nan,
            "final_median_success": float(np.median([r["final_error"] for r in succ])) if succ else math.nan,
            "contact_success": float(np.median([r["contact_steps"] for r in succ])) if succ else math.nan,
            "contact_fail": float(np.median([r["contact_steps"] for r in rand if not r.get("success") and "contact_steps" in r]))
            if n - k else math.nan,
            "time_median": float(np.median(times)) if times.size else math.nan,
            "time_p95": float(np.percentile(times, 95)) if times.size else math.nan,
            "solves": int(times.size),
            "phase": {p: float(np.median([ph[p] for ph in phases])) for p in ("qp", "projection", "lcp")} if phases else None,
            "gaps": gaps, "gap_n": int(gaps_a.size),
            "gap_median": float(np.median(gaps_a)) if gaps_a.size else math.nan,
            "gap_p95": float(np.percentile(gaps_a, 95)) if gaps_a.size else math.nan,
            "gap_max": float(gaps_a.max()) if gaps_a.size else math.nan,
            "gap_min": float(gaps_a.min()) if gaps_a.size else math.nan,
            "gap_optimal": int((gaps_a <= 1e-6).sum()),
            "gap_contact": (int(contact_a.sum()), float(np.median(gaps_a[contact_a])) if contact_a.any() else math.nan),
            "gap_free": (int((~contact_a).sum()), float(np.median(gaps_a[~contact_a])) if (~contact_a).any() else math.nan),
            "x0": x0r, "x0_gap": x0_gap,
            "fail_n": len(fails), "fail_bouncing": sum(int(r.get("contact_last100", 0)) > 0 for r in fails),
            "fail_final": float(np.median([r["final_error"] for r in fails])) if fails else math.nan,
            "fail_pos": float(np.median([r["max_abs"][0] for r in fails])) if fails else math.nan,
            "fail_angle": float(np.median([r["max_abs"][1] for r in fails])) if fails else math.nan,
            "stopped_early": sum(bool(r.get("stopped_early")) for r in by_state.values()),
            "qp_failures": sum(int(r.get("qp_failures", 0)) for r in by_state.values()),
        }
    ex = [e for e in exact.values() if "cost" in e]
    if ex:
        checked = [e for e in ex if "enumerated_cost" in e]
        out["exact"] = {
            "n": len(ex), "errors": sum("error" in e for e in exact.values()),
            "scip_median": float(np.median([e["scip_time"] for e in ex])),
            "scip_p95": float(np.percentile([e["scip_time"] for e in ex], 95)),
            "big_m_active": sum(bool(e["big_m_active"]) for e in ex),
            "max_lam": max(e["max_lam"] for e in ex), "max_gap": max(e["max_gap"] for e in ex),
            "complementarity": max(e["complementarity"] for e in ex),
            "rollout_vs_plan": max(abs(e["cost"] - e["objective"]) / e["cost"] for e in ex),
            "scip_max": float(np.max([e["scip_time"] for e in ex])),
            "scip_status": ", ".join(f"{v}: {k}" for k, v in sorted(
                {st: sum(e.get("status") == st for e in ex) for st in {e.get("status") for e in ex}}.items(),
                key=lambda kv: -kv[1])),
            "enum_median": float(np.median([e["enumeration_time"] for e in checked])) if checked else math.nan,
            "checked": len(checked), "scip_matches": sum(bool(e.get("scip_matches")) for e in checked),
            "check_max": max((e["scip_cost"] / e["enumerated_cost"] - 1 for e in checked if "scip_cost" in e),
                             default=math.nan),
            "contact_modes": sum(any(any(row) for row in e["modes"]) for e in ex),
        }
    return out


def write_report(out: str, settings: Settings, cmd: str) -> dict[str, Any]:
    """``OUT/cartpole_c3.md`` and ``OUT/cartpole_c3.png`` from the units in ``OUT``."""
    records = load_records(os.path.join(out, f"{FILE}.jsonl"))
    s = summarize(records, settings)
    dates = sorted({r["date"] for r in records if "date" in r})
    date = dates[0] if len(dates) == 1 else (f"{dates[0]} to {dates[-1]}" if dates else today())
    loads = [r["load"] for r in records if "load" in r]
    stamp = (f"Command: `{cmd}`; date {date}; machine: {MACHINE}"
             + (f" (1-minute load average {min(loads):.1f} to {max(loads):.1f} while it ran: the two cores were "
                "shared with other work, so absolute times are pessimistic)" if loads else "") + ".")
    C = s["controllers"]
    order = [c for c in ("defaults", "defaults, penalize_input_change", "auto", "lcp", "c3+", "qp", "miqp enum", "miqp", "lqr", "c3+ cvxpy") if c in C]
    L: list[str] = []
    w = L.append
    w("# C3 on the cart-pole with soft walls: closed loop, cost gap, time per solve\n")
    w("C3 (`lcs_cvx.control.C3`) controls C3's published cart-pole between two soft walls "
      "(`lcs_cvx.control.c3_cartpole()`: the linearised LCS, dt = 0.01 s, walls at ±0.35 m, stiffness 100; "
      "horizon N = 5, Q = diag(10, 2, 1, 1), R = 1, terminal weight from the Riccati equation, C3's "
      "published G and U for each projection, 10 ADMM iterations, ρ scale 2). The plant is that same exact "
      "LCS, so the study measures the controller, not model error.\n")
    w(f"Initial states: {settings.states} drawn uniformly (seed {SEED}) from |x_c| ≤ {BOX[0]} m, "
      f"|θ| ≤ {BOX[1]} rad, |ẋ_c| ≤ {BOX[2]} m/s, |θ̇| ≤ {BOX[3]} rad/s (a box around C3's x0 = "
      "(0.1, −0.5, 0.5, −0.4), which is run separately). A run succeeds when |x|∞ ≤ 0.1 holds for "
      f"30 consecutive steps within {settings.steps} steps ({settings.steps * 0.01:g} s). "
      "The exact (`miqp`) projection runs two ways: by its 3^n_λ active sets in closed form "
      "(`projection_solver=\"enumerate\"`, every state), and as C3 solves it, big-M binaries through CVXPY "
      f"and SCIP (about a second or more per solve), on the first {settings.miqp_states} of these states "
      "only, each of those runs stopping 30 steps after it settles "
      "(its final error is the error at that step); `c3+ cvxpy` runs on the first "
      f"{settings.cvxpy_states} states, for its time per solve.\n")
    w(stamp + "\n")

    w("## Closed-loop success\n")
    w("| controller | runs | success | 95 % interval | median settling step | final error median | final error p95 | "
      "wall-contact steps, successes / failures (median) | from C3's x0 |")
    w("| --- | ---: | ---: | --- | ---: | ---: | ---: | --- | --- |")
    for c in order:
        d = C[c]
        x0r = d["x0"]
        x0s = "–" if x0r is None else ("settled at step " + str(x0r["settled"]) if x0r.get("success")
                                       else f"not settled ({x0r.get('simulated', '?')} steps)")
        note = " (stopped once settled)" if d["stopped_early"] else ""
        rate = f"{d['k']}/{d['n']} = {_fmt(100 * d['rate'], 3)} %" if d["n"] else "–"
        ci = f"{_fmt(100 * d['ci'][0], 3)}–{_fmt(100 * d['ci'][1], 3)} %" if d["n"] else "–"
        w(f"| {LABELS[c]} | {d['n']} | {rate} | {ci} | {_fmt(d['settle_median'])} | "
          f"{_fmt(d['final_median'])}{note} | {_fmt(d['final_p95'])} | {_fmt(d['contact_success'])} / "
          f"{_fmt(d['contact_fail'])} | {x0s} |")
    w("")
    w("The final error is |x|∞ after the last step. Wall-contact steps count the steps at which the pole "
      "presses into a wall (the state beyond a wall's gap, D x + c < 0).\n")
    for c in order:
        d = C[c]
        if d["fail_n"]:
            w(f"- {LABELS[c]}: {d['fail_n']} failing runs, median final |x|∞ {_fmt(d['fail_final'])}, median "
              f"largest |x_c| {_fmt(d['fail_pos'])} m and |θ| {_fmt(d['fail_angle'])} rad over the run; "
              f"{d['fail_bouncing']} of them still in wall contact in their last 100 steps.")
    w("")
    if "miqp" in C:
        n_m = C["miqp"]["n"]
        w(f"The miqp projection runs from the first {settings.miqp_states} random states only (plus C3's x0), "
          f"against {C['c3+']['n'] if 'c3+' in C else '–'} for the others"
          + (f"; {n_m} of them have finished so far" if n_m < settings.miqp_states else "")
          + ": its success rate is the least certain.\n")
    if {"miqp", "miqp enum"} <= set(C):
        r1, r2 = s["runs"]["miqp"], s["runs"]["miqp enum"]
        both = [x for x in r1 if x in r2 and "settled" in r1[x] and "settled" in r2[x]]
        same = sum(r1[x]["settled"] == r2[x]["settled"] for x in both)
        w(f"The exact projection by SCIP and by active sets: on the {len(both)} states both ran, the runs settle "
          f"at the same step (or both fail) from {same}.\n")
    for one, two in (("c3+", "lqr"), ("qp", "lqr"), ("qp", "c3+"), ("miqp enum", "c3+")):
        if {one, two} <= set(C):
            r1, r2 = s["runs"][one], s["runs"][two]
            both = [x for x in r1 if x != "x0" and x in r2 and "success" in r1[x] and "success" in r2[x]]
            a = sum(bool(r1[x]["success"]) and not r2[x]["success"] for x in both)
            b = sum(bool(r2[x]["success"]) and not r1[x]["success"] for x in both)
            w(f"- On the same {len(both)} states, {LABELS[one]} succeeds where {LABELS[two]} fails from {a} states, "
              f"and the reverse happens from {b}.")
    w("")
    w("The model is linearised about the upright pole; a failing run with angles of several radians has "
      "left the region where it describes a cart-pole, and only says that the controller let it diverge.\n")
    w("## Cost gap of C3's plan to the exact optimum\n")
    w("For each initial state the optimum of the horizon problem is one mixed-integer QP over the whole "
      "horizon (dynamics and big-M complementarity, M = 1000, at every step; CVXPY, SCIP; "
      "`studies/control/exact.py`). The contact modes SCIP picks are fixed and that QP re-solved by "
      "Clarabel, and its inputs are rolled out through the exact LCS. C3's first plan from the same state "
      "(cold start) is evaluated the same way: its inputs u_0..u_4 rolled out through the exact LCS, so both "
      "costs are costs of feasible trajectories. Gap = (C3 − optimum) / optimum over the random states; "
      "\"at the optimum\" counts gaps ≤ 1e-6. LQR's row is its own 5-step closed-loop trajectory.\n")
    w("| controller | states | gap median | gap p95 | gap max | at the optimum | median, optimum without contact | "
      "median, optimum with contact | gap from C3's x0 |")
    w("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for c in order:
        d = C[c]
        if not d["gap_n"]:
            continue
        w(f"| {LABELS[c]} | {d['gap_n']} | {_fmt(d['gap_median'])} | {_fmt(d['gap_p95'])} | {_fmt(d['gap_max'])} | "
          f"{d['gap_optimal']}/{d['gap_n']} | {_fmt(d['gap_free'][1])} ({d['gap_free'][0]}) | "
          f"{_fmt(d['gap_contact'][1])} ({d['gap_contact'][0]}) | {_fmt(d['x0_gap'])} |")
    w("")
    w("When the optimal plan touches no wall, the horizon problem is an LQR problem whose terminal weight is "
      "the Riccati solution, and its optimum is u = −K x itself: LQR's gaps there are zero to rounding. "
      "C3's plans carry the consensus terms of its last QP step and stay slightly above the optimum even "
      "then.\n")
    if "defaults" in C and C["defaults"]["gap_n"]:
        d = C["defaults"]
        w(f"C3's defaults polish the plan: its inputs re-planned in the contact modes the model's rollout of them "
          f"visits, without the consensus terms (at most 3 QPs, the cheapest plan kept). Their first plans are at "
          f"the optimum from {d['gap_optimal']} of {d['gap_n']} states (gap median {_fmt(d['gap_median'])}): where "
          "the ADMM finds the optimal contact modes, the polish finds the optimal inputs in them.\n")
    e = s["exact"]
    if e:
        w(f"The exact problem: {e['n']} states solved ({e['errors']} failures). SCIP takes {_fmt(e['scip_median'])} s "
          f"median, {_fmt(e['scip_p95'])} s p95, {_fmt(e['scip_max'])} s at most ({e['scip_status']}); it stops at a "
          "relative gap of 1e-4, because at smaller gaps (1e-6, or its default 0) it refined the cost's cones for "
          "minutes on some states without closing the last ~1e-5. Every optimum is therefore certified by "
          "trying every mode sequence (the first step's mode is fixed by x0; 2^8 convex QPs, "
          f"{_fmt(e['enum_median'])} s per state): on {e['checked']} states SCIP's modes gave the optimum on "
          f"{e['scip_matches']} (largest relative excess {_fmt(e['check_max'])}). No big-M bound is active at "
          f"any optimum: the largest λ is {_fmt(e['max_lam'])} and the largest complementarity gap "
          f"{_fmt(e['max_gap'])}, both far below M = 1000 ({e['big_m_active']} states with a bound within 0.1 % "
          f"of M). Complementarity holds to {_fmt(e['complementarity'])}; the rolled-out cost equals the "
          f"optimum's planned cost to {_fmt(e['rollout_vs_plan'])} (relative). {e['contact_modes']} of "
          f"{e['n']} optimal plans use a wall contact.\n")

    w("## Time per solve\n")
    w("Wall time of one controller call `ctrl(x)` (warm-started from the previous plan) in the closed-loop "
      "runs, one state at a time, all calls pooled; the phases are medians of `plan.times`.\n")
    w("| controller | solves | median | p95 | median QP step / projection / LCP |")
    w("| --- | ---: | ---: | ---: | --- |")
    for c in order:
        d = C[c]
        ph = d["phase"]
        phs = "–" if ph is None else f"{_fmt(ph['qp'])} / {_fmt(ph['projection'])} / {_fmt(ph['lcp'])} ms"
        w(f"| {LABELS[c]} | {d['solves']} | {_fmt(d['time_median'])} ms | {_fmt(d['time_p95'])} ms | {phs} |")
    w("")
    fast, slow = s["runs"]["c3+"], s["runs"]["c3+ cvxpy"]
    shared = [x for x in slow if x in fast and "plan_u" in slow[x] and "plan_u" in fast[x]]
    if shared:
        diff = max(float(np.abs(np.subtract(fast[x]["plan_u"], slow[x]["plan_u"])).max()) for x in shared)
        alike = [x for x in shared if fast[x]["steps"] == slow[x]["steps"]]
        same = sum(fast[x].get("settled") == slow[x].get("settled") for x in alike)
        w(f"The two QP paths of the c3+ controller plan the same inputs: on the {len(shared)} states run on both, "
          f"the first plans' inputs differ by at most {_fmt(diff)} N"
          + (f", and the closed-loop runs settle at the same step (or both fail) on {same} of {len(alike)}"
             if alike else "") + ".\n")
    b = s["batch"]
    w("## The batched fast path: many rollouts at once\n")
    if b is None:
        w("Not run yet.\n")
    else:
        k = sum(1 for v in b["settled"] if v >= 0)
        lo, hi = wilson(k, b["rollouts"])
        w(f"`closed_loop(C3(..., projection=\"c3+\"), model, X0 ({b['rollouts']}, 4), {b['steps']})`: "
          f"{b['rollouts']} closed-loop rollouts from the first {b['rollouts']} states of the same draw, all "
          "solved together by each controller call.\n")
        w("| rollouts | steps | wall time | per step (all rollouts) | per rollout-step | success | 95 % interval | "
          "final error median |")
        w("| ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: |")
        w(f"| {b['rollouts']} | {b['steps']} | {_fmt(b['wall'])} s | {_fmt(b['per_step_ms'])} ms | "
          f"{_fmt(1e3 * b['per_step_ms'] / b['rollouts'])} µs | {k}/{b['rollouts']} = {_fmt(100 * b['success_rate'])} % | "
          f"{_fmt(100 * lo)}–{_fmt(100 * hi)} % | {_fmt(b['final_error_median'])} |")
        w("")
        one = s["runs"]["c3+"]
        shared = [x for x in one if x != "x0" and int(x) < b["rollouts"]]
        if shared:
            same = sum(int(one[x]["settled"]) == int(b["settled"][int(x)]) for x in shared)
            w(f"On the {len(shared)} states run one at a time too, the batched runs settle at the same step in "
              f"{same} of {len(shared)}.\n")
            if "c3+" in C and math.isfinite(C["c3+"]["time_median"]):
                w(f"One state at a time the same controller takes {_fmt(C['c3+']['time_median'])} ms per call, "
                  f"so the batch does {_fmt(b['rollouts'] * C['c3+']['time_median'] / b['per_step_ms'])} "
                  "times the work per unit of time.\n")
    w("## Figure\n")
    w(f"![trajectories, success and time per solve]({FILE}.png)\n")
    w("Top two rows: cart position and pole angle in closed loop from C3's x0 and the first two random "
      "states, per controller (the pole touches a wall when x_c − 0.6 θ leaves ±0.35 m). Bottom: success rate (95 % interval), time per solve (median, bar to p95) "
      "and the cost gap per controller.\n")
    with open(os.path.join(out, f"{FILE}.md"), "w") as f:
        f.write("\n".join(L))
    plot(s, os.path.join(out, f"{FILE}.png"), settings)
    return s


def plot(s: dict[str, Any], path: str, settings: Settings) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 3, figsize=(13, 10))
    runs = s["runs"]
    for j, state in enumerate(TRAJ_STATES):
        for c, by_state in runs.items():
            r = by_state.get(state)
            if r is None or "traj" not in r:
                continue
            tr = np.asarray(r["traj"])
            t = 0.01 * np.arange(tr.shape[0])
            for i in range(2):
                axes[i, j].plot(t, tr[:, i], color=COLORS[c], lw=1.2, label=c + ("" if r.get("success") else " (fails)"))
        title = "C3's x0" if state == "x0" else f"random state {state}"
        axes[0, j].set_title(title, fontsize=10)
        for i, lab in enumerate(("cart position (m)", "pole angle (rad)")):
            axes[i, j].axhline(0, color="k", lw=0.5)
            axes[i, j].set_xlabel("t (s)")
            axes[i, j].set_ylabel(lab)
            axes[i, j].grid(alpha=0.3)
        axes[0, j].legend(fontsize=7)
    C = s["controllers"]
    names = [c for c in ("auto", "lcp", "c3+", "qp", "miqp enum", "miqp", "lqr", "c3+ cvxpy") if c in C and C[c]["n"]]
    ax = axes[2, 0]
    for i, c in enumerate(names):
        d = C[c]
        ax.bar(i, 100 * d["rate"], color=COLORS[c])
        ax.errorbar(i, 100 * d["rate"], yerr=[[100 * (d["rate"] - d["ci"][0])], [100 * (d["ci"][1] - d["rate"])]],
                    color="k", capsize=3)
        ax.text(i, 2, f"n={d['n']}", ha="center", fontsize=7, color="w")
    if s["batch"] is not None:
        i = len(names)
        ax.bar(i, 100 * s["batch"]["success_rate"], color=COLORS["c3+"], hatch="//")
        ax.text(i, 2, f"n={s['batch']['rollouts']}", ha="center", fontsize=7, color="w")
        names_b = names + ["c3+ batch"]
    else:
        names_b = names
    ax.set_xticks(range(len(names_b)))
    ax.set_xticklabels(names_b, rotation=20, fontsize=8)
    ax.set_ylabel("success (%)")
    ax.set_ylim(0, 100)
    ax.set_title(f"settled within {settings.steps} steps", fontsize=10)
    ax = axes[2, 1]
    for i, c in enumerate(names):
        d = C[c]
        if math.isfinite(d["time_median"]):
            ax.bar(i, d["time_median"], color=COLORS[c])
            ax.errorbar(i, d["time_median"], yerr=[[0], [d["time_p95"] - d["time_median"]]], color="k", capsize=3)
    if s["batch"] is not None:
        ax.bar(len(names), s["batch"]["per_step_ms"] / s["batch"]["rollouts"], color=COLORS["c3+"], hatch="//")
    ax.set_xticks(range(len(names_b)))
    ax.set_xticklabels(names_b, rotation=20, fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel("ms per solve (batch: per rollout)")
    ax.set_title("time per solve, 1 torch thread", fontsize=10)
    ax.grid(alpha=0.3, axis="y", which="both")
    ax = axes[2, 2]
    data, labels = [], []
    for c in names:
        gaps = [g for g in C[c]["gaps"] if math.isfinite(g)]
        if gaps:
            data.append(np.maximum(np.asarray(gaps), 1e-9))
            labels.append(c)
    if data:
        ax.boxplot(data, whis=(5, 95))
        ax.set_xticks(range(1, len(labels) + 1))
        ax.set_xticklabels(labels, rotation=20, fontsize=8)
        ax.set_yscale("log")
    ax.set_ylabel("(cost − optimum) / optimum (floored at 1e-9)")
    ax.set_title("cost gap of the first plan", fontsize=10)
    ax.grid(alpha=0.3, axis="y", which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
