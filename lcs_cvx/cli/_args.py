"""The command line's argument types and the checks its commands share: an option's value is
refused with a message naming ``--option`` (:func:`reraise_for`), printed as one line by
:func:`lcs_cvx.cli.main`."""

from __future__ import annotations

import argparse
import math
import os
from typing import Any

from .. import Dataset, LCSInputError, Trajectories, relative_error
from ..data import read_csv
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


def load_data(option: str, path: str) -> Dataset:
    """:meth:`Dataset.load` with errors naming ``--option``; an empty data set is refused."""
    try:
        data = Dataset.load(path)
    except LCSInputError as exc:
        err = reraise_for(option, exc)
        raise err if repr(path) in str(err) else LCSInputError(f"{err} (in {path!r})") from None
    if len(data) == 0:
        raise LCSInputError(f"{option}: expected at least one sample, received none in {path!r}")
    return data


def load_trajectories(option: str, path: str) -> Trajectories | None:
    """:meth:`Trajectories.load` with errors naming ``--option`` when ``path`` is a trajectory
    file (an ``.npz`` with an ``offsets`` array, a ``.csv`` with a ``trajectory`` column), else
    None: a file that cannot be read is left to :func:`load_data` to report."""
    try:
        if path.lower().endswith(".csv"):
            found = "trajectory" in read_csv(path)[0]
        else:
            found = os.path.isfile(path) and "offsets" in read_npz(path, "an .npz file")
    except LCSInputError:
        return None
    if not found:
        return None
    try:
        return Trajectories.load(path)
    except LCSInputError as exc:
        err = reraise_for(option, exc)
        raise err if repr(path) in str(err) else LCSInputError(f"{err} (in {path!r})") from None


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
