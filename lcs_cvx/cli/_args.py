"""The command line's argument types and the checks its commands share: an option's value is
refused with a message naming ``--option`` (:func:`reraise_for`), printed as one line by
:func:`lcs_cvx.cli.main`."""

from __future__ import annotations

import argparse
import csv
import math
import os
import re
from dataclasses import dataclass
from typing import Any

from .. import Dataset, LCSInputError, Trajectories, relative_error
from ..io import read_npz

#: The program name in messages.
PROG = "lcs-cvx"


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, received {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, received {text!r}")
    return value


def positive_ints(text: str) -> list[int]:
    """``"200,2000"`` -> ``[200, 2000]``, each an integer >= 1."""
    try:
        out = [int(v.replace("_", "")) for v in text.split(",") if v.strip()]
    except ValueError:
        out = []
    if not out or min(out) < 1:
        raise argparse.ArgumentTypeError(f"expected integers >= 1, comma-separated, received {text!r}")
    return out


def seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer seed, received {text!r}") from None
    if not 0 <= value < 2**63:
        raise argparse.ArgumentTypeError(f"expected a seed in [0, 2**63), received {text!r}")
    return value


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0, received {text!r}") from None
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, received {text!r}")
    return value


def kinematics_spec(text: str) -> Any:
    """``"dt=0.01 positions=0:2,1:3"`` -> :class:`lcs_cvx.Kinematics` (:meth:`~lcs_cvx.Kinematics.parse`)."""
    from ..kinematics import Kinematics

    try:
        return Kinematics.parse(text)
    except LCSInputError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("kinematics: ")) from None


def sizes(text: str) -> list[tuple[int, int, int]]:
    """``"10,4,4;128,4,10"`` -> ``[(10, 4, 4), (128, 4, 10)]``."""
    try:
        out = [tuple(int(v) for v in part.split(",")) for part in text.split(";") if part.strip()]
    except ValueError:
        out = []
    if not out or any(len(t) != 3 or min(t) < 0 or t[0] < 1 or t[2] < 1 for t in out):
        raise argparse.ArgumentTypeError(
            f"expected 'n_x,n_u,n_lam[;n_x,n_u,n_lam...]' with positive sizes, received {text!r}"
        )
    return out  # type: ignore[return-value]


def horizons(text: str) -> tuple[int, ...]:
    """``"1,5,20"`` -> ``(1, 5, 20)``."""
    try:
        out = tuple(int(v) for v in text.split(","))
    except ValueError:
        out = ()
    if not out or min(out) < 1:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers >= 1 such as '1,5,20', received {text!r}"
        )
    return out


