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

__all__ = ["ensembles", "run_ensemble", "ENSEMBLE_FIELDS"]

#: Cells that agree on these fields (all but their seeds and bookkeeping) train as one ensemble.
ENSEMBLE_FIELDS = ("system", "data", "learner", "recipe", "fit", "method")


def _group_key(cell: dict[str, Any]) -> str:
    return json.dumps({k: cell[k] for k in ENSEMBLE_FIELDS}, sort_keys=True, separators=(",", ":"))


def ensembles(cells: list[dict[str, Any]], size: int | None = None) -> list[dict[str, Any]]:
    """The jobs of ``cells``: each a dict ``{"key", "cells", "value", "trial", "method"}`` of up to
    ``size`` cells (None: no limit) that differ only in their seeds, in the order of their first
    cell. ``key`` is the SHA-256 of the members' keys; ``value``, ``trial`` and ``method`` are the
    first member's (for messages)."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for c in cells:
        groups.setdefault(_group_key(c), []).append(c)
    jobs = []
    for members in groups.values():
        step = size or len(members)
        for i in range(0, len(members), step):
            part = members[i : i + step]
            key = hashlib.sha256("".join(c["key"] for c in part).encode()).hexdigest()
            jobs.append({"key": key, "cells": part, "value": part[0]["value"],
                         "trial": part[0]["trial"], "method": part[0]["method"]})
    return jobs


def run_ensemble(job: dict[str, Any]) -> list[Any]:
    """Train the cells of ``job`` (:func:`ensembles`) as one ensemble (in a worker; one torch
    thread). Returns, per cell in order, the dict :func:`~lcs_cvx.study.cells.run_cell` returns
    for it, or the :class:`lcs_cvx.SolverError` of a cell whose training diverged (the other
    cells go on)."""
    import torch

    from .. import fit_ensemble, relative_error

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
