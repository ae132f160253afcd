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
import math
import os
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from . import (
    Dataset,
    FallbackWarning,
    LCSInputError,
    SolverError,
    count_modes,
    make_dataset,
    random_lcs,
    relative_error,
    solve_lcp,
)

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
    p.add_argument(
        "--learn-n-lam", type=int, default=4,
        help="n_lam of the system learned in the second part; 0 skips learning (default: 4)",
    )
    p.add_argument(
        "--learn-n", type=_positive_int, default=10_000,
        help="training samples of the learning part (default: 10000)",
    )
    p.add_argument(
        "--learn-iterations", type=_positive_int, default=1500,
        help="Adam iterations of each learning run (default: 1500)",
    )


def _demo_learning(args: argparse.Namespace) -> None:
    """Learn a paper-style system (n_x, n_u, --learn-n-lam) with both losses from one start."""
    from . import LCS, fit, relative_error

    n_lam = args.learn_n_lam
    truth = random_lcs(args.n_x, args.n_u, n_lam, stiffness=args.stiffness, seed=args.seed + 1)
    train = make_dataset(truth, args.learn_n, noise=TRAIN_NOISE, seed=args.seed + 2)
    test = make_dataset(truth, 1000, seed=args.seed + 3)
    print(
        f"learning: a random LCS n_x={args.n_x}, n_u={args.n_u}, n_lam={n_lam} "
        f"({count_modes(truth, train)} modes in {len(train)} noisy samples)"
    )
    runs = (
        ("violation", {"recipe": "best", "refine_iterations": 5}),
        ("prediction", {"lr": 5e-3}),
    )
    for loss, options in runs:
        model = LCS(args.n_x, args.n_u, n_lam, stiffness=1.0, seed=args.seed + 4)
        t0 = time.perf_counter()
        fit(model, train, loss=loss, iterations=args.learn_iterations, progress=False,
            seed=args.seed, **options)
        print(
            f"  {loss:<10s} loss: e_test {relative_error(model, test):.3e} "
            f"({time.perf_counter() - t0:.1f} s, {'recipe best' if 'recipe' in options else 'Adam'})"
        )


def run_demo(args: argparse.Namespace) -> int:
    """Random paper-style LCS, a training set of ``--n`` samples, the fast LCP solve timed and
    checked against the Clarabel reference on a random subset."""
    system = random_lcs(args.n_x, args.n_u, args.n_lam, stiffness=args.stiffness, seed=args.seed)
    print(
        f"LCS: n_x={system.n_x}, n_u={system.n_u}, n_lam={system.n_lam} "
        f"(stiffness {args.stiffness:g}, seed {args.seed})"
    )
    print(f"sigma_min(F+F^T): {system.sigma_min:.6g}")

    t0 = time.perf_counter()
    data = make_dataset(system, args.n, noise=TRAIN_NOISE, seed=args.seed)
    print(f"data: {len(data)} samples, noise {TRAIN_NOISE:g} ({time.perf_counter() - t0:.2f} s)")
    print(f"hybrid modes: {count_modes(system, data)} distinct active sets in the data")

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
    if args.learn_n_lam > 0:
        _demo_learning(args)
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
    p.add_argument("--lcp", action="store_true",
                   help="instead: batched LCP solve rate vs Clarabel (n_lam 4, 10, 20; batch 200, 50,000)")
    p.add_argument("--threads", type=_positive_int, default=1, help="torch CPU threads (default: 1)")


def run_bench(args: argparse.Namespace) -> int:
    """Loss + gradient throughput of each solver path, side by side, with ratios to diffcp-Clarabel."""
    from .bench import DEFAULT_SIZES, format_table, run_lcp_bench
    from .bench import run_bench as bench_rows

    if args.lcp:
        table = run_lcp_bench(repeats=args.repeats)
    else:
        rows = bench_rows(args.sizes or DEFAULT_SIZES, args.paths, args.losses, batch=args.batch,
                          repeats=args.repeats, progress=lambda line: print(line, flush=True))
        table = format_table(rows)
    print(table)
    if args.out:
        from .io import atomic_write

        try:
            atomic_write(args.out, lambda f: f.write((table + "\n").encode()), name="out")
        except LCSInputError as exc:
            raise _reraise_for("out", exc) from None
    return 0


