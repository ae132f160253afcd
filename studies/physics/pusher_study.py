r"""The pusher-slider study: learn LCSs of the MuJoCo pusher-slider
(:mod:`studies.physics.pusher_plant`) from data and compare them with baselines along a learning
curve.

:func:`run_study` (config ``studies/configs/pusher_slider.toml``, the ``lcs-cvx study`` runner's
``kind = "module"`` protocol):

1. data: one stream of training trajectories, a test set and a wide-input test set, each from
   its own seed; every ``val_every``-th trajectory of the stream is held out for validation. For a
   training size ``n`` of ``data.sizes`` the training set is the first ``n`` training samples and
   its validation set the held-out trajectories interleaved with them (:func:`split_sizes`; the
   sets are nested: a larger size extends a smaller one). By default the samples hold the
   simulator's states; with ``[data] sensor = "mocap"`` every set is logged as motion capture
   would log it (:mod:`studies.physics.sensor`: jittered positions, velocities by finite
   differences);
2. training: per size, one :func:`lcs_cvx.fit` per ``(loss, n_lam, seed)`` (the library normalises
   the data and starts the model itself; the model comes back in physical units), one MLP per
   point of the ``[mlp]`` grid and one PARC fit (``[parc]``: piecewise-affine regression and
   classification on the raw ``[x, u] -> x'`` data, :func:`studies.physics.models.fit_parc`,
   by default with K = 4 pieces, the number of true contact modes, and the authors' other
   settings) -- the jobs of :mod:`studies.physics.jobs`, run on an
   :mod:`lcs_cvx.study.executors` executor and stored in ``<out>/studies.sqlite`` as they finish
   (a second run resumes, running only what is missing);
3. selection, per size, on the validation set alone: per ``(loss, n_lam)`` the restart with the
   lowest one-step validation error; per loss the ``n_lam`` that
   :func:`lcs_cvx.selection.choose` picks from those errors; the MLP grid point with the lowest
   one-step validation error (the same relative error as the LCS's). PARC has one fit per size
   (nothing to select). The affine least-squares model and the per-mode oracle are fitted here;
4. evaluation (:mod:`studies.physics.evaluation`): one-step error per true contact mode and
   open-loop rollout errors on the test and wide-input sets, for every size (the rollouts are
   :func:`studies.physics.evaluation.rollout_errors` rather than :func:`lcs_cvx.rollout_error`
   because the mode oracle must be told the true mode of every step; at the longest horizon the
   two agree, the tests check it); the target check
   (LCS against MLP), the figures (:mod:`studies.physics.pusher_figures`), ``metrics.json`` and
   ``report.md`` (:mod:`studies.physics.pusher_report`).

The results do not depend on the executor: every job runs one torch thread from its own seeds.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from typing import Any

import numpy as np

from lcs_cvx.study.baselines import OPTIONS as BASELINE_OPTIONS
from lcs_cvx.study.baselines import baseline_options

from .config import check_sections, from_table, lcs_section, section
from .jobs import make_job, run_jobs
from .pusher_plant import (
    INPUT_NAMES,
    MODES,
    STATE_NAMES,
    STATE_UNITS,
    Physics,
    PusherTransitions,
    Sampling,
    sample_transitions,
)
from .sensor import SENSORS

__all__ = ["CONFIG_SECTIONS", "BASELINES", "PARC", "parse_config", "split_sizes", "run_study"]

CONFIG_SECTIONS = ("physics", "sampling", "data", "lcs", "mlp", "parc", "eval")
#: PARC's name in the tables.
PARC = "PARC (piecewise-affine regression)"
#: The baselines, in the order of the tables.
BASELINES = ("affine (least squares)", "MLP", "affine per true mode (oracle)", PARC)

_DATA_DEFAULTS = {"sizes": [500, 2000, 10000, 20000], "n_test": 5000, "n_wide": 5000, "seed_train": 0,
                  "seed_test": 1, "seed_wide": 2, "wide_factor": 1.5, "val_every": 10, "sensor": "exact"}
_LCS_DEFAULTS = {"n_lam": [4, 8, 16, 24], "losses": ["violation", "prediction"], "seeds": [0, 1],
                 "tolerance": 0.1, "init": ["increment", "affine"], "stiffness": 1.0, "init_scale": 0.1,
                 "violation": {"recipe": "best", "iterations": 16000, "keep_best": True},
                 "prediction": {"recipe": "paper", "normalize": True, "lr": 5e-3, "iterations": 16000,
                                "keep_best": True}}
_MLP_DEFAULTS = {"hidden": [[64, 64], [128, 128], [64, 64, 64]], "weight_decay": [0.0, 1e-4],
                 "iterations": 20000, "batch_size": 256, "lr": 3e-3, "seed": 0}
#: The options of :mod:`lcs_cvx.study.baselines.parc` (the authors' settings), K = the four true
#: contact modes, and the seed of its k-means++ starts.
_PARC_DEFAULTS = {**{k: default for k, (default, _) in BASELINE_OPTIONS["parc"].items()}, "K": len(MODES), "seed": 0}
_EVAL_DEFAULTS = {"horizons": [1, 5, 20], "target": 1.5}


def _log(msg: str) -> None:
    print(f"[pusher_slider] {msg}", file=sys.stderr, flush=True)


def _distinct_list(where: str, value: Any, integers: bool, at_least: float) -> list:
    kind = (int,) if integers else (int, float)
    if (not isinstance(value, list) or not value or len(set(value)) != len(value)
            or any(isinstance(v, bool) or not isinstance(v, kind) or v < at_least for v in value)):
        raise ValueError(f"config: {where}: expected a non-empty list of distinct "
                         f"{'integers' if integers else 'numbers'} >= {at_least:g}, received {value!r}")
    return value


def parse_config(config: dict[str, Any]) -> dict[str, Any]:
    """Check a study config (a dict as TOML reads it) and fill in the defaults."""
    check_sections(config, CONFIG_SECTIONS)
    data = section(config, "data", _DATA_DEFAULTS)
    data["sizes"] = sorted(_distinct_list("data.sizes", data["sizes"], True, 2))
    if data["sensor"] not in SENSORS["pusher"]:
        raise ValueError(f"config: data.sensor: expected one of {sorted(SENSORS['pusher'])}, "
                         f"received {data['sensor']!r}")
    mlp = section(config, "mlp", _MLP_DEFAULTS)
    if not isinstance(mlp["hidden"], list) or not mlp["hidden"] or not all(
            isinstance(h, list) and h and all(isinstance(w, int) and w >= 1 for w in h) for h in mlp["hidden"]):
        raise ValueError(f"config: mlp.hidden: expected a list of layer-width lists such as [[64, 64]], "
                         f"received {mlp['hidden']!r}")
    _distinct_list("mlp.weight_decay", mlp["weight_decay"], False, 0)
    parc = section(config, "parc", _PARC_DEFAULTS)
    seed = parc.pop("seed")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"config: parc.seed: expected an integer >= 0, received {seed!r}")
    parc = {**baseline_options("parc", parc, where="config"), "seed": seed}
    return {
        "name": config.get("name", "pusher_slider"),
        "physics": from_table(Physics, config.get("physics"), "config: [physics]"),
        "sampling": from_table(Sampling, config.get("sampling"), "config: [sampling]"),
        "data": data,
        "lcs": lcs_section(config, _LCS_DEFAULTS),
        "mlp": mlp,
        "parc": parc,
        "eval": section(config, "eval", _EVAL_DEFAULTS),
    }


# -- data --------------------------------------------------------------------------------------
def split_sizes(stream: PusherTransitions, sizes: list[int], val_every: int
                ) -> dict[int, tuple[PusherTransitions, PusherTransitions]]:
    """Per training size ``n``: the first ``n`` samples of the stream's training trajectories
    (every trajectory but each ``val_every``-th) and, for validation, the held-out trajectories
    among the stream's first ``m`` trajectories, ``m`` the number the training samples reach
    into, rounded up to a multiple of ``val_every`` (so at least one)."""
    is_val = stream.traj % val_every == val_every - 1
    train_all, val_all = stream.select(~is_val), stream.select(is_val)
    if len(train_all) < max(sizes):
        raise ValueError(f"data.sizes: the stream holds {len(train_all)} training samples, "
                         f"fewer than the largest size {max(sizes)}")
    out = {}
    for n in sizes:
        train = train_all.select(np.arange(len(train_all)) < n)
        reach = -(-(int(train.traj[-1]) + 1) // val_every) * val_every
        out[n] = (train, val_all.select(val_all.traj < reach))
    return out


def _data(cfg: dict[str, Any]) -> tuple[dict[int, tuple[PusherTransitions, PusherTransitions]], dict[str, PusherTransitions]]:
    phys, samp, d = cfg["physics"], cfg["sampling"], cfg["data"]
    k = d["val_every"]
    n_stream = math.ceil(max(d["sizes"]) * k / (k - 1) * 1.05) + k * samp.traj_len  # a margin for short trajectories
    sensor = d["sensor"]
    stream = sample_transitions(n_stream, d["seed_train"], phys, samp, sensor=sensor)
    tests = {"test": sample_transitions(d["n_test"], d["seed_test"], phys, samp, sensor=sensor),
             f"wide-input test ({d['wide_factor']:g}×)":
                 sample_transitions(d["n_wide"], d["seed_wide"], phys, samp, d["wide_factor"], sensor=sensor)}
    return split_sizes(stream, d["sizes"], k), tests


# -- training jobs -----------------------------------------------------------------------------
def _jobs(cfg: dict[str, Any], splits: dict[int, tuple[PusherTransitions, PusherTransitions]], scalings: dict[int, Any]
          ) -> tuple[list[dict[str, Any]], list[tuple]]:
    """The jobs of every size (the largest size and ``n_lam`` first: the slowest start first),
    and a tag per job: ``("lcs", size, loss, n_lam, init, seed)``, ``("mlp", size, hidden,
    weight_decay)`` or ``("parc", size)``; the restarts of an ``(n_lam, loss)`` are every start
    ``init`` with every seed."""
    from .models import encode

    lc, mc = cfg["lcs"], cfg["mlp"]
    parc = dict(cfg["parc"])
    parc_seed = parc.pop("seed")
    jobs, tags = [], []
    for n in sorted(splits, reverse=True):
        train, val = splits[n]
        data = {"x": train.x, "u": train.u, "x_next": train.x_next, "x_val": val.x, "u_val": val.u,
                "x_next_val": val.x_next}
        for n_lam in sorted(lc["n_lam"], reverse=True):
            for loss in lc["losses"]:
                opts = dict(lc[loss])
                recipe = opts.pop("recipe")
                for init in lc["init"]:
                    for seed in lc["seeds"]:
                        jobs.append(make_job("fit_lcs", {
                            **data, "n_lam": int(n_lam), "loss": loss, "recipe": recipe,
                            "options": opts, "stiffness": lc["stiffness"],
                            "init_scale": lc["init_scale"], "init": init, "seed": int(seed)}))
                        tags.append(("lcs", n, loss, int(n_lam), init, int(seed)))
        z, v, y = encode(scalings[n], train.x, train.u, train.x_next)
        zv, vv, yv = encode(scalings[n], val.x, val.u, val.x_next)
        for hidden in mc["hidden"]:
            for wd in mc["weight_decay"]:
                jobs.append(make_job("fit_mlp", {
                    "z": z, "v": v, "y": y, "z_val": zv, "v_val": vv, "y_val": yv, "hidden": hidden,
                    "weight_decay": float(wd), **{k: mc[k] for k in ("iterations", "batch_size", "lr", "seed")}}))
                tags.append(("mlp", n, tuple(hidden), float(wd)))
        jobs.append(make_job("fit_parc", {"x": train.x, "u": train.u, "x_next": train.x_next, "options": parc,
                                          "modes": len(MODES), "seed": int(parc_seed)}))
        tags.append(("parc", n))
    return jobs, tags


# -- selection ---------------------------------------------------------------------------------
def _select(cfg: dict[str, Any], tags: list[tuple], results: list[dict[str, Any]],
            splits: dict[int, tuple[PusherTransitions, PusherTransitions]], scalings: dict[int, Any]
            ) -> tuple[dict[int, dict[str, Any]], dict[int, dict[str, Any]]]:
    """Per size: the chosen models (``"LCS, <loss> loss"``, ``"MLP"`` and ``"PARC"``, each
    ``(validation error, model, result)``) and the selection record (every restart's and grid
    point's validation error, the n_λ chosen, PARC's fit: its validation error, wall time, the
    fit's ``info`` and the ``error`` of a fit that failed)."""
    from lcs_cvx.selection import choose

    from . import evaluation as ev
    from .models import LCSModel, mlp_from_result, parc_from_result

    n_x, n_u = len(STATE_NAMES), len(INPUT_NAMES)
    chosen: dict[int, dict[str, Any]] = {n: {} for n in splits}
    record: dict[int, dict[str, Any]] = {n: {"lcs": [], "mlp": [], "n_lam": {}, "parc": None} for n in splits}
    best: dict[tuple[int, str, int], tuple[float, dict[str, Any], int]] = {}
    for tag, res in zip(tags, results, strict=True):
        n, val = tag[1], splits[tag[1]][1]
        if tag[0] == "lcs":
            _, _, loss, n_lam, init, seed = tag
            record[n]["lcs"].append({"loss": loss, "n_lam": n_lam, "init": init, "seed": seed,
                                     "val_error": res["val_error"],
                                     "wall_time": res["wall_time"], "error": res.get("error")})
            key = (n, loss, n_lam)
            if res["matrices"] is not None and (key not in best or res["val_error"] < best[key][0]):
                best[key] = (res["val_error"], res, f"{init} {seed}")
        elif tag[0] == "parc":
            rec = {"val_error": None, "wall_time": res["wall_time"], "info": res["info"], "error": res["error"]}
            if res["error"] is None:
                model = parc_from_result(res)
                rec["val_error"] = ev.relative_error(model.predict(val.x, val.u), val.x_next)
                chosen[n]["PARC"] = (rec["val_error"], model, res)
            else:
                _log(f"size {n}: PARC failed: {res['error']}")
            record[n]["parc"] = rec
        else:
            model = mlp_from_result(res, scalings[n], n_x + n_u, n_x)
            err = ev.relative_error(model.predict(val.x, val.u), val.x_next)
            record[n]["mlp"].append({"hidden": list(tag[2]), "weight_decay": tag[3], "val_error": err,
                                     "wall_time": res["wall_time"]})
            if "MLP" not in chosen[n] or err < chosen[n]["MLP"][0]:
                chosen[n]["MLP"] = (err, model, res["wall_time"])
    for n in splits:
        for loss in cfg["lcs"]["losses"]:
            errors = {k[2]: v[0] for k, v in best.items() if k[:2] == (n, loss)}
            if not errors:
                _log(f"size {n}, {loss} loss: every restart failed")
                continue
            n_lam = choose(errors, cfg["lcs"]["tolerance"])
            err, res, seed = best[(n, loss, n_lam)]
            record[n]["n_lam"][loss] = {"chosen": n_lam, "seed": seed,
                                        "val_error": {str(k): v for k, v in sorted(errors.items())}}
            chosen[n][f"LCS, {loss} loss"] = (err, LCSModel.from_matrices(res["matrices"]), res)
    return chosen, record


# -- evaluation --------------------------------------------------------------------------------
def _rows(models: dict[str, Any], sets: dict[str, PusherTransitions], horizons: list[int],
          failed: dict[str, str]) -> tuple[dict[str, list[dict[str, Any]]], dict[str, dict[str, np.ndarray]]]:
    """Per set, one row per model (one-step error per mode, rollout errors, ``"error": None``)
    and one per model whose fit ``failed`` (``{name: error}``: no numbers, its ``"error"``), and
    the rollout error curves."""
    from . import evaluation as ev

    H = max(horizons)
    rows: dict[str, list[dict[str, Any]]] = {}
    curves: dict[str, dict[str, np.ndarray]] = {}
    for set_name, data in sets.items():
        rows[set_name], curves[set_name] = [], {}
        for name, model in models.items():
            errs = ev.rollout_errors(model, data, H)
            curves[set_name][name] = errs
            rows[set_name].append({"name": name, "one_step": ev.mode_errors(model, data, MODES),
                                   "rollout": {str(h): float(errs[h - 1]) for h in horizons},
                                   "rollout_curve": [float(e) for e in errs], "error": None})
        rows[set_name] += [{"name": name, "one_step": None, "rollout": None, "rollout_curve": None, "error": err}
                           for name, err in failed.items()]
    return rows, curves


def target_check(per_size: dict[str, Any], losses: list[str], H: int, factor: float) -> list[dict[str, Any]]:
    """Per size, set and loss: how many times lower the LCS's one-step contact error and
    ``H``-step rollout error are than the MLP's, and whether both reach ``factor``."""
    out = []
    for n, entry in per_size.items():
        for set_name, rows in entry["sets"].items():
            by = {r["name"]: r for r in rows}
            mlp = by.get("MLP")
            for loss in losses:
                lcs = by.get(f"LCS, {loss} loss")
                if lcs is None or mlp is None:
                    continue
                contact = _ratio(mlp["one_step"]["contact"], lcs["one_step"]["contact"])
                rollout = _ratio(mlp["rollout"][str(H)], lcs["rollout"][str(H)])
                out.append({"size": int(n), "set": set_name, "loss": loss, "contact_ratio": contact,
                            "rollout_ratio": rollout, "met": contact >= factor and rollout >= factor})
    return out


def _ratio(baseline: float, ours: float) -> float:
    """``baseline / ours`` (how many times lower ours is); 0 where ours diverged, inf where the
    baseline did and ours did not."""
    if not math.isfinite(ours):
        return 0.0
    if not math.isfinite(baseline):
        return math.inf
    return baseline / ours if ours > 0 else math.inf


# -- the study ---------------------------------------------------------------------------------
def run_study(config: dict[str, Any], out_dir: str, workers: int = 2, scheduler: str | None = None) -> None:
    """Run the whole study (data, training, selection, evaluation, report) into ``out_dir``.

    Writes ``report.md``, ``metrics.json``, ``learning_curve.png``, ``error_vs_horizon.png``,
    ``rollouts.png``, ``models/lcs_<loss>_n<size>.npz`` (the chosen LCSs in physical units,
    :func:`lcs_cvx.save_model` files) and ``studies.sqlite`` (the finished training jobs; a run
    with the same config reuses them). ``config`` is the TOML as a dict (the ``lcs-cvx study``
    runner's ``kind = "module"`` protocol); the jobs run in this process (``workers = 1``), on
    ``workers`` local processes, or on the Dask ``scheduler`` (``"local"`` or ``tcp://host:port``).
    """
    import torch

    import lcs_cvx
    from lcs_cvx.scaling import Scaling
    from lcs_cvx.study.baselines.parc import import_parc

    from . import evaluation as ev
    from . import pusher_figures as figs
    from .models import AffineModel, ModeAffineModel
    from .provenance import code_version, json_default, machine
    from .pusher_report import write_report

    torch.set_num_threads(1)
    t_start = time.perf_counter()
    cfg = parse_config(config)
    import_parc()  # before any training: PARC needs the extra "baselines"
    phys, lc, horizons = cfg["physics"], cfg["lcs"], [int(h) for h in cfg["eval"]["horizons"]]
    H, sizes = max(horizons), cfg["data"]["sizes"]
    os.makedirs(os.path.join(out_dir, "models"), exist_ok=True)

    t0 = time.perf_counter()
    splits, sets = _data(cfg)
    t_data = time.perf_counter() - t0
    _log(f"data ({t_data:.1f} s): sizes {sizes}, validation "
         f"{[len(splits[n][1]) for n in sizes]}, " + ", ".join(f"{k} {len(v)}" for k, v in sets.items()))
    scalings = {n: Scaling.fit(lcs_cvx.Dataset.from_arrays(tr.x, tr.u, tr.x_next)) for n, (tr, _) in splits.items()}
    jobs, tags = _jobs(cfg, splits, scalings)
    t0 = time.perf_counter()
    results, run_now = run_jobs(jobs, out_dir, cfg["name"], workers, scheduler, log=_log)
    t_train = time.perf_counter() - t0
    chosen, record = _select(cfg, tags, results, splits, scalings)

    t0 = time.perf_counter()
    per_size: dict[str, Any] = {}
    exported: dict[str, str] = {}
    for n in sizes:
        train = splits[n][0]
        models = {f"LCS, {loss} loss": chosen[n][f"LCS, {loss} loss"][1] for loss in lc["losses"]
                  if f"LCS, {loss} loss" in chosen[n]}
        models["affine (least squares)"] = AffineModel.fit(train.x, train.u, train.x_next)
        if "MLP" in chosen[n]:
            models["MLP"] = chosen[n]["MLP"][1]
        models["affine per true mode (oracle)"] = ModeAffineModel.fit(train.x, train.u, train.x_next, train.contact)
        failed = {}
        if "PARC" in chosen[n]:
            models[PARC] = chosen[n]["PARC"][1]
        elif record[n]["parc"] is not None:
            failed[PARC] = record[n]["parc"]["error"]
        rows, curves = _rows(models, sets, horizons, failed)
        per_size[str(n)] = {"n_train": len(train), "n_validation": len(splits[n][1]), "sets": rows,
                            "selection": record[n]}
        for loss, sel in record[n]["n_lam"].items():
            path = os.path.join(out_dir, "models", f"lcs_{loss}_n{n}.npz")
            res = chosen[n][f"LCS, {loss} loss"][2]
            lcs_cvx.save_model(models[f"LCS, {loss} loss"].lcs, path, metadata={
                "study": cfg["name"], "system": "pusher-slider (MuJoCo)", "state": list(STATE_NAMES),
                "state_units": list(STATE_UNITS), "input": list(INPUT_NAMES),
                "control_period_s": phys.control_period, "loss": loss, "n_lam": sel["chosen"],
                "seed": sel["seed"], "n_train": n, "val_error": chosen[n][f"LCS, {loss} loss"][0],
                "fit_settings": res["settings"]})
            exported[f"LCS, {loss} loss, N = {n}"] = os.path.relpath(path, out_dir)
    test = sets["test"]  # the figures show the largest size: the last of the loop
    start = ev.pick_contact_window(test, H)
    figs.plot_learning_curve(per_size, H, os.path.join(out_dir, "learning_curve.png"))
    ev.plot_error_vs_horizon(curves, os.path.join(out_dir, "error_vs_horizon.png"), phys.control_period)
    if start is not None:
        figs.plot_rollout(models, test, start, H, phys, os.path.join(out_dir, "rollouts.png"))
    t_eval = time.perf_counter() - t0

    summary = {
        "config": {k: (dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v) for k, v in cfg.items()},
        "data": _data_summary(splits, sets, H),
        "sizes": per_size,
        "target": target_check(per_size, lc["losses"], H, cfg["eval"]["target"]),
        "exported_models": exported,
        "fit_settings": {loss: next((r[2]["settings"] for name, r in chosen[sizes[-1]].items()
                                     if name == f"LCS, {loss} loss"), None) for loss in lc["losses"]},
        "rollout_window_start": start,
        "timing_s": {"data": t_data, "training": t_train, "evaluation": t_eval,
                     "total": time.perf_counter() - t_start,
                     "jobs_cpu": sum(r["wall_time"] for r in results)},
        "workers": workers,
        "scheduler": scheduler,
        "jobs": {"total": len(jobs), "run_now": run_now},
        "code": code_version(),
        "machine": machine(),
    }
    with open(os.path.join(out_dir, "metrics.json"), "w") as f:
        json.dump(summary, f, indent=1, default=json_default)
    with open(os.path.join(out_dir, "report.md"), "w") as f:
        f.write(write_report(summary, cfg))
    _log(f"done in {summary['timing_s']['total']:.0f} s; wrote {out_dir}/report.md")


def _data_summary(splits: dict[int, tuple[PusherTransitions, PusherTransitions]], sets: dict[str, PusherTransitions],
                  H: int) -> dict[str, Any]:
    """Samples, trajectories, mode fractions and ``H``-step windows of every set."""
    named = {f"train (N = {n})": tr for n, (tr, _) in splits.items()}
    named[f"validation (N = {max(splits)})"] = splits[max(splits)][1]
    named.update(sets)
    return {name: {"n": len(d), "trajectories": int(len(np.unique(d.traj))), "windows_H": int(len(d.windows(H))),
                   "modes": {m: float((d.contact == k).mean()) for k, m in enumerate(MODES)}}
            for name, d in named.items()}
