"""Recorded trajectories ``x_0, u_0, x_1, u_1, ..., x_T`` and their open-loop rollout error.

Trajectory ``i`` has states ``xs[i]`` of shape ``(T_i + 1, n_x)`` and inputs ``us[i]`` of shape
``(T_i, n_u)``, ``T_i >= 1``; the lengths may differ. Its transitions are the pairs
``(x_t, u_t, x_{t+1})``, ``t = 0 .. T_i - 1``.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
import torch

from ._checks import LCSInputError
from .data import Dataset, csv_columns, csv_numbers, read_csv
from .io import atomic_write, read_npz
from .streams import Description

__all__ = ["Trajectories", "rollout_error"]

_F64 = torch.float64


def _matrix(name: str, value: Any) -> torch.Tensor:
    """``value`` as a 2-D float64 CPU tensor, refused by ``name`` otherwise."""
    try:
        if isinstance(value, torch.Tensor):
            t = value.detach().to(device="cpu", dtype=_F64)
        else:
            t = torch.from_numpy(np.array(value, dtype=np.float64))
    except (TypeError, ValueError, RuntimeError) as exc:
        raise LCSInputError(f"{name}: expected a 2-D array of numbers, received {type(value).__name__} ({exc})") from None
    if t.dim() != 2:
        raise LCSInputError(f"{name}: expected a 2-D array, received shape {tuple(t.shape)}")
    bad = ~torch.isfinite(t)
    if bool(bad.any()):
        row, col = (int(i) for i in bad.nonzero()[0])
        raise LCSInputError(f"{name}: expected finite values, received {int(bad.sum())} NaN/inf entries, "
                            f"the first in row {row}, column {col} ({float(t[row, col])})")
    return t


def _as_list(name: str, value: Any) -> list[Any]:
    if isinstance(value, (list, tuple)) or (isinstance(value, (np.ndarray, torch.Tensor)) and value.ndim == 3):
        return list(value)
    raise LCSInputError(
        f"{name}: expected a list of 2-D arrays (one per trajectory), received {type(value).__name__}"
        + (f" of shape {tuple(value.shape)}" if isinstance(value, (np.ndarray, torch.Tensor)) else "")
    )


class Trajectories:
    """``K`` recorded trajectories of possibly different lengths.

    Args:
        xs: a list of ``K`` state arrays (NumPy arrays or tensors), ``xs[i]`` of shape
            ``(T_i + 1, n_x)`` with ``T_i >= 1``.
        us: a list of ``K`` input arrays, ``us[i]`` of shape ``(T_i, n_u)``: ``u_t`` drives
            ``x_t`` to ``x_{t+1}``.
        names: optional names of the ``n_x`` state coordinates (with units, say ``"z [m]"``):
            the plots' labels (:mod:`lcs_cvx.plot`); a CSV file's column names by default.
        input_names: optional names of the ``n_u`` inputs.

    The arrays are copied as float64 CPU tensors. Every problem is an :class:`LCSInputError`
    naming the argument (``us[3]: expected 17 rows (one fewer than xs[3]'s 18), received 16``):
    an empty list, lists of different lengths, an array that is not 2-D, mismatched rows,
    ``n_x`` or ``n_u`` that differ between trajectories, NaN or inf entries.
    """

    def __init__(self, xs: Sequence[Any], us: Sequence[Any], names: Sequence[str] | None = None,
                 input_names: Sequence[str] | None = None) -> None:
        xs_l, us_l = _as_list("xs", xs), _as_list("us", us)
        if not xs_l:
            raise LCSInputError("xs: expected at least one trajectory, received an empty list")
        if len(us_l) != len(xs_l):
            raise LCSInputError(
                f"us: expected {len(xs_l)} input arrays (one per trajectory of xs), received {len(us_l)}"
            )
        self._xs: tuple[torch.Tensor, ...] = tuple(_matrix(f"xs[{i}]", x) for i, x in enumerate(xs_l))
        self._us: tuple[torch.Tensor, ...] = tuple(_matrix(f"us[{i}]", u) for i, u in enumerate(us_l))
        for i, (x, u) in enumerate(zip(self._xs, self._us, strict=True)):
            if x.shape[0] < 2:
                raise LCSInputError(
                    f"xs[{i}]: expected at least 2 rows (a state and the next), received {x.shape[0]}"
                )
            if u.shape[0] != x.shape[0] - 1:
                raise LCSInputError(
                    f"us[{i}]: expected {x.shape[0] - 1} rows (one fewer than xs[{i}]'s "
                    f"{x.shape[0]}), received {u.shape[0]}"
                )
            for name, a, ref in (("xs", x, self._xs[0]), ("us", u, self._us[0])):
                if a.shape[1] != ref.shape[1]:
                    what = "n_x" if name == "xs" else "n_u"
                    raise LCSInputError(
                        f"{name}[{i}]: expected {ref.shape[1]} columns ({what} of {name}[0]), "
                        f"received {a.shape[1]}"
                    )
        self.names = _names("names", names, self.n_x)
        self.input_names = _names("input_names", input_names, self.n_u)
        #: what a reader did to make these runs (:class:`lcs_cvx.streams.Description`), or None
        self.description: Description | None = None

    # -- properties -----------------------------------------------------------------------
    @property
    def n_x(self) -> int:
        return self._xs[0].shape[1]

    @property
    def n_u(self) -> int:
        return self._us[0].shape[1]

    @property
    def xs(self) -> tuple[torch.Tensor, ...]:
        """The state arrays, ``(T_i + 1, n_x)`` float64 each."""
        return self._xs

    @property
    def us(self) -> tuple[torch.Tensor, ...]:
        """The input arrays, ``(T_i, n_u)`` float64 each."""
        return self._us

    @property
    def lengths(self) -> tuple[int, ...]:
        """The number of steps ``T_i`` of each trajectory (its transitions)."""
        return tuple(u.shape[0] for u in self._us)

    def __len__(self) -> int:
        return len(self._xs)

    def __repr__(self) -> str:
        return (f"Trajectories(K={len(self)}, transitions={sum(self.lengths)}, n_x={self.n_x}, "
                f"n_u={self.n_u})")

    # -- conversions ----------------------------------------------------------------------
    def to_transitions(self) -> Dataset:
        """Every ``(x_t, u_t, x_{t+1})`` of every trajectory, in order, as a :class:`Dataset`."""
        return Dataset(
            torch.cat([x[:-1] for x in self._xs]),
            torch.cat(self._us),
            torch.cat([x[1:] for x in self._xs]),
        )

    def split(self, frac: float, seed: int = 0) -> tuple[Trajectories, Trajectories]:
        """Random split by whole trajectories into ``(first, second)``, ``round(frac * K)`` in
        ``first``; each part must get at least one trajectory."""
        if not (0.0 < float(frac) < 1.0):
            raise LCSInputError(f"frac: expected a fraction in (0, 1), received {frac!r}")
        k = int(round(float(frac) * len(self)))
        if not 1 <= k <= len(self) - 1:
            raise LCSInputError(
                f"frac: expected a split with at least one of the {len(self)} trajectories on each "
                f"side, received {frac!r} ({k} in the first part)"
            )
        perm = torch.randperm(len(self), generator=torch.Generator().manual_seed(int(seed))).tolist()
        parts = perm[:k], perm[k:]
        return tuple(Trajectories([self._xs[i] for i in p], [self._us[i] for i in p], self.names,  # type: ignore[return-value]
                                  self.input_names) for p in parts)

    def describe(self, velocities: Mapping[Any, Any] | None = None, dt: float | None = None) -> str:
        """What these runs are, in words: their count, lengths and columns, what a reader did to
        make them (each stream's measured period, what was resampled, split or dropped), and
        with ``velocities`` (``{position: velocity}``, indices or names) each pair's *effective
        period*: the least-squares slope of the position's change on the next velocity,
        ``sum dp_t v_{t+1} / sum v_{t+1}^2`` over every run -- the period a known integration
        ``p' = p + dt v'`` must use, compared with ``dt`` (default: the reader's clock)."""
        lines = [repr(self) + f", steps per run {min(self.lengths)}-{max(self.lengths)}"]
        if self.names:
            lines.append("  state: " + ", ".join(self.names))
        if self.input_names:
            lines.append("  input: " + ", ".join(self.input_names))
        if self.description is not None:
            lines.append(str(self.description))
        step = dt if dt is not None else (self.description.dt if self.description is not None else None)
        for p, v in (velocities or {}).items():
            i, j = (self._column(c) for c in (p, v))
            dp = torch.cat([x[1:, i] - x[:-1, i] for x in self._xs])
            vn = torch.cat([x[1:, j] for x in self._xs])
            period = float(dp @ vn / (vn @ vn)) if float(vn @ vn) > 0 else float("nan")
            lines.append(f"  effective period of {self._label(i)} by {self._label(j)}: {period:.6g} s"
                         + (f" (clock {step:.6g} s, ratio {period / step:.4g})" if step else ""))
        return "\n".join(lines)

    def _column(self, c: Any) -> int:
        if isinstance(c, str):
            if not self.names or c not in self.names:
                raise LCSInputError(f"velocities: expected state names {list(self.names or ())} or indices, received {c!r}")
            return self.names.index(c)
        if isinstance(c, bool) or not isinstance(c, (int, np.integer)) or not 0 <= c < self.n_x:
            raise LCSInputError(f"velocities: expected state indices in [0, {self.n_x}), received {c!r}")
        return int(c)

    def _label(self, i: int) -> str:
        return self.names[i] if self.names else f"x[{i}]"

    # -- robot logs -------------------------------------------------------------------------
    @classmethod
    def _from_runs(cls, read: tuple) -> Trajectories:
        runs, names, input_names, desc = read
        out = cls([x for x, _ in runs], [u for _, u in runs], names or None, input_names or None)
        out.description = desc
        return out

    @classmethod
    def from_mcap(cls, path: str | os.PathLike, state: Mapping[str, Sequence[str]],
                  input: Mapping[str, Sequence[str]] | None = None, dt: float | None = None,
                  max_gap: float | None = None, drop_nan: bool = False) -> Trajectories:
        """A ROS 2 bag in MCAP (:func:`lcs_cvx.recordings.read_mcap`; the ``logs`` extra):
        ``state``/``input`` map topics to fields, ``{"/joint_states": ["position[0]",
        "velocity[0]"]}``; CDR (ROS 2) and JSON channels; each topic timed by its messages' log
        time and put on one clock of period ``dt`` (default: the slowest topic's period) by
        :func:`lcs_cvx.streams.align` -- states interpolated, inputs held, the run split at
        gaps longer than ``max_gap``. :meth:`describe` says what was done."""
        from .recordings import read_mcap

        return cls._from_runs(read_mcap(path, state, input, dt, max_gap, drop_nan))

    @classmethod
    def from_hdf5(cls, path: str | os.PathLike, state: Sequence[str], input: Sequence[str] = (),
                  runs: Any = "data", time: str | Mapping[str, str] | None = None, period: float | None = None,
                  dt: float | None = None, max_gap: float | None = None, drop_nan: bool = False) -> Trajectories:
        """An HDF5 file with one group per run (:func:`lcs_cvx.recordings.read_hdf5`; robomimic's
        ``data/demo_<i>`` by default, or a list of group paths): ``state``/``input`` list
        datasets of a run (``"obs/joint_pos"``, or one column ``"obs/joint_pos[0]"``), timed by
        the run's ``time`` dataset (or ``{dataset: its time dataset}``) or ``period`` seconds
        per row, on one clock as :meth:`from_mcap`."""
        from .recordings import read_hdf5

        return cls._from_runs(read_hdf5(path, state, input, runs, time, period, dt, max_gap, drop_nan))

    @classmethod
    def from_lerobot(cls, path: str | os.PathLike, state: str = "observation.state", input: str | None = "action",
                     dt: float | None = None, max_gap: float | None = None, drop_nan: bool = False) -> Trajectories:
        """A LeRobot dataset folder, layouts v2.1 and v3.0 (:func:`lcs_cvx.recordings.read_lerobot`):
        each episode a run, ``observation.state`` the state and ``action`` the input (held),
        timed by ``timestamp`` and put on one clock (default: the dataset's ``fps``)."""
        from .recordings import read_lerobot

        return cls._from_runs(read_lerobot(path, state, input, dt, max_gap, drop_nan))

    # -- files ----------------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> None:
        """Write an ``.npz`` (no pickle) to exactly ``path``, atomically
        (:func:`lcs_cvx.io.atomic_write`): ``x`` ``(sum_i (T_i + 1), n_x)`` and ``u``
        ``(sum_i T_i, n_u)``, the trajectories one after the other, and ``offsets`` ``(K + 1,)``:
        trajectory ``i``'s states are ``x[offsets[i]:offsets[i+1]]``, its inputs
        ``u[offsets[i] - i : offsets[i+1] - i - 1]``."""
        offsets = np.cumsum([0] + [x.shape[0] for x in self._xs]).astype(np.int64)
        arrays = {"x": torch.cat(self._xs).numpy(), "u": torch.cat(self._us).numpy(), "offsets": offsets}
        atomic_write(path, lambda f: np.savez(f, **arrays))

    @classmethod
    def load(
        cls,
        path: str | os.PathLike,
        columns: Mapping[str, Sequence[str]] | None = None,
        trajectory: str = "trajectory",
        time: str | None = None,
    ) -> Trajectories:
        """Load an ``.npz`` written by :meth:`save`, or a ``.csv`` (the name ends in ``.csv``,
        any case) with a header row and one state per row.

        In a CSV file the column ``trajectory`` holds the trajectory id: the rows of one id, in
        file order, are one trajectory, and the trajectories come in the order their ids first
        appear. The states are the columns ``x_0, ..., x_{n_x-1}`` and the inputs ``u_0, ...``
        by default, or ``columns={"x": [...], "u": [...]}`` names them (``"u": []``: no
        inputs, ``n_u = 0``); other columns are
        ignored. Row ``t`` holds ``x_t`` and ``u_t``, the input that drives ``x_t`` to
        ``x_{t+1}``; the last row of a trajectory has no next state, so its inputs are not
        read (leave them empty). Blank lines and lines starting with ``#`` are skipped.
        ``time`` names a time column: an LCS is discrete-time, so steps of uneven length within a
        trajectory (a spread above 1 % of the median step) are reported by a ``UserWarning``
        naming the trajectory and the spread.

        Every problem is an :class:`LCSInputError` naming the file (and the line and column
        where there is one), as for :meth:`Dataset.from_csv`; a trajectory with a single row
        is refused.
        """
        path = os.fspath(path)
        if path.lower().endswith(".csv"):
            return cls._from_csv(path, columns, trajectory, time)
        if time is not None:
            raise LCSInputError(f"time: only for .csv files, received time={time!r} for {path!r}")
        if columns is not None:
            raise LCSInputError(f"columns: only for .csv files, received columns={columns!r} for {path!r}")
        if not os.path.isfile(path):
            raise LCSInputError(f"path: expected an existing .npz file, received {path!r} (not found)")
        arrays = read_npz(path, "an .npz trajectory file with arrays x, u, offsets")
        missing = [k for k in ("x", "u", "offsets") if k not in arrays]
        if missing:
            raise LCSInputError(
                f"path: expected arrays 'x', 'u', 'offsets' in {path!r}, missing {missing} (found {sorted(arrays)})"
            )
        x, u, off = arrays["x"], arrays["u"], arrays["offsets"]
        n_rows = x.shape[0] if x.ndim >= 1 else 0
        if (off.ndim != 1 or off.dtype.kind not in "iu" or off.shape[0] < 2 or off[0] != 0
                or off[-1] != n_rows or np.any(np.diff(off) < 2)):
            raise LCSInputError(
                f"path: array 'offsets' in {path!r}: expected increasing integers from 0 to "
                f"{n_rows} (the rows of x) in steps of at least 2, received {off.tolist()!r}"
            )
        if u.ndim < 1 or u.shape[0] != n_rows - (off.shape[0] - 1):
            raise LCSInputError(
                f"path: array 'u' in {path!r}: expected {n_rows - (off.shape[0] - 1)} rows (one "
                f"per transition), received shape {u.shape}"
            )
        k = off.shape[0] - 1
        try:
            return cls([x[off[i]:off[i + 1]] for i in range(k)],
                       [u[off[i] - i:off[i + 1] - i - 1] for i in range(k)])
        except LCSInputError as exc:
            raise LCSInputError(f"path: in {path!r}: {exc}") from None

    @classmethod
    def _from_csv(cls, path: str, columns: Mapping[str, Sequence[str]] | None, trajectory: str,
                  time: str | None) -> Trajectories:
        header, rows = read_csv(path)
        if time is not None and time not in header:
            raise LCSInputError(f"time: expected a column {time!r} in the header of {path!r}, received {header}")
        if trajectory not in header:
            raise LCSInputError(
                f"trajectory: expected a column {trajectory!r} (the trajectory id) in the header of "
                f"{path!r}, received {header}"
            )
        names = csv_columns(path, header, columns, ("x", "u"), ("x", "u"), may_be_empty=("u",))
        if trajectory in names["x"] + names["u"]:
            raise LCSInputError(f"columns: the trajectory id column {trajectory!r} cannot be a state or input")
        j = header.index(trajectory)
        groups: dict[str, list[tuple[int, list[str]]]] = {}
        for lineno, row in rows:
            tid = row[j].strip()
            if not tid:
                raise LCSInputError(f"path: line {lineno} of {path!r}, column {trajectory!r}: expected a trajectory id, received ''")
            groups.setdefault(tid, []).append((lineno, row))
        xs, us = [], []
        for tid, g in groups.items():
            if len(g) < 2:
                raise LCSInputError(
                    f"path: trajectory {tid!r} of {path!r} (line {g[0][0]}): expected at least 2 rows "
                    f"(a state and the next), received 1"
                )
            xs.append(csv_numbers(path, header, g, names["x"]))
            us.append(csv_numbers(path, header, g[:-1], names["u"]))  # the last row's inputs: unread
            if time is not None:
                _check_steps(path, tid, csv_numbers(path, header, g, [time])[:, 0])
        return cls(xs, us, names["x"], names["u"] or None)


def _names(name: str, names: Sequence[str] | None, k: int) -> tuple[str, ...] | None:
    if names is None:
        return None
    if isinstance(names, str) or len(names) != k or not all(isinstance(n, str) for n in names):
        raise LCSInputError(f"{name}: expected {k} strings (one per column), received {names!r}")
    return tuple(names)


def _check_steps(path: str, tid: str, t: Any) -> None:
    """A ``UserWarning`` when the time steps of trajectory ``tid`` spread by more than 1 % of
    their median (the LCS is discrete-time: one step is one sampling period)."""
    import warnings

    dt = np.diff(np.asarray(t, dtype=np.float64))
    med = float(np.median(dt))
    if med <= 0:
        raise LCSInputError(f"time: trajectory {tid!r} of {path!r}: expected increasing times, received a median step of {med:g}")
    spread = float(dt.max() - dt.min())
    if spread > 0.01 * med:
        warnings.warn(f"time: trajectory {tid!r} of {path!r} has uneven steps: from {dt.min():g} to {dt.max():g} "
                      f"(spread {spread:g}, {100 * spread / med:.3g} % of the median step {med:g}); an LCS is "
                      "discrete-time, one step per sample: resample to a uniform step", UserWarning, stacklevel=3)


def rollout_error(model: Any, trajectories: Trajectories, horizons: int | Iterable[int] = (1, 5, 20)) -> dict[int, float]:
    """The open-loop rollout error of ``model`` (an :class:`lcs_cvx.LCS`) at each horizon ``H``:

        e_H = sum_windows ||x_hat_{s+H} - x_{s+H}||^2 / sum_windows ||x_{s+H}||^2,

    where ``x_hat`` starts at the recorded ``x_s`` and steps the model (exact LCP) under the
    recorded inputs ``u_s, ..., u_{s+H-1}``, over every window, i.e. every trajectory ``i`` and
    start ``s`` with ``s + H <= T_i`` (windows overlap). ``e_1`` is :func:`relative_error` on
    :meth:`Trajectories.to_transitions`. All windows of all trajectories are stepped together:
    one ``model.step`` per step of the longest horizon.

    Returns ``{H: e_H}`` in the order of ``horizons``. A horizon that is not an integer >= 1 or
    that no trajectory is long enough for is an :class:`LCSInputError` naming it.
    """
    if not isinstance(trajectories, Trajectories):
        raise LCSInputError(f"trajectories: expected an lcs_cvx.Trajectories, received {type(trajectories).__name__}")
    hs = [horizons] if isinstance(horizons, int) else list(horizons)
    if not hs or any(isinstance(h, bool) or not isinstance(h, (int, np.integer)) or h < 1 for h in hs):
        raise LCSInputError(f"horizons: expected integers >= 1, received {horizons!r}")
    hs = list(dict.fromkeys(int(h) for h in hs))
    longest = max(trajectories.lengths)
    too_long = [h for h in hs if h > longest]
    if too_long:
        raise LCSInputError(
            f"horizons: expected at most {longest} steps (the longest trajectory's), received "
            f"{too_long} (no window)"
        )
    if (trajectories.n_x, trajectories.n_u) != (model.n_x, model.n_u):
        raise LCSInputError(
            f"trajectories: expected n_x={model.n_x}, n_u={model.n_u} (the model's), received "
            f"n_x={trajectories.n_x}, n_u={trajectories.n_u}"
        )
    kw = {"dtype": model.dtype, "device": model.device}
    X = torch.cat(trajectories.xs).to(**kw)
    U = torch.cat(trajectories.us).to(**kw)
    x_rows, u_rows, remaining = [], [], []  # one window per start (i, s): its first rows, T_i - s
    x0 = u0 = 0
    for T in trajectories.lengths:
        x_rows.append(torch.arange(x0, x0 + T))
        u_rows.append(torch.arange(u0, u0 + T))
        remaining.append(torch.arange(T, 0, -1))
        x0, u0 = x0 + T + 1, u0 + T
    order = torch.argsort(torch.cat(remaining), descending=True, stable=True)
    rem = torch.cat(remaining)[order]  # windows still running at step h: a prefix
    xi, ui = torch.cat(x_rows)[order].to(model.device), torch.cat(u_rows)[order].to(model.device)
    out: dict[int, float] = {}
    with torch.no_grad():
        x_hat = X[xi]
        for h in range(1, max(hs) + 1):
            n = int((rem >= h).sum())
            x_hat = model.step(x_hat[:n], U[ui[:n] + h - 1])
            if h in hs:
                target = X[xi[:n] + h]
                den = float((target**2).sum())
                if den == 0.0:
                    raise LCSInputError(f"trajectories: expected states not identically zero at horizon {h} (e_H divides by them)")
                out[h] = float(((x_hat - target) ** 2).sum()) / den
    return {h: out[h] for h in hs}