# -- fit and predict -------------------------------------------------------------------------
def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0, received {text!r}") from None
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, received {text!r}")
    return value


def _require(args: argparse.Namespace, *names: str) -> None:
    """An :class:`LCSInputError` naming the first option of ``names`` that was not given."""
    for name in names:
        if getattr(args, name) is None:
            raise LCSInputError(f"{name}: expected a value (the option is required), received none")


def _reraise_for(option: str, exc: LCSInputError) -> LCSInputError:
    """``exc`` with its message attributed to the command-line ``option`` (``"data"`` ->
    ``"--data: ..."`` once :func:`main` prints it); a leading ``"path: "`` is dropped."""
    message = str(exc).removeprefix("path: ")
    return LCSInputError(f"{option}: {message}")


def _load_data(option: str, path: str) -> Dataset:
    """:meth:`Dataset.load` with errors naming ``--option``; an empty data set is refused."""
    try:
        data = Dataset.load(path)
    except LCSInputError as exc:
        err = _reraise_for(option, exc)
        raise err if repr(path) in str(err) else LCSInputError(f"{err} (in {path!r})") from None
    if len(data) == 0:
        raise LCSInputError(f"{option}: expected at least one sample, received none in {path!r}")
    return data


def _check_target(option: str, path: str | None) -> None:
    """``path`` (if given) can be a file written later: not a directory, in an existing one."""
    if path is not None and (
        os.path.isdir(path) or not os.path.isdir(os.path.dirname(os.path.abspath(path)))
    ):
        raise LCSInputError(f"{option}: expected a file in an existing directory, received {path!r}")


def _check_dims(option: str, path: str, data: Dataset, n_x: int, n_u: int, against: str) -> None:
    if (data.n_x, data.n_u) != (n_x, n_u):
        raise LCSInputError(
            f"{option}: expected n_x={n_x}, n_u={n_u} ({against}), received "
            f"n_x={data.n_x}, n_u={data.n_u} in {path!r}"
        )


def _relative_error(option: str, model: Any, data: Dataset) -> float:
    """:func:`lcs_cvx.relative_error` with errors naming ``--option``."""
    try:
        return relative_error(model, data)
    except LCSInputError as exc:
        raise _reraise_for(option, exc) from None


