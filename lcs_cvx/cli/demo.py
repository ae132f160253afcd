"""``lcs-cvx demo``: a random paper-style LCS, its data, the fast LCP solve timed and checked
against the Clarabel reference, then learning a small system with both losses."""

from __future__ import annotations

import argparse
import sys
import time

import torch

from .. import count_modes, make_dataset, random_lcs, solve_lcp
from ._args import PROG, positive_int, seed

__all__ = ["configure_demo", "run_demo"]

#: Standard deviation of the noise on the paper's training data (Sec. 5).
TRAIN_NOISE = 1e-2

#: Samples the demo re-solves with the Clarabel reference.
N_CHECK = 20

#: The demo fails when ``max |lam_fast - lam_ref| > CHECK_TOL * (1 + max |lam_ref|)``.
CHECK_TOL = 1e-6


def configure_demo(p: argparse.ArgumentParser) -> None:
    p.add_argument("--n-x", type=int, default=10, help="state dimension (default: 10)")
    p.add_argument("--n-u", type=int, default=4, help="input dimension (default: 4)")
    p.add_argument("--n-lam", type=int, default=20, help="complementarity dimension (default: 20)")
    p.add_argument("--n", type=int, default=50_000, help="number of samples (default: 50000)")
    p.add_argument(
        "--seed", type=seed, default=0, help="seed of the system and the data (default: 0)"
    )
    p.add_argument(
        "--stiffness",
        type=float,
        default=0.5,
        help="s in F = G G^T + H - H^T + s I; sigma_min(F + F^T) >= 2 s (default: 0.5)",
    )
    p.add_argument(
        "--threads", type=positive_int, default=1, help="torch CPU threads (default: 1)"
    )
    p.add_argument(
        "--learn-n-lam", type=int, default=4,
        help="n_lam of the system learned in the second part; 0 skips learning (default: 4)",
    )
    p.add_argument(
        "--learn-n", type=positive_int, default=10_000,
        help="training samples of the learning part (default: 10000)",
    )
    p.add_argument(
        "--learn-iterations", type=positive_int, default=1500,
        help="Adam iterations of each learning run (default: 1500)",
    )


def _demo_learning(args: argparse.Namespace) -> None:
    """Learn a paper-style system (n_x, n_u, --learn-n-lam) with both losses from one start."""
    from .. import LCS, fit, relative_error

    n_lam = args.learn_n_lam
    truth = random_lcs(args.n_x, args.n_u, n_lam, stiffness=args.stiffness, seed=args.seed + 1)
    train = make_dataset(truth, args.learn_n, noise=TRAIN_NOISE, seed=args.seed + 2)
    test = make_dataset(truth, 1000, seed=args.seed + 3)
    print(
        f"learning: a random LCS n_x={args.n_x}, n_u={args.n_u}, n_lam={n_lam} "
        f"({count_modes(truth, train)} modes in {len(train)} noisy samples; the first run on a machine "
        f"also compiles the training kernels, about a minute, cached on disk for the next)"
    )
    runs = (
        ("violation", {"recipe": "best", "refine_iterations": 5}),
        ("prediction", {"recipe": "plain", "lr": 5e-3}),
    )
    for loss, options in runs:
        model = LCS(args.n_x, args.n_u, n_lam, stiffness=1.0, seed=args.seed + 4)
        t0 = time.perf_counter()
        fit(model, train, loss=loss, iterations=args.learn_iterations, progress=False,
            seed=args.seed, **options)
        print(
            f"  {loss:<10s} loss: e_test {relative_error(model, test):.3e} "
            f"({time.perf_counter() - t0:.1f} s, {'recipe best' if options['recipe'] == 'best' else 'Adam'})"
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
