r"""Measured with noise: the LCS against the least-squares affine map on held-out rollouts, when
the data are exact simulator states and when they are logged by a sensor (positions with noise,
velocities by finite differences; :mod:`studies.physics.sensor`).

Run with (one config per plant)::

    python -m studies.physics.noisy --config studies/configs/physics_cartpole_noisy.toml \
        --out studies/results/physics
    python -m studies.physics.noisy --config studies/configs/pusher_slider_noisy.toml \
        --out studies/results/pusher_slider

or ``lcs-cvx study run <config> --out <dir>``. It writes ``noisy.json`` and ``noisy.md`` into
``<dir>`` (the study's other results are untouched); ``--report-only`` rewrites ``noisy.md``
from ``noisy.json``. Each finished fit is kept in ``noisy.partial.json``: a run stopped half way
resumes with the fits it has.

For each sensor of ``[data] sensors`` (``"exact"``, the plant's noisy one and, to separate the
noise from the differencing, ``"differenced"``):

1. data: the training trajectories (``n_train`` transitions, every ``val_every``-th trajectory
   the validation set) and a test set (``n_test``), logged by the sensor
   (:func:`studies.physics.plant.sample_measured`,
   :func:`studies.physics.pusher_plant.sample_measured`), as :class:`lcs_cvx.Trajectories`;
   and the same test trajectories logged by the ``"differenced"`` sensor (exact positions,
   velocities by differences: the noise-free value of what a differencing sensor measures);
2. fits: per seed of ``[fit] seeds``, ``lcs_cvx.fit(LCS(n_x, n_u, n_lam, seed), train,
   validation=val, holdout_horizon=H, recipe=..., **options)`` with the one-step losses only
   (``rollout_horizon=None``) and with the simulation-error phase (``rollout_horizon=`` each of
   ``[fit] rollout_horizons``; ``"auto"``, fit's default: windows of ``H`` steps) -- the
   "default" fit is the latter with ``"auto"``;
3. scores: :attr:`lcs_cvx.FitResult.heldout_error` and
   :attr:`~lcs_cvx.FitResult.affine_heldout_error` (the ``H``-step rollout error on the held-out
   validation trajectories, measured data), :attr:`~lcs_cvx.FitResult.heldout_growth`, and
   :func:`lcs_cvx.rollout_error` on the test trajectories at ``[eval] horizons``: against the
   measured states (what a user can compute) and, for a noisy sensor, against the noise-free
   differenced states of the same trajectories (rollouts from the noise-free start). The affine
   map is the least-squares fit on the same training transitions (the one ``fit`` compares with).

Evaluation is on measured data: a model of logged states predicts logged states (for a
differencing sensor, mean velocities over the last period), so its rollouts are compared with
logged states -- the sensor's own (noisy) and, to separate the noise from the model, the
noise-free ones -- not with the simulator's instantaneous velocities.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import hashlib
import json
import os
import sys
import time
import tomllib
from typing import Any

import numpy as np

from .config import check_sections, section
from .provenance import json_default

__all__ = ["CONFIG_SECTIONS", "parse_config", "run_study", "main"]

CONFIG_SECTIONS = ("plant", "data", "fit", "eval", "run", "mlp")
_PLANTS = ("cartpole", "pusher")
_DATA_DEFAULTS = {"n_train": 6000, "n_test": 3000, "seed_train": 0, "seed_test": 1, "val_every": 10,
                  "sensors": ["exact"]}
_FIT_DEFAULTS = {"n_lam": 8, "seeds": [0], "recipe": "best", "options": {}, "rollout_horizons": ["auto"]}
_EVAL_DEFAULTS = {"horizons": [1, 5, 20]}
_RUN_DEFAULTS = {"date": None, "machine": None, "command": None}


def _log(msg: str) -> None:
    print(f"[noisy] {msg}", file=sys.stderr, flush=True)


def parse_config(config: dict[str, Any]) -> dict[str, Any]:
    """Check a config of this module (a dict as TOML reads it) and fill in the defaults:
    ``[plant] name`` (``"cartpole"`` or ``"pusher"``), ``[data]``, ``[fit]`` (``options``: more
    :func:`lcs_cvx.fit` keywords), ``[eval] horizons``, ``[mlp]`` (the MLP baseline's options,
    :func:`lcs_cvx.study.baselines.baseline_options`) and ``[run]`` (the date, machine and command
    written into the report)."""
    from lcs_cvx.study.baselines import baseline_options

    from .sensor import SENSORS

    check_sections(config, CONFIG_SECTIONS)
    plant = config.get("plant", {}).get("name")
    if plant not in _PLANTS:
        raise ValueError(f"config: plant.name: expected one of {list(_PLANTS)}, received {plant!r}")
    data = section(config, "data", _DATA_DEFAULTS)
    for s in data["sensors"]:
        if s not in SENSORS[plant]:
            raise ValueError(f"config: data.sensors: expected names among {sorted(SENSORS[plant])}, "
                             f"received {s!r}")
    fit = section(config, "fit", _FIT_DEFAULTS)
    horizons = [int(h) for h in section(config, "eval", _EVAL_DEFAULTS)["horizons"]]
    return {"name": config.get("name", f"{plant}_noisy"), "plant": plant, "data": data, "fit": fit,
            "eval": {"horizons": horizons}, "run": section(config, "run", _RUN_DEFAULTS),
            "mlp": baseline_options("mlp", config.get("mlp"), where="mlp")}


# -- data ---------------------------------------------------------------------------------------
def _plant(name: str) -> Any:
    from . import plant, pusher_plant

    return plant if name == "cartpole" else pusher_plant


def datasets(cfg: dict[str, Any], sensor: str) -> dict[str, Any]:
    """``train``, ``validation``, ``test`` (:class:`lcs_cvx.Trajectories` as ``sensor`` logs them)
    and ``test_clean`` (the test trajectories logged without noise: by the ``"differenced"``
    sensor; the test set itself for ``"exact"`` and ``"differenced"``), with the samples' counts."""
    mod, d = _plant(cfg["plant"]), cfg["data"]
    train_all = mod.sample_transitions(d["n_train"], d["seed_train"], sensor=sensor)
    test = mod.sample_transitions(d["n_test"], d["seed_test"], sensor=sensor)
    noise_free = sensor in ("exact", "differenced")
    clean = test if noise_free else mod.sample_transitions(d["n_test"], d["seed_test"], sensor="differenced")
    if not (np.array_equal(clean.traj, test.traj) and np.array_equal(clean.step, test.step)):
        raise RuntimeError("the noise-free test set does not hold the same samples as the measured one")
    is_val = train_all.traj % d["val_every"] == d["val_every"] - 1
    train, val = train_all.select(~is_val), train_all.select(is_val)
    return {"train": train.to_trajectories(), "validation": val.to_trajectories(), "test": test.to_trajectories(),
            "test_clean": clean.to_trajectories(),
            "counts": {k: {"transitions": len(v), "trajectories": int(len(np.unique(v.traj)))}
                       for k, v in (("train", train), ("validation", val), ("test", test))}}


