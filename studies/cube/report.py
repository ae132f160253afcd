r"""The report of the cube study (:mod:`studies.cube.study`): ``report.md`` (tables of every model
x metric x training size, the split, the settings, the target check), ``learning_curve.png`` and
``rollouts.png`` (true vs predicted height and horizontal position of a few test tosses)."""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np
import torch

from lcs_cvx.datasets import CUBE_DT, cube_tosses
from lcs_cvx.metrics import AffineMap, affine_lstsq

from . import kinematic
from . import models as M
from .metrics import CUTOFF_GROWTH, DIVERGED_GROWTH, GROUPS, UNITS, rollout, rollouts
from .tosses import DATE, MACHINE, SMOKE_TOSSES, SPLIT_SEED, study_parts, subset

__all__ = ["write_report", "target_check", "linear_floor", "ROLLOUT_METRICS"]

#: The rollout metrics of the target check: (label, horizon key, field).
ROLLOUT_METRICS = (("position H=10 (m)", "H10", "pos"), ("rotation H=10 (rad)", "H10", "rot"),
                   ("position H=30 (m)", "H30", "pos"), ("rotation H=30 (rad)", "H30", "rot"),
                   ("position to end (m)", "end", "pos"), ("rotation to end (rad)", "end", "rot"))
BASELINES = ("affine LS", "MLP")


def _f(v: Any, digits: int = 4) -> str:
    if v is None:
        return "–"
    if isinstance(v, str):
        return v
    if isinstance(v, float) and math.isinf(v):
        return "∞"
    if isinstance(v, float) and math.isnan(v):
        return "nan"
    return f"{v:.{digits}g}"


def _val(v: Any) -> float:
    return float(v) if not isinstance(v, str) else float(v.replace("Infinity", "inf"))


def _chosen(rec: dict[str, Any]) -> str:
    fit = rec["fit"]
    if "n_lam" in fit:
        s = f"n_λ = {fit['n_lam']}"
        if "n_lam_by_one_step" in fit and fit["n_lam_by_one_step"] != fit["n_lam"]:
            s += f" (one-step: {fit['n_lam_by_one_step']})"
        return s
    if "chosen" in fit:
        c = fit["chosen"]
        return f"{'×'.join(map(str, c['hidden']))}, wd {c['weight_decay']:g}, step {c['best_step']}"
    return ""


def target_check(records: list[dict[str, Any]]) -> list[str]:
    """One line per (size, LCS model, rollout metric) where the LCS is worse than a baseline, and
    per rollout set where a model diverged."""
    lines = []
    sizes = sorted({r["size"] for r in records})
    by = {(r["size"], r["model"]): r for r in records}
    for n in sizes:
        for r in [r for r in records if r["size"] == n]:
            for hk in ("H10", "H30", "end"):
                d = r["rollout"][hk]["diverged"]
                if d:
                    lines.append(f"- {n} tosses, **{r['model']}**: {d} of {r['rollout'][hk]['rollouts']} "
                                 f"rollouts ({hk}) diverged (NaN/inf or growth > {DIVERGED_GROWTH:g}).")
            if not r["model"].startswith("LCS"):
                continue
            worse = []
            for label, hk, field in ROLLOUT_METRICS:
                ours = _val(r["rollout"][hk][field])
                for b in BASELINES:
                    if (n, b) in by:
                        theirs = _val(by[(n, b)]["rollout"][hk][field])
                        if not ours <= theirs:
                            worse.append(f"{label}: {_f(ours)} vs {b} {_f(theirs)}")
            if worse:
                lines.append(f"- {n} tosses, **{r['model']}** worse than a baseline in " + "; ".join(worse) + ".")
    return lines


def linear_floor(test: Any) -> dict[str, dict[str, float]]:
    """The rollout errors (:func:`.metrics.rollouts`) of the affine map fitted by least squares
    on the test tosses themselves (an oracle no user has: the best affine map of these tosses at
    one step)."""
    amap = AffineMap(affine_lstsq(test.to_transitions()).W)
    return rollouts(lambda x: amap.step(x, x.new_zeros(x.shape[0], 0)), test.xs, (10, 30))


def _floor_lines(floor: dict[str, dict[str, float]]) -> list[str]:
    cells = "; ".join(f"{label} {_f(_val(floor[hk][field]))}" for label, hk, field in ROLLOUT_METRICS)
    return ["**The linear floor** (dashed in `learning_curve.png`). The affine map fitted by least squares on "
            f"the test tosses themselves (an oracle, not a model a user could fit): {cells}. It rotates no "
            "better than the models learned from the training tosses: their rotation error comes from the "
            "class of models (affine in the state, or affine between few mode switches), not from too few "
            "tosses."]


