"""The records of C3's cart-pole study (:mod:`studies.control.cartpole_c3`): its settings,
controllers and initial states, and its units as JSON lines (one per initial state and
controller, the exact optimum per state, the batch run), read back by the study and its report
(:mod:`studies.control.cartpole_c3_report`)."""

from __future__ import annotations

import dataclasses
import datetime
import json
import os
import subprocess
from typing import Any

import numpy as np

__all__ = ["Settings", "initial_states", "unit_key", "load_records", "jsonable", "today", "CONTROLLERS", "OPTIONS", "LABELS",
           "FILE"]

#: half-widths of the box of initial states around the origin (cart position, pole angle,
#: cart velocity, pole angular velocity)
BOX = np.array([0.3, 0.6, 0.6, 0.6])
SEED = 0
TOL, HOLD = 0.1, 30
MACHINE = "2-core x86-64 VM, 1 torch thread"
#: controller name -> (projection, qp_path); None: the LQR baseline
CONTROLLERS: dict[str, tuple[str, str | None, int] | None] = {
    "c3+": ("c3+", "fast", 0), "lqr": None, "c3+ cvxpy": ("c3+", "cvxpy", 0), "qp": ("qp", None, 0),
    "miqp": ("miqp", None, 0), "miqp enum": ("miqp", None, 0), "lcp": ("lcp", "fast", 0), "auto": ("auto", "fast", 0),
    "defaults": ("auto", "fast", 3), "defaults, penalize_input_change": ("auto", "fast", 3),
}
#: other C3 options of a controller
OPTIONS = {"defaults, penalize_input_change": {"penalize_input_change": True}}
#: controllers whose projection is solved another way than by default
PROJECTION_SOLVER = {"miqp enum": "enumerate"}
LABELS = {"c3+": "C3, c3+ projection (fast path)", "c3+ cvxpy": "C3, c3+ projection (CVXPY QP path)",
          "qp": "C3, qp projection", "miqp": "C3, miqp projection (SCIP)",
          "miqp enum": "C3, miqp projection (active sets)", "lqr": "LQR ignoring contact",
          "lcp": "C3, lcp projection (the model's own forces)", "auto": "C3, auto projection (lcp or c3+), no polish",
          "defaults": "C3, defaults (auto, polished)",
          "defaults, penalize_input_change": "C3, defaults with penalize_input_change"}
COLORS = {"c3+": "C0", "c3+ cvxpy": "C4", "qp": "C2", "miqp": "C3", "miqp enum": "C1", "lqr": "C7", "lcp": "C5",
          "auto": "C6", "defaults": "C8", "defaults, penalize_input_change": "C9"}
#: states whose trajectories (cart position, pole angle) are stored and drawn
TRAJ_STATES = ("x0", "0", "1")
FILE = "cartpole_c3"


@dataclasses.dataclass(frozen=True)
class Settings:
    """How many states and steps each part gets (``--smoke``: a few seconds)."""

    states: int = 100
    miqp_states: int = 20
    cvxpy_states: int = 5
    check_states: int | None = None  # exact optima certified by enumerating every mode sequence (None: all)
    batch: int = 1000
    steps: int = 600  # c3+, lqr, the batch
    qp_steps: int = 600  # qp and c3+ cvxpy
    miqp_steps: int = 600
    miqp_stop_when_settled: bool = True  # a miqp run stops 30 steps after it settles
    report_every_phase: bool = True  # else only once, at the end

    @classmethod
    def smoke(cls, states: int = 3) -> Settings:
        return cls(states=states, miqp_states=0, cvxpy_states=0, check_states=1, batch=50, steps=300,
                   qp_steps=10, miqp_steps=1, report_every_phase=False)


def initial_states(n: int, seed: int = SEED) -> np.ndarray:
    """``n`` initial states uniform in ``[-BOX, BOX]``; the first ``k`` are the same for every
    ``n >= k`` (the per-state runs use the first ones of the batch run's states)."""
    return np.random.default_rng(seed).uniform(-BOX, BOX, (n, 4))


def unit_key(rec: dict[str, Any]) -> tuple[str, str, int]:
    return rec["controller"], str(rec["state"]), int(rec["steps"])


def load_records(path: str) -> list[dict[str, Any]]:
    """The finished units in ``path`` (a JSON line each; a torn last line is ignored)."""
    if not os.path.exists(path):
        return []
    out = []
    with open(path) as f:
        for line in f:
            line = line.strip()
            if not line:
                continue
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return out


def jsonable(v: Any) -> Any:
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(type(v).__name__)


def today() -> str:
    try:
        return subprocess.run(["date", "-u", "+%F"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d")
