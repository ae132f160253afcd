"""The cells of a grid study and the work of one cell (paper Sec. 5, Fig. 1).

A cell is one training round: draw the ground truth ``theta*`` (:func:`lcs_cvx.random_lcs`), the
noisy training set and the noiseless test set (:func:`lcs_cvx.make_dataset`), initialise the
learner (:class:`lcs_cvx.LCS`), train it with one loss (:func:`lcs_cvx.fit`) and measure e_test.
A baseline method (:mod:`lcs_cvx.study.baselines`) fits its own model to the same data instead.

Time limit. A config's ``time_limit`` runs each cell in a child process killed at the limit
(:mod:`lcs_cvx.study.limits`); a killed cell's result has ``status = "timeout"``, no e_test, the
hybrid modes of its data and the seconds it ran, and is stored like a finished one.

Failed baselines. A baseline whose own fitting algorithm fails on the cell's data (PARC with
thousands of modes; :class:`lcs_cvx.study.baselines.BaselineFailed`) gives a result with
``status = "failed"``: no e_test, the error in its settings. It is a finished cell -- the method's
result on that problem -- stored once, never retried, and shown in the reports.

Seeds. Every random draw of a cell has its own seed, derived from the config's ``seed``, the swept
value's index ``i`` and the trial ``t`` only::

    seed[stream] = int(SeedSequence([seed, i, t, stream]).generate_state(1, uint32)[0])
    stream: 0 truth, 1 training data, 2 test data, 3 initialisation, 4 fit (minibatch order)

The method is not an input, so both methods of a ``(value, trial)`` train on the same truth and
data from the same initialisation. With ``sweep.shared_truth`` (a sweep of a fit option, Fig. 1(d),
(e)) ``i`` is replaced by 0: every value of a trial -- and its reference cells -- shares them.

A cell is a plain JSON-able dict (it travels to process-pool and Dask workers); its key is the
SHA-256 of its canonical JSON without the bookkeeping fields, so identical work is never repeated.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
import time
import warnings
from typing import Any

import numpy as np

from .._checks import LCSInputError
from ..system import ACTIVE_TOL
from ..train.recipes import RECIPE_VERSIONS
from .baselines import BASELINES, BaselineFailed
from .config import config_hash, fit_options, method_parts

__all__ = ["STREAMS", "cell_seeds", "expand", "cell_key", "setup_cell", "run_cell", "work",
           "REFERENCE"]

STREAMS = ("truth", "train", "test", "init", "fit")
#: ``value_index`` of a reference cell (trained once per trial, independent of the swept value).
REFERENCE = -1
#: Fields of a cell that name it but do not change its result (left out of its key).
_BOOKKEEPING = ("study", "config_hash", "value_index", "value", "trial", "time_limit")


def cell_seeds(seed: int, value_index: int, trial: int) -> dict[str, int]:
    """The five seeds of a cell (see the module docstring), each in ``[0, 2**32)`` (``fit``
    multiplies its seed by ~10^6 before seeding a torch generator, which takes 64 bits)."""
    return {
        name: int(np.random.SeedSequence([seed, value_index, trial, k]).generate_state(1, np.uint32)[0])
        for k, name in enumerate(STREAMS)
    }


def cell_key(cell: dict[str, Any]) -> str:
    """SHA-256 (hex) of the cell's canonical JSON, bookkeeping fields left out."""
    body = {k: v for k, v in cell.items() if k not in _BOOKKEEPING}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def _cell(config: dict, h: str, index: int, value: Any, trial: int, method: str) -> dict[str, Any]:
    sweep = config["sweep"]
    sections = {s: dict(config[s]) for s in ("system", "data", "learner")}
    if value is not None and not sweep["param"].startswith("fit."):
        section, key = sweep["param"].split(".", 1)
        sections[section][key] = value
    slot = 0 if sweep["shared_truth"] else index
    cell = {
        "study": config["name"], "config_hash": h, "value_index": index, "value": value,
        "trial": trial, "method": method, "seeds": cell_seeds(config["seed"], slot, trial),
        **sections,
    }
    if method in BASELINES:
        cell.update(recipe=None, fit=None, baseline=config["baselines"][method])
    else:
        recipe = method_parts(method, config["recipe"])[1]
        cell.update(recipe=recipe, fit=fit_options(config, method, value))
        if recipe is not None and RECIPE_VERSIONS[recipe] > 1:  # keys of version 1 unchanged
            cell["recipe_version"] = RECIPE_VERSIONS[recipe]
    if config.get("time_limit") is not None:
        cell["time_limit"] = config["time_limit"]
    return cell