# -- fits ---------------------------------------------------------------------------------------
def _affine_lcs(train: Any, like: Any) -> Any:
    """The least-squares affine map of ``train``'s transitions as an LCS with ``C = 0``."""
    from lcs_cvx.metrics import affine_lstsq
    from lcs_cvx.train.holdout import affine_lcs

    return affine_lcs(affine_lstsq(train.to_transitions()), like)


def _scores(model: Any, data: dict[str, Any], horizons: list[int]) -> dict[str, dict[str, float]]:
    """Validation: ``fit``'s held-out score (the rollout error at the longest horizon relative to
    the recorded change, each coordinate scaled by the training runs' spread of its change);
    test: the relative rollout errors at every horizon."""
    from lcs_cvx import rollout_error
    from lcs_cvx.scaling import Scaling
    from lcs_cvx.simulation_error import change_error

    H = max(horizons)
    scale = Scaling.fit(data["train"].to_transitions()).sy
    return {"validation": {str(H): change_error(model, data["validation"], H, scale)},
            "test": {str(h): e for h, e in rollout_error(model, data["test"], horizons).items()},
            "test_clean": {str(h): e for h, e in rollout_error(model, data["test_clean"], horizons).items()}}


def fit_one(cfg: dict[str, Any], data: dict[str, Any], seed: int, rollout_horizon: int | None) -> dict[str, Any]:
    """One :func:`lcs_cvx.fit` (module docstring, step 2) and its scores (step 3), as plain data."""
    import lcs_cvx

    f, horizons = cfg["fit"], cfg["eval"]["horizons"]
    H = max(horizons)
    train = data["train"]
    model = lcs_cvx.LCS(train.n_x, train.n_u, int(f["n_lam"]), seed=seed)
    # None: one-step losses only (the phase is on by default with trajectories)
    extra = {"rollout_horizon": None if rollout_horizon is None else
             rollout_horizon if rollout_horizon == "auto" else int(rollout_horizon)}
    t0 = time.perf_counter()
    try:
        res = lcs_cvx.fit(model, train, validation=data["validation"], holdout_horizon=H, recipe=f["recipe"],
                          seed=seed, progress=False, **{**f["options"], **extra})
    except lcs_cvx.SolverError as exc:
        return {"seed": seed, "rollout_horizon": rollout_horizon, "error": str(exc),
                "wall_time": time.perf_counter() - t0}
    wall = time.perf_counter() - t0
    return {"seed": seed, "rollout_horizon": rollout_horizon, "error": None, "wall_time": wall,
            "heldout_error": res.heldout_error, "affine_heldout_error": res.affine_heldout_error,
            "heldout_growth": res.heldout_growth, "affine_heldout_growth": res.affine_heldout_growth,
            "grows_more": res.grows_more, "beats_affine": res.beats_affine, "verdict": res.verdict,
            "refinement_kept": res.refinement_kept,
            "restart_scores": list(res.restart_scores), "scores": _scores(res.model, data, horizons)}


