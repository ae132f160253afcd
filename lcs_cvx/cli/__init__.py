"""Command-line interface: ``lcs-cvx <command> [options]``.

Each subcommand is one :class:`Command` -- a name, a one-line help, a function that adds its
options to an ``argparse`` parser and a function that runs it and returns the exit code -- and
all of them are listed once, in :data:`COMMANDS`. A new subcommand is a new pair of functions and
one more entry there.

Exit codes: 0 success, 1 a failed check or a solver failure, 2 bad arguments (argparse's own
errors, and :class:`lcs_cvx.LCSInputError` raised by the library, printed as one line).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from .. import LCSInputError, SolverError
from ._args import PROG
from .bench import configure_bench, run_bench
from .demo import configure_demo, run_demo
from .fit import configure_fit, configure_predict, run_fit, run_predict
from .study import configure_study, run_study_command

__all__ = ["Command", "COMMANDS", "build_parser", "main"]


@dataclass(frozen=True)
class Command:
    """One subcommand: ``configure(parser)`` adds its options, ``run(args)`` returns the exit code."""

    name: str
    help: str
    configure: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


COMMANDS: tuple[Command, ...] = (
    Command(
        "demo",
        "random LCS and data set; the fast LCP solve timed and checked against Clarabel",
        configure_demo,
        run_demo,
    ),
    Command(
        "bench",
        "loss + gradient throughput of the fast path against the cvxpylayers references",
        configure_bench,
        run_bench,
    ),
    Command(
        "fit",
        "learn an LCS from a data set (lcs_cvx.fit) and save it",
        configure_fit,
        run_fit,
    ),
    Command(
        "predict",
        "e_test and hybrid modes of a saved model on a data set; optionally its predictions",
        configure_predict,
        run_predict,
    ),
    Command(
        "study",
        "run a config-driven study of the paper's Fig. 1 (run CONFIG) or report on it (report DIR)",
        configure_study,
        run_study_command,
    ),
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG, description="Learning linear complementarity systems (LCS) from data."
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="command")
    for cmd in COMMANDS:
        p = sub.add_parser(cmd.name, help=cmd.help, description=cmd.help)
        cmd.configure(p)
        p.set_defaults(run=cmd.run)
    return parser


def _option_message(message: str, args: argparse.Namespace) -> str:
    """Name the command-line option in a library message ``"n_lam: ..."`` -> ``"--n-lam: ..."``."""
    name, sep, rest = message.partition(":")
    if sep and name in vars(args) and name not in ("command", "run"):
        return f"--{name.replace('_', '-')}:{rest}"
    return message


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``lcs-cvx`` with ``argv`` (default ``sys.argv[1:]``); return the exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse has printed its message (or --help)
        return exc.code if isinstance(exc.code, int) else 2
    threads = torch.get_num_threads()
    wanted = getattr(args, "threads", 1)  # bench --throughput takes several counts: the first here
    torch.set_num_threads(wanted[0] if isinstance(wanted, list) else wanted)
    try:
        return args.run(args)
    except LCSInputError as exc:
        print(f"{PROG} {args.command}: error: {_option_message(str(exc), args)}", file=sys.stderr)
        return 2
    except SolverError as exc:
        print(f"{PROG} {args.command}: solver error: {exc}", file=sys.stderr)
        return 1
    finally:
        torch.set_num_threads(threads)


if __name__ == "__main__":
    raise SystemExit(main())
