"""Transition data ``(x, u, x')`` and the paper's data generator (Sec. 5): the random ground truth
(:func:`random_lcs`) and its transitions (:func:`make_dataset`).

:func:`make_dataset` samples ``x ~ U[-x_scale, x_scale]^{n_x}``, ``u ~ U[-u_scale, u_scale]^{n_u}``
(the paper: 10 and 5), steps the system with the exact LCP, and adds ``N(0, noise^2)`` to ``x'``
(the paper: 1e-2 on training data, none on test data).
"""

from __future__ import annotations

import csv
import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ._checks import LCSInputError, as_batch, check_positive
from .io import atomic_write, read_npz
from .system import DEFAULT_STIFFNESS, LCS, PARAMETER_NAMES

__all__ = ["Dataset", "make_dataset", "random_lcs"]

#: The arrays of a dataset, in the order :meth:`Dataset.from_csv` reads their columns.
_GROUPS = ("x", "u", "x_next", "lam")


@dataclass(frozen=True)
class Dataset:
    """A frozen set of ``N`` transitions.

    Attributes:
        x: ``(N, n_x)`` float64; u: ``(N, n_u)``; x_next: ``(N, n_x)``.
        lam: ``(N, n_lam)`` true complementarity variables when known (generated data), else None.
    """

    x: torch.Tensor
    u: torch.Tensor
    x_next: torch.Tensor
    lam: torch.Tensor | None = None

    def __post_init__(self) -> None:
        n = self.x.shape[0]
        for name in ("x", "u", "x_next") + (("lam",) if self.lam is not None else ()):
            t = getattr(self, name)
            if not isinstance(t, torch.Tensor) or t.dim() != 2 or t.shape[0] != n:
                raise LCSInputError(
                    f"{name}: expected a 2-D tensor with {n} rows, received "
                    f"{tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__}"
                )
        if self.x_next.shape[1] != self.x.shape[1]:
            raise LCSInputError(
                f"x_next: expected {self.x.shape[1]} columns (n_x of x), received {self.x_next.shape[1]}"
            )

    # -- constructors -------------------------------------------------------------------
    @classmethod
    def from_arrays(cls, x: Any, u: Any, x_next: Any, lam: Any | None = None) -> Dataset:
        """Build a dataset from a user's arrays (validated: 2-D, matching rows, finite); tensors
        are taken without their autograd history."""
        x_arr = np.asarray(x, dtype=np.float64) if not isinstance(x, torch.Tensor) else x
        if x_arr.ndim != 2:
            raise LCSInputError(f"x: expected shape (N, n_x), received shape {tuple(x_arr.shape)}")
        N, n_x = x_arr.shape
        x_t = as_batch("x", x_arr, n_x)
        u_arr = np.asarray(u, dtype=np.float64) if not isinstance(u, torch.Tensor) else u
        if u_arr.ndim == 1 and u_arr.shape[0] == N:
            u_arr = u_arr.reshape(N, 1)
        if u_arr.ndim != 2:
            raise LCSInputError(f"u: expected shape ({N}, n_u), received shape {tuple(u_arr.shape)}")
        u_t = as_batch("u", u_arr, u_arr.shape[1], batch=N)
        xn_t = as_batch("x_next", x_next, n_x, batch=N)
        lam_t = None
        if lam is not None:
            lam_arr = np.asarray(lam, dtype=np.float64) if not isinstance(lam, torch.Tensor) else lam
            if lam_arr.ndim != 2:
                raise LCSInputError(f"lam: expected shape ({N}, n_lam), received {tuple(lam_arr.shape)}")
            lam_t = as_batch("lam", lam_arr, lam_arr.shape[1], batch=N).detach()
        # data, not a graph: a tensor computed by a model (say, x_next = model.step(x, u)) would
        # otherwise keep its autograd graph alive and refuse .numpy()
        return cls(x_t.detach(), u_t.detach(), xn_t.detach(), lam_t)

    @classmethod
    def load(cls, path: str | os.PathLike, columns: Mapping[str, Sequence[str]] | None = None) -> Dataset:
        """Load an ``.npz`` written by :meth:`save` (arrays ``x``, ``u``, ``x_next``, optional ``lam``),
        or a ``.csv`` file (the name ends in ``.csv``, any case) with named columns: see
        :meth:`from_csv`, which ``columns`` is passed to."""
        path = os.fspath(path)
        if path.lower().endswith(".csv"):
            return cls.from_csv(path, columns=columns)
        if columns is not None:
            raise LCSInputError(
                f"columns: only for .csv files, received columns={columns!r} for {path!r}"
            )
        if not os.path.exists(path):
            raise LCSInputError(f"path: expected an existing .npz file, received {path!r} (not found)")
        arrays = read_npz(os.fspath(path), "an .npz data file with arrays x, u, x_next")
        missing = [k for k in ("x", "u", "x_next") if k not in arrays]
        if missing:
            raise LCSInputError(
                f"path: expected arrays 'x', 'u', 'x_next' in {path!r}, missing {missing} "
                f"(found {sorted(arrays)})"
            )
        return cls.from_arrays(arrays["x"], arrays["u"], arrays["x_next"], arrays.get("lam"))

    @classmethod
    def from_csv(
        cls, path: str | os.PathLike, columns: Mapping[str, Sequence[str]] | None = None
    ) -> Dataset:
        """Load transitions from a CSV file with a header row, one transition per row.

        By default the columns are found by name: ``x_0, ..., x_{n_x-1}`` (the state),
        ``u_0, ..., u_{n_u-1}`` (the input), ``x_next_0, ..., x_next_{n_x-1}`` (the next state)
        and, optionally, ``lam_0, ...``; any other column (a time stamp, a trajectory id) is
        ignored. ``columns`` names them instead, e.g.
        ``{"x": ["pos", "vel"], "u": ["force"], "x_next": ["pos_next", "vel_next"]}`` (keys
        ``"x"``, ``"u"``, ``"x_next"`` and optionally ``"lam"``, in the order of the vectors;
        ``"u": []`` for a system without inputs, ``n_u = 0``).
        Blank lines and lines starting with ``#`` are skipped; the delimiter is a comma.

        Every problem is an :class:`LCSInputError` that names the file, and the line and column
        where there is one: a missing file, no header, duplicate or missing columns, a gap in the
        numbering (``x_0, x_2``), a row with the wrong number of fields, a value that is not a
        finite number, no data rows, or inconsistent sizes (``x_next`` must match ``x``).
        """
        path = os.fspath(path)
        header, rows = read_csv(path)
        names = csv_columns(path, header, columns, _GROUPS, ("x", "u", "x_next"), may_be_empty=("u",))
        if len(names["x_next"]) != len(names["x"]):
            raise LCSInputError(
                f"path: expected as many next-state columns as state columns in {path!r}, received "
                f"x: {names['x']}, x_next: {names['x_next']}"
            )
        arrays = {g: csv_numbers(path, header, rows, cols) for g, cols in names.items()}
        return cls.from_arrays(arrays["x"], arrays["u"], arrays["x_next"], arrays.get("lam"))

    def save(self, path: str | os.PathLike) -> None:
        """Write an ``.npz`` (no pickle) with arrays ``x``, ``u``, ``x_next`` (and ``lam``) to
        exactly ``path`` (no ``.npz`` appended), atomically (:func:`lcs_cvx.io.atomic_write`)."""
        arrays = {"x": self.x, "u": self.u, "x_next": self.x_next}
        if self.lam is not None:
            arrays["lam"] = self.lam
        arrays_np = {k: v.detach().cpu().numpy() for k, v in arrays.items()}
        atomic_write(path, lambda f: np.savez(f, **arrays_np))

    # -- container protocol -------------------------------------------------------------
    @property
    def n_x(self) -> int:
        return self.x.shape[1]

    @property
    def n_u(self) -> int:
        return self.u.shape[1]

    def __len__(self) -> int:
        return self.x.shape[0]

    def __getitem__(self, idx: Any) -> Dataset:
        if isinstance(idx, (int, np.integer)):  # one sample, kept 2-D
            i, n = int(idx), len(self)
            if not -n <= i < n:  # the IndexError also ends `for sample in dataset`
                raise IndexError(f"index {i} out of range for a dataset of {n} samples")
            idx = slice(i % n, i % n + 1)
        lam = self.lam[idx] if self.lam is not None else None
        return Dataset(self.x[idx], self.u[idx], self.x_next[idx], lam)

    def split(self, frac: float, seed: int = 0) -> tuple[Dataset, Dataset]:
        """Random split into ``(first, second)`` with ``round(frac * N)`` samples in ``first``."""
        if not (0.0 < float(frac) < 1.0):
            raise LCSInputError(f"frac: expected a fraction in (0, 1), received {frac!r}")
        perm = torch.randperm(len(self), generator=torch.Generator().manual_seed(int(seed)))
        k = int(round(float(frac) * len(self)))
        return self[perm[:k]], self[perm[k:]]

    def to(self, device: torch.device | str) -> Dataset:
        lam = self.lam.to(device) if self.lam is not None else None
        return Dataset(self.x.to(device), self.u.to(device), self.x_next.to(device), lam)

    def __repr__(self) -> str:
        return f"Dataset(N={len(self)}, n_x={self.n_x}, n_u={self.n_u}, lam={'yes' if self.lam is not None else 'no'})"


