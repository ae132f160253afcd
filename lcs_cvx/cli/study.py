"""``lcs-cvx study run CONFIG`` and ``lcs-cvx study report DIR`` (:mod:`lcs_cvx.study`)."""

from __future__ import annotations

import argparse
import sys

from .. import LCSInputError
from ._args import PROG, positive_int

__all__ = ["configure_study", "run_study_command"]


def configure_study(p: argparse.ArgumentParser) -> None:
    from ..study.runner import DEFAULT_OUT

    # not required here, but by run_study_command: every command parses with no arguments (test_cli)
    sub = p.add_subparsers(dest="study_command", metavar="{run,report}")
    run = sub.add_parser("run", help="run (or resume) the study of a config file",
                         description="Run the grid of a study config (studies/configs/*.toml); "
                         "finished cells are skipped, every result is written at once.")
    run.add_argument("config", help="study config, a TOML file (studies/configs/)")
    run.add_argument("--workers", type=positive_int, default=None,
                     help="local worker processes, also of --scheduler local (default: the CPU "
                     "count; a tcp:// cluster has its own)")
    run.add_argument("--scheduler", default=None, metavar="ADDRESS",
                     help="run the cells on Dask: 'local' (a LocalCluster of --workers processes) "
                     "or a scheduler address tcp://host:8786 (default: a local process pool)")
    run.add_argument("--out", default=DEFAULT_OUT,
                     help=f"output directory holding the database (default: {DEFAULT_OUT})")
    run.add_argument("--only", default=None, metavar="KEY=VALUE[,...]",
                     help="run only matching cells; keys value, value_index, trial, method")
    run.add_argument("--max-cells", type=positive_int, default=None,
                     help="run at most this many unfinished cells (the rest on a later run)")
    run.add_argument("--ensemble", action="store_true",
                     help="train the trials of each swept value and method together, in one "
                     "batched loop per worker (the same results as one by one)")
    run.add_argument("--ensemble-size", type=positive_int, default=None, metavar="K",
                     help="with --ensemble: at most K cells per ensemble (default: all the trials "
                     "of a swept value and method)")
    rep = sub.add_parser("report", help="figures and tables of every study in a directory",
                         description="Write <name>.png, <name>.pdf and <name>.md for every study "
                         "in DIR/studies.sqlite, with the authors' numbers from studies/anchors.toml.")
    rep.add_argument("dir", help="output directory of lcs-cvx study run")
    rep.add_argument("--anchors", default="default",
                     help="anchors file (default: studies/anchors.toml)")


def run_study_command(args: argparse.Namespace) -> int:
    """``lcs-cvx study run CONFIG`` / ``lcs-cvx study report DIR`` (see :mod:`lcs_cvx.study`)."""
    from ..study import StudyError, report, run_config
    from ..study.runner import parse_only

    if args.study_command is None:
        raise LCSInputError("study: expected a subcommand, 'run CONFIG' or 'report DIR'")
    if args.study_command == "report":
        for path in report(args.dir, anchors_path=args.anchors):
            print(f"wrote {path}")
        return 0
    only = parse_only(args.only) if args.only is not None else None
    try:
        summary = run_config(args.config, out=args.out, workers=args.workers,
                             scheduler=args.scheduler, only=only, max_cells=args.max_cells,
                             ensemble=args.ensemble, ensemble_size=args.ensemble_size)
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
          f"({summary.wall_time:.1f} s)"
          + (f"; {summary.timed_out} timed out" if summary.timed_out else "")
          + (f"; {summary.baseline_failed} baseline fits failed (recorded as 'failed')"
             if summary.baseline_failed else ""))
    print(f"database: {summary.database}")
    return 1 if summary.failed else 0
