"""Training on a GPU against the CPU: one ``fit`` of the same model and data on each device.

The same Adam run (``recipe="paper"`` with the batch, step count and learning rate given) is
timed on every ``--device``: on the CPU with ``--threads`` threads (the compiled kernels'), on a
GPU on torch arrays. Large batches are where a GPU pays (the benchmarks page's throughput
curves); the paper's batch of 200 is faster on the CPU. Each row: the device, the wall time of
``fit``, the time per step, and the final model's relative error on a held-out test set (the
paper's ``e_test``), which agree between devices to round-off.

    python -m studies.solvers.device_training --devices cpu cuda --samples 1000000 \\
        --batch 1000000 --iterations 100 --threads 16
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

import lcs_cvx
from lcs_cvx.bench import perturbed, random_lcs

__all__ = ["main", "time_fit"]


def time_fit(device: str, size: tuple[int, int, int], samples: int, batch: int, iterations: int,
             lr: float, threads: int, seed: int = 0) -> dict:
    """One ``fit`` on ``device``: a perturbed copy of a random LCS of ``size`` from ``samples``
    noisy transitions; returns the row (wall time, time per step, e_test)."""
    truth = random_lcs(*size, stiffness=0.5, seed=seed)
    train = lcs_cvx.make_dataset(truth, samples, noise=1e-2, seed=seed + 1).to(device)
    test = lcs_cvx.make_dataset(truth, 2000, seed=seed + 3).to(device)
    model = perturbed(truth, 0.05, seed + 2).to(device)
    torch.set_num_threads(threads)
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    options = {"recipe": "paper", "batch_size": batch, "lr": lr, "progress": False, "threads": threads}
    # the same fit on a copy first, untimed: CUDA's libraries load and the CPU kernels compile
    # (about half a minute on a machine without numba's cache) on first use
    lcs_cvx.fit(perturbed(truth, 0.05, seed + 2).to(device), train, iterations=iterations,
                eval_every=iterations, **options)
    sync()
    t0 = time.perf_counter()
    lcs_cvx.fit(model, train, iterations=iterations, eval_every=iterations, **options)
    sync()
    wall = time.perf_counter() - t0
    e_test = lcs_cvx.relative_error(model, test)
    return {"device": torch.device(device).type, "threads": threads, "samples": samples, "batch": batch,
            "iterations": iterations, "wall_s": wall, "ms_per_step": 1e3 * wall / iterations,
            "e_test": float(e_test)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--devices", nargs="+", default=["cpu"])
    p.add_argument("--size", default="10,4,4", help="n_x,n_u,n_lam")
    p.add_argument("--samples", type=int, default=1_000_000)
    p.add_argument("--batch", type=int, default=1_000_000)
    p.add_argument("--iterations", type=int, default=100)
    p.add_argument("--lr", type=float, default=1e-2)
    p.add_argument("--threads", type=int, default=torch.get_num_threads())
    p.add_argument("--out", default=None, help="also write the markdown table here")
    args = p.parse_args(argv)
    size = tuple(int(v) for v in args.size.split(","))
    lines = ["| device | threads | samples | batch | steps | fit (s) | ms / step | e_test |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for device in args.devices:
        r = time_fit(device, size, args.samples, args.batch, args.iterations, args.lr, args.threads)
        lines.append(f"| {r['device']} | {r['threads']} | {r['samples']:,} | {r['batch']:,} | "
                     f"{r['iterations']} | {r['wall_s']:.2f} | {r['ms_per_step']:.1f} | {r['e_test']:.3e} |")
        print(lines[-1], flush=True)
    table = "\n".join(lines)
    print(table)
    if args.out:
        Path(args.out).write_text(table + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