def _verdicts(records: list[dict[str, Any]]) -> list[str]:
    """One line per chosen LCS: its ``FitResult.verdict`` (validation rollout error against the
    affine map's)."""
    return [f"- {r['size']} tosses, **{r['model']}**: {r['fit']['verdict']}" for r in records
            if r["fit"].get("verdict")]


def _tables(records: list[dict[str, Any]]) -> list[str]:
    lines = ["## Rollouts on the test tosses", "",
             "Mean over the rollouts (∞ when any diverged; the count and the mean over the others "
             "beside it). Position: RMS over the rollout's steps (m); rotation: mean geodesic angle "
             "(rad). Windows start at every step of every test toss.", "",
             "| tosses | model | chosen | pos H=10 | rot H=10 | pos H=30 | rot H=30 | pos to end | rot to end | "
             "diverged H10 / H30 / end | largest growth (end) | fit (s) |",
             "| ---: | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: |"]
    for r in records:
        ro = r["rollout"]
        cells = []
        for _, hk, field in ROLLOUT_METRICS:
            v = _val(ro[hk][field])
            cells.append(_f(v) if math.isfinite(v) else f"∞ ({_f(_val(ro[hk][field + '_ok']))})")
        div = " / ".join(f"{ro[h]['diverged']}/{ro[h]['rollouts']}" for h in ("H10", "H30", "end"))
        lines.append(f"| {r['size']} | {r['model']} | {_chosen(r)} | " + " | ".join(cells)
                     + f" | {div} | {_f(_val(ro['end']['growth_max']), 3)} | {r['fit']['wall']:.0f} |")
    lines += ["", "## One-step errors on the test tosses", "",
              "Relative error of the predicted change x' − x per state group, each coordinate scaled by "
              "the spread of its change over the test transitions (0: exact, 1: as bad as predicting no "
              "change), and the plain RMS error of x' in units.", "",
              "| tosses | model | " + " | ".join(f"{g} rel" for g in GROUPS) + " | all rel | "
              + " | ".join(f"{g} RMS ({UNITS[g]})" for g in GROUPS) + " |",
              "| ---: | --- | " + " | ".join("---:" for _ in range(2 * len(GROUPS) + 1)) + " |"]
    for r in records:
        o = r["one_step"]
        lines.append(f"| {r['size']} | {r['model']} | " + " | ".join(_f(_val(o[f'{g} rel']), 3) for g in GROUPS)
                     + f" | {_f(_val(o['all rel']), 3)} | " + " | ".join(_f(_val(o[f'{g} rms']), 3) for g in GROUPS) + " |")
    return lines


def _selection(records: list[dict[str, Any]]) -> list[str]:
    lines = ["## Model selection on the validation tosses", "",
             f"Validation rollout error: `lcs_cvx.rollout_error` at H = {M.VALIDATION_HORIZON} on the "
             "validation tosses (relative squared state error; ∞: diverged).", "",
             "| tosses | model | candidate | validation one-step | validation rollout H=30 | fit (s) |",
             "| ---: | --- | --- | ---: | ---: | ---: |"]
    for r in records:
        fit = r["fit"]
        if "candidates" in fit:
            for c in fit["candidates"]:
                mark = " ✓" if c["n_lam"] == fit["n_lam"] else ""
                extra = ""
                if c.get("heldout_error") is not None:
                    extra = (f" (fit's held-out {_f(_val(c['heldout_error']), 3)}, affine "
                             f"{_f(_val(c['affine_heldout_error']), 3)}, growth {_f(_val(c['heldout_growth']), 3)}"
                             + (f", best iterate {c['best_iteration']}" if c.get("best_iteration") is not None
                                else "") + ")")
                lines.append(f"| {r['size']} | {r['model']} | n_λ = {c['n_lam']}{mark} | {_f(_val(c['val_one_step']), 3)} | "
                             f"{_f(_val(c['val_rollout']), 3)}{extra} | {_val(c['wall']):.0f} |")
        elif "grid" in fit:
            for g in fit["grid"]:
                mark = " ✓" if _val(g["val_rollout"]) == _val(fit["val_rollout"]) else ""
                lines.append(f"| {r['size']} | MLP | {'×'.join(map(str, g['hidden']))}, wd {g['weight_decay']:g}, "
                             f"best step {g['best_step']} of {g['steps']}{mark} | {_f(_val(g['val_one_step_mse']), 3)} (MSE, normalised) | "
                             f"{_f(_val(g['val_rollout']), 3)} | – |")
    return lines


