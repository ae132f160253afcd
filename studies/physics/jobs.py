"""The training jobs of the physics study and where they run.

A job is a plain dict ``{"key", "function", "args"}``: ``function`` names a function of
:mod:`studies.physics.models` (``"fit_lcs"``, ``"fit_mlp"`` or ``"fit_parc"``) and ``args`` is its argument
(numpy arrays and plain values). Its ``key`` is the SHA-256 of ``function`` and ``args`` (arrays
by dtype, shape and bytes), so the same work has the same key in every run.

:func:`run_jobs` sends the jobs to an executor of :mod:`lcs_cvx.study.executors` -- this process
(``workers = 1``), a local process pool, or a Dask cluster (``scheduler``) -- and writes each
result to the study database (``<out_dir>/studies.sqlite``, table ``jobs``) the moment it
arrives. A job whose key the database already holds is not run again: an interrupted study,
run again with the same config, resumes where it stopped, and a finished one only redoes the
evaluation.
"""

from __future__ import annotations

import hashlib
import json
import traceback
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import numpy as np

__all__ = ["FUNCTIONS", "make_job", "job_key", "run_job", "run_jobs", "JobError"]

#: The job functions (in :mod:`studies.physics.models`).
FUNCTIONS = ("fit_lcs", "fit_mlp", "fit_parc")


class JobError(RuntimeError):
    """A job failed (its traceback in the message); the finished ones are in the database."""


def _feed(h: Any, value: Any) -> None:
    """Hash ``value`` canonically into ``h`` (dicts by sorted key, arrays by dtype/shape/bytes)."""
    if isinstance(value, np.ndarray):
        h.update(f"array:{value.dtype.str}:{value.shape}:".encode())
        h.update(np.ascontiguousarray(value).tobytes())
    elif isinstance(value, dict):
        h.update(b"dict:")
        for k in sorted(value):
            h.update(json.dumps(str(k)).encode() + b"=")
            _feed(h, value[k])
            h.update(b";")
    elif isinstance(value, (list, tuple)):
        h.update(b"list:")
        for v in value:
            _feed(h, v)
            h.update(b",")
    else:
        h.update(json.dumps(value).encode())


def job_key(function: str, args: dict[str, Any]) -> str:
    """SHA-256 (hex) of the job ``function(args)``; a tuple and the list of its items agree."""
    h = hashlib.sha256(f"{function}:".encode())
    _feed(h, args)
    return h.hexdigest()


def make_job(function: str, args: dict[str, Any]) -> dict[str, Any]:
    """The job ``function(args)`` with its key."""
    if function not in FUNCTIONS:
        raise ValueError(f"function: expected one of {FUNCTIONS}, received {function!r}")
    return {"key": job_key(function, args), "function": function, "args": args}


def run_job(job: dict[str, Any]) -> dict[str, Any]:
    """Run one job (in a worker): ``models.<function>(args)``."""
    from . import models

    return getattr(models, job["function"])(job["args"])


def _executor(jobs: list[dict[str, Any]], workers: int, scheduler: str | None) -> Any:
    from lcs_cvx.study.executors import dask_cluster, in_process, process_pool

    if scheduler is not None:
        return dask_cluster(jobs, scheduler, workers, fn=run_job)
    if workers <= 1:
        return in_process(jobs, fn=run_job)
    return process_pool(jobs, workers, fn=run_job)


def run_jobs(jobs: list[dict[str, Any]], out_dir: str, study: str, workers: int,
             scheduler: str | None = None, log: Any = None) -> tuple[list[dict[str, Any]], int]:
    """Results of ``jobs`` (in their order) and how many were run now; the others come from
    ``<out_dir>/studies.sqlite``, where every new result is written as it arrives.

    Args:
        workers: local processes (1: this process); with ``scheduler``, the size of a Dask
            ``"local"`` cluster.
        scheduler: None, ``"local"`` or a Dask scheduler address ``tcp://host:port``.
        log: a function taking one line of text (progress), or None.

    Raises:
        JobError: a job raised (or a worker process died); what finished is in the database.
    """
    from lcs_cvx.study.store import Store

    keys = [j["key"] for j in jobs]
    if len(set(keys)) != len(keys):
        raise ValueError("jobs: expected distinct jobs, received two with the same function and "
                         "arguments (the same key)")
    with Store(out_dir) as store:
        done = store.jobs(keys)
        todo = [j for j in jobs if j["key"] not in done]
        if log is not None:
            log(f"{len(done)} of {len(jobs)} jobs already in {store.path}; running {len(todo)} "
                + (f"on {scheduler}" if scheduler else f"on {workers} worker(s)"))
        if todo:
            with _executor(todo, workers, scheduler) as outcomes:
                for job, result in outcomes:
                    if isinstance(result, BaseException):
                        what = ("a worker process died" if isinstance(result, BrokenProcessPool)
                                else f"job {job['function']} failed")
                        text = "".join(traceback.format_exception(result)).strip()
                        raise JobError(f"{what}; {len(done)} finished jobs are in {store.path}: "
                                       f"run again to resume\n{text}") from None
                    store.add_job(job["key"], study, job["function"], result)
                    done[job["key"]] = result
                    if log is not None:
                        log(f"job {len(done)}/{len(jobs)} done ({job['function']})")
        # the stored form (tuples as lists), the same whether run now or read back
        results = store.jobs(keys)
    return [results[k] for k in keys], len(todo)
