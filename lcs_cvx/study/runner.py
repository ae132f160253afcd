"""``lcs-cvx study run``: expand a config into cells, skip the finished ones, run the rest.

The client process expands the grid (:func:`lcs_cvx.study.cells.expand`), reads which cell keys
the database already holds, sends the others to an executor and writes every result to the
database the moment it arrives. Running a config again therefore resumes where it stopped and
redoes nothing finished. A cell that raised is logged in ``failures`` and retried on the next
run. A cell killed at the config's ``time_limit`` is stored with ``status = "timeout"`` and
counts as finished until the config asks for a larger limit (then it runs again). A baseline
whose own fitting algorithm failed on the cell's data (PARC at thousands of modes) is stored with
``status = "failed"``: the method's result on that problem, finished, never run again.

With ``ensemble=True`` (``--ensemble``) the cells to run are grouped into ensembles
(:mod:`lcs_cvx.study.batched_cells`: the trials of one swept value and method), each trained by one
worker in one batched loop; every finished cell is stored exactly as on its own, when its
ensemble finishes.

A ``kind = "module"`` config is handed to its module's ``run_study(config, out_dir, workers)``
(with ``scheduler=`` when one is given), which may use the same executors and store
(``studies/physics/jobs.py`` does).
"""

from __future__ import annotations

import importlib
import inspect
import os
import sys
import time
import traceback
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

from .._checks import LCSInputError
from .batched_cells import ensembles, run_ensemble
from .cells import expand
from .config import config_hash, load_config
from .executors import dask_cluster, process_pool
from .store import Store

__all__ = ["RunSummary", "StudyError", "run_config", "parse_only", "DEFAULT_OUT"]

#: Default output directory (ignored by git: results are written down by hand, with the command).
DEFAULT_OUT = os.path.join("out", "studies")
_ONLY_KEYS = ("value", "value_index", "trial", "method")


class StudyError(RuntimeError):
    """The run could not go on (a worker process died); what finished is in the database."""


@dataclass(frozen=True)
class RunSummary:
    """What one ``study run`` did: cells in the grid, already finished, run now (``timed_out``
    of them killed at the time limit, ``baseline_failed`` of them baselines whose own fit
    failed, recorded as ``"failed"``), failed (raised; logged in ``failures``)."""

    study: str
    config_hash: str
    database: str
    total: int
    skipped: int
    executed: int
    failed: int
    wall_time: float
    timed_out: int = 0
    baseline_failed: int = 0


def parse_only(text: str) -> dict[str, Any]:
    """``"value=4,trial=0,method=violation"`` -> a filter on cells (see :func:`run_config`)."""
    out: dict[str, Any] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        key, sep, val = part.partition("=")
        if not sep or key not in _ONLY_KEYS:
            raise LCSInputError(f"only: expected KEY=VALUE[,KEY=VALUE] with KEY in {_ONLY_KEYS}, "
                                f"received {text!r}")
        try:
            out[key] = val if key == "method" else (float(val) if key == "value" else int(val))
        except ValueError:
            raise LCSInputError(f"only: {key}: expected a number, received {val!r}") from None
    return out


def _matches(cell: dict[str, Any], only: dict[str, Any]) -> bool:
    return all(cell[k] is not None and cell[k] == v for k, v in only.items())


class _Progress:
    """One tqdm bar over the cells when stderr is a terminal; otherwise a plain line every
    ``every`` seconds (and at the end) with the count, the failures and an ETA."""

    def __init__(self, name: str, total: int, done: int, planned: int, enabled: bool,
                 every: float = 30.0):
        self.name, self.total, self.done, self.failed = name, total, done, 0
        self.planned = planned  # cells this run will try (--only, --max-cells: fewer than left)
        self.start, self.every, self.last = time.perf_counter(), every, 0.0
        self.run_now = 0
        self.bar = None
        self.enabled = enabled
        if enabled and sys.stderr.isatty():
            from tqdm.auto import tqdm

            self.bar = tqdm(total=done + planned, initial=done, desc=name, unit="cell",
                            dynamic_ncols=True)

    def update(self, ok: bool) -> None:
        self.done += ok
        self.failed += not ok
        self.run_now += 1
        if self.bar is not None:
            self.bar.update(1)
            if self.failed:
                self.bar.set_postfix(failed=self.failed)
        elif self.enabled and time.perf_counter() - self.last >= self.every:
            self.line()

    def line(self) -> None:
        elapsed = time.perf_counter() - self.start
        left = self.planned - self.run_now
        eta = f", ETA {elapsed / self.run_now * left:.0f} s" if self.run_now and left else ""
        print(f"{self.name}: {self.done}/{self.total} cells done, {self.failed} failed, "
              f"{elapsed:.0f} s elapsed{eta}", file=sys.stderr, flush=True)
        self.last = time.perf_counter()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _store(store: Store, config: dict[str, Any], cell: dict[str, Any], result: Any) -> str | None:
    """Write one cell's result, or log its failure (and say so on stderr); the status stored
    (``"ok"``, ``"timeout"``, ``"failed"``: a line on stderr for the last two), None for a
    logged failure."""
    where = f"value {cell['value']}, trial {cell['trial']}, {cell['method']}"
    if isinstance(result, BaseException):
        text = "".join(traceback.format_exception(result)).strip()
        store.add_failure(cell, text)
        print(f"{config['name']}: cell failed ({where}): {type(result).__name__}: {result}; "
              "logged in 'failures', retried by the next run", file=sys.stderr, flush=True)
        return None
    store.add_cell(cell, config["seed"], result)
    status = result.get("status", "ok")
    if status == "timeout":
        print(f"{config['name']}: cell timed out after {result['wall_time']:.0f} s ({where}); "
              "recorded as 'timeout'", file=sys.stderr, flush=True)
    elif status == "failed":
        print(f"{config['name']}: the method's own fit failed ({where}): "
              f"{result['settings'].get('error')}; recorded as 'failed'", file=sys.stderr,
              flush=True)
    return status