def make_dataset(
    system: Any,
    n: int,
    noise: float = 0.0,
    seed: int = 0,
    x_scale: float = 10.0,
    u_scale: float = 5.0,
    batch_size: int = 50_000,
) -> Dataset:
    """Sample ``n`` transitions of ``system`` (an :class:`lcs_cvx.LCS`) as in the paper's Sec. 5.

    ``x ~ U[-x_scale, x_scale]``, ``u ~ U[-u_scale, u_scale]``, ``x' = system.step(x, u)`` plus
    ``N(0, noise^2)``; ``lam`` holds the exact (noise-free) complementarity variables.
    Reproducible in ``seed``.
    """
    n = check_positive("n", n, integer=True)
    if isinstance(noise, bool) or not isinstance(noise, (int, float)) or not noise >= 0 or noise == float("inf"):
        raise LCSInputError(f"noise: expected a finite standard deviation >= 0, received {noise!r}")
    check_positive("x_scale", x_scale)
    check_positive("u_scale", u_scale)
    gen = torch.Generator().manual_seed(int(seed))
    f64 = torch.float64
    x = (torch.rand(n, system.n_x, generator=gen, dtype=f64) * 2 - 1) * x_scale
    u = (torch.rand(n, system.n_u, generator=gen, dtype=f64) * 2 - 1) * u_scale
    noise_draw = torch.randn(n, system.n_x, generator=gen, dtype=f64) * float(noise)
    xs, lams = [], []
    with torch.no_grad():
        for i in range(0, n, batch_size):
            xb = x[i : i + batch_size].to(system.dtype)
            ub = u[i : i + batch_size].to(system.dtype)
            lam = system.solve_lcp(xb, ub).lam
            xn = xb @ system.A.mT + ub @ system.B.mT + lam @ system.C.mT + system.d
            xs.append(xn if system.kinematics is None else system.kinematics.integrate(xb, xn))
            lams.append(lam)
    x_next = torch.cat(xs).to(f64) + noise_draw
    return Dataset(x, u, x_next, torch.cat(lams).to(f64))


