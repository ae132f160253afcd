"""Where the cells run: a local process pool (default) or a Dask distributed cluster.

Both yield ``(cell, result_or_exception)`` as cells finish; results come back to the client,
which alone writes the database. Workers run ``fn(cell)``: by default
:func:`lcs_cvx.study.cells.run_cell` (a grid cell); a ``kind = "module"`` study passes its own
job function (a module-level function, imported by the workers, e.g.
``studies.physics.jobs.run_job``) and its jobs (dicts with a unique ``"key"``). Workers run one
torch thread, so a cell's result does not depend on where it ran.

- :func:`process_pool`: ``concurrent.futures.ProcessPoolExecutor`` with the ``forkserver`` start
  method (``spawn`` where there is none), the study modules preloaded, ``torch.set_num_threads(1)``
  in the initializer, and workers that end when the client process is gone.
- :func:`dask_cluster`: ``address="local"`` starts a ``LocalCluster`` on this machine
  (``n_workers=workers``, one thread each, non-daemonic processes, so that a cell with a time
  limit can start its child process); any other address (``tcp://host:8786``) connects to an
  existing scheduler (for time limits, its workers need ``distributed.worker.daemon: False``). The workers need ``lcs_cvx`` installed and, for a module
  study, its package importable (started from the repository root with ``PYTHONPATH=.``).
- :func:`in_process`: the cells one after another in this process (a module study's
  ``workers = 1``).
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import os
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from .cells import run_cell
from .limits import exit_with

__all__ = ["process_pool", "dask_cluster", "in_process"]

Outcome = tuple[dict[str, Any], Any]
#: The work of one cell: a module-level function (workers import it by name).
CellFn = Callable[[dict[str, Any]], Any]


def _init_worker(client: int) -> None:
    import torch

    torch.set_num_threads(1)
    threading.Thread(target=exit_with, args=(client,), daemon=True).start()


def _context() -> mp.context.BaseContext:
    if "forkserver" in mp.get_all_start_methods():
        ctx = mp.get_context("forkserver")
        # torch.optim's first Adam imports torch._dynamo (~2 s): once, in the server, not per worker
        ctx.set_forkserver_preload(["lcs_cvx", "lcs_cvx.study.cells", "lcs_cvx.study.batched_cells",
                                    "torch._dynamo"])
        return ctx
    return mp.get_context("spawn")


@contextmanager
def process_pool(cells: list[dict[str, Any]], workers: int,
                 fn: CellFn = run_cell) -> Iterator[Iterator[Outcome]]:
    """Run ``fn`` on each of ``cells`` on ``workers`` local processes; the iterator yields
    outcomes as they finish.

    Leaving the ``with`` block early (an exception, Ctrl-C) cancels the cells not yet started.
    """
    pool = cf.ProcessPoolExecutor(max_workers=max(1, min(workers, len(cells))),
                                  mp_context=_context(), initializer=_init_worker,
                                  initargs=(os.getpid(),))
    futures = {pool.submit(fn, c): c for c in cells}

    def outcomes() -> Iterator[Outcome]:
        for fut in cf.as_completed(futures):
            exc = fut.exception()
            yield futures[fut], (exc if exc is not None else fut.result())

    try:
        yield outcomes()
    except BaseException:  # Ctrl-C or an error in the client: stop the workers now
        for proc in list((getattr(pool, "_processes", None) or {}).values()):
            proc.terminate()
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown(wait=True)


@contextmanager
def dask_cluster(cells: list[dict[str, Any]], address: str, workers: int,
                 fn: CellFn = run_cell) -> Iterator[Iterator[Outcome]]:
    """Run ``fn`` on each of ``cells`` on a Dask cluster (``address`` ``"local"`` or
    ``tcp://host:port``); the iterator yields outcomes as they finish."""
    from .._checks import LCSInputError
    from .._optional import require

    distributed = require("dask.distributed", "studies", "lcs-cvx study run --scheduler")
    Client, LocalCluster, as_completed = (
        distributed.Client, distributed.LocalCluster, distributed.as_completed)

    cluster = None
    if address == "local":
        import dask

        # non-daemonic workers: a cell with a time limit runs in a child process
        with dask.config.set({"distributed.worker.daemon": False}):
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   host="127.0.0.1", dashboard_address=None)
        client = Client(cluster)
    else:
        try:
            client = Client(address, timeout=30)
        except (OSError, TimeoutError, ValueError) as exc:
            raise LCSInputError(f"scheduler: could not connect to {address!r}: {exc}") from None
    futures: dict[str, tuple[Any, dict[str, Any]]] = {}
    try:
        for c in cells:
            fut = client.submit(fn, c, key=f"cell-{c['key'][:32]}", pure=False)
            futures[fut.key] = (fut, c)

        def outcomes() -> Iterator[Outcome]:
            for fut in as_completed([f for f, _ in futures.values()]):
                cell = futures[fut.key][1]
                yield cell, (fut.result() if fut.status == "finished" else fut.exception())

        yield outcomes()
    finally:
        client.cancel([f for f, _ in futures.values()])
        client.close()
        if cluster is not None:
            cluster.close()


@contextmanager
def in_process(cells: list[dict[str, Any]], fn: CellFn = run_cell) -> Iterator[Iterator[Outcome]]:
    """Run ``fn`` on each of ``cells`` in this process, in order (no pool to start), with the
    caller's torch threads (set one for results equal to the workers'); an exception of a cell
    is its outcome, as on the other executors."""

    def outcomes() -> Iterator[Outcome]:
        for c in cells:
            try:
                result = fn(c)
            except Exception as exc:  # the cell's outcome, as a worker would report it
                result = exc
            yield c, result

    yield outcomes()
