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
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from . import LCSInputError, SolverError, count_modes, make_dataset, random_lcs, solve_lcp
from .lcp import FallbackWarning

__all__ = ["Command", "COMMANDS", "build_parser", "main"]

PROG = "lcs-cvx"

#: Standard deviation of the noise on the paper's training data (Sec. 5).
TRAIN_NOISE = 1e-2
#: Samples the demo re-solves with the Clarabel reference.
N_CHECK = 20
#: The demo fails when ``max |lam_fast - lam_ref| > CHECK_TOL * (1 + max |lam_ref|)``.
CHECK_TOL = 1e-6


@dataclass(frozen=True)
class Command:
    """One subcommand: ``configure(parser)`` adds its options, ``run(args)`` returns the exit code."""

    name: str
    help: str
    configure: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


# -- argument types --------------------------------------------------------------------------
def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, received {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, received {text!r}")
    return value


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer seed, received {text!r}") from None
    if not 0 <= value < 2**63:
        raise argparse.ArgumentTypeError(f"expected a seed in [0, 2**63), received {text!r}")
    return value


# -- demo ------------------------------------------------------------------------------------
def _configure_demo(p: argparse.ArgumentParser) -> None:
    p.add_argument("--n-x", type=int, default=10, help="state dimension (default: 10)")
    p.add_argument("--n-u", type=int, default=4, help="input dimension (default: 4)")
    p.add_argument("--n-lam", type=int, default=20, help="complementarity dimension (default: 20)")
    p.add_argument("--n", type=int, default=50_000, help="number of samples (default: 50000)")
    p.add_argument(
        "--seed", type=_seed, default=0, help="seed of the system and the data (default: 0)"
    )
    p.add_argument(
        "--stiffness",
        type=float,
        default=0.5,
        help="s in F = G G^T + H - H^T + s I; sigma_min(F + F^T) >= 2 s (default: 0.5)",
    )
    p.add_argument(
        "--threads", type=_positive_int, default=1, help="torch CPU threads (default: 1)"
    )


def run_demo(args: argparse.Namespace) -> int:
    """Random paper-style LCS, a training set of ``--n`` samples, the fast LCP solve timed and
    checked against the Clarabel reference on a random subset."""
    system = random_lcs(args.n_x, args.n_u, args.n_lam, args.stiffness, args.seed)
    print(
        f"LCS: n_x={system.n_x}, n_u={system.n_u}, n_lam={system.n_lam} "
        f"(stiffness {args.stiffness:g}, seed {args.seed})"
    )
    print(f"sigma_min(F+F^T): {system.sigma_min:.6g}")

    t0 = time.perf_counter()
    data = make_dataset(system, args.n, noise=TRAIN_NOISE, seed=args.seed)
    print(f"data: {len(data)} samples, noise {TRAIN_NOISE:g} ({time.perf_counter() - t0:.2f} s)")
    print(f"hybrid modes: {count_modes(system, data.x, data.u)} distinct active sets in the data")

    with torch.no_grad():
        F = system.F
        q = system.lcp_offset(data.x, data.u)
    t0 = time.perf_counter()
    fast = solve_lcp(F, q)
    t_fast = time.perf_counter() - t0
    rate_fast = len(q) / t_fast
    threads = torch.get_num_threads()
    print(
        f"fast LCP: {rate_fast:.0f} samples/s ({len(q)} in {t_fast:.3f} s, "
        f"{threads} thread{'s' * (threads != 1)}, {fast.iterations} pivoting sweeps)"
    )
    print(f"max LCP residual: {float(fast.residual.max()):.3g}")
    print(f"fallbacks: {fast.n_fallback}")

    gen = torch.Generator().manual_seed(args.seed)
    idx = torch.randperm(len(q), generator=gen)[: min(N_CHECK, len(q))]
    solve_lcp(F, q[idx[:1]], method="cvxpy")  # warm-up: CVXPY compiles the DPP problem once
    t0 = time.perf_counter()
    ref = solve_lcp(F, q[idx], method="cvxpy")
    t_ref = time.perf_counter() - t0
    rate_ref = len(idx) / t_ref
    diff = float((fast.lam[idx] - ref.lam).abs().max())
    print(f"Clarabel: {rate_ref:.0f} samples/s ({len(idx)} in {t_ref:.3f} s)")
    print(f"max |lam_fast - lam_clarabel|: {diff:.3g} over {len(idx)} random samples")
    print(f"speed-up: {rate_fast / rate_ref:.0f}x (fast vs Clarabel, samples/s)")

    bound = CHECK_TOL * (1.0 + float(ref.lam.abs().max()))
    if not diff <= bound:
        print(
            f"{PROG} demo: check failed: max |lam_fast - lam_clarabel| = {diff:.3g} > {bound:.3g}",
            file=sys.stderr,
        )
        return 1
    return 0


def _sizes(text: str) -> list[tuple[int, int, int]]:
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


def _configure_bench(p: argparse.ArgumentParser) -> None:
    from .bench import LOSSES, PATHS

    p.add_argument("--sizes", type=_sizes, default=None,
                   help="'n_x,n_u,n_lam;...' (default: the five sizes of the solver comparison)")
    p.add_argument("--paths", nargs="+", choices=PATHS, default=list(PATHS),
                   help="solver paths (default: all)")
    p.add_argument("--losses", nargs="+", choices=LOSSES, default=list(LOSSES))
    p.add_argument("--batch", type=_positive_int, default=200, help="batch size (default: 200)")
    p.add_argument("--repeats", type=_positive_int, default=5, help="timed calls; the median is kept")
    p.add_argument("--out", default=None, help="also write the markdown table to this file")
    p.add_argument("--threads", type=_positive_int, default=1, help="torch CPU threads (default: 1)")


def run_bench(args: argparse.Namespace) -> int:
    """Loss + gradient throughput of each solver path, side by side, with ratios to diffcp-Clarabel."""
    from .bench import DEFAULT_SIZES, format_table
    from .bench import run_bench as _run

    rows = _run(args.sizes or DEFAULT_SIZES, args.paths, args.losses, batch=args.batch,
                repeats=args.repeats, progress=lambda line: print(line, flush=True))
    table = format_table(rows)
    print(table)
    if args.out:
        with open(args.out, "w") as f:
            f.write(table + "\n")
    return 0


# -- registry and entry point ----------------------------------------------------------------
COMMANDS: tuple[Command, ...] = (
    Command(
        "demo",
        "random LCS and data set; the fast LCP solve timed and checked against Clarabel",
        _configure_demo,
        run_demo,
    ),
    Command(
        "bench",
        "loss + gradient throughput of the fast path against the cvxpylayers references",
        _configure_bench,
        run_bench,
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
    torch.set_num_threads(getattr(args, "threads", 1))
    try:
        with warnings.catch_warnings():
            # a fallback is reported in the output ("fallbacks: k"), not as a warning
            warnings.simplefilter("ignore", FallbackWarning)
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