# -- CSV reading, shared with :mod:`lcs_cvx.trajectories` ---------------------------------------
def read_csv(path: str) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """The header (stripped names) and the data rows ``(line number, fields)`` of the CSV file
    ``path``; blank lines and lines starting with ``#`` are skipped. An :class:`LCSInputError`
    naming the file (and the line) for a missing or unreadable file, no header, an empty or
    duplicate column name, a row with the wrong number of fields, or no data rows."""
    if not os.path.exists(path):
        raise LCSInputError(f"path: expected an existing .csv file, received {path!r} (not found)")
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            lines = [(i, line) for i, line in enumerate(f.read().splitlines(), start=1)
                     if line.strip() and not line.lstrip().startswith("#")]
    except (OSError, UnicodeDecodeError) as exc:
        raise LCSInputError(f"path: expected a CSV text file, could not read {path!r}: {exc}") from exc
    if not lines:
        raise LCSInputError(f"path: expected a CSV file with a header row, {path!r} is empty")
    try:
        rows = [(lineno, next(csv.reader([line]))) for lineno, line in lines]  # one row per line
    except csv.Error as exc:  # e.g. a field over csv.field_size_limit()
        raise LCSInputError(f"path: expected a CSV text file, could not read {path!r}: {exc}") from exc
    header = [h.strip() for h in rows[0][1]]
    seen: set[str] = set()
    for h in header:
        if not h:
            raise LCSInputError(f"path: line {lines[0][0]} of {path!r} (the header) has an empty column name")
        if h in seen:
            raise LCSInputError(f"path: duplicate column {h!r} in the header of {path!r}")
        seen.add(h)
    if len(rows) == 1:
        raise LCSInputError(f"path: expected at least one data row in {path!r}, found only the header")
    for lineno, row in rows[1:]:
        if len(row) != len(header):
            raise LCSInputError(
                f"path: line {lineno} of {path!r} has {len(row)} fields, expected "
                f"{len(header)} (the header's)"
            )
    return header, rows[1:]


def csv_numbers(
    path: str, header: list[str], rows: Sequence[tuple[int, list[str]]], cols: Sequence[str]
) -> np.ndarray:
    """The columns ``cols`` of ``rows`` (from :func:`read_csv`) as a ``(len(rows), len(cols))``
    float64 array; a field that is not a finite number is an :class:`LCSInputError` naming the
    file, the line and the column."""
    index = {h: j for j, h in enumerate(header)}
    wanted = [index[c] for c in cols]
    values = np.empty((len(rows), len(wanted)), dtype=np.float64)
    for r, (lineno, row) in enumerate(rows):
        for k, j in enumerate(wanted):
            text = row[j].strip()
            try:
                v = float(text)
            except ValueError:
                v = math.nan
            if not math.isfinite(v):
                raise LCSInputError(
                    f"path: line {lineno} of {path!r}, column {header[j]!r}: expected a finite "
                    f"number, received {text!r}"
                )
            values[r, k] = v
    return values