def n_lam_or_auto(text: str) -> int | str:
    """``"4"`` -> ``4``; ``"auto"`` -> ``"auto"`` (choose among ``--candidates``)."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        return positive_int(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"expected an integer >= 1 or 'auto', received {text!r}"
        ) from None


def candidates(text: str) -> tuple[int, ...]:
    """``"1,2,4,8"`` -> ``(1, 2, 4, 8)``: distinct integers >= 1."""
    try:
        out = tuple(int(v) for v in text.split(","))
    except ValueError:
        out = ()
    if not out or min(out) < 1 or len(set(out)) != len(out):
        raise argparse.ArgumentTypeError(
            f"expected distinct comma-separated integers >= 1 such as '1,2,4,8', received {text!r}"
        )
    return out


def fraction(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"expected a fraction in (0, 1), received {text!r}")
    return value


def nonnegative_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0.0 <= value < math.inf:
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, received {text!r}")
    return value


def column_names(text: str) -> list[str]:
    """``"x, z,vx"`` -> ``["x", "z", "vx"]``; ``""`` -> ``[]`` (no columns)."""
    if not text.strip():
        return []
    out = [c.strip() for c in text.split(",")]
    if any(not c for c in out) or len(set(out)) != len(out):
        raise argparse.ArgumentTypeError(
            f"expected distinct comma-separated column names such as 'x,z,vx,vz', received {text!r}"
        )
    return out


# -- data files: .npz, .csv with the user's column names, trajectory files ----------------------
#: The Python-only hint of the library's CSV messages, and what the command line says instead.
_PYTHON_HINT = "; or name them with columns="
_CLI_HINT = ("; or name them with --state and --input (the next states: columns named by "
             "--next-suffix, or the next row of a --trajectory-column)")


def add_column_options(p: argparse.ArgumentParser) -> None:
    """The options naming the columns of CSV data files (every data option of the command)."""
    p.add_argument("--state", type=column_names, default=None, metavar="NAMES",
                   help="state columns of the CSV files, e.g. x,z,vx,vz (default: x_0, x_1, ...)")
    p.add_argument("--input", type=column_names, default=None, metavar="NAMES",
                   help="input columns, e.g. fx,fz ('' for none); required with --state")
    p.add_argument("--next-suffix", default=None, metavar="SUFFIX",
                   help="with --state: the next state of column C is column C+SUFFIX (default: _next)")
    p.add_argument("--trajectory-column", default=None, metavar="NAME",
                   help="trajectory id column: the next state is the next row of the same id "
                   "(default: a column named 'trajectory', if there is one)")


@dataclass(frozen=True)
class Columns:
    """The column options of a command: ``state``/``inputs`` None for the default names."""

    state: list[str] | None = None
    inputs: list[str] | None = None
    next_suffix: str = "_next"
    trajectory: str = "trajectory"
    trajectory_given: bool = False

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> Columns:
        state, inputs = args.state, args.input
        if state is None and inputs is not None:
            raise LCSInputError(
                f"input: expected --state too (they name the CSV columns together), received "
                f"--input {','.join(inputs)!r} alone"
            )
        if state is not None and inputs is None:
            raise LCSInputError(
                "input: expected the input columns with --state (--input '' for a system without "
                "inputs), received none"
            )
        if state == []:
            raise LCSInputError("state: expected at least one state column, received ''")
        suffix = "_next" if args.next_suffix is None else args.next_suffix
        if args.next_suffix is not None and state is None:
            raise LCSInputError(
                f"next_suffix: expected --state too (the default next-state columns are x_next_0, "
                f"x_next_1, ...), received --next-suffix {suffix!r} alone"
            )
        if not suffix:
            raise LCSInputError("next_suffix: expected a non-empty suffix such as '_next', received ''")
        trajectory = args.trajectory_column if args.trajectory_column is not None else "trajectory"
        if not trajectory.strip():
            raise LCSInputError("trajectory_column: expected a column name, received ''")
        if state is not None:
            both = [c for c in state if c in inputs]
            if both:
                raise LCSInputError(f"input: expected columns other than --state's, received {both} in both")
            if args.trajectory_column is not None and trajectory in state + inputs:
                raise LCSInputError(
                    f"trajectory_column: expected a column that is not a state or an input, "
                    f"received {trajectory!r}"
                )
            clash = [c + suffix for c in state if c + suffix in state + inputs]
            if clash:
                raise LCSInputError(
                    f"next_suffix: expected next-state columns other than the states and inputs, "
                    f"received {clash} (--state + {suffix!r})"
                )
        return cls(state, inputs, suffix, trajectory.strip(), args.trajectory_column is not None)

    @property
    def next_state(self) -> list[str] | None:
        return None if self.state is None else [c + self.next_suffix for c in self.state]


def _csv_header(path: str) -> list[str] | None:
    """The header of the CSV file ``path`` (its first line that is not blank or a comment), or
    None when it cannot be read: the library's reader then says why."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            for line in f:
                if line.strip() and not line.lstrip().startswith("#"):
                    return [h.strip() for h in next(csv.reader([line]))]
    except (OSError, UnicodeDecodeError, csv.Error):
        return None
    return None