def _run_module(config: dict[str, Any], out: str, workers: int, scheduler: str | None) -> None:
    where = config["path"]
    if os.getcwd() not in sys.path:  # `studies.physics.x` from the repository root, also when
        sys.path.append(os.getcwd())  # run by the console script (whose sys.path[0] is its bin/)
    try:
        module = importlib.import_module(config["module"])
    except ImportError as exc:
        raise LCSInputError(f"{where}: module: cannot import {config['module']!r}: {exc}") from None
    run_study = getattr(module, "run_study", None)
    if not callable(run_study):
        raise LCSInputError(f"{where}: module: {config['module']!r} has no function "
                            "run_study(config, out_dir, workers)")
    body = {k: v for k, v in config.items() if k != "path"}
    if scheduler is None:
        run_study(body, out, workers)
        return
    if "scheduler" not in inspect.signature(run_study).parameters:
        raise LCSInputError(f"scheduler: {config['module']}.run_study runs its own executor (it "
                            "takes no scheduler argument); drop --scheduler")
    run_study(body, out, workers, scheduler=scheduler)


def run_config(
    path: str | os.PathLike,
    *,
    out: str | os.PathLike = DEFAULT_OUT,
    workers: int | None = None,
    scheduler: str | None = None,
    only: dict[str, Any] | None = None,
    max_cells: int | None = None,
    progress: bool = True,
    ensemble: bool = False,
    ensemble_size: int | None = None,
) -> RunSummary | None:
    """Run the study of the config at ``path`` into ``out`` (see the module docstring).

    Args:
        workers: local processes (process pool or ``scheduler="local"``); default: CPU count.
        scheduler: None (process pool), ``"local"`` (a Dask LocalCluster) or a Dask scheduler
            address ``tcp://host:port``; passed on to a module study whose ``run_study`` takes a
            ``scheduler`` keyword.
        only: run only cells matching ``{"value": 4.0, "trial": 0, "method": "violation"}``.
        max_cells: run at most this many unfinished cells (the rest on a later run).
        progress: a bar (terminal) or periodic lines on stderr.
        ensemble: train the cells that differ only in their seeds (a swept value's trials, one
            method) together, one ensemble per worker (:mod:`lcs_cvx.study.batched_cells`); the
            results are those of the cells run one by one.
        ensemble_size: at most this many cells per ensemble (None: a swept value's trials of
            one method); smaller ensembles share the work between more workers.

    Returns:
        A :class:`RunSummary`; None for a ``kind = "module"`` config (its module writes its own).
    """
    if ensemble_size is not None and not ensemble:
        raise LCSInputError(f"ensemble_size: applies to ensembles only (ensemble=True), received "
                            f"ensemble_size={ensemble_size!r} with ensemble=False")
    config = load_config(path)
    workers = workers or os.cpu_count() or 1
    out = os.fspath(out)
    if config["kind"] == "module":
        os.makedirs(out, exist_ok=True)
        _run_module(config, out, workers, scheduler)
        return None

    t0 = time.perf_counter()
    h = config_hash(config)
    cells = expand(config)
    if only and not any(_matches(c, only) for c in cells):
        raise LCSInputError(f"only: no cell of {config['name']} matches {only}")
    with Store(out) as store:
        store.add_study(h, config)
        finished = store.finished_keys(config.get("time_limit"))
        todo, seen = [], set()
        for c in cells:
            if c["key"] not in finished and c["key"] not in seen and _matches(c, only or {}):
                todo.append(c)
                seen.add(c["key"])
        skipped = sum(c["key"] in finished for c in cells)
        if max_cells is not None:
            todo = todo[:max_cells]
        bar = _Progress(config["name"], len(cells), skipped, len(todo), progress)
        stored: dict[str | None, int] = {}
        if todo:
            jobs, fn = (ensembles(todo, ensemble_size), run_ensemble) if ensemble else (todo, None)
            kw = {} if fn is None else {"fn": fn}
            executor = (process_pool(jobs, workers, **kw) if scheduler is None
                        else dask_cluster(jobs, scheduler, workers, **kw))
            try:
                with executor as outcomes:
                    for job, outcome in outcomes:
                        if isinstance(outcome, BrokenProcessPool):
                            raise StudyError(
                                f"a worker process died ({outcome}); the {bar.done} finished cells "
                                f"are in {store.path}: run the same command again to resume")
                        if not ensemble:
                            pairs: Any = [(job, outcome)]
                        elif isinstance(outcome, BaseException):  # the whole ensemble failed
                            pairs = [(c, outcome) for c in job["cells"]]
                        else:
                            pairs = zip(job["cells"], outcome, strict=True)
                        for cell, result in pairs:
                            status = _store(store, config, cell, result)
                            stored[status] = stored.get(status, 0) + 1
                            bar.update(not isinstance(result, BaseException))
            finally:
                bar.close()
        if progress and bar.bar is None:
            bar.line()
    return RunSummary(config["name"], h, store.path, len(cells), skipped, bar.done - skipped,
                      bar.failed, time.perf_counter() - t0, stored.get("timeout", 0),
                      stored.get("failed", 0))
