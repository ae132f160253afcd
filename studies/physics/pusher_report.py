r"""The markdown report of the pusher-slider study (``report.md``): the system and data, the
models, the target check (LCS against MLP) with conclusions computed from it, the learning curve,
the results at the largest training size per contact mode, the selections (n_λ, MLP grid), the
figures and the exported models. Every number comes from the study's summary (``metrics.json``).
"""

from __future__ import annotations

from typing import Any

from .evaluation import fmt
from .pusher_plant import MODES

__all__ = ["write_report"]

_SHOWN_SETTINGS = ("iterations", "batch_size", "lr", "lr_schedule", "gamma", "eps", "eps_start", "reg",
                   "reinit_saturated", "extra_units", "refine", "keep_best", "normalize", "init")


def _table(head: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)] + ["| " + " | ".join(r) + " |" for r in rows]


def _times(r: float) -> str:
    return "diverged" if r == 0 else ("∞" if r == float("inf") else f"{r:.2f}×")


def _header(s: dict[str, Any], name: str) -> list[str]:
    t, jobs = s["timing_s"], s["jobs"]
    reused = jobs["total"] - jobs["run_now"]
    where = (f"training jobs on the Dask scheduler {s['scheduler']}" if s.get("scheduler")
             else f"{s['workers']} training process(es), one torch thread each")
    code = s["code"]
    changed = f" with uncommitted changes to {', '.join(code['lcs_cvx_changed'])}" if code["lcs_cvx_changed"] else ""
    return [
        "# Learning an LCS of a MuJoCo pusher-slider",
        "",
        f"Study `{name}`, written by `studies/physics/pusher_study.py` "
        f"(`lcs-cvx study run studies/configs/{name}.toml --out <dir>`).",
        f"Code: commit `{code['commit']}`{changed}. Machine: {s['machine']}; {where}"
        + (f" ({reused} of {jobs['total']} jobs read from the study database of an earlier run)" if reused else "")
        + f". Wall time **{t['total']:.0f} s** (data {t['data']:.0f} s, training {t['training']:.0f} s, "
        f"evaluation and figures {t['evaluation']:.0f} s); the training jobs' own wall times sum to "
        f"{t['jobs_cpu']:.0f} s.",
    ]


def _system(s: dict[str, Any], cfg: dict[str, Any], H: int) -> list[str]:
    p, sm, d = cfg["physics"], cfg["sampling"], cfg["data"]
    out = [
        "", "## System and data", "",
        f"A box slider ({p.slider_mass} kg, {200 * p.slider_half_size:g} cm × {200 * p.slider_half_size:g} cm × "
        f"{200 * p.slider_half_height:g} cm) on a table (friction μ = {p.mu_table}), pushed by a sphere of radius "
        f"{100 * p.pusher_radius:g} cm driven by velocity servos (kv = {p.pusher_kv:g} N s/m, {p.pusher_mass} kg); "
        f"pusher friction μ = {p.mu_pusher} along the face; MuJoCo's pyramidal friction cone; timestep "
        f"{p.timestep} s, control period {p.control_period:.3g} s ({p.substeps} substeps, zero-order hold). "
        "The system is simulated in the slider's frame (re-expressed at the start of every period): "
        "state x = (p_x, p_y, v_x, v_y, ω), the pusher's position relative to the slider (cm) and the "
        "slider's velocity (cm/s, rad/s); input u = the pusher's commanded velocity (cm/s). Every number: "
        "`studies/physics/pusher_plant.py`.",
        f"Commands u_x ~ U[{sm.ux_range[0]:g}, {sm.ux_range[1]:g}] cm/s, u_y = −{sm.uy_gain:g} p_y + w, "
        f"w ~ U[−{sm.uy_noise:g}, {sm.uy_noise:g}] cm/s, per period (wide-input test: both ranges × "
        f"{d['wide_factor']:g} about their centres); trajectories of ≤ {sm.traj_len} periods from the slider at "
        f"rest and the pusher behind its back face (gap U[0, {sm.gap0_max:g}] cm, offset "
        f"U[−{sm.offset0_max:g}, {sm.offset0_max:g}] cm), ended when |p_y| > {sm.face_limit:g} cm or the gap "
        f"exceeds {sm.gap_limit:g} cm. Seeds: training stream {d['seed_train']}, test {d['seed_test']}, wide "
        f"{d['seed_wide']}; every {d['val_every']}th trajectory of the stream is held out for validation "
        "(selection only). The contact mode of each sample is recorded for evaluation only.",
        "",
    ]
    rows = [[name, str(v["n"]), str(v["trajectories"])] + [f"{100 * v['modes'][m]:.1f} %" for m in MODES]
            + [str(v["windows_H"])] for name, v in s["data"].items()]
    return out + _table(["set", "samples", "trajectories", *MODES, f"{H}-step windows"], rows)