def expand(config: dict[str, Any]) -> list[dict[str, Any]]:
    """Every cell of a grid config: trial-major (so a partial run covers every value early),
    then value, then method; reference cells (``value_index = REFERENCE``) first in each trial.
    A method of ``method_trials`` has cells in its first ``method_trials[method]`` trials only."""
    h = config_hash(config)
    cells = []
    per_method = config.get("method_trials", {})
    for trial in range(config["trials"]):
        for method in config["reference_methods"]:
            if trial < per_method.get(method, config["trials"]):
                cells.append(_cell(config, h, REFERENCE, None, trial, method))
        for i, value in enumerate(config["sweep"]["values"]):
            for method in config["methods"]:
                if trial < per_method.get(method, config["trials"]):
                    cells.append(_cell(config, h, i, value, trial, method))
    for c in cells:
        c["key"] = cell_key(c)
    return cells


def setup_cell(cell: dict[str, Any]) -> tuple[Any, Any, Any, Any, dict[str, Any]]:
    """What a cell trains on, drawn from its seeds: ``(truth, train, test, learner, options)``,
    with ``options`` the keyword arguments of :func:`lcs_cvx.fit` besides ``recipe`` and
    ``seed`` (``cell["recipe"]``, ``cell["seeds"]["fit"]``); ``{}`` for a baseline cell."""
    from .. import LCS, make_dataset, random_lcs

    s, d, ln, seeds = cell["system"], cell["data"], cell["learner"], cell["seeds"]
    truth = random_lcs(s["n_x"], s["n_u"], s["n_lam"], stiffness=s["stiffness"],
                       seed=seeds["truth"], g_scale=s["g_scale"])
    scales = {"x_scale": d["x_scale"], "u_scale": d["u_scale"]}
    train = make_dataset(truth, d["n_train"], noise=d["noise"], seed=seeds["train"], **scales)
    test = make_dataset(truth, d["n_test"], noise=0.0, seed=seeds["test"], **scales)
    learner = LCS(s["n_x"], s["n_u"], s["n_lam"], stiffness=ln["stiffness"],
                  init_scale=ln["init_scale"], seed=seeds["init"])
    options = {k: tuple(v) if isinstance(v, list) else v for k, v in (cell["fit"] or {}).items()}
    return truth, train, test, learner, options


def run_cell(cell: dict[str, Any]) -> dict[str, Any]:
    """Run one cell (in a worker; one torch thread) and return its metrics and curve: the
    result of :func:`work`, in a child process killed at ``cell["time_limit"]`` where the
    config sets one (then a killed cell returns ``status = "timeout"``, see below). A baseline
    whose own fit failed returns ``status = "failed"`` (see :func:`work`), with or without a
    limit.

    A timed-out cell's result: ``status`` ``"timeout"``, ``e_test`` and ``final_loss`` None,
    ``modes`` and ``sigma_min`` of its data (None if it was killed before drawing them),
    ``fit_wall_time`` (s from the end of the setup to the kill) and ``wall_time`` (s from the
    child's start to the kill), ``time_limit``, empty ``settings``, ``curve`` and ``warnings``.
    """
    limit = cell.get("time_limit")
    if limit is None:
        return work(cell)
    from .limits import TimeLimitExceeded, run_limited

    try:
        return run_limited(work, cell, limit)
    except TimeLimitExceeded as exc:
        setup = exc.reported
        return {
            "status": "timeout", "e_test": None, "final_loss": None,
            "modes": setup.get("modes"), "sigma_min": setup.get("sigma_min"),
            "fit_wall_time": exc.since_report, "wall_time": exc.elapsed, "time_limit": limit,
            "settings": {}, "curve": [], "warnings": [],
            "host": f"{socket.gethostname()}:{os.getpid()}",
        }