def _curve(records: list[dict[str, Any]], path: str, floor: dict[str, dict[str, float]] | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(14, 7.5), sharex=True)
    names = list(dict.fromkeys(r["model"] for r in records))
    for k, (label, hk, field) in enumerate(ROLLOUT_METRICS):
        ax = axes[k % 2, k // 2]
        for name in names:
            rs = sorted((r for r in records if r["model"] == name), key=lambda r: r["size"])
            xs = [r["size"] for r in rs]
            ys = [_val(r["rollout"][hk][field]) for r in rs]
            ys_ok = [_val(r["rollout"][hk][field + "_ok"]) for r in rs]
            line, = ax.plot(xs, [y if math.isfinite(y) else np.nan for y in ys], "o-", label=name, ms=4)
            bad = [(x, y) for x, y, z in zip(xs, ys_ok, ys, strict=True) if not math.isfinite(z)]
            if bad:  # diverged somewhere: the mean over the rest, hollow
                ax.plot(*zip(*bad, strict=True), "x", color=line.get_color(), ms=9)
        if floor is not None:
            ax.axhline(_val(floor[hk][field]), color="0.4", ls="--", lw=1,
                       label="affine map of the test tosses (oracle)")
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_title(label, fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        if k % 2 == 1:
            ax.set_xlabel("training tosses")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("Cube tosses: open-loop rollout errors on the test tosses (× : some rollouts diverged; "
                 "mean over the others)", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _rollout_figure(out: str, records: list[dict[str, Any]], test_xs: list[torch.Tensor], path: str,
                    dt: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    size = max(r["size"] for r in records)
    rs = [r for r in records if r["size"] == size]
    picks = [0, len(test_xs) // 2, len(test_xs) - 1][: len(test_xs)]
    fig, axes = plt.subplots(2, len(picks), figsize=(5 * len(picks), 7), squeeze=False)
    for j, i in enumerate(picks):
        x = test_xs[i]
        t = np.arange(x.shape[0]) * dt
        axes[0, j].plot(t, x[:, 6].numpy(), "k-", lw=2.5, label="recorded")
        axes[1, j].plot(t, x[:, 4].numpy(), "k-", lw=2.5, label="recorded")
        for r in rs:
            spec = next(s for s in M.specs() if s.name == r["model"])
            step = spec.load(os.path.join(out, r["model_file"]))
            maxnorm = torch.linalg.vector_norm(x, dim=1).max().reshape(1)
            pred = rollout(step, x[:1], x.shape[0] - 1, maxnorm)[0].numpy()
            axes[0, j].plot(t, pred[:, 6], "-", lw=1.2, label=r["model"])
            axes[1, j].plot(t, pred[:, 4], "-", lw=1.2, label=r["model"])
        lo, hi = float(x[:, 6].min()), float(x[:, 6].max())
        axes[0, j].set_ylim(lo - 0.1, hi + 0.1)
        lo, hi = float(x[:, 4].min()), float(x[:, 4].max())
        axes[1, j].set_ylim(lo - 0.2, hi + 0.2)
        axes[0, j].set_title(f"test toss {i}: height p_z (m)", fontsize=10)
        axes[1, j].set_title(f"test toss {i}: horizontal p_x (m)", fontsize=10)
        axes[1, j].set_xlabel("time (s)")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"Open-loop rollouts from each toss's first state, models fitted on {size} tosses", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(out: str, records: list[dict[str, Any]], *, cmd: str, smoke: bool = False,
                 wall: float = 0.0) -> None:
    data = cube_tosses()
    parts = study_parts(len(data), smoke)
    test = subset(data, parts["test"])
    budget = M.SMOKE_BUDGET if smoke else M.Budget()
    sizes = sorted({r["size"] for r in records})
    names = list(dict.fromkeys(r["model"] for r in records))
    suffix = "_smoke" if smoke else ""
    check = target_check(records)
    L = [
        "# Learning a tossed cube from real data: LCS vs affine and MLP",
        "",
        f"Written by `{cmd}` on {DATE} ({MACHINE}); the cells are kept in `cube{suffix}.jsonl`, the "
        f"fitted models in `models{suffix}/`"
        + (f" (this invocation ran {wall:.0f} s, skipping the cells already there)." if wall >= 1 else "."),
        "",
        "**Data.** The 550 ContactNets cube tosses (`lcs_cvx.datasets.cube_tosses()`, 148 Hz motion capture "
        "of a 0.1048 m, 0.37 kg cube; state: quaternion, position, body angular velocity, linear "
        "velocity; no input). **Split by toss**, 50 / 25 / 25 % as dair_pll splits real data: a fixed "
        f"permutation (NumPy `default_rng({SPLIT_SEED})`) gives {len(parts['train'])} training, "
        f"{len(parts['validation'])} validation and {len(parts['test'])} test tosses "
        f"({sum(test.lengths)} test transitions)"
        + (f" (smoke: the first {SMOKE_TOSSES} validation and test tosses only)" if smoke else "")
        + ". The training set of size n is the first n training tosses (nested); every size is "
        "validated on the whole validation quarter (not scaled with the size) and tested on the whole "
        "test quarter.",
        "",
        "**Models** (all fitted on the same training tosses, chosen on the validation tosses by the "
        f"rollout error `lcs_cvx.rollout_error` at H = {M.VALIDATION_HORIZON}):",
        "",
        "- *affine LS*: x' = W [x; 1] by least squares;",
        f"- *MLP*: x' = x + s·MLP((x − μ)/σ) (tanh; μ, σ, s from the training states and increments), "
        f"AdamW lr 1e-3, batch {budget.mlp_batch}, at most {budget.mlp_steps} steps, early stopping on "
        f"the validation one-step error (checked every {budget.mlp_eval_every} steps, patience "
        f"{budget.mlp_patience}); grid: " + ", ".join(
            f"{'×'.join(map(str, g['hidden']))} wd {g['weight_decay']:g}" for g in budget.mlp_grid) + ";",
        "- *constant increment*: x' = x + m, m the mean training increment (where `lcs_cvx.fit` starts; "
        "a reference without dynamics, not a target);",
        f"- *LCS*: `lcs_cvx.select_n_lam(train, {list(budget.n_lams)}, validation=val, "
        f"holdout_horizon={M.VALIDATION_HORIZON}, rollout_horizon={budget.rollout_horizon}, "
        "recipe=\"plain\")` on the tosses as `lcs_cvx.Trajectories`, with the "
        "plain defaults otherwise" + (" (10,000 Adam iterations of batch 200, violation loss, "
        "normalised coordinates, then the simulation-error phase: 300 Adam steps on 10-step windows, "
        "kept only if the held-out score fell)" if budget.lcs_iterations == 10_000
        else f" but `iterations={budget.lcs_iterations}`") + "; on trajectories with a held-out part "
        "`fit` returns the iterate with the lowest held-out rollout error (the starting model "
        "included), and `select_n_lam` chooses n_λ by that error;",
        "- *LCS, known structure*: the same with `d` fixed to gravity (v_z' = v_z − g dt, p_z' = p_z − g dt², "
        "g = 9.81 m/s²; the recorded positions follow p' = p + dt v') and `A` masked to the free-flight "
        "pattern (p_i' from p_i, v_i; w_i' from w_i; v_i' from v_i; q' from q, w); the values of the "
        "unmasked entries of A are learned, as `LCS.fix` fixes whole parameters, not entries "
        "(`studies.cube.models.structured_lcs`);",
        "- *LCS, one-step losses only*: *LCS* with `rollout_horizon=None` (no simulation-error phase), at "
        "the n_λ *LCS* chose at the same size: what the phase buys;",
        "- *LCS, known kinematics*: *LCS* with `lcs_cvx.Kinematics` declared: p' = p + dt v' and "
        "q' = q ⊗ exp(dt w'/2) (body angular velocity, renormalised) integrated exactly from the learned "
        "velocity rows, and gravity held in `d` (v_z' gains −g dt; `LCS.hold`) "
        "(`studies.cube.kinematic.kinematic_lcs`);",
        "- *LCS, contact coordinates*: the same on the state with the cube's up coordinates appended, "
        "g = R(q)ᵀ e_z (`Kinematics(..., up=...)`: computed from the integrated quaternion), in which the "
        "height p_z + r_c · g of each of the 8 corners r_c is linear, and free flight held too "
        "(v' = v − g dt e_z and w' = w plus C λ: only the contacts change the velocities); its first 8 "
        "units start with D x + c at those heights, n_λ among "
        f"{list(kinematic.CONTACT_N_LAMS)} (`studies.cube.kinematic.contact_lcs`);",
        "- *LCS, cube symmetry*: the contact-coordinates LCS stepped in the body frame whose +z face points "
        "most upwards: of the cube's 24 rotational symmetries (signed permutations S of the body axes), one "
        "per face, chosen at each state by the largest (S g)_z, the state mapped into it (q ⊗ s⁻¹, S w, "
        "S g) before the step and back after; fitted on the tosses cut where that frame changes (each piece "
        "in its frame, every transition kept once; a piece shorter than a window trains the one-step losses and "
        "has no window in the rollout scores), n_λ among "
        f"{list(kinematic.CONTACT_N_LAMS)}, the complementarity rows blind to the quaternion and the "
        "horizontal position (held at 0; the contacts see the orientation through g only), started at free "
        "flight (C = 0). In its frame "
        "the lowest face is always −z, so the corners' torque arms r_c × g vary over one face's cap "
        "instead of the whole sphere, and the frame changes where a tipping cube passes over an edge "
        "(`studies.cube.symmetry`).",
    ]
    L += [
        "",
        "**Metrics** on the test tosses (`studies/cube/metrics.py`): one-step errors per state group; "
        "open-loop rollouts over every window of H = 10 and 30 steps and from each toss's first state "
        "to its end: position error (RMS over the rollout, m), rotation error (mean geodesic angle "
        "2 acos|⟨q, q̂/‖q̂‖⟩| over the rollout, rad), and the growth max ‖x̂‖ / max ‖x‖ (the "
        f"toss's largest recorded state). A rollout *diverges* when it produces NaN/inf or its growth "
        f"exceeds {DIVERGED_GROWTH:g} (a state beyond {CUTOFF_GROWTH:g} times is set to NaN); diverged "
        "rollouts are counted, never dropped.",
        "",
        "## Target check",
        "",
        "The target: every LCS at or below both baselines in every rollout metric at every size, and no "
        "diverging rollout.",
        "",
    ]
    L += check if check else ["Met: no LCS is worse than a baseline in any rollout metric and no rollout diverged."]
    L += ["", "Two things no linear model of this state can do: the quaternion kinematics "
          "q' = q + (dt/2) q ⊗ (0, w) is bilinear in q and w, so the affine map and every LCS (linear in x "
          "between mode switches) predict the rotation with one linear map per mode, while the MLP can "
          "represent it; and the height of a corner of the cube, what contact depends on, is "
          "p_z + (R(q) r)_z, quadratic in q, so the LCS's gap D x + c can only approximate it with a "
          "plane. The kinematic LCSs take both off the learner: the first integrates the quaternion "
          "exactly, the second also makes the corner heights linear in its state, the third (cube symmetry) "
          "also keeps the torque of a corner's force, r_c × g λ (bilinear in g and λ), within one face's "
          "cap of orientations, where one constant C describes it far better than over the whole sphere. "
          "The *held-out verdict* lines below are `FitResult.verdict` of each chosen LCS: its "
          f"validation rollout error at H = {M.VALIDATION_HORIZON} against the affine map's.", ""]
    L += _verdicts(records)
    floor = linear_floor(test)
    L += ["", *_floor_lines(floor), ""]
    L += _tables(records)
    L += [""]
    L += _selection(records)
    L += ["", "## Figures", "",
          f"`learning_curve{suffix}.png`: the rollout errors against the training tosses per model. "
          f"`rollouts{suffix}.png`: three test tosses, recorded vs predicted height p_z and horizontal "
          f"position p_x, models fitted on {max(sizes)} tosses.", ""]
    wall_rows = [f"| {n} | " + " | ".join(
        f"{next((r['fit']['wall'] for r in records if r['size'] == n and r['model'] == m), float('nan')):.0f}"
        for m in names) + " |" for n in sizes]
    L += ["## Wall times (fit and selection, s)", "", "| tosses | " + " | ".join(names) + " |",
          "| ---: | " + " | ".join("---:" for _ in names) + " |", *wall_rows, ""]
    with open(os.path.join(out, f"report{suffix}.md"), "w") as f:
        f.write("\n".join(L))
    _curve(records, os.path.join(out, f"learning_curve{suffix}.png"), floor)
    _rollout_figure(out, records, list(test.xs), os.path.join(out, f"rollouts{suffix}.png"), CUBE_DT)
