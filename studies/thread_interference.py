"""Other thread pools' spinning threads against the compiled kernels' threads: the speed-up of two
threads over one for `violation_value_and_grad` at 50,000 samples, (10, 4, 4), when a NumPy
matrix product on two BLAS threads, or a parallel torch operation, runs just before each call,
with and without the environment that makes those pools' idle threads sleep at once.

    python -m studies.thread_interference [--out studies/results] [--repeats 41]

Each case runs in its own process (the environment is read when a library loads); in it, 1 and 2
threads are timed in turn, ``repeats`` times each after a warm-up, and the medians kept. Writes
``OUT/thread_interference.md``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time

#: (name, what runs before each call, extra environment)
CASES = (
    ("nothing before the call", "none", {}),
    ("a 300 x 300 NumPy product on 2 BLAS threads", "numpy", {}),
    ("the same, OPENBLAS_NUM_THREADS=1", "numpy", {"OPENBLAS_NUM_THREADS": "1"}),
    ("the same, NumPy's BLAS set to 1 thread after the product (threadpoolctl)", "numpy-limit", {}),
    ("a parallel torch operation (2 threads)", "torch", {}),
    ("the same, OMP_WAIT_POLICY=PASSIVE", "torch", {"OMP_WAIT_POLICY": "PASSIVE"}),
    ("the same, GOMP_SPINCOUNT=0", "torch", {"GOMP_SPINCOUNT": "0"}),
)


def case(before: str, repeats: int) -> float:
    """The speed-up of 2 threads over 1 with ``before`` run before each call (in this process)."""
    import numpy as np
    import torch
    from threadpoolctl import ThreadpoolController

    from lcs_cvx.bench import perturbed
    from lcs_cvx.data import make_dataset, random_lcs
    from lcs_cvx.value_and_grad import violation_value_and_grad

    truth = random_lcs(10, 4, 4, stiffness=0.5, seed=0)
    data = make_dataset(truth, 50_000, noise=1e-2, seed=1)
    model = perturbed(truth, 0.05, 2)
    big, M = torch.rand(2_000_000, dtype=torch.float64), np.random.default_rng(0).random((300, 300))
    numpy_blas = [lib for lib in ThreadpoolController().select(user_api="blas").lib_controllers
                  if "numpy" in lib.filepath]
    counts = [lib.get_num_threads() for lib in numpy_blas]

    def call(threads: int) -> float:
        torch.set_num_threads(threads)
        if before.startswith("numpy"):
            M @ M
            if before == "numpy-limit":
                for lib in numpy_blas:
                    lib.set_num_threads(1)
        elif before == "torch":
            (big * 2.0).sum()
        t0 = time.perf_counter()
        violation_value_and_grad(model, data.x, data.u, data.x_next, threads=threads)
        dt = time.perf_counter() - t0
        if before == "numpy-limit":  # NumPy's BLAS back to its threads for the next product
            for lib, count in zip(numpy_blas, counts, strict=True):
                lib.set_num_threads(count)
        return dt

    for _ in range(5):
        call(1), call(2)
    times: dict[int, list[float]] = {1: [], 2: []}
    for _ in range(repeats):
        for t in (1, 2):
            times[t].append(call(t))
    return statistics.median(times[1]) / statistics.median(times[2])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join("studies", "results"))
    ap.add_argument("--repeats", type=int, default=41)
    ap.add_argument("--case", default=None, help=argparse.SUPPRESS)  # one case, in a child process
    args = ap.parse_args(argv)
    if args.case is not None:
        print(case(args.case, args.repeats))
        return 0
    lines = ["| before each call | 2 threads / 1 thread |", "|---|---:|"]
    for name, before, env in CASES:
        out = subprocess.run([sys.executable, "-m", "studies.thread_interference", "--case", before,
                              "--repeats", str(args.repeats)], env={**os.environ, **env},
                             capture_output=True, text=True, check=True)
        lines.append(f"| {name} | {float(out.stdout.split()[-1]):.2f}× |")
        print(lines[-1], flush=True)
    text = ("# Other thread pools against the compiled kernels' threads\n\n"
            f"`python -m studies.thread_interference --repeats {args.repeats}` (violation loss and gradient, "
            "(10, 4, 4), 50,000 samples, medians of interleaved calls; each case in its own process).\n\n"
            + "\n".join(lines) + "\n")
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "thread_interference.md"), "w") as fh:
        fh.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