def csv_columns(
    path: str,
    header: list[str],
    columns: Mapping[str, Sequence[str]] | None,
    groups: Sequence[str],
    required: Sequence[str],
    may_be_empty: Sequence[str] = (),
) -> dict[str, list[str]]:
    """The column names of each array (``groups``, of which ``required`` must be present): given
    by ``columns`` or found by the default names ``{group}_0, {group}_1, ...``. In ``columns``,
    the groups of ``may_be_empty`` may name no column (``"u": []``: a system without inputs)."""
    optional = [g for g in groups if g not in required]
    keys = ", ".join(repr(g) for g in required) + (
        f" (and optionally {', '.join(repr(g) for g in optional)})" if optional else ""
    )
    if columns is not None:
        if not isinstance(columns, Mapping):
            raise LCSInputError(
                f"columns: expected a dict of column-name lists, received {type(columns).__name__}"
            )
        unknown = sorted(set(columns) - set(groups))
        missing = [g for g in required if g not in columns]
        if unknown or missing:
            raise LCSInputError(f"columns: expected keys {keys}, received {sorted(columns)}")
        names = {}
        for g, cols in columns.items():
            if (isinstance(cols, str) or not all(isinstance(c, str) for c in cols)
                    or not (cols or g in may_be_empty)):
                raise LCSInputError(
                    f"columns: expected a {'' if g in may_be_empty else 'non-empty '}list of "
                    f"column names for {g!r}, received {cols!r}"
                )
            absent = [c for c in cols if c not in header]
            if absent:
                raise LCSInputError(
                    f"columns: {g!r} names {absent} not in the header of {path!r} (found {header})"
                )
            names[g] = list(cols)
        return names
    pattern = re.compile(rf"^({'|'.join(re.escape(g) for g in groups)})_(\d+)$")
    found: dict[str, dict[int, str]] = {}
    for h in header:
        m = pattern.match(h)
        if m:
            found.setdefault(m.group(1), {})[int(m.group(2))] = h
    missing = [g for g in required if g not in found]
    if missing:
        wanted = ", ".join(f"{g}_0.." for g in required)
        extra = f" (optionally {', '.join(f'{g}_0..' for g in optional)})" if optional else ""
        raise LCSInputError(
            f"path: expected columns {wanted}{extra} in {path!r}, "
            f"missing {[g + '_0..' for g in missing]} (found {header}); or name them with columns="
        )
    names = {}
    for g in groups:
        if g not in found:
            continue
        idx = found[g]
        gap = [f"{g}_{i}" for i in range(max(idx) + 1) if i not in idx]
        if gap:
            raise LCSInputError(
                f"path: expected columns {g}_0 .. {g}_{max(idx)} in {path!r}, missing {gap}"
            )
        names[g] = [idx[i] for i in range(len(idx))]
    return names


def random_lcs(
    n_x: int,
    n_u: int,
    n_lam: int,
    stiffness: float = DEFAULT_STIFFNESS,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
    g_scale: float = 1.0,
) -> LCS:
    """The paper's random ground truth (Sec. 5): every entry of A, B, C, d, D, E, G, H, c
    uniform in [-1, 1], ``F = G G^T + H - H^T + s I``.

    ``g_scale`` multiplies ``G`` after the draw (the other entries are unchanged): ``g_scale=0``
    gives ``F + F^T = 2 s I`` exactly, the stiff systems of Fig. 1(c) (``sigma_min = 2 s``).

    The result's ``sigma_min`` attribute is ``sigma_min(F + F^T)`` (``>= 2 s``). Its
    parameters do not require grad: every parameter is fixed (see :class:`LCS`), as a ground
    truth's; ``.requires_grad_(True)`` makes them learnable (e.g. to prune or train it).
    """
    if isinstance(g_scale, bool) or not isinstance(g_scale, (int, float)) \
            or not 0 <= g_scale < float("inf"):
        raise LCSInputError(f"g_scale: expected a finite number >= 0, received {g_scale!r}")
    model = LCS(n_x, n_u, n_lam, stiffness=stiffness, init_scale=0.0, dtype=dtype)
    gen = torch.Generator().manual_seed(int(seed))
    with torch.no_grad():
        for name in PARAMETER_NAMES:
            p = getattr(model, name)
            p.copy_((torch.rand(p.shape, generator=gen, dtype=torch.float64) * 2.0 - 1.0).to(dtype))
        model.G.mul_(float(g_scale))
    model.requires_grad_(False)
    return model
