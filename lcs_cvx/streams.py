"""Timestamped streams on one clock: what a robot log holds, as :class:`lcs_cvx.Trajectories`.

A log records each quantity at its own rate (joint encoders at 1 kHz, motion capture at
100--240 Hz, commands at the controller's rate). An LCS steps at one period ``dt``, so
:func:`align` puts every :class:`Stream` on the grid ``t_k = t_0 + k dt`` of the span all
streams cover:

- a state stream by linear interpolation between its two neighbouring samples,
  ``x(t) = x_i + (t - t_i) (x_{i+1} - x_i) / (t_{i+1} - t_i)``;
- an input stream zero-order held, ``u(t) = u_i`` for ``t_i <= t < t_{i+1}``, as a controller
  applies a command until the next (its last sample for one step ``dt`` past it: the last
  state needs no input);
- a run is split where any stream has a gap longer than ``max_gap`` (interpolating across it
  would invent the motion in between), and a piece shorter than one step is dropped.

Nothing is dropped silently: :class:`Description` counts what was resampled, split and dropped,
with each stream's measured period; :meth:`lcs_cvx.Trajectories.describe` prints it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ._checks import LCSInputError

__all__ = ["Stream", "Description", "align", "SNAP"]

#: A sample this many steps ``dt`` from a grid point or closer is at it (:func:`align`).
SNAP = 1e-4


@dataclass(frozen=True)
class Stream:
    """One recorded quantity: ``t`` ``(N,)`` seconds, ``values`` ``(N, k)``, ``kind`` ``"state"``
    (interpolated) or ``"input"`` (held); ``names`` of its ``k`` columns; ``run`` the run it
    belongs to (a file's episode or group)."""

    name: str
    t: np.ndarray
    values: np.ndarray
    kind: str
    names: tuple[str, ...]
    run: str = ""

    def __post_init__(self) -> None:
        if self.kind not in ("state", "input"):
            raise LCSInputError(f"kind: expected 'state' or 'input', received {self.kind!r}")
        t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        v = np.asarray(self.values, dtype=np.float64)
        v = v.reshape(len(v), -1) if v.ndim != 2 else v
        if len(t) != len(v):
            raise LCSInputError(f"{self._where}: expected one time stamp per sample, received {len(t)} "
                                f"time stamps and {len(v)} samples")
        if len(self.names) != v.shape[1]:
            raise LCSInputError(f"{self._where}: expected {v.shape[1]} column names, received {len(self.names)}")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "values", v)

    @property
    def _where(self) -> str:
        return f"stream {self.name!r}" + (f" of run {self.run!r}" if self.run else "")

    @property
    def period(self) -> float:
        """The median interval between time stamps (s; nan with fewer than two samples)."""
        return float(np.median(np.diff(self.t))) if len(self.t) > 1 else math.nan


@dataclass(frozen=True)
class Description:
    """What :func:`align` did. ``streams``: per stream, ``(name, samples, median period (s),
    span (s), gaps)``; ``dt`` the common period; ``runs`` the runs made and ``transitions`` in
    them; ``splits`` where gaps cut a run; ``dropped_pieces`` pieces shorter than one step;
    ``dropped_nan`` samples dropped for NaN (``drop_nan=True``); ``source`` the file read."""

    dt: float
    streams: tuple[tuple[str, int, float, float, int], ...] = ()
    runs: int = 0
    transitions: int = 0
    splits: int = 0
    dropped_pieces: int = 0
    dropped_nan: int = 0
    source: str = ""

    def merge(self, other: Description) -> Description:
        """This run's description with another run's counts added."""
        return dataclasses.replace(
            self, streams=self.streams + other.streams, runs=self.runs + other.runs,
            transitions=self.transitions + other.transitions, splits=self.splits + other.splits,
            dropped_pieces=self.dropped_pieces + other.dropped_pieces,
            dropped_nan=self.dropped_nan + other.dropped_nan)

    def __str__(self) -> str:
        lines = [f"{self.source}: " if self.source else ""]
        lines[0] += (f"{self.runs} runs, {self.transitions} transitions on one clock of dt = {self.dt:.6g} s "
                     f"({1 / self.dt:.6g} Hz)")
        rates: dict[str, list[float]] = {}
        for name, _, period, _, _ in self.streams:
            rates.setdefault(name, []).append(period)
        for name, periods in rates.items():
            n = sum(s[1] for s in self.streams if s[0] == name)
            gaps = sum(s[4] for s in self.streams if s[0] == name)
            p = float(np.nanmedian(periods)) if not all(math.isnan(q) for q in periods) else math.nan
            lines.append(f"  {name}: {n} samples, median period {p:.6g} s ({1 / p:.6g} Hz)"
                         + (f", {gaps} gaps" if gaps else "") + (" -- resampled" if not math.isclose(p, self.dt, rel_tol=1e-6) else ""))
        lines.append(f"  split at {self.splits} gaps; dropped {self.dropped_pieces} pieces shorter than one step "
                     f"and {self.dropped_nan} samples with NaN")
        return "\n".join(lines)