def _parc(s: dict[str, Any], cfg: dict[str, Any]) -> str:
    """The PARC bullet: what it is, its settings and, per training size, its fit (wall time,
    pieces kept, iterations) or the error it failed with."""
    pc = cfg["parc"]
    fits = []
    for n in sorted(s["sizes"], key=int):
        r = s["sizes"][n]["selection"].get("parc")
        if r is None:
            continue
        if r["error"] is not None:
            fits.append(f"N = {n}: **failed** after {r['wall_time']:.1f} s ({r['error']})")
        else:
            fits.append(f"N = {n}: {r['wall_time']:.1f} s, {r['info']['K_final']} pieces kept, "
                        f"{r['info']['iterations']} iterations")
    K = "the number of true contact modes, 4" if pc["K"] == "modes" else str(pc["K"])
    return ("- **PARC (piecewise-affine regression)**: piecewise-affine regression and classification (Bemporad, "
            "IEEE TAC 2023; package `pyparc`, through `lcs_cvx.study.baselines.parc`): K affine maps "
            "x' = A_j x + B_j u + d_j on the cells of a piecewise-linear partition of [x; u] "
            "(j = argmax_i ω_iᵀ[x; u] + γ_i), fitted together by block-coordinate descent from a k-means++ "
            "clustering, on the same training samples in physical units ([x, u] → x', as the authors call it). "
            f"K = {K} (told how many modes there are, not which sample is in which), separation "
            f"{pc['separation']}, σ = {pc['sigma']:g}, α = {pc['alpha']:g}, β = {pc['beta']:g}, at most "
            f"{pc['maxiter']} iterations, cost tolerance {pc['cost_tol']:g}, clusters under {pc['min_number']} "
            f"samples merged, fit_on_partition = {str(pc['fit_on_partition']).lower()}, {pc['kmeans_init']} "
            f"k-means++ starts, seed {pc['seed']} (the authors' settings); one fit per training size, nothing "
            "selected. Fit wall time (one thread): " + "; ".join(fits) + ".")


def _models(s: dict[str, Any], cfg: dict[str, Any], H: int) -> list[str]:
    lc, mc = cfg["lcs"], cfg["mlp"]
    opts = "; ".join(f"{loss} loss: " + ", ".join(f"{k}={v}" for k, v in lc[loss].items()) for loss in lc["losses"])
    settings = "; ".join(f"{loss}: " + ", ".join(f"{k}={v}" for k, v in (s["fit_settings"].get(loss) or {}).items()
                                                 if k in _SHOWN_SETTINGS) for loss in lc["losses"])
    return [
        "", "## Models", "",
        f"- **LCS** (`lcs_cvx.fit`, which normalises the data and starts the model itself, `init=\"{lc['init']}\"`, "
        f"and returns it in physical units), for each loss, n_λ ∈ {lc['n_lam']} and restart seeds {lc['seeds']} "
        f"(F stiffness {lc['stiffness']}, other parameters {lc['init_scale']}·N(0, 1) in normalised coordinates). "
        f"{opts}. Per (training size, loss, n_λ) the restart with the lowest one-step validation error is kept; "
        f"per (training size, loss) `lcs_cvx.selection.choose(errors, tolerance={lc['tolerance']})` picks n_λ "
        "from those errors (the smallest n_λ within (1 + tolerance) of the lowest).",
        f"  Resolved `lcs_cvx.fit` settings at the largest size: {settings}.",
        "- **affine (least squares)**: x' = A x + B u + d on the same training samples.",
        f"- **MLP**: x' = x + f(x, u), tanh MLP on the normalised coordinates, Adam (lr {mc['lr']:g}, cosine) for "
        f"{mc['iterations']} iterations of batch {mc['batch_size']}, best validation iterate; the grid hidden "
        f"layers ∈ {mc['hidden']} × weight decay ∈ {mc['weight_decay']}, the point with the lowest one-step "
        "validation error (the LCS's criterion) kept per training size.",
        "- **affine per true mode (oracle)**: one least-squares affine model per true contact mode "
        "(separated / sticking / sliding +y / sliding −y), told the true mode of every sample and every rollout step.",
        _parc(s, cfg),
        "",
        "One-step error: Σ‖x̂' − x'‖² / Σ‖x'‖² (the paper's e_test) over the samples of each true contact mode, "
        "over the samples in contact (every mode but separated) and over all. Rollout error at H: open-loop from "
        f"the true state over the recorded inputs, Σ‖x̂_H − x_H‖² / Σ‖x_H‖² over all {H}-step windows "
        "(`studies.physics.evaluation.rollout_errors`; the same windows for every H and every model, the oracle "
        "given the true mode of each step; at the longest H equal to `lcs_cvx.rollout_error`).",
    ]


