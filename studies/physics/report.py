r"""The markdown report of the physics study (``report.md``): the system and data, the models,
one table per test set (:func:`studies.physics.evaluation.markdown_table`), conclusions computed
from the test set, the restarts, the figures and the exported models.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .evaluation import markdown_table

__all__ = ["write_report"]


def _where(s: dict[str, Any]) -> str:
    """Where the training jobs ran, and how many came from the database of an earlier run."""
    jobs = s.get("jobs") or {}
    reused = jobs.get("total", 0) - jobs.get("run_now", 0)
    where = (f"training jobs on the Dask scheduler {s['scheduler']}" if s.get("scheduler")
             else f"{s['workers']} training process(es)")
    if reused:
        where += f" ({reused} of {jobs['total']} jobs read from the study database of an earlier run)"
    return where


def _ratio_text(a: float, b: float) -> str:
    """How ``a`` (ours) compares with ``b`` (a baseline): "3.2× lower" / "1.5× higher"."""
    if not (np.isfinite(a) and np.isfinite(b)) or a <= 0 or b <= 0:
        return "not comparable (a model diverged)"
    return f"{b / a:.1f}× lower" if a < b else f"{a / b:.1f}× higher"


_SHOWN_SETTINGS = ("optimizer", "iterations", "batch_size", "lr", "lr_schedule", "gamma", "eps",
                   "eps_start", "reg", "reinit_saturated", "extra_units", "refine",
                   "refine_iterations", "refine_batch")


def write_report(s: dict[str, Any], cfg: dict[str, Any], horizons: list[int], best_of: dict[str, str],
                 name: str) -> str:
    """The markdown report of a finished study.

    Args:
        s: the summary written to ``metrics.json`` (data, metrics, restarts, timing, ...).
        cfg: the parsed config (:func:`studies.physics.study.parse_config`).
        horizons: the rollout horizons reported (the largest, ``H``, in the conclusions).
        best_of: per loss the LCS shown in the rollout figure.
        name: the study's name (its config file is ``studies/configs/<name>.toml``).
    """
    p, sm, d, lc = cfg["physics"], cfg["sampling"], cfg["data"], cfg["lcs"]
    t = s["timing_s"]
    H = max(horizons)
    out = [
        "# Learning an LCS of a MuJoCo cart-pole with two soft walls",
        "",
        f"Study `{name}`, written by `studies/physics/study.py` "
        f"(`python -m studies.physics.cartpole_walls --config studies/configs/{name}.toml --out <dir>`, "
        f"or `lcs-cvx study run studies/configs/{name}.toml --out <dir>`).",
        f"Code: commit `{s['code']['commit']}`"
        + (f" with uncommitted changes to {', '.join(s['code']['lcs_cvx_changed'])}"
           if s["code"]["lcs_cvx_changed"] else "") + ". "
        f"Machine: {s['machine']}; {_where(s)}, one torch thread each. "
        f"Wall time **{t['total']:.0f} s** (data {t['data']:.0f} s, training {t['training']:.0f} s, "
        f"evaluation and figures {t['evaluation']:.0f} s).",
        "",
        "## System and data",
        "",
        f"Cart {p.cart_mass} kg, uniform pole {p.pole_mass} kg × {p.pole_length} m, frictionless walls "
        f"at x = ±{p.wall_distance} m touched by the pole tip (sphere of radius {p.tip_radius} m), "
        f"MuJoCo contact `solref = (-{p.wall_stiffness:g}, -{p.wall_damping:g})` (stiffness "
        f"{p.wall_stiffness:g} s⁻², damping {p.wall_damping:g} s⁻¹, mass-normalised), `solimp` "
        f"impedance {p.wall_impedance}; timestep {p.timestep} s, control period "
        f"{p.control_period:.3g} s ({p.substeps} substeps, zero-order hold). State "
        "x = (x_c, θ, ẋ_c, θ̇), input u = force on the cart (N).",
        f"Inputs u = −{sm.kp:g} x_c − {sm.kd:g} ẋ_c + w, w ~ U[−{sm.u_max:g}, {sm.u_max:g}] N per period "
        f"(wide-input test: w range × {d['wide_factor']:g}); trajectories of ≤ {sm.traj_len} periods "
        f"from random states, reset when |x_c| > {sm.x_limit:g} m or |θ| > {sm.theta_limit:g} rad. "
        f"Seeds: train {d['seed_train']}, test {d['seed_test']}, wide {d['seed_wide']}; every "
        f"{d['val_every']}th training trajectory is held out for validation (model selection only).",
        "",
        "| set | samples | trajectories | in contact | left / right wall | "
        f"{H}-step windows |",
        "|---|---|---|---|---|---|",
    ]
    for set_name, info in s["data"].items():
        l, r = info["contact_fraction_per_wall"]
        out.append(f"| {set_name} | {info['n']} | {info['trajectories']} | "
                   f"{100 * info['contact_fraction']:.1f} % | {100 * l:.1f} % / {100 * r:.1f} % | "
                   f"{info['windows_H']} |")
    opts = {loss: ", ".join(f"{k}={v}" for k, v in lc[loss].items()) for loss in lc["losses"]}
    out += [
        "",
        "## Models",
        "",
        f"- **LCS** (`lcs_cvx.fit`), n_λ ∈ {lc['n_lam']}, learned in the library's normalised "
        "coordinates (`lcs_cvx.scaling.Scaling`: x and u centred and scaled to the spread of the "
        "paper's data, the increment x' − x to unit variance, on the training set) and folded back "
        "by `lcs_cvx.fit` into an exact LCS in physical units. "
        + "; ".join(f"{loss} loss: {opts[loss]}" for loss in lc["losses"])
        + f". Restarts: every start `init` in {lc['init']} (`lcs_cvx.fit`'s option, "
        f"`lcs_cvx.train.starts`; the other parameters {lc['init_scale']}·N(0, 1) in normalised "
        f"coordinates; F stiffness {lc['stiffness']}) with every seed in {lc['seeds']}, the one "
        "with the lowest validation error kept.",
        "  Resolved `lcs_cvx.fit` settings (the recipe as it stood when the study ran): "
        + "; ".join(f"{loss}: " + ", ".join(f"{k}={v}" for k, v in (s['fit_settings'].get(loss) or {}).items()
                                               if k in _SHOWN_SETTINGS and not (
                                                   k.startswith("refine_") and not s['fit_settings'][loss].get("refine")))
                    for loss in lc["losses"]) + ".",
        "- **affine (least squares)**: x' = A x + B u + d on the same training samples.",
        f"- **MLP**: x' = x + f(x, u), tanh MLP with hidden layers {cfg['mlp']['hidden']}, Adam "
        f"(lr {cfg['mlp']['lr']:g}, cosine) for {cfg['mlp']['iterations']} iterations of batch "
        f"{cfg['mlp']['batch_size']}, best validation iterate.",
        "- **affine per true mode (oracle)**: one least-squares affine model per true contact mode "
        "(free / left / right), given the true mode of every sample and every rollout step.",
        "",
        "One-step error: Σ‖x̂' − x'‖² / Σ‖x'‖² (the paper's e_test) over the free samples, the samples "
        "in which a wall pushes during the control period, and all samples. Rollout error at H: "
        f"open-loop from the true state over the recorded inputs, Σ‖x̂_H − x_H‖² / Σ‖x_H‖² over all "
        f"{H}-step windows. λ/contact agreement: fraction of (sample, wall) pairs where \"some λ_i "
        "assigned to the wall is > 0\" matches the true contact, under the best assignment of λ's "
        "coordinates to {left, right, neither}; the trivial \"never in contact\" level is given "
        "below each table. \"Either sign\": each wall identified with one coordinate (distinct), "
        "counted as in contact when that coordinate is active or, if that agrees better, inactive "
        "-- an LCS may describe a wall by a unit that is active off contact.",
    ]
    for set_name, rows in s["metrics"].items():
        trivial = next((r["agreement"]["trivial"] for r in rows if r["agreement"]), None)
        out += ["", f"## Results: {set_name}", "", markdown_table(rows, horizons), ""]
        if trivial is not None:
            out.append(f"Trivial agreement (never in contact): {trivial:.3f}. \"train (s)\": the "
                       "summed wall time of all restarts of that model.")
    # conclusions, computed
    rows = {r["name"]: r for r in s["metrics"]["test"]}
    lcs_names = [n for n in rows if n.startswith("LCS")]
    base = {b: rows[b] for b in ("affine (least squares)", "MLP") if b in rows}
    for loss, c in s.get("n_lam_choice", {}).items():
        errs = ", ".join(f"n_λ={k}: {v:.3g}" for k, v in c["val_error"].items())
        out.append(f"- n_λ chosen from the validation errors (`lcs_cvx.selection.choose`, {loss} "
                   f"loss): **{c['n_lam']}** ({errs}).")
    out += ["", "## Conclusions (computed from the test set)", ""]
    if lcs_names and base:
        best = min(lcs_names, key=lambda n: rows[n]["one_step"]["contact"])
        for b, br in base.items():
            beaten = [n for n in lcs_names if rows[n]["one_step"]["contact"] < br["one_step"]["contact"]]
            out.append(
                f"- In contact, {len(beaten)} of {len(lcs_names)} LCS models beat the {b} baseline "
                f"(one-step contact error {br['one_step']['contact']:.3g}); the best, {best}, is "
                f"{_ratio_text(rows[best]['one_step']['contact'], br['one_step']['contact'])} "
                f"({rows[best]['one_step']['contact']:.3g})."
            )
        best_roll = min(lcs_names, key=lambda n: rows[n]["rollout"][str(H)])
        for b, br in base.items():
            out.append(
                f"- {H}-step rollouts: the best LCS, {best_roll} ({rows[best_roll]['rollout'][str(H)]:.3g}), "
                f"is {_ratio_text(rows[best_roll]['rollout'][str(H)], br['rollout'][str(H)])} than "
                f"the {b} ({br['rollout'][str(H)]:.3g})."
            )
        orc = rows.get("affine per true mode (oracle)")
        if orc:
            out.append(
                f"- Against the mode oracle (contact {orc['one_step']['contact']:.3g}, free "
                f"{orc['one_step']['free']:.3g}, {H}-step {orc['rollout'][str(H)]:.3g}) the best "
                f"LCS's contact error is {_ratio_text(rows[best]['one_step']['contact'], orc['one_step']['contact'])}."
            )
        wide = {r["name"]: r for r in s["metrics"].get("wide-input test (1.5×)", [])}
        if wide:
            wb = min(lcs_names, key=lambda n: wide[n]["one_step"]["contact"])
            parts = [f"{b}: {wide[b]['one_step']['contact']:.3g}" for b in base]
            out.append(f"- Wide inputs: best LCS contact error {wide[wb]['one_step']['contact']:.3g} "
                       f"({wb}) against " + ", ".join(parts) + ".")
    out += ["", "## Restarts (model selection on the validation trajectories)", "",
            "| model | init | seed | validation error | test 1-step all | selected | time (s) |",
            "|---|---|---|---|---|---|---|"]
    for r in s["restarts"]:
        test_all = "failed: " + r["error"] if r["test_one_step"] is None else f"{r['test_one_step']['all']:.4f}"
        out.append(f"| {r['model']} | {r.get('init', '')} | {r['seed']} | {r['val_error']:.3g} | {test_all} | "
                   f"{'yes' if r['selected'] else ''} | {r['wall_time']:.0f} |")
    out += ["", "## Figures", ""]
    if s["rollout_window_start"] is not None:
        shown = ", ".join(best_of.values())
        out += [f"Open-loop rollouts through a wall contact (LCS shown: the lowest validation error "
                f"per loss, {shown}):", "", "![rollouts](rollouts.png)", ""]
    out += ["Rollout error against the horizon:", "", "![error vs horizon](error_vs_horizon.png)", "",
            "## Exported models", "",
            "The selected LCSs in physical units (`lcs_cvx.load_model(path)`; `model.to_matrices()` "
            "or `model.to_c3()` for the matrices):", ""]
    out += [f"- {n}: `{path}`" for n, path in s["exported_models"].items()]
    return "\n".join(out) + "\n"


# -- measured with noise (studies/physics/noisy.py) ---------------------------------------------
def _fit_label(f: dict[str, Any]) -> str:
    rh = f["rollout_horizon"]
    if rh is None:
        what = "LCS, one-step losses only"
    else:
        kept = f.get("refinement_kept")
        what = (f"LCS + simulation error (rollout_horizon={rh}" + (", the default" if rh == "auto" else "")
                + ("" if kept is None else ", kept" if kept else ", undone: held-out score not lower") + ")")
    return f"{what}, seed {f['seed']}"


def measured_with_noise(s: dict[str, Any]) -> list[str]:
    """The "Measured with noise" section from a summary of :mod:`studies.physics.noisy`
    (``noisy.json``): per sensor one table of the LCS fits and the affine map, then the
    comparison with the affine map and the effect of the simulation-error refinement."""
    from .evaluation import fmt

    cfg, H = s["config"], s["horizon"]
    hs = cfg["eval"]["horizons"]
    d, f = cfg["data"], cfg["fit"]
    out = ["## Measured with noise", ""]
    out += [f"- **{name}**: {sens['description']}." for name, sens in s["sensors"].items()]
    opts = ", ".join(f"{k}={v}" for k, v in f["options"].items())
    out += [
        "",
        f"Data per sensor: {d['n_train']} training transitions from seed {d['seed_train']} (every "
        f"{d['val_every']}th trajectory held out for validation), {d['n_test']} test transitions from seed "
        f"{d['seed_test']}, as `lcs_cvx.Trajectories`. Fits: `lcs_cvx.fit(LCS(n_x, n_u, {f['n_lam']}, seed), "
        f"train, validation=val, holdout_horizon={H}, recipe=\"{f['recipe']}\"" + (f", {opts}" if opts else "")
        + ", rollout_horizon=None)` (one-step losses only) and the same with the simulation-error phase "
        f"(`rollout_horizon=` {', '.join(str(h) for h in f['rollout_horizons'])}; with `Trajectories` `fit` runs it "
        "by default, 10 steps, and keeps its result only if the held-out score fell), seeds "
        f"{f['seeds']}; every fit returns its iterate of lowest held-out score (`keep_best`"
        + (", set in the options" if "keep_best" in f["options"] else ", `fit`'s default with held-out trajectories")
        + "). The affine map: least squares "
        "on the same training transitions (the map `fit` compares with).",
        "",
        f"Columns: **held-out** -- `fit`'s held-out score on the validation trajectories, the {H}-step "
        "rollout error relative to the recorded change with each coordinate scaled by the spread of its "
        "one-step change (`FitResult.heldout_error` / `affine_heldout_error`, measured data: what a user "
        "sees); **test** -- "
        "`lcs_cvx.rollout_error` on the test trajectories at each horizon, against the measured states; **test, "
        f"noise-free** -- at H = {H} from and against the same test trajectories logged without noise "
        "(exact positions, velocities by the same differences: the true value of what the sensor measures; "
        "for the exact and differenced sensors the same as test); **growth** -- `FitResult.heldout_growth`; **< affine** -- "
        "`FitResult.beats_affine` (a lower held-out score, and rollouts that do not grow past 1.5 times the data's "
        "and the affine map's growth). A model of logged states predicts logged states (for a differencing "
        "sensor, mean velocities over the last control period), so it is scored against logged states, "
        "not against the simulator's instantaneous velocities.",
    ]
    head = (["sensor", "model", f"held-out H={H}"] + [f"test H={h}" for h in hs]
            + [f"test H={H}, noise-free", "growth", "< affine", "fit (s)"])
    for sensor, r in s["results"].items():
        c = r["counts"]
        out += ["", f"### Sensor `{sensor}`", "",
                f"{c['train']['transitions']} training transitions ({c['train']['trajectories']} trajectories), "
                f"{c['validation']['transitions']} validation ({c['validation']['trajectories']}), "
                f"{c['test']['transitions']} test ({c['test']['trajectories']}).", "",
                "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for fr in r["fits"]:
            if fr["error"] is not None:
                out.append(f"| {sensor} | {_fit_label(fr)} | failed: {fr['error']} |" + " |" * (len(head) - 3))
                continue
            sc = fr["scores"]
            cells = ([sensor, _fit_label(fr), fmt(fr["heldout_error"])] + [fmt(sc["test"][str(h)]) for h in hs]
                     + [fmt(sc["test_clean"][str(H)]), f"{fr['heldout_growth']:.3g}",
                        "yes" if fr["beats_affine"] else "**no**", f"{fr['wall_time']:.0f}"])
            out.append("| " + " | ".join(cells) + " |")
        a = r["affine"]
        out.append("| " + " | ".join([sensor, "affine (least squares)", fmt(a["validation"][str(H)])]
                                     + [fmt(a["test"][str(h)]) for h in hs]
                                     + [fmt(a["test_clean"][str(H)]), "–", "–", "0"]) + " |")
        m = r.get("mlp")
        if m is not None:
            sm = m["scores"]
            label = f"MLP (tanh {'×'.join(map(str, m['hidden']))}, lr {m['lr']:g})"
            out.append("| " + " | ".join([sensor, label, fmt(sm["validation"][str(H)])]
                                         + [fmt(sm["test"][str(h)]) for h in hs]
                                         + [fmt(sm["test_clean"][str(H)]), "–", "–", f"{m['wall_time']:.0f}"]) + " |")
    out += ["", "### The LCS against the affine map, and the refinement (computed)", ""]
    for sensor, r in s["results"].items():
        a = r["affine"]
        ok = [fr for fr in r["fits"] if fr["error"] is None]
        default = [fr for fr in ok if fr["rollout_horizon"] is None]
        won = sum(bool(fr["beats_affine"]) for fr in default)
        won_test = sum(fr["scores"]["test"][str(H)] < a["test"][str(H)] for fr in default)
        out.append(f"- `{sensor}`: the one-step fit beats the affine map on the held-out {H}-step rollouts in "
                   f"{won} of {len(default)} fits and on the test rollouts in {won_test} of {len(default)} "
                   f"(affine: held-out {a['validation'][str(H)]:.3g}, test {a['test'][str(H)]:.3g}).")
        m = r.get("mlp")
        if m is not None:
            mh, mt = m["scores"]["validation"][str(H)], m["scores"]["test"][str(H)]
            out.append(f"- `{sensor}`, against the MLP (the `lcs_cvx.study` baseline: its default grid, tuned on "
                       f"held-out training transitions; held-out {mh:.3g}, test {mt:.3g}): the LCS fits are at or below "
                       f"it held out in {sum(fr['heldout_error'] <= mh for fr in ok)} of {len(ok)}, on the test "
                       f"rollouts in {sum(fr['scores']['test'][str(H)] <= mt for fr in ok)} of {len(ok)}.")
        for rh in f["rollout_horizons"]:
            refined = [fr for fr in ok if fr["rollout_horizon"] == rh]
            mlp_part = ""
            if m is not None:
                mlp_part = (f"; at or below the MLP held out in {sum(fr['heldout_error'] <= mh for fr in refined)} of "
                            f"{len(refined)}, on the test rollouts in "
                            f"{sum(fr['scores']['test'][str(H)] <= mt for fr in refined)} of {len(refined)}")
            out.append(f"  - with the simulation-error phase (rollout_horizon={rh}): beats the affine map on the "
                       f"held-out rollouts in {sum(bool(fr['beats_affine']) for fr in refined)} of {len(refined)} and "
                       f"on the test rollouts in {sum(fr['scores']['test'][str(H)] < a['test'][str(H)] for fr in refined)} "
                       f"of {len(refined)}{mlp_part}.")
        for rh in f["rollout_horizons"]:
            pairs = [(d0, d1) for d0 in default for d1 in ok
                     if d1["rollout_horizon"] == rh and d1["seed"] == d0["seed"]]
            for d0, d1 in pairs:
                out.append(f"  - seed {d0['seed']}, rollout_horizon={rh}: held-out {d0['heldout_error']:.3g} → "
                           f"{d1['heldout_error']:.3g}, test H={H} {d0['scores']['test'][str(H)]:.3g} → "
                           f"{d1['scores']['test'][str(H)]:.3g}, noise-free {d0['scores']['test_clean'][str(H)]:.3g} → "
                           f"{d1['scores']['test_clean'][str(H)]:.3g}, fit time {d0['wall_time']:.0f} s → "
                           f"{d1['wall_time']:.0f} s.")
    return out


def noisy_header(s: dict[str, Any], title: str, config_path: str, out_dir: str) -> list[str]:
    """The title and provenance lines of ``noisy.md``."""
    run = s["config"]["run"]
    command = run.get("command") or (f"python -m studies.physics.noisy --config {config_path} --out {out_dir}")
    return [f"# {title}: measured with noise", "",
            f"Written by `studies/physics/noisy.py`: `{command}` "
            f"(`--report-only` rewrites this file from `noisy.json`).",
            f"Date: {run.get('date') or 'not recorded'}. Machine: {run.get('machine') or s['machine']} "
            f"({s['machine']}). Wall time {s['wall_time_s']:.0f} s, of which the fits "
            f"{s['fits_wall_time_s']:.0f} s (one after the other, one torch thread).", ""]


def write_noisy_report(s: dict[str, Any]) -> str:
    """``noisy.md`` of the cart-pole (:mod:`studies.physics.noisy`)."""
    name = s["config"]["name"]
    return "\n".join(noisy_header(s, "Learning an LCS of a MuJoCo cart-pole with two soft walls",
                                  f"studies/configs/{name}.toml", "studies/results/physics")
                     + measured_with_noise(s)) + "\n"
