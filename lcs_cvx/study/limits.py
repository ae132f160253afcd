"""A wall-clock time limit on one cell: run ``fn(arg, report)`` in a child process and kill it
when the limit is reached.

:func:`run_limited` starts a child process (the ``forkserver`` start method, with ``lcs_cvx``,
torch and -- where installed -- ``pyparc`` preloaded; ``spawn`` where there is no forkserver) in
its own process group. The child says when it starts, may report progress (``report(dict)``,
e.g. the hybrid modes of the data once it has drawn them), then sends its result or the
traceback of its exception. The limit counts from the child's start (its start-up, bounded by
:data:`STARTUP_S`, is not the cell's work); at the limit the child's process group is killed
(SIGKILL) and :class:`TimeLimitExceeded` is raised with what it had reported. The child also
ends itself when the process that started it is gone.

A Dask worker runs as a daemon process by default and may start no children: a cell with a time
limit then raises ``RuntimeError`` naming the setting (``distributed.worker.daemon: False``,
which :func:`lcs_cvx.study.executors.dask_cluster` sets for the clusters it starts).
"""

from __future__ import annotations

import importlib.util
import multiprocessing as mp
import os
import signal
import threading
import time
import traceback
from collections.abc import Callable
from typing import Any

__all__ = ["run_limited", "TimeLimitExceeded", "ChildError", "exit_with", "STARTUP_S"]

#: Seconds a child may take to start (import torch) before the limit starts counting.
STARTUP_S = 120.0


class TimeLimitExceeded(Exception):
    """The child ran past ``limit`` seconds and was killed.

    Attributes:
        limit: the limit (s).
        elapsed: seconds from the child's start to its kill.
        since_report: seconds from its last progress report to its kill (None: none came).
        reported: its last progress report (``{}``: none came).
    """

    def __init__(self, limit: float, elapsed: float, since_report: float | None,
                 reported: dict[str, Any]) -> None:
        super().__init__(f"time limit of {limit:g} s reached (killed after {elapsed:.1f} s)")
        self.limit, self.elapsed, self.since_report, self.reported = limit, elapsed, since_report, reported


class ChildError(RuntimeError):
    """The child raised (the message holds its traceback) or died without a result."""


def exit_with(pid: int, every: float = 2.0) -> None:
    """End this process (``os._exit(1)``) once process ``pid`` is gone; run it in a daemon
    thread. For workers and children whose parent may be killed with SIGKILL."""
    while True:
        time.sleep(every)
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            os._exit(1)
        except PermissionError:  # it exists
            pass


def _context() -> mp.context.BaseContext:
    if "forkserver" not in mp.get_all_start_methods():
        return mp.get_context("spawn")
    ctx = mp.get_context("forkserver")
    preload = ["lcs_cvx", "lcs_cvx.study.cells", "torch._dynamo"]
    if importlib.util.find_spec("pyparc") is not None:
        preload.append("pyparc.parc")
    ctx.set_forkserver_preload(preload)  # no effect once this process's forkserver runs
    return ctx


def _child(fn: Callable[..., Any], arg: Any, conn: Any, parent: int) -> None:
    try:
        os.setpgrp()  # the parent kills the whole group (and anything the cell started)
    except (AttributeError, OSError):
        pass
    threading.Thread(target=exit_with, args=(parent,), daemon=True).start()
    conn.send(("started", None))
    try:
        result = fn(arg, lambda info: conn.send(("progress", info)))
    except BaseException:
        conn.send(("error", traceback.format_exc()))
    else:
        conn.send(("result", result))
    finally:
        conn.close()


def _kill(proc: Any) -> None:
    if proc.is_alive():
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except (AttributeError, ProcessLookupError, PermissionError):
            proc.kill()
    proc.join()


def run_limited(fn: Callable[[Any, Callable[[dict[str, Any]], None]], Any], arg: Any,
                limit: float) -> Any:
    """``fn(arg, report)`` in a child process, killed after ``limit`` seconds (module docstring).

    ``fn`` is a module-level function (the child imports it by name); ``arg`` and its result are
    pickled; ``report(info)`` sends a progress dict to this process.

    Raises:
        TimeLimitExceeded: the child ran past ``limit`` (it is killed first).
        ChildError: the child raised (its traceback in the message) or died without a result.
        RuntimeError: the child could not be started (a daemonic process: a Dask worker with
            ``distributed.worker.daemon`` true) or did not start within :data:`STARTUP_S`.
    """
    if not (isinstance(limit, (int, float)) and limit > 0):
        raise ValueError(f"limit: expected a number of seconds > 0, received {limit!r}")
    ctx = _context()
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(fn, arg, send, os.getpid()), name="lcs-cvx-cell")
    try:
        proc.start()
    except AssertionError as exc:  # "daemonic processes are not allowed to have children"
        recv.close()
        send.close()
        raise RuntimeError(
            f"time_limit: a cell with a time limit runs in a child process, and this process may "
            f"start none ({exc}); on Dask, run the workers with distributed.worker.daemon: False "
            "(environment DASK_DISTRIBUTED__WORKER__DAEMON=False)") from None
    send.close()
    started = last = None
    finished = False
    reported: dict[str, Any] = {}
    deadline = time.monotonic() + STARTUP_S
    try:
        while True:
            left = deadline - time.monotonic()
            if left <= 0 or not recv.poll(left):
                now = time.monotonic()
                if started is None:
                    raise RuntimeError(f"time_limit: the cell's process did not start within "
                                       f"{STARTUP_S:g} s")
                raise TimeLimitExceeded(limit, now - started,
                                        None if last is None else now - last, reported)
            try:
                kind, payload = recv.recv()
            except EOFError:
                proc.join(5.0)
                raise ChildError(f"the cell's process ended without a result (exit code "
                                 f"{proc.exitcode})") from None
            if kind == "started":
                started = time.monotonic()
                deadline = started + limit
            elif kind == "progress":
                reported, last = payload, time.monotonic()
            elif kind == "result":
                finished = True
                return payload
            else:
                raise ChildError(f"the cell raised in its process:\n{payload}")
    finally:
        recv.close()
        if finished:
            proc.join(10.0)  # a child that sent its result ends by itself
        _kill(proc)