def _target(s: dict[str, Any], cfg: dict[str, Any], H: int) -> list[str]:
    factor = cfg["eval"]["target"]
    rows = [[str(r["size"]), r["set"], r["loss"], _times(r["contact_ratio"]), _times(r["rollout_ratio"]),
             "yes" if r["met"] else "**no**"] for r in s["target"]]
    out = ["", f"## Target: the LCS {factor:g}× below the MLP", "",
           f"The MLP's error divided by the LCS's (above 1: the LCS is better), for the one-step error in contact and "
           f"the {H}-step rollout error; the target is ≥ {factor:g} in both.", ""]
    out += _table(["training samples", "set", "LCS loss", "one-step contact, MLP / LCS", f"{H}-step rollout, MLP / LCS",
                   "target met"], rows)
    out += ["", "Conclusions (computed from the table):", ""]
    sizes = sorted({r["size"] for r in s["target"]})
    small = sizes[:2]
    for loss in cfg["lcs"]["losses"]:
        mine = [r for r in s["target"] if r["loss"] == loss]
        met = [r for r in mine if r["met"]]
        missed = [r for r in mine if not r["met"] and r["size"] in small]
        head = f"- {loss} loss: target met in {len(met)} of {len(mine)} (size, set) cells"
        if not mine:
            continue
        if not missed:
            out.append(head + f"; at the two smallest sizes ({', '.join(map(str, small))}) on every set.")
        else:
            where = "; ".join(f"N = {r['size']}, {r['set']}: contact {_times(r['contact_ratio'])}, "
                              f"{H}-step {_times(r['rollout_ratio'])}" for r in missed)
            out.append(head + f". **Not met** at the two smallest sizes in: {where}.")
    return out


def _learning_curve(s: dict[str, Any], H: int) -> list[str]:
    sizes = sorted(s["sizes"], key=int)
    out = ["", "## Learning curve", "", "![learning curve](learning_curve.png)", ""]
    for set_name in s["sizes"][sizes[0]]["sets"]:
        names = [r["name"] for r in s["sizes"][sizes[0]]["sets"][set_name]]
        rows = []
        for name in names:
            cells = [name]
            for n in sizes:
                r = next((r for r in s["sizes"][n]["sets"][set_name] if r["name"] == name), None)
                cells.append("–" if r is None else "failed (see Models)" if r["error"] is not None else
                             f"{fmt(r['one_step']['contact'])} / {fmt(r['rollout'][str(H)])}")
            rows.append(cells)
        out += [f"{set_name}: one-step error in contact / {H}-step rollout error, per number of training samples.", ""]
        out += _table(["model", *[f"N = {n}" for n in sizes]], rows) + [""]
    return out


