"""Training logs of :func:`lcs_cvx.fit` (``log=``): a callback, or TensorBoard event files.

:func:`record_logger` turns ``fit``'s ``log`` argument into a function of one history record:
a callable is used as it is; a directory gets a :class:`TensorBoardLog`, which writes every
record through :class:`torch.utils.tensorboard.SummaryWriter` (the ``plot`` extra installs
``tensorboard``) and flushes it at once, so an interrupted run loses no record.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from typing import Any

from .._checks import LCSInputError
from .._optional import require

__all__ = ["TensorBoardLog", "record_logger", "SCALARS"]

#: The record's numbers written as TensorBoard scalars, each under ``restart_<k>/<name>``
#: (the step is the record's ``iteration``); ``phase`` is written as its index in
#: :data:`PHASE_NAMES` and, where it changes, as text.
SCALARS = ("loss", "heldout", "e_test", "lr", "eps", "wall_time", "n_fallback")

#: The phases as :func:`lcs_cvx.fit` names them in records, in the order a run goes through them.
PHASE_NAMES = ("adam", "prune", "gauss-newton", "newton", "polish", "rollout")


class TensorBoardLog:
    """TensorBoard event files in ``directory``, one scalar per record and name of
    :data:`SCALARS` (None and non-finite values are skipped: a diverged score is not a point)."""

    def __init__(self, directory: str | os.PathLike) -> None:
        require("tensorboard", "plot", "fit(..., log=DIRECTORY)")
        from torch.utils.tensorboard import SummaryWriter

        self.directory = os.fspath(directory)
        self.writer = SummaryWriter(log_dir=self.directory)
        self._phase: dict[int, str] = {}

    def __call__(self, record: dict[str, Any]) -> None:
        run, step = record.get("restart", 0), record["iteration"]
        for name in SCALARS:
            value = record.get(name)
            if value is not None and math.isfinite(float(value)):
                self.writer.add_scalar(f"restart_{run}/{name}", float(value), step)
        phase = record["phase"]
        self.writer.add_scalar(f"restart_{run}/phase",
                               float(PHASE_NAMES.index(phase)) if phase in PHASE_NAMES else -1.0, step)
        if self._phase.get(run) != phase:
            self.writer.add_text(f"restart_{run}/phase", phase, step)
            self._phase[run] = phase
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


def record_logger(log: Any) -> tuple[Callable[[dict[str, Any]], Any] | None, Callable[[], None]]:
    """``(log one record, close)`` for ``fit``'s ``log``: None, a callable of a record, or a
    directory (a path; created if missing) for TensorBoard events."""
    if log is None:
        return None, lambda: None
    if callable(log):
        return log, lambda: None
    if isinstance(log, (str, os.PathLike)):
        board = TensorBoardLog(log)
        return board, board.close
    raise LCSInputError(f"log: expected None, a callable of a history record or a directory for TensorBoard "
                        f"events, received {type(log).__name__}")
