"""Cells trained as ensembles (``lcs-cvx study run CONFIG --ensemble``): the cells that differ only
in their seeds -- the trials of one swept value and method -- go to a worker together and are
trained in one :func:`lcs_cvx.fit_ensemble` loop.

Each cell keeps its own truth, data, initialisation and minibatch order (its seeds,
:func:`lcs_cvx.study.cells.cell_seeds`), and ``fit_ensemble`` trains every model exactly as
``fit`` trains it alone, so a cell's result is the one :func:`~lcs_cvx.study.cells.run_cell`
gives (its e_test and curve bit for bit on CPU; tested) and is stored the same way. What an
ensemble shares: its wall time (each cell records the ensemble's divided by its size) and its
warnings (each cell lists the ensemble's). The client stores the cells when the ensemble
finishes: an interrupted run loses the ensembles in flight, never a finished cell.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
import time
import warnings
from typing import Any

from ..system import ACTIVE_TOL
from .cells import setup_cell

__all__ = ["ensembles", "run_ensemble", "alone", "work", "ENSEMBLE_FIELDS"]

#: Cells that agree on these fields (all but their seeds and bookkeeping) train as one ensemble.
ENSEMBLE_FIELDS = ("system", "data", "learner", "recipe", "fit", "method")


def _group_key(cell: dict[str, Any]) -> str:
    return json.dumps({k: cell[k] for k in ENSEMBLE_FIELDS}, sort_keys=True, separators=(",", ":"))


def alone(cell: dict[str, Any]) -> bool:
    """Whether ``cell`` must run by itself (:func:`~lcs_cvx.study.cells.run_cell`): a baseline, or
    ``fit`` options the ensemble loop does not run (extra units, refinement, ...: see
    :func:`lcs_cvx.fit_ensemble`)."""
    from .._checks import LCSInputError
    from ..train import resolve_options
    from ..train.ensemble import check_supported

    if cell.get("baseline") is not None or cell.get("fit") is None:
        return True
    options = {k: tuple(v) if isinstance(v, list) else v for k, v in cell["fit"].items()}
    try:
        check_supported(resolve_options(cell["recipe"], **options))
    except LCSInputError:
        return True
    return False


def ensembles(cells: list[dict[str, Any]], size: int | None = None) -> list[dict[str, Any]]:
    """The jobs of ``cells``: each a dict ``{"key", "cells", "value", "trial", "method", "alone"}``
    of up to ``size`` cells (None: no limit) that differ only in their seeds; a cell that must run
    by itself (:func:`alone`) is a job of its own with ``alone = True``. ``key`` is the SHA-256 of
    the members' keys; ``value``, ``trial`` and ``method`` are the first member's (for messages).

    The ensembles come first, largest :func:`work` first, then the cells that run alone, each
    part in the order of the jobs' first cells: a pool that takes its jobs in this order starts
    the longest ensembles while the others still have work to fill in beside them, instead of
    ending on two long ones (longest-processing-time-first scheduling)."""
    groups: dict[str, list[dict[str, Any]]] = {}
    single: dict[str, bool] = {}
    for c in cells:
        by_itself = alone(c)
        key = c["key"] if by_itself else _group_key(c)
        groups.setdefault(key, []).append(c)
        single[key] = by_itself
    jobs = []
    for group, members in groups.items():
        step = 1 if single[group] else (size or len(members))
        for i in range(0, len(members), step):
            part = members[i : i + step]
            key = hashlib.sha256("".join(c["key"] for c in part).encode()).hexdigest()
            jobs.append({"key": key, "cells": part, "value": part[0]["value"],
                         "trial": part[0]["trial"], "method": part[0]["method"], "alone": single[group]})
    return sorted(jobs, key=lambda job: (job["alone"], 0 if job["alone"] else -work(job["cells"])))


def work(cells: list[dict[str, Any]]) -> int:
    """A proxy of the work of training ``cells`` (one ensemble), for ordering jobs only: cells x
    iterations x batch size x ``(n_x + n_u + n_lam)^2``, the size of a sample's products (a
    missing field counts 1)."""
    total = 0
    for c in cells:
        fit, system = c.get("fit") or {}, c.get("system") or {}
        n = sum(int(system.get(f, 0)) for f in ("n_x", "n_u", "n_lam")) or 1
        total += int(fit.get("iterations", 1)) * int(fit.get("batch_size", 1)) * n * n
    return total


def run_ensemble(job: dict[str, Any]) -> list[Any]:
    """Train the cells of ``job`` (:func:`ensembles`) as one ensemble (in a worker; one torch
    thread). Returns, per cell in order, the dict :func:`~lcs_cvx.study.cells.run_cell` returns
    for it, or the :class:`lcs_cvx.SolverError` of a cell whose training diverged (the other
    cells go on). A job of a cell that runs by itself (``job["alone"]``) is that cell's
    :func:`~lcs_cvx.study.cells.run_cell` (its time limit included)."""
    import torch

    from .. import fit_ensemble, relative_error
    from .cells import run_cell

    if job.get("alone"):
        return [run_cell(c) for c in job["cells"]]
    torch.set_num_threads(1)
    cells = job["cells"]
    K = len(cells)
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        setups = [setup_cell(c) for c in cells]
        options = setups[0][4]
        results = fit_ensemble([s[3] for s in setups], [s[1] for s in setups], tests=[s[2] for s in setups],
                               recipe=cells[0]["recipe"], seeds=[c["seeds"]["fit"] for c in cells],
                               throw=False, progress=False, **options)
        e_tests = [None if isinstance(r, Exception) else relative_error(r.model, s[2])
                   for r, s in zip(results, setups, strict=True)]
    wall = (time.perf_counter() - t0) / K
    said = sorted({f"{w.category.__name__}: {w.message}" for w in caught})[:20]
    out: list[Any] = []
    for (truth, train, _, _, _), result, e_test in zip(setups, results, e_tests, strict=True):
        if isinstance(result, Exception):
            out.append(result)
            continue
        out.append({
            "e_test": e_test,
            "final_loss": result.history[-1]["loss"] if result.history else float("nan"),
            "modes": int(torch.unique(train.lam > ACTIVE_TOL, dim=0).shape[0]),
            "sigma_min": truth.sigma_min,
            "fit_wall_time": result.wall_time / K,
            "wall_time": wall,
            "settings": result.settings.flat(),
            "curve": result.history,
            "warnings": said,
            "host": f"{socket.gethostname()}:{os.getpid()}",
        })
    return out
