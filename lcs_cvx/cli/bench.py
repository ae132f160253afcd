"""``lcs-cvx bench``: loss + gradient throughput of every solver path, side by side."""

from __future__ import annotations

import argparse

from .. import LCSInputError
from ._args import positive_int, positive_ints, reraise_for, sizes

__all__ = ["configure_bench", "run_bench"]


def configure_bench(p: argparse.ArgumentParser) -> None:
    from ..bench import LOSSES, PATHS

    p.add_argument("--sizes", type=sizes, default=None,
                   help="'n_x,n_u,n_lam;...' (default: the five sizes of the solver comparison)")
    p.add_argument("--paths", nargs="+", choices=PATHS, default=list(PATHS),
                   help="solver paths (default: all)")
    p.add_argument("--losses", nargs="+", choices=LOSSES, default=list(LOSSES))
    p.add_argument("--batch", type=positive_int, default=200, help="batch size (default: 200)")
    p.add_argument("--repeats", type=positive_int, default=5, help="timed calls; the median is kept")
    p.add_argument("--out", default=None, help="also write the markdown table to this file")
    p.add_argument("--lcp", action="store_true",
                   help="instead: batched LCP solve rate vs Clarabel (n_lam 4, 10, 20; batch 200, 50,000)")
    p.add_argument("--threads", type=positive_ints, default=[1],
                   help="CPU threads: torch's, and the compiled kernels' on large batches (default: 1); "
                        "with --throughput, several comma-separated counts are timed side by side")
    p.add_argument("--rigid-body", action="store_true",
                   help="instead: loss + gradient of the cube's per-sample LCSs (lcs_cvx.RigidBodyContact, 8 corners, "
                        "4 friction directions) on --batch recorded transitions near contact, fast vs cvxpylayers")
    p.add_argument("--throughput", action="store_true",
                   help="instead: one-call loss + gradient throughput against the batch size "
                        "(--batches, --device, --dtype, --threads; sizes default (10, 4, 4))")
    p.add_argument("--fit-step", action="store_true",
                   help="instead: one fit step at full batch (paper recipe) against the one-call loss + gradient "
                        "of the same data (--batches, default 200,000 and 1,000,000; --threads; --losses)")
    p.add_argument("--c3", action="store_true",
                   help="instead: ms per C3 solve on C3's cart-pole, C3's defaults (unbounded and |u| bounded) "
                        "and the c3+ projection against a plain dense NumPy C3+")
    p.add_argument("--authors", default=None, metavar="PATH",
                   help="instead: loss + gradient and loss + backward() against the paper's authors' learners, from "
                        "a DAIRLab/Learning-LCS checkout at PATH (needs casadi), at the n_x = 10 sizes of Fig. 1 "
                        "(or --sizes), --batch, --repeats (default 5), one torch thread")
    p.add_argument("--batches", type=positive_ints, default=None,
                   help="batch sizes of --throughput (default: 200 to 1,000,000) or --fit-step, comma-separated")
    p.add_argument("--device", default="cpu", help="device of --throughput: cpu (default) or cuda")
    p.add_argument("--dtype", choices=("float64", "float32"), default="float64",
                   help="dtype of --throughput (default: float64)")


def run_bench(args: argparse.Namespace) -> int:
    """Loss + gradient throughput of each solver path, side by side, with ratios to diffcp-Clarabel."""
    from ..bench import DEFAULT_SIZES, format_table, run_lcp_bench
    from ..bench import run_bench as bench_rows

    if args.device != "cpu" and not args.throughput:
        raise LCSInputError(f"--device: the solver comparison runs on the CPU (its reference paths are "
                            f"CVXPY's); expected cpu, or --throughput, received {args.device!r}")
    if args.throughput:
        import torch

        from ..bench import THROUGHPUT_BATCHES, run_throughput

        if args.device.startswith("cuda") and not torch.cuda.is_available():
            raise LCSInputError(f"--device: expected a device this machine has, received {args.device!r} "
                                "(torch.cuda.is_available() is False)")
        if args.device != "cpu" and not args.device.startswith("cuda"):
            raise LCSInputError(f"--device: expected cpu or cuda[:N], received {args.device!r}")
        table = run_throughput(args.sizes or ((10, 4, 4),), args.losses, args.batches or THROUGHPUT_BATCHES,
                               device=args.device, threads=args.threads, dtype=getattr(torch, args.dtype),
                               repeats=args.repeats, progress=lambda line: print(line, flush=True))
    elif args.fit_step:
        from ..speed import run_fit_step

        table = "\n\n".join(
            run_fit_step(args.batches or (200_000, 1_000_000), *(args.sizes or ((10, 4, 4),))[:1], loss=loss,
                         threads=args.threads[0], repeats=args.repeats, progress=lambda line: print(line, flush=True))
            for loss in args.losses)
    elif args.authors:
        from ..authors import N_X_10_SIZES, run_authors

        table = run_authors(args.authors, list(args.sizes or N_X_10_SIZES), tuple(args.losses), batch=args.batch,
                            repeats=args.repeats, progress=lambda line: print(line, flush=True))
    elif args.c3:
        from ..speed import run_c3_bench

        table = run_c3_bench(repeats=args.repeats, progress=lambda line: print(line, flush=True))
    elif args.lcp:
        table = run_lcp_bench(repeats=args.repeats)
    elif args.rigid_body:
        from ..bench import run_rigid_body_bench

        table = run_rigid_body_bench(batch=args.batch, repeats=args.repeats,
                                     progress=lambda line: print(line, flush=True))
    else:
        rows = bench_rows(args.sizes or DEFAULT_SIZES, args.paths, args.losses, batch=args.batch,
                          repeats=args.repeats, progress=lambda line: print(line, flush=True))
        table = format_table(rows)
    print(table)
    if args.out:
        from ..io import atomic_write

        try:
            atomic_write(args.out, lambda f: f.write((table + "\n").encode()), name="out")
        except LCSInputError as exc:
            raise reraise_for("out", exc) from None
    return 0