class _Stepper:
    """A baseline's ``step(x, u)`` with the attributes :func:`lcs_cvx.rollout_error` reads."""

    def __init__(self, model: Any, like: Any) -> None:
        import torch

        self.model, self.n_x, self.n_u = model, like.n_x, like.n_u
        self.dtype, self.device = torch.float64, torch.device("cpu")

    def step(self, x: Any, u: Any) -> Any:
        return self.model.step(x, u)


def fit_mlp(data: dict[str, Any], options: dict[str, Any], horizons: list[int], seed: int = 0) -> dict[str, Any]:
    """The MLP baseline (:mod:`lcs_cvx.study.baselines.mlp`: its grid tuned on held-out training
    transitions; ``options`` complete, the config's ``[mlp]``) on the training runs' transitions,
    and its scores as :func:`_scores`."""
    from lcs_cvx.study.baselines.mlp import fit as mlp_fit

    t0 = time.perf_counter()
    model, info = mlp_fit(data["train"].to_transitions(), options, seed=seed, modes=0)
    wall = time.perf_counter() - t0
    return {"hidden": info["hidden"], "lr": info["lr"], "wall_time": wall,
            "scores": _scores(_Stepper(model, data["train"]), data, horizons)}


def _key(cfg: dict[str, Any], sensor: str, seed: int, rollout_horizon: int | str | None) -> str:
    what = {k: cfg[k] for k in ("plant", "data", "fit", "eval")}
    what = {**what, "data": {k: v for k, v in what["data"].items() if k != "sensors"},
            "fit": {k: v for k, v in what["fit"].items() if k not in ("seeds", "rollout_horizons")}}
    text = json.dumps([what, sensor, seed, rollout_horizon], sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


# -- the study ----------------------------------------------------------------------------------
def run_study(config: dict[str, Any], out_dir: str, workers: int = 1, scheduler: str | None = None) -> None:
    """Run the comparison (module docstring) into ``out_dir``: ``noisy.json`` and ``noisy.md``.
    The fits run one after the other in this process, one torch thread (``workers`` and
    ``scheduler`` are accepted for the ``lcs-cvx study`` runner and not used)."""
    import torch

    import lcs_cvx

    from .provenance import machine

    torch.set_num_threads(1)
    cfg = parse_config(config)
    os.makedirs(out_dir, exist_ok=True)
    partial_path = os.path.join(out_dir, "noisy.partial.json")
    partial: dict[str, Any] = {}
    if os.path.exists(partial_path):
        with open(partial_path) as fh:
            partial = json.load(fh)
    t_start = time.perf_counter()
    H = max(cfg["eval"]["horizons"])
    per_sensor: dict[str, Any] = {}
    for sensor in cfg["data"]["sensors"]:
        t0 = time.perf_counter()
        data = datasets(cfg, sensor)
        _log(f"{sensor}: data in {time.perf_counter() - t0:.1f} s: {data['counts']}")
        like = lcs_cvx.LCS(data["train"].n_x, data["train"].n_u, 1)
        affine = _affine_lcs(data["train"], like)
        fits = []
        for seed in cfg["fit"]["seeds"]:
            for rh in [None, *cfg["fit"]["rollout_horizons"]]:
                key = _key(cfg, sensor, int(seed), rh)
                if key not in partial:
                    _log(f"{sensor}: fit seed {seed}, rollout_horizon {rh} ...")
                    partial[key] = fit_one(cfg, data, int(seed), rh)
                    with open(partial_path + ".tmp", "w") as fh:
                        json.dump(partial, fh, default=json_default)
                    os.replace(partial_path + ".tmp", partial_path)
                    r = partial[key]
                    _log(f"  {r.get('verdict', r.get('error'))} ({r['wall_time']:.0f} s)")
                fits.append(copy.deepcopy(partial[key]))
        key = _key(cfg, sensor, 0, "mlp:" + json.dumps(cfg["mlp"], sort_keys=True))
        if key not in partial:
            _log(f"{sensor}: the MLP baseline ...")
            partial[key] = fit_mlp(data, cfg["mlp"], cfg["eval"]["horizons"])
            with open(partial_path + ".tmp", "w") as fh:
                json.dump(partial, fh, default=json_default)
            os.replace(partial_path + ".tmp", partial_path)
        per_sensor[sensor] = {"counts": data["counts"], "affine": _scores(affine, data, cfg["eval"]["horizons"]),
                              "mlp": copy.deepcopy(partial[key]), "fits": fits}
    mod = _plant(cfg["plant"])
    from .sensor import sensor as get_sensor

    summary = {
        "config": cfg,
        "sensors": {s: dataclasses.asdict(get_sensor(cfg["plant"], s)) for s in cfg["data"]["sensors"]},
        "horizon": H,
        "state": list(mod.STATE_NAMES), "state_units": list(mod.STATE_UNITS),
        "results": per_sensor,
        "wall_time_s": time.perf_counter() - t_start,
        "fits_wall_time_s": sum(f["wall_time"] for v in per_sensor.values() for f in v["fits"]),
        "machine": machine(),
    }
    with open(os.path.join(out_dir, "noisy.json"), "w") as fh:
        json.dump(summary, fh, indent=1, default=json_default)
    write_noisy_report(summary, out_dir)
    _log(f"done in {summary['wall_time_s']:.0f} s; wrote {out_dir}/noisy.md")


def write_noisy_report(summary: dict[str, Any], out_dir: str) -> None:
    """``noisy.md`` from a summary (``noisy.json``), through the plant's report module."""
    if summary["config"]["plant"] == "cartpole":
        from .report import write_noisy_report as write
    else:
        from .pusher_report import write_noisy_report as write
    with open(os.path.join(out_dir, "noisy.md"), "w") as fh:
        fh.write(write(summary))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="LCS vs affine map on held-out rollouts, exact vs measured data.")
    ap.add_argument("--config", required=True, help="TOML config (studies/configs/physics_cartpole_noisy.toml)")
    ap.add_argument("--out", required=True, help="output directory (e.g. studies/results/physics)")
    ap.add_argument("--report-only", action="store_true", help="rewrite noisy.md from <out>/noisy.json")
    args = ap.parse_args(argv)
    if args.report_only:
        with open(os.path.join(args.out, "noisy.json")) as fh:
            write_noisy_report(json.load(fh), args.out)
        return 0
    with open(args.config, "rb") as fh:
        config = tomllib.load(fh)
    config.setdefault("name", os.path.splitext(os.path.basename(args.config))[0])
    run_study(config, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