def _jsonable(value: Any) -> Any:
    """``value`` with everything JSON cannot hold (non-finite floats, dtypes, paths, ...) as text."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    return str(value)


def _configure_fit(p: argparse.ArgumentParser) -> None:
    # required, but checked by run_fit: every command parses with no arguments (test_cli)
    p.add_argument("--data", help="training set, an .npz with x, u, x_next (required)")
    p.add_argument("--n-lam", type=_positive_int,
                   help="number of complementarity variables of the learned LCS (required)")
    p.add_argument("--out", help="model file to write, with lcs_cvx.save_model (required)")
    p.add_argument("--test", default=None, help="test set (.npz); its e_test is printed")
    p.add_argument("--stiffness", type=_positive_float, default=1.0,
                   help="s in F = G G^T + H - H^T + s I of the learned LCS (default: 1.0)")
    # None = not given: lcs_cvx.fit's own defaults and recipes decide
    p.add_argument("--loss", choices=("violation", "prediction"), default=None)
    p.add_argument("--optimizer", choices=("adam", "gauss-newton", "newton"), default=None)
    p.add_argument("--recipe", choices=("paper", "best"), default=None)
    p.add_argument("--iterations", type=_positive_int, default=None)
    p.add_argument("--lr", type=_positive_float, default=None, help="learning rate")
    p.add_argument("--batch-size", type=_positive_int, default=None)
    p.add_argument("--gamma", type=_positive_float, default=None,
                   help="gamma of the violation loss, 0 < gamma < sigma_min(F + F^T)")
    p.add_argument("--eps", type=_positive_float, default=None, help="epsilon of the violation loss")
    p.add_argument("--seed", type=_seed, default=None,
                   help="seed of the initialisation (default: 0) and of the training")
    p.add_argument("--checkpoint", default=None, help="checkpoint file written during training")
    p.add_argument("--resume", action="store_true", default=None,
                   help="continue from --checkpoint")
    p.add_argument("--threads", type=_positive_int, default=1, help="torch CPU threads (default: 1)")


def run_fit(args: argparse.Namespace) -> int:
    """Learn an LCS from ``--data`` with :func:`lcs_cvx.fit` and write it to ``--out``."""
    from dataclasses import asdict

    from . import LCS
    from . import fit as fit_lcs  # looked up at run time: tests replace lcs_cvx.fit
    from .io import save_model

    _require(args, "data", "n_lam", "out")
    train = _load_data("data", args.data)
    test = None
    if args.test is not None:
        test = _load_data("test", args.test)
        _check_dims("test", args.test, test, train.n_x, train.n_u, f"as in {args.data!r}")
    _check_target("out", args.out)  # fail before training, not after
    _check_target("checkpoint", args.checkpoint)
    if args.resume and args.checkpoint is None:
        raise LCSInputError("resume: expected --checkpoint PATH to resume from, received none")
    seed = 0 if args.seed is None else args.seed
    model = LCS(train.n_x, train.n_u, args.n_lam, stiffness=args.stiffness, seed=seed)
    # passed on to lcs_cvx.fit only when given: fit's defaults and recipes decide the rest
    passed = ("loss", "optimizer", "recipe", "iterations", "lr", "batch_size", "gamma", "eps",
              "seed", "checkpoint", "resume")
    options = {k: getattr(args, k) for k in passed if getattr(args, k) is not None}
    print(
        f"data: {len(train)} samples (n_x={train.n_x}, n_u={train.n_u})"
        + (f", test {len(test)} samples" if test is not None else "")
    )
    print(f"model: n_lam={args.n_lam}, stiffness {args.stiffness:g}, init seed {seed}", flush=True)

    t0 = time.perf_counter()
    try:
        result = fit_lcs(model, train, test=test, progress=True, **options)
    except LCSInputError as exc:  # fit names the training set "train"; here it is --data
        if str(exc).startswith("train: "):
            raise _reraise_for("data", LCSInputError(str(exc).removeprefix("train: "))) from None
        raise
    wall = time.perf_counter() - t0

    metadata = {
        "fit": _jsonable(asdict(result.settings)),
        "init": {"n_lam": args.n_lam, "stiffness": args.stiffness, "seed": seed},
        "data": {"train": args.data, "test": args.test, "n_train": len(train)},
    }
    try:
        save_model(result.model, args.out, metadata=metadata)
    except LCSInputError as exc:
        raise _reraise_for("out", exc) from None
    if test is not None:
        print(f"e_test: {_relative_error('test', result.model, test):.6g}")
    print(f"train relative error: {_relative_error('data', result.model, train):.6g}")
    print(f"wall time: {wall:.2f} s")
    print(f"saved: {args.out}")
    return 0


def _configure_predict(p: argparse.ArgumentParser) -> None:
    # required, but checked by run_predict: every command parses with no arguments (test_cli)
    p.add_argument("--model", help="model file written by lcs-cvx fit / save_model (required)")
    p.add_argument("--data", help="data set, an .npz with x, u, x_next (required)")
    p.add_argument("--out", default=None,
                   help="also write the predictions (arrays x_next_pred, lam) to this .npz")
    p.add_argument("--threads", type=_positive_int, default=1, help="torch CPU threads (default: 1)")


def run_predict(args: argparse.Namespace) -> int:
    """e_test and the number of hybrid modes of a saved model on a data set."""
    from .io import atomic_write, load_model

    _require(args, "model", "data")
    _check_target("out", args.out)
    try:
        model = load_model(args.model)
    except LCSInputError as exc:
        raise _reraise_for("model", exc) from None
    data = _load_data("data", args.data)
    _check_dims("data", args.data, data, model.n_x, model.n_u, f"the model's, {args.model!r}")
    model.requires_grad_(False)
    x, u = data.x.to(model.dtype), data.u.to(model.dtype)
    print(f"model: n_x={model.n_x}, n_u={model.n_u}, n_lam={model.n_lam} ({args.model})")
    print(f"data: {len(data)} samples ({args.data})")
    print(f"e_test: {_relative_error('data', model, data):.6g}")
    print(f"modes: {count_modes(model, data)}")
    if args.out is not None:
        with torch.no_grad():
            lam = model.solve_lcp(x, u).lam
            x_next = x @ model.A.mT + u @ model.B.mT + lam @ model.C.mT + model.d
        arrays = {"x_next_pred": x_next.cpu().numpy(), "lam": lam.cpu().numpy()}
        try:
            atomic_write(args.out, lambda f: np.savez(f, **arrays), name="out")
        except LCSInputError as exc:
            raise _reraise_for("out", exc) from None
        print(f"predictions: {args.out}")
    return 0


# -- study -----------------------------------------------------------------------------------
def _configure_study(p: argparse.ArgumentParser) -> None:
    from .study.runner import DEFAULT_OUT

    # not required here, but by run_study_command: every command parses with no arguments (test_cli)
    sub = p.add_subparsers(dest="study_command", metavar="{run,report}")
    run = sub.add_parser("run", help="run (or resume) the study of a config file",
                         description="Run the grid of a study config (studies/configs/*.toml); "
                         "finished cells are skipped, every result is written at once.")
    run.add_argument("config", help="study config, a TOML file (studies/configs/)")
    run.add_argument("--workers", type=_positive_int, default=None,
                     help="local worker processes, also of --scheduler local (default: the CPU "
                     "count; a tcp:// cluster has its own)")
    run.add_argument("--scheduler", default=None, metavar="ADDRESS",
                     help="run the cells on Dask: 'local' (a LocalCluster of --workers processes) "
                     "or a scheduler address tcp://host:8786 (default: a local process pool)")
    run.add_argument("--out", default=DEFAULT_OUT,
                     help=f"output directory holding the database (default: {DEFAULT_OUT})")
    run.add_argument("--only", default=None, metavar="KEY=VALUE[,...]",
                     help="run only matching cells; keys value, value_index, trial, method")
    run.add_argument("--max-cells", type=_positive_int, default=None,
                     help="run at most this many unfinished cells (the rest on a later run)")
    rep = sub.add_parser("report", help="figures and tables of every study in a directory",
                         description="Write <name>.png, <name>.pdf and <name>.md for every study "
                         "in DIR/studies.sqlite, with the authors' numbers from studies/anchors.toml.")
    rep.add_argument("dir", help="output directory of lcs-cvx study run")
    rep.add_argument("--anchors", default="default",
                     help="anchors file (default: studies/anchors.toml)")


def run_study_command(args: argparse.Namespace) -> int:
    """``lcs-cvx study run CONFIG`` / ``lcs-cvx study report DIR`` (see :mod:`lcs_cvx.study`)."""
    from .study import StudyError, report, run_config
    from .study.runner import parse_only

    if args.study_command is None:
        raise LCSInputError("study: expected a subcommand, 'run CONFIG' or 'report DIR'")
    if args.study_command == "report":
        for path in report(args.dir, anchors_path=args.anchors):
            print(f"wrote {path}")
        return 0
    only = parse_only(args.only) if args.only is not None else None
    try:
        summary = run_config(args.config, out=args.out, workers=args.workers,
                             scheduler=args.scheduler, only=only, max_cells=args.max_cells)
    except StudyError as exc:
        print(f"{PROG} study: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG} study: interrupted; finished cells are in {args.out}: run the same "
              "command again to resume", file=sys.stderr)
        return 130
    if summary is None:
        print(f"module study done: {args.config} -> {args.out}")
        return 0
    print(f"study {summary.study} (config {summary.config_hash}): {summary.total} cells, "
          f"{summary.skipped} already finished, {summary.executed} run now, {summary.failed} failed "
          f"({summary.wall_time:.1f} s)")
    print(f"database: {summary.database}")
    return 1 if summary.failed else 0


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
    Command(
        "fit",
        "learn an LCS from a data set (lcs_cvx.fit) and save it",
        _configure_fit,
        run_fit,
    ),
    Command(
        "predict",
        "e_test and hybrid modes of a saved model on a data set; optionally its predictions",
        _configure_predict,
        run_predict,
    ),
    Command(
        "study",
        "run a config-driven study of the paper's Fig. 1 (run CONFIG) or report on it (report DIR)",
        _configure_study,
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