def read_table(option: str, path: str, cols: Columns) -> tuple[Dataset, Trajectories | None]:
    """The transitions of the data file ``path`` given to ``--option``, and its trajectories
    when it is a trajectory file (else None); every problem is an :class:`LCSInputError` naming
    the option (or the column option at fault), the file and, for a missing column, the file's
    columns.

    - ``.npz``: :meth:`Dataset.save`'s arrays ``x, u, x_next``, or :meth:`Trajectories.save`'s
      ``x, u, offsets`` (a trajectory file).
    - ``.csv``: with a trajectory id column (``cols.trajectory``) and no next-state columns,
      or with the id column named by ``--trajectory-column``: one state per row, the next
      state in the next row of the same id (:meth:`Trajectories.load`); else one transition
      per row (:meth:`Dataset.from_csv`), the next state of column ``C`` in column
      ``C + cols.next_suffix``. ``cols.state`` / ``cols.inputs`` name the columns, or the
      default names ``x_0, ..., u_0, ..., x_next_0, ...`` are used.
    """
    where = f"--{option} file {path!r}"
    trajs = None
    try:
        if path.lower().endswith(".csv"):
            header = _csv_header(path)
            if cols.next_state is None:
                has_next = header is not None and any(re.fullmatch(r"x_next_\d+", h) for h in header)
            else:
                has_next = header is not None and all(c in header for c in cols.next_state)
            # a trajectory id column alongside next-state columns is a label, unless named
            is_traj = (header is not None and cols.trajectory in header
                       and (cols.trajectory_given or not has_next))
            if header is not None and cols.trajectory_given and not is_traj:
                raise LCSInputError(
                    f"trajectory_column: expected a column {cols.trajectory!r} (the trajectory id) "
                    f"in {where}, received columns {header}"
                )
            columns = None
            if cols.state is not None and cols.inputs is not None and header is not None:
                for name, wanted in (("state", cols.state), ("input", cols.inputs)):
                    missing = [c for c in wanted if c not in header]
                    if missing:
                        raise LCSInputError(
                            f"{name}: expected columns {wanted} in {where}, missing {missing} "
                            f"(its columns: {header})"
                        )
                columns = {"x": cols.state, "u": cols.inputs}
                if not is_traj:
                    nxt = cols.next_state or []
                    missing = [c for c in nxt if c not in header]
                    if missing:
                        raise LCSInputError(
                            f"next_suffix: expected next-state columns {nxt} (--state + "
                            f"{cols.next_suffix!r}) in {where}, missing {missing} (its columns: "
                            f"{header}); or a trajectory id column (--trajectory-column)"
                        )
                    columns["x_next"] = nxt
            if is_traj:
                trajs = Trajectories.load(path, columns=columns, trajectory=cols.trajectory)
            else:
                data = Dataset.load(path, columns=columns)
        elif os.path.isfile(path) and "offsets" in read_npz(path, "an .npz data or trajectory file"):
            trajs = Trajectories.load(path)
        else:
            data = Dataset.load(path)
    except LCSInputError as exc:
        message = str(exc)
        if message.split(":", 1)[0] in ("state", "input", "next_suffix", "trajectory_column"):
            raise
        message = message.removesuffix(_PYTHON_HINT) + (_CLI_HINT if message.endswith(_PYTHON_HINT) else "")
        err = reraise_for(option, LCSInputError(message))
        raise err if repr(path) in str(err) else LCSInputError(f"{err} (in {path!r})") from None
    if trajs is not None:
        data = trajs.to_transitions()
    if len(data) == 0:
        raise LCSInputError(f"{option}: expected at least one sample, received none in {path!r}")
    return data, trajs


def require(args: argparse.Namespace, *names: str) -> None:
    """An :class:`LCSInputError` naming the first option of ``names`` that was not given."""
    for name in names:
        if getattr(args, name) is None:
            raise LCSInputError(f"{name}: expected a value (the option is required), received none")


def reraise_for(option: str, exc: LCSInputError) -> LCSInputError:
    """``exc`` with its message attributed to the command-line ``option`` (``"data"`` ->
    ``"--data: ..."`` once :func:`main` prints it); a leading ``"path: "`` is dropped."""
    message = str(exc).removeprefix("path: ")
    return LCSInputError(f"{option}: {message}")


def check_target(option: str, path: str | None) -> None:
    """``path`` (if given) can be a file written later: not a directory, in an existing one."""
    if path is not None and (
        os.path.isdir(path) or not os.path.isdir(os.path.dirname(os.path.abspath(path)))
    ):
        raise LCSInputError(f"{option}: expected a file in an existing directory, received {path!r}")


def check_dims(option: str, path: str, data: Dataset, n_x: int, n_u: int, against: str) -> None:
    if (data.n_x, data.n_u) != (n_x, n_u):
        raise LCSInputError(
            f"{option}: expected n_x={n_x}, n_u={n_u} ({against}), received "
            f"n_x={data.n_x}, n_u={data.n_u} in {path!r}"
        )


def relative_error_for(option: str, model: Any, data: Dataset) -> float:
    """:func:`lcs_cvx.relative_error` with errors naming ``--option``."""
    try:
        return relative_error(model, data)
    except LCSInputError as exc:
        raise reraise_for(option, exc) from None


def jsonable(value: Any) -> Any:
    """``value`` with everything JSON cannot hold (non-finite floats, dtypes, paths, ...) as text."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    return str(value)
