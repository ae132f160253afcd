"""Solver-comparison study: loss + gradient throughput of each solver path.

Writes ``studies/results/solver_comparison.md`` (markdown table, with the command and the
machine) and ``solver_comparison.png`` (samples/s per size, log scale, one bar per path).

    python studies/solver_comparison.py [--repeats 5] [--batch 200] [--out studies/results]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys

import torch

from lcs_cvx.bench import DEFAULT_SIZES, LOSSES, PATHS, format_table, run_bench


def plot(rows, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sizes = sorted({(r.n_x, r.n_u, r.n_lam) for r in rows}, key=lambda s: (s[2], s[0]))
    fig, axes = plt.subplots(1, len(LOSSES), figsize=(11, 4), sharey=True)
    width = 0.8 / len(PATHS)
    for ax, loss in zip(axes, LOSSES, strict=True):
        for k, solver_path in enumerate(PATHS):
            vals = [
                next((r.samples_per_s for r in rows if (r.n_x, r.n_u, r.n_lam) == s
                      and r.loss == loss and r.path == solver_path), float("nan"))
                for s in sizes
            ]
            ax.bar([i + k * width for i in range(len(sizes))], vals, width, label=solver_path)
        ax.set_xticks([i + width for i in range(len(sizes))])
        ax.set_xticklabels([f"{s}" for s in sizes], rotation=30, fontsize=8)
        ax.set_yscale("log")
        ax.set_title(f"{loss} loss + gradient, batch {rows[0].batch}")
        ax.set_xlabel("(n_x, n_u, n_λ)")
        ax.grid(True, axis="y", which="both", alpha=0.3)
    axes[0].set_ylabel("samples / s (1 torch thread)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--batch", type=int, default=200)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results"))
    ap.add_argument("--quick", action="store_true", help="one small size, fast path + Clarabel")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    sizes = [(4, 2, 3)] if args.quick else DEFAULT_SIZES
    paths = ("fast", "cvxpylayers") if args.quick else PATHS
    rows = run_bench(sizes, paths, LOSSES, batch=args.batch, repeats=args.repeats,
                     progress=lambda s: print(s, flush=True))
    os.makedirs(args.out, exist_ok=True)
    table = format_table(rows)
    cmd = "python studies/solver_comparison.py " + " ".join(argv if argv is not None else sys.argv[1:])
    with open(os.path.join(args.out, "solver_comparison.md"), "w") as f:
        f.write("# Solver comparison: loss + gradient throughput\n\n")
        f.write(f"Command: `{cmd.strip()}`  \nMachine: {platform.processor() or platform.machine()}, "
                f"{os.cpu_count()} cores, torch {torch.__version__}, 1 torch thread, "
                f"median of {args.repeats} repeats, batch {args.batch}, γ = 1e-2, ε = 1e-4.\n\n")
        f.write(table + "\n")
    with open(os.path.join(args.out, "solver_comparison.json"), "w") as f:
        json.dump([r.as_dict() for r in rows], f, indent=1)
    plot(rows, os.path.join(args.out, "solver_comparison.png"))
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