def _checked(stream: Stream, drop_nan: bool) -> tuple[Stream, int]:
    """The stream with increasing time stamps and finite values (NaN rows dropped with
    ``drop_nan``, else refused by run and time)."""
    t, v = stream.t, stream.values
    bad = ~np.isfinite(v).all(axis=1) | ~np.isfinite(t)
    if bad.any() and not drop_nan:
        i = int(np.flatnonzero(bad)[0])
        raise LCSInputError(f"{stream._where}: expected finite values, received {int(bad.sum())} samples with "
                            f"NaN/inf, the first at t = {t[i]:.6g} s (sample {i}); pass drop_nan=True to drop them")
    t, v = t[~bad], v[~bad]
    back = np.flatnonzero(np.diff(t) <= 0)
    if len(back):
        i = int(back[0])
        raise LCSInputError(f"{stream._where}: expected increasing time stamps, received t = {t[i]:.9g} s then "
                            f"{t[i + 1]:.9g} s (samples {i}, {i + 1})")
    if len(t) < 2:
        raise LCSInputError(f"{stream._where}: expected at least two samples, received {len(t)}")
    return dataclasses.replace(stream, t=t, values=v), int(bad.sum())


def _resample(s: Stream, grid: np.ndarray, dt: float) -> np.ndarray:
    """``s`` on ``grid`` (inside its span): interpolated (state) or held (input). A grid point
    within :data:`SNAP` steps of a sample takes that sample as it is (time stamps rounded to
    nanoseconds or to float32 are not moved off the grid by their rounding)."""
    tol = SNAP * dt
    i = np.clip(np.searchsorted(s.t, grid + tol, side="right") - 1, 0, len(s.t) - 1)  # last at or before
    if s.kind == "input":
        return s.values[i]
    out = np.stack([np.interp(grid, s.t, s.values[:, j]) for j in range(s.values.shape[1])], axis=1)
    near = np.abs(s.t[i] - grid) <= tol
    out[near] = s.values[i[near]]
    return out


def align(streams: Sequence[Stream], dt: float | None = None, max_gap: float | None = None,
          drop_nan: bool = False, run: str = "") -> tuple[list[tuple[np.ndarray, np.ndarray]], Description]:
    """The streams of one run on one clock: ``([(xs, us), ...], description)``, one pair per
    piece between gaps, ``xs`` ``(T + 1, n_x)`` (the state streams side by side, in order),
    ``us`` ``(T, n_u)`` (the inputs at ``t_0 .. t_{T-1}``).

    Args:
        streams: the run's :class:`Stream` s (at least one state stream).
        dt: the common period (s); default: the slowest stream's median period. At most that
            (a longer step would skip recorded samples of that stream).
        max_gap: a gap between two samples of a stream longer than this splits the run
            (default: 5 times that stream's median period).
        drop_nan: drop samples with NaN or inf (counted) instead of refusing them.
        run: the run's name, for messages.
    """
    checked, nan = [], 0
    for s in streams:
        c, n = _checked(s, drop_nan)
        checked.append(c)
        nan += n
    if not any(s.kind == "state" for s in checked):
        raise LCSInputError(f"state: expected at least one state stream in run {run!r}, received none")
    slowest = max(s.period for s in checked)
    if dt is None:
        dt = slowest
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not math.isfinite(dt) or dt <= 0:
        raise LCSInputError(f"dt: expected a number > 0, received {dt!r}")
    if dt > slowest * (1 + 1e-4):  # (time stamps rounded to float32 move a period by ~1e-7)
        raise LCSInputError(f"dt: expected at most the slowest stream's period, {slowest:.6g} s (a longer step "
                            f"skips its samples), received {dt!r}")
    if max_gap is not None and (not isinstance(max_gap, (int, float)) or not max_gap > 0):
        raise LCSInputError(f"max_gap: expected a number > 0 (s), received {max_gap!r}")
    # the span every stream covers (an input's last sample is held for one step: x_T needs no
    # input), cut at every stream's gaps
    lo = max(s.t[0] for s in checked)
    hi = min(s.t[-1] + (dt if s.kind == "input" else 0.0) for s in checked)
    cuts: list[tuple[float, float]] = []
    gaps_per: list[int] = []
    for s in checked:
        limit = 5 * s.period if max_gap is None else max_gap
        d = np.diff(s.t)
        at = np.flatnonzero(d > limit)
        gaps_per.append(len(at))
        cuts += [(float(s.t[i]), float(s.t[i + 1])) for i in at]
    pieces, start = [], lo
    for a, b in sorted(cuts):
        if a >= hi:  # past the common span
            break
        if a >= start:  # (a lone sample between two gaps is a piece too, dropped and counted)
            pieces.append((start, a))
        start = max(start, b)
    if start < hi:
        pieces.append((start, hi))
    runs, dropped = [], 0
    states = [s for s in checked if s.kind == "state"]
    inputs = [s for s in checked if s.kind == "input"]
    for a, b in pieces:
        steps = int(math.floor((b - a) / dt + SNAP))
        if steps < 1:
            dropped += 1
            continue
        grid = a + dt * np.arange(steps + 1)
        xs = np.concatenate([_resample(s, grid, dt) for s in states], axis=1)
        us = (np.concatenate([_resample(s, grid[:-1], dt) for s in inputs], axis=1) if inputs
              else np.zeros((steps, 0)))
        runs.append((xs, us))
    desc = Description(
        dt=float(dt), streams=tuple((s.name, len(s.t), s.period, float(s.t[-1] - s.t[0]), g)
                                    for s, g in zip(checked, gaps_per, strict=True)),
        runs=len(runs), transitions=sum(len(u) for _, u in runs), splits=max(0, len(pieces) - 1),
        dropped_pieces=dropped, dropped_nan=nan)
    if not runs:
        raise LCSInputError(f"run {run!r}: expected at least one step of dt = {dt:.6g} s where every stream has "
                            f"samples, received none (the streams' common span is {max(0.0, hi - lo):.6g} s"
                            + (f", cut at {len(cuts)} gaps" if cuts else "") + ")")
    return runs, desc
