r"""The physics study: learn LCSs of the MuJoCo cart-pole with soft walls
(:mod:`studies.physics.plant`) and compare them with baselines.

:func:`run_study` (config ``studies/configs/physics_cartpole.toml``, the ``lcs-cvx study``
runner's ``kind = "module"`` protocol):

1. data: training, test and wide-input test transitions (:func:`~studies.physics.plant.sample_transitions`),
   as the simulator's states or, with ``[data] sensor = "encoder"``, as encoders log them
   (:mod:`studies.physics.sensor`: quantised positions, velocities by finite differences; every
   set, the test sets too, is then measured); every ``val_every``-th training trajectory is held
   out for validation;
2. training: the jobs of :mod:`studies.physics.jobs` -- per ``(loss, n_lam, seed)`` one
   :func:`lcs_cvx.fit` in normalised coordinates, and the MLP baseline -- on an
   :mod:`lcs_cvx.study.executors` executor, each result stored in ``<out>/studies.sqlite`` as it
   arrives (a second run resumes, running only what is missing);
3. selection: per ``(loss, n_lam)`` the restart with the lowest validation error, folded back
   into physical units and exported (``models/lcs_<loss>_nlam<k>.npz``); the least-squares affine
   model and the per-mode oracle are fitted here;
4. evaluation (:mod:`studies.physics.evaluation`) on the test sets, the figures, ``metrics.json``
   and ``report.md`` (:mod:`studies.physics.report`).

The results do not depend on the executor: every job runs one torch thread from its own seeds.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from typing import Any

import numpy as np

from .config import check_sections, from_table, lcs_section, section
from .jobs import make_job, run_jobs
from .plant import STATE_NAMES, STATE_UNITS, Physics, Sampling, Transitions, sample_transitions
from .provenance import code_version, json_default, machine
from .sensor import SENSORS

__all__ = ["CONFIG_SECTIONS", "parse_config", "training_jobs", "run_study"]

# -- the config --------------------------------------------------------------------------------
#: Keys of a study config (besides the runner's ``name``, ``kind``, ``module``, ``description``).
CONFIG_SECTIONS = ("physics", "sampling", "data", "lcs", "mlp", "eval")

_DATA_DEFAULTS = {"n_train": 20000, "n_test": 5000, "n_wide": 5000, "seed_train": 0, "seed_test": 1,
                  "seed_wide": 2, "wide_factor": 1.5, "val_every": 10, "sensor": "exact"}
_LCS_DEFAULTS = {"n_lam": [2, 4, 8], "losses": ["violation", "prediction"], "seeds": [0, 1, 2, 3],
                 "init": ["increment"], "stiffness": 1.0, "init_scale": 0.1,
                 "violation": {"recipe": "best", "iterations": 12000},
                 "prediction": {"recipe": "paper", "normalize": True, "lr": 5e-3, "iterations": 12000}}
_MLP_DEFAULTS = {"hidden": [64, 64], "iterations": 20000, "batch_size": 256, "lr": 3e-3,
                 "weight_decay": 0.0, "seed": 0}
_EVAL_DEFAULTS = {"horizons": [1, 5, 20], "active_tol": 1e-9}


def parse_config(config: dict[str, Any]) -> dict[str, Any]:
    """Check a study config (a dict as TOML reads it) and fill in the defaults."""
    check_sections(config, CONFIG_SECTIONS)
    lcs = lcs_section(config, _LCS_DEFAULTS)
    data = section(config, "data", _DATA_DEFAULTS)
    if data["sensor"] not in SENSORS["cartpole"]:
        raise ValueError(f"config: data.sensor: expected one of {sorted(SENSORS['cartpole'])}, "
                         f"received {data['sensor']!r}")
    return {
        "name": config.get("name", "physics_cartpole"),
        "physics": from_table(Physics, config.get("physics"), "config: [physics]"),
        "sampling": from_table(Sampling, config.get("sampling"), "config: [sampling]"),
        "data": data,
        "lcs": lcs,
        "mlp": section(config, "mlp", _MLP_DEFAULTS),
        "eval": section(config, "eval", _EVAL_DEFAULTS),
    }


def _log(msg: str) -> None:
    print(f"[cartpole_walls] {msg}", file=sys.stderr, flush=True)


# -- the study ---------------------------------------------------------------------------------
def _data(cfg: dict[str, Any]) -> dict[str, Transitions]:
    """``train``, ``validation``, ``test`` and ``wide`` transitions of the config, logged by its
    ``data.sensor`` (:mod:`studies.physics.sensor`; ``"exact"``: the simulator's states)."""
    phys, samp, dcfg = cfg["physics"], cfg["sampling"], cfg["data"]
    sensor = dcfg["sensor"]
    train_all = sample_transitions(dcfg["n_train"], dcfg["seed_train"], phys, samp, sensor=sensor)
    test = sample_transitions(dcfg["n_test"], dcfg["seed_test"], phys, samp, sensor=sensor)
    wide = sample_transitions(dcfg["n_wide"], dcfg["seed_wide"], phys, samp, dcfg["wide_factor"], sensor=sensor)
    is_val = train_all.traj % dcfg["val_every"] == dcfg["val_every"] - 1
    return {"train": train_all.select(~is_val), "validation": train_all.select(is_val),
            "test": test, "wide": wide}


def training_jobs(cfg: dict[str, Any], scaling: Any, train: Transitions, val: Transitions
                  ) -> tuple[list[dict[str, Any]], list[tuple[str, int, str, int]]]:
    """The jobs (:func:`studies.physics.jobs.make_job`) of a parsed config: per ``n_lam`` (the
    largest, slowest, first), loss, start (``init``) and seed one ``fit_lcs`` -- the restarts of
    that ``(loss, n_lam)`` -- and the ``fit_mlp`` job in the middle of the list (index
    ``len(jobs) // 2``). Also returns the ``(loss, n_lam, init, seed)`` of each ``fit_lcs`` job,
    in order."""
    from .models import encode

    lcfg = cfg["lcs"]
    z, v, y = encode(scaling, train.x, train.u, train.x_next)
    zv, vv, yv = encode(scaling, val.x, val.u, val.x_next)
    normalised = {"z": z, "v": v, "y": y, "z_val": zv, "v_val": vv, "y_val": yv}  # the MLP's
    data = {"x": train.x, "u": train.u, "x_next": train.x_next, "x_val": val.x, "u_val": val.u,
            "x_next_val": val.x_next}
    jobs: list[dict[str, Any]] = []
    keys: list[tuple[str, int, str, int]] = []
    for n_lam in sorted(lcfg["n_lam"], reverse=True):  # the slow ones first
        for loss in lcfg["losses"]:
            opts = {k: (tuple(v_) if isinstance(v_, list) else v_) for k, v_ in lcfg[loss].items()}
            recipe = opts.pop("recipe")
            for init in lcfg["init"]:
                for seed in lcfg["seeds"]:
                    jobs.append(make_job("fit_lcs", {
                        **data, "n_lam": int(n_lam), "loss": loss, "recipe": recipe,
                        "options": opts, "stiffness": lcfg["stiffness"],
                        "init_scale": lcfg["init_scale"], "init": init, "seed": int(seed)}))
                    keys.append((loss, int(n_lam), init, int(seed)))
    jobs.insert(len(jobs) // 2, make_job("fit_mlp", {**normalised, **cfg["mlp"]}))
    return jobs, keys


def _select(keys: list[tuple[str, int, str, int]], results: list[dict[str, Any]]
            ) -> tuple[dict[str, list[dict[str, Any]]], dict[str, tuple[dict[str, Any], tuple]]]:
    """Per model name ``"LCS <loss> n_λ=<k>"``: every restart, and the one with the lowest
    validation error (a failed restart is never chosen)."""
    restarts: dict[str, list[dict[str, Any]]] = {}
    chosen: dict[str, tuple[dict[str, Any], tuple[str, int, int]]] = {}
    for key, res in zip(keys, results, strict=True):
        loss, n_lam, init, seed = key
        name = f"LCS {loss} n_λ={n_lam}"
        restarts.setdefault(name, []).append({"seed": seed, "init": init, "val_error": res["val_error"],
                                              "wall_time": res["wall_time"], "result": res})
        if res["matrices"] is None:
            _log(f"{name}, init {init}, seed {seed} failed: {res['error']}")
            continue
        if name not in chosen or res["val_error"] < chosen[name][0]["val_error"]:
            chosen[name] = (res, key)
    return restarts, chosen


def _choose_n_lam(chosen: dict[str, tuple[dict[str, Any], tuple]], losses: list[str]
                  ) -> dict[str, dict[str, Any]]:
    """Per loss, the n_λ :func:`lcs_cvx.selection.choose` picks from the selected restarts'
    validation errors, with those errors."""
    from lcs_cvx.selection import choose

    out = {}
    for loss in losses:
        errors = {key[1]: res["val_error"] for res, key in chosen.values() if key[0] == loss}
        if errors:
            out[loss] = {"n_lam": choose(errors), "val_error": {str(k): v for k, v in sorted(errors.items())}}
    return out


def _evaluate(models: dict[str, Any], sets: dict[str, Transitions], horizons: list[int],
              active_tol: float, train_time: dict[str, float]) -> tuple[dict, dict]:
    """Metric rows per set (one per model) and the rollout error curves per set and model."""
    from . import evaluation as ev
    from .models import LCSModel

    H = max(horizons)
    metrics: dict[str, Any] = {}
    curves: dict[str, dict[str, np.ndarray]] = {}
    for set_name, data in sets.items():
        rows, curves[set_name] = [], {}
        for name, model in models.items():
            errs = ev.rollout_errors(model, data, H)
            curves[set_name][name] = errs
            agreement = None
            if isinstance(model, LCSModel):
                active = model.lam(data.x, data.u) > active_tol
                agreement = ev.contact_agreement(active, data.contact)
            rows.append({
                "name": name,
                "one_step": ev.one_step_errors(model, data),
                "rollout": {str(h): float(errs[h - 1]) for h in horizons},
                "rollout_curve": [float(e) for e in errs],
                "agreement": agreement,
                "train_s": train_time[name],
            })
        metrics[set_name] = rows
    return metrics, curves


def run_study(config: dict[str, Any], out_dir: str, workers: int = 2,
              scheduler: str | None = None) -> None:
    """Run the whole study (data, training, evaluation, report) into ``out_dir``.

    Writes ``report.md`` (tables and conclusions), ``metrics.json``, ``rollouts.png``,
    ``error_vs_horizon.png``, ``models/lcs_<loss>_nlam<k>.npz`` (the selected LCSs in physical
    units, :func:`lcs_cvx.save_model` files) and ``studies.sqlite`` (the finished training jobs;
    a run with the same config reuses them). ``config`` is the TOML as a dict (the ``lcs-cvx
    study`` runner's ``kind = "module"`` protocol); the jobs run in this process
    (``workers = 1``), on ``workers`` local processes, or on the Dask ``scheduler``
    (``"local"`` or ``tcp://host:port``).
    """
    import torch

    import lcs_cvx
    from lcs_cvx.scaling import Scaling

    from . import evaluation as ev
    from .models import AffineModel, LCSModel, ModeAffineModel, mlp_from_result
    from .report import write_report

    torch.set_num_threads(1)
    t_start = time.perf_counter()
    code = code_version()
    cfg = parse_config(config)
    phys, lcfg = cfg["physics"], cfg["lcs"]
    horizons = [int(h) for h in cfg["eval"]["horizons"]]
    H = max(horizons)
    os.makedirs(os.path.join(out_dir, "models"), exist_ok=True)

    t0 = time.perf_counter()
    data = _data(cfg)
    train, val, test, wide = (data[k] for k in ("train", "validation", "test", "wide"))
    t_data = time.perf_counter() - t0
    _log(f"data: {len(train)} train + {len(val)} validation, {len(test)} test, {len(wide)} wide "
         f"({t_data:.1f} s); contact fraction "
         f"{np.concatenate([train.in_contact, val.in_contact]).mean():.3f}")

    scaling = Scaling.fit(lcs_cvx.Dataset.from_arrays(train.x, train.u, train.x_next))
    jobs, keys = training_jobs(cfg, scaling, train, val)
    t0 = time.perf_counter()
    results, run_now = run_jobs(jobs, out_dir, cfg["name"], workers, scheduler, log=_log)
    t_train = time.perf_counter() - t0
    _log(f"training done in {t_train:.0f} s")
    mlp_result = results.pop(len(jobs) // 2)
    restarts, chosen = _select(keys, results)

    models: dict[str, Any] = {}
    train_time: dict[str, float] = {}
    exported: dict[str, str] = {}
    for name, (res, (loss, n_lam, init, seed)) in chosen.items():
        model = LCSModel.from_matrices(res["matrices"])
        models[name] = model
        train_time[name] = sum(r["wall_time"] for r in restarts[name])
        path = os.path.join(out_dir, "models", f"lcs_{loss}_nlam{n_lam}.npz")
        lcs_cvx.save_model(model.lcs, path, metadata={
            "study": cfg["name"], "system": "cart-pole with soft walls (MuJoCo)",
            "state": list(STATE_NAMES), "state_units": list(STATE_UNITS), "input": ["force (N)"],
            "control_period_s": phys.control_period, "loss": loss, "n_lam": n_lam, "init": init,
            "seed": seed,
            "val_error": res["val_error"], "fit_settings": res["settings"],
        })
        exported[name] = os.path.relpath(path, out_dir)
    t0 = time.perf_counter()
    models["affine (least squares)"] = AffineModel.fit(train.x, train.u, train.x_next)
    train_time["affine (least squares)"] = time.perf_counter() - t0
    models["MLP"] = mlp_from_result(mlp_result, scaling, train.x.shape[1] + train.u.shape[1], train.x.shape[1])
    train_time["MLP"] = mlp_result["wall_time"]
    t0 = time.perf_counter()
    models["affine per true mode (oracle)"] = ModeAffineModel.fit(train.x, train.u, train.x_next, train.contact)
    train_time["affine per true mode (oracle)"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    sets = {"test": test, "wide-input test (1.5×)": wide}
    metrics, curves = _evaluate(models, sets, horizons, cfg["eval"]["active_tol"], train_time)
    restart_rows = []
    for name, entries in restarts.items():
        for e in entries:
            ok = e["result"]["matrices"] is not None
            m = LCSModel.from_matrices(e["result"]["matrices"]) if ok else None
            restart_rows.append({"model": name, "init": e["init"], "seed": e["seed"],
                                 "val_error": e["val_error"],
                                 "test_one_step": ev.one_step_errors(m, test) if ok else None,
                                 "selected": name in chosen and e["result"] is chosen[name][0],
                                 "error": e["result"].get("error"), "wall_time": e["wall_time"]})

    # figures: per loss the LCS with the lowest validation error, and the baselines
    start = ev.pick_contact_window(test, H)
    best_of = {}
    for loss in lcfg["losses"]:
        names = [n for n in chosen if f" {loss} " in n]
        if names:
            best_of[loss] = min(names, key=lambda n: chosen[n][0]["val_error"])
    fig_models = {n: models[n] for n in best_of.values()}
    for n in ("affine (least squares)", "MLP", "affine per true mode (oracle)"):
        fig_models[n] = models[n]
    if start is not None:
        ev.plot_rollouts(fig_models, test, start, H, phys, os.path.join(out_dir, "rollouts.png"),
                         f"Open-loop rollout of {H} steps through a wall contact (test window {start})")
    ev.plot_error_vs_horizon(curves, os.path.join(out_dir, "error_vs_horizon.png"), phys.control_period)
    t_eval = time.perf_counter() - t0

    wall = time.perf_counter() - t_start
    summary = {
        "config": {k: (dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v) for k, v in cfg.items()},
        "data": {name: {"n": len(d), "contact_fraction": float(d.in_contact.mean()),
                        "contact_fraction_per_wall": [float(f) for f in d.contact.mean(axis=0)],
                        "trajectories": int(len(np.unique(d.traj))), "windows_H": int(len(d.windows(H)))}
                 for name, d in {"train": train, "validation": val, **sets}.items()},
        "metrics": metrics,
        "restarts": restart_rows,
        "exported_models": exported,
        "n_lam_choice": _choose_n_lam(chosen, lcfg["losses"]),
        "fit_settings": {loss: next((chosen[n][0]["settings"] for n in chosen if f" {loss} " in n), None)
                         for loss in lcfg["losses"]},
        "rollout_window_start": start,
        "timing_s": {"data": t_data, "training": t_train, "evaluation": t_eval, "total": wall},
        "workers": workers,
        "scheduler": scheduler,
        "jobs": {"total": len(jobs), "run_now": run_now},
        "code": code,
        "machine": machine(),
    }
    with open(os.path.join(out_dir, "metrics.json"), "w") as f:
        json.dump(summary, f, indent=1, default=json_default)
    with open(os.path.join(out_dir, "report.md"), "w") as f:
        f.write(write_report(summary, cfg, horizons, best_of, config.get("name", cfg["name"])))
    _log(f"done in {wall:.0f} s; wrote {out_dir}/report.md")