def work(cell: dict[str, Any], report: Any = None) -> dict[str, Any]:
    """The work of one cell, in this process: draw its truth and data, fit its method, measure.

    ``report``, if given, is called once with ``{"modes", "sigma_min"}`` when the data are drawn
    (before the fit), so that a time-limited cell killed in its fit still records them.

    Returns a dict: ``status`` ``"ok"``, ``e_test`` (the paper's mean relative prediction error
    on the noiseless test set, :func:`lcs_cvx.relative_error`), ``final_loss`` (None for a
    baseline), ``modes`` (distinct active sets of the truth on the training inputs),
    ``sigma_min`` (``sigma_min(F + F^T)`` of the truth), ``fit_wall_time`` and ``wall_time``
    (s; the latter includes drawing the data), ``settings`` (the resolved ``FitOptions``, or a
    baseline's options and what its fit chose), ``curve`` (``fit``'s history; empty for a
    baseline), ``warnings`` (distinct warning messages) and ``host``.

    A baseline whose own fitting algorithm fails (``BaselineFailed`` of
    :mod:`lcs_cvx.study.baselines`, e.g. PARC at thousands of modes) is a result, not an
    error: ``status`` ``"failed"``, ``e_test`` and ``final_loss`` None, ``modes`` and
    ``sigma_min`` as above, ``fit_wall_time`` (s from the start of the fit to the failure),
    ``settings`` (the baseline's options and ``"error"``: the failure's message), empty
    ``curve``, ``warnings`` as above. (A timed-out cell, :func:`run_cell`, has ``status = "timeout"``.) Any other
    exception propagates (the runner logs it in ``failures`` and retries the cell).
    """
    import torch

    from .. import fit, relative_error

    torch.set_num_threads(1)  # reproducible and no oversubscription (DESIGN.md)
    t0 = time.perf_counter()
    status, e_test = "ok", None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        truth, train, test, learner, options = setup_cell(cell)
        # = count_modes(truth, train), without solving the (possibly stiff) LCPs again
        modes = int(torch.unique(train.lam > ACTIVE_TOL, dim=0).shape[0])
        if report is not None:
            report({"modes": modes, "sigma_min": truth.sigma_min})
        if cell["method"] in BASELINES:
            from .baselines import fit_baseline
            from .baselines.parc import import_parc

            if cell["method"] == "parc":
                import_parc()  # imported before the clock starts, as lcs_cvx is for the others
            t_fit = time.perf_counter()
            try:
                model, info = fit_baseline(cell["method"], cell["baseline"], train,
                                           seed=cell["seeds"]["fit"], modes=modes)
            except BaselineFailed as exc:  # the method's result on this problem
                model, info, status = None, {"error": str(exc)}, "failed"
            fit_time = time.perf_counter() - t_fit
            settings, final_loss, curve = {**cell["baseline"], **info}, None, []
        else:
            version = RECIPE_VERSIONS.get(cell["recipe"], 1) if cell["recipe"] else 1
            if cell.get("recipe_version", 1) != version:  # e.g. a worker with other code
                raise LCSInputError(
                    f"recipe_version: cell {cell['key'][:12]} was made for version "
                    f"{cell.get('recipe_version', 1)} of recipe {cell['recipe']!r}; this "
                    f"installation has version {version}")
            result = fit(learner, train, test=test, recipe=cell["recipe"], progress=False,
                         seed=cell["seeds"]["fit"], **options)
            model, fit_time, curve = result.model, result.wall_time, result.history
            settings = result.settings.flat()
            final_loss = result.kept_history[-1]["loss"] if result.history else float("nan")
        if model is not None:
            e_test = relative_error(model, test)
    return {
        "status": status,
        "e_test": e_test,
        "final_loss": final_loss,
        "modes": modes,
        "sigma_min": truth.sigma_min,
        "fit_wall_time": fit_time,
        "wall_time": time.perf_counter() - t0,
        "settings": settings,
        "curve": curve,
        "warnings": sorted({f"{w.category.__name__}: {w.message}" for w in caught})[:20],
        "host": f"{socket.gethostname()}:{os.getpid()}",
    }