def _per_mode(s: dict[str, Any], horizons: list[int]) -> list[str]:
    n = max(s["sizes"], key=int)
    out = ["", f"## Results at N = {n} training samples, per contact mode", ""]
    for set_name, rows in s["sizes"][n]["sets"].items():
        table = []
        for r in rows:
            if r["error"] is not None:
                table.append([r["name"]] + [f"fit failed: {r['error']}"] + ["–"] * (len(MODES) + 1 + len(horizons)))
                continue
            table.append([r["name"]] + [fmt(r["one_step"][m]) for m in (*MODES, "contact", "all")]
                         + [fmt(r["rollout"][str(h)]) for h in horizons])
        out += [f"### {set_name}", ""]
        out += _table(["model", *[f"1-step {m}" for m in MODES], "1-step contact", "1-step all",
                       *[f"rollout H={h}" for h in horizons]], table) + [""]
    return out


def _selection(s: dict[str, Any]) -> list[str]:
    out = ["", "## Selection on the validation set", "",
           "n_λ per (training size, loss): the best restart's one-step validation error per n_λ, and the choice.", ""]
    rows = []
    for n in sorted(s["sizes"], key=int):
        for loss, c in s["sizes"][n]["selection"]["n_lam"].items():
            errs = ", ".join(f"{k}: {v:.3g}" for k, v in c["val_error"].items())
            rows.append([n, str(s["sizes"][n]["n_validation"]), loss, errs, f"**{c['chosen']}** (seed {c['seed']})"])
    out += _table(["training samples", "validation samples", "loss", "validation error per n_λ", "chosen n_λ"], rows)
    out += ["", "MLP grid per training size (one-step validation error; lowest kept):", ""]
    rows = []
    for n in sorted(s["sizes"], key=int):
        grid = s["sizes"][n]["selection"]["mlp"]
        best = min(grid, key=lambda g: g["val_error"]) if grid else None
        rows += [[n, str(g["hidden"]), f"{g['weight_decay']:g}", f"{g['val_error']:.3g}", f"{g['wall_time']:.0f}",
                  "yes" if g is best else ""] for g in grid]
    out += _table(["training samples", "hidden", "weight decay", "validation error", "time (s)", "kept"], rows)
    failed = [(n, r) for n in s["sizes"] for r in s["sizes"][n]["selection"]["lcs"] if r.get("error")]
    if failed:
        out += ["", "Failed LCS restarts (never chosen): "
                + "; ".join(f"N = {n}, {r['loss']}, n_λ = {r['n_lam']}, seed {r['seed']}: {r['error']}" for n, r in failed)]
    return out


def write_report(s: dict[str, Any], cfg: dict[str, Any]) -> str:
    """The markdown report of a finished study from its summary ``s`` (``metrics.json``) and its
    parsed config ``cfg`` (:func:`studies.physics.pusher_study.parse_config`)."""
    horizons = [int(h) for h in cfg["eval"]["horizons"]]
    H = max(horizons)
    out = _header(s, cfg["name"]) + _system(s, cfg, H) + _models(s, cfg, H) + _target(s, cfg, H)
    out += _learning_curve(s, H) + _per_mode(s, horizons) + _selection(s)
    out += ["", "## Figures", "", f"Rollout error against the horizon at N = {max(s['sizes'], key=int)}:", "",
            "![error vs horizon](error_vs_horizon.png)", ""]
    if s["rollout_window_start"] is not None:
        out += ["One open-loop rollout of the test set through the contact modes, at the largest size:", "",
                "![rollouts](rollouts.png)", ""]
    out += ["## Exported models", "", "The chosen LCSs in physical units (`lcs_cvx.load_model(path)`; "
            "`model.to_matrices()` or `model.to_c3()` for the matrices):", ""]
    out += [f"- {name}: `{path}`" for name, path in s["exported_models"].items()]
    return "\n".join(out) + "\n"


def write_noisy_report(s: dict[str, Any]) -> str:
    """``noisy.md`` of the pusher-slider (:mod:`studies.physics.noisy`): the "Measured with
    noise" section of :func:`studies.physics.report.measured_with_noise`."""
    from .report import measured_with_noise, noisy_header

    name = s["config"]["name"]
    return "\n".join(noisy_header(s, "Learning an LCS of a MuJoCo pusher-slider",
                                  f"studies/configs/{name}.toml", "studies/results/pusher_slider")
                     + measured_with_noise(s)) + "\n"
