"""Solver-comparison benchmark: loss + gradient throughput of each solver path.

For each system size, a random ground truth (:func:`lcs_cvx.random_lcs`, stiffness 0.5), a
noisy batch from it (:func:`lcs_cvx.make_dataset`, noise 1e-2) and a model that is the truth
with every parameter perturbed by ``0.05 N(0, 1)`` (a mid-training model: the active sets are
neither trivial nor those of the truth). One timed call is ``loss(...)`` followed by
``.backward()``, as in a training step (without the diagnostics of the ``*_loss_info`` variants);
throughput is ``batch / median(time)`` over ``repeats`` timed repeats (more, to fill
:data:`MIN_TIMED_S`) after a warm-up of :data:`WARMUP_S`, a repeat being the mean of as many calls
as fill :data:`MIN_REPEAT_S` (one call of a reference path).
Errors are the max-abs difference of ``lam`` and the relative difference of the loss,
``|loss - loss_fast| / (1 + |loss_fast|)``, against the fast path.

Measure with one torch thread (``torch.set_num_threads(1)``) in one process, side by side.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass

import torch

from .data import make_dataset, random_lcs
from .losses import prediction_loss, prediction_loss_info, violation_loss, violation_loss_info
from .system import LCS

__all__ = ["BenchRow", "DEFAULT_SIZES", "THROUGHPUT_BATCHES", "run_bench", "format_table", "run_lcp_bench",
           "run_throughput", "run_rigid_body_bench", "median_time", "perturbed"]

#: (n_x, n_u, n_lam) of the comparison with the authors' code (the paper's sizes).
DEFAULT_SIZES: tuple[tuple[int, int, int], ...] = (
    (10, 4, 4),
    (10, 4, 10),
    (10, 4, 20),
    (64, 4, 10),
    (128, 4, 10),
)
PATHS = ("fast", "cvxpylayers", "cvxpylayers-scs")
LOSSES = ("violation", "prediction")


@dataclass(frozen=True)
class BenchRow:
    """One measurement: a loss on one path at one size."""

    n_x: int
    n_u: int
    n_lam: int
    loss: str
    path: str
    batch: int
    samples_per_s: float
    median_s: float
    lam_err: float
    loss_err: float

    def as_dict(self) -> dict:
        return asdict(self)


def perturbed(truth: LCS, scale: float, seed: int) -> LCS:
    """A copy of ``truth`` with every parameter plus ``scale * N(0, 1)`` (seeded): a
    mid-training model, whose active sets are neither trivial nor the truth's."""
    model = LCS(truth.n_x, truth.n_u, truth.n_lam, stiffness=float(truth.stiffness), init_scale=0.0)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            src = getattr(truth, name)
            p.copy_(src + scale * torch.randn(src.shape, generator=gen, dtype=src.dtype))
    return model


def _loss_fn(loss: str, gamma: float, eps: float) -> Callable:
    """``fn(model, x, u, x_next, solver, info)``: the loss, or its :class:`LossInfo` if ``info``."""
    if loss == "violation":
        return lambda m, x, u, xn, solver, info=False: (violation_loss_info if info else violation_loss)(
            m, x, u, xn, gamma=gamma, eps=eps, solver=solver
        )
    return lambda m, x, u, xn, solver, info=False: (prediction_loss_info if info else prediction_loss)(
        m, x, u, xn, solver=solver
    )


#: One timed repeat lasts at least this long: a fast call (~1 ms) is repeated inside it and
#: averaged, so the median over repeats is not one call's scheduling jitter.
MIN_REPEAT_S = 0.05

#: Before the timed repeats a path is called for at least this long (once if one call takes
#: longer): the first calls of a process run slower than the steady state (allocations,
#: imports, caches), and the first row of a benchmark would otherwise measure them.
WARMUP_S = 0.5

#: A path is timed for at least this long, in more repeats than asked if they are short: a
#: shared machine can have slow phases longer than a few short repeats, which would then fall
#: into one entirely; the median over a longer window is the machine's usual speed.
MIN_TIMED_S = 3.0


def median_time(fn: Callable[[], None], repeats: int) -> float:
    """Median over at least ``repeats`` repeats (and :data:`MIN_TIMED_S`) of the mean time of
    one call, each repeat ``ceil(MIN_REPEAT_S / t_call)`` calls long (one call for the slow
    reference paths), after a warm-up: one call (which compiles the CVXPY problem / layer on
    first use), then calls for :data:`WARMUP_S`, whose mean is ``t_call``."""
    fn()
    t0, n = time.perf_counter(), 0
    while True:
        fn()
        n += 1
        if time.perf_counter() - t0 >= WARMUP_S:
            break
    calls = max(1, math.ceil(MIN_REPEAT_S * n / max(time.perf_counter() - t0, 1e-9)))
    times: list[float] = []
    start = time.perf_counter()
    while len(times) < repeats or time.perf_counter() - start < MIN_TIMED_S:
        t0 = time.perf_counter()
        for _ in range(calls):
            fn()
        times.append((time.perf_counter() - t0) / calls)
    return statistics.median(times)


def run_bench(
    sizes: Iterable[tuple[int, int, int]] = DEFAULT_SIZES,
    paths: Iterable[str] = PATHS,
    losses: Iterable[str] = LOSSES,
    batch: int = 200,
    repeats: int = 5,
    gamma: float = 1e-2,
    eps: float = 1e-4,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> list[BenchRow]:
    """Measure every (size, loss, path); returns one :class:`BenchRow` each."""
    rows: list[BenchRow] = []
    paths = list(paths)
    for n_x, n_u, n_lam in sizes:
        truth = random_lcs(n_x, n_u, n_lam, stiffness=0.5, seed=seed)
        data = make_dataset(truth, batch, noise=1e-2, seed=seed + 1)
        model = perturbed(truth, 0.05, seed + 2)
        for loss in losses:
            fn = _loss_fn(loss, gamma, eps)
            ref_info = fn(model, data.x, data.u, data.x_next, "fast", True)
            ref_loss = ref_info.loss
            for path in paths:
                def call(path=path, fn=fn, model=model, data=data):  # what a training step runs
                    model.zero_grad()
                    fn(model, data.x, data.u, data.x_next, path).backward()

                med = median_time(call, repeats)
                info = fn(model, data.x, data.u, data.x_next, path, True)
                value = info.loss
                row = BenchRow(
                    n_x, n_u, n_lam, loss, path, batch, batch / med, med,
                    float((info.lam - ref_info.lam).abs().max()),
                    float((value - ref_loss).abs().detach() / (1.0 + ref_loss.abs().detach())),
                )
                rows.append(row)
                if progress is not None:
                    progress(
                        f"({n_x},{n_u},{n_lam}) {loss:<10s} {path:<16s} "
                        f"{row.samples_per_s:>10.0f} samples/s"
                    )
    return rows


def format_table(rows: list[BenchRow]) -> str:
    """Markdown table with the ratio of each path to the diffcp-Clarabel reference."""
    ref = {
        (r.n_x, r.n_u, r.n_lam, r.loss): r.samples_per_s for r in rows if r.path == "cvxpylayers"
    }
    lines = [
        "| (n_x, n_u, n_λ) | loss | path | samples/s | × reference | max abs Δλ | rel. Δloss |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        base = ref.get((r.n_x, r.n_u, r.n_lam, r.loss))
        ratio = f"{r.samples_per_s / base:.1f}" if base else "—"
        lines.append(
            f"| ({r.n_x}, {r.n_u}, {r.n_lam}) | {r.loss} | {r.path} | {r.samples_per_s:,.0f} | "
            f"{ratio} | {r.lam_err:.1e} | {r.loss_err:.1e} |"
        )
    return "\n".join(lines)


def run_lcp_bench(
    n_lams: Iterable[int] = (4, 10, 20),
    batches: Iterable[int] = (200, 50_000),
    repeats: int = 5,
    n_reference: int = 50,
    seed: int = 0,
) -> str:
    """Batched LCP solve rate (``lcs_cvx.solve_lcp``, fast path) against the Clarabel reference
    (``method="cvxpy"``, one CVXPY solve per sample, on ``n_reference`` samples), n_x = 10,
    n_u = 4, in one process. Returns a markdown table."""
    from .lcp import solve_lcp

    lines = [
        "| n_λ | batch | fast samples/s | Clarabel samples/s | ratio | max abs Δλ |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for n_lam in n_lams:
        truth = random_lcs(10, 4, n_lam, stiffness=0.5, seed=seed)
        data = make_dataset(truth, max(batches), seed=seed + 1)
        with torch.no_grad():
            F, q_all = truth.F, truth.lcp_offset(data.x, data.u)
        q_ref = q_all[:n_reference]
        ref = solve_lcp(F, q_ref[:1], method="cvxpy")  # compile the DPP problem once
        t_ref = median_time(lambda F=F, q_ref=q_ref: solve_lcp(F, q_ref, method="cvxpy"), max(1, repeats // 2))
        ref = solve_lcp(F, q_ref, method="cvxpy")
        for batch in batches:
            q = q_all[:batch]
            t_fast = median_time(lambda F=F, q=q: solve_lcp(F, q), repeats)
            err = float((solve_lcp(F, q_ref).lam - ref.lam).abs().max())
            fast, clar = batch / t_fast, len(q_ref) / t_ref
            lines.append(
                f"| {n_lam} | {batch:,} | {fast:,.0f} | {clar:,.0f} | {fast / clar:,.0f} | {err:.1e} |"
            )
    return "\n".join(lines)


#: The batch sizes of :func:`run_throughput` (a curve from a training minibatch to a full batch).
THROUGHPUT_BATCHES: tuple[int, ...] = (200, 2_000, 20_000, 50_000, 200_000, 1_000_000)


def run_throughput(
    sizes: Iterable[tuple[int, int, int]] = ((10, 4, 4),),
    losses: Iterable[str] = LOSSES,
    batches: Iterable[int] = THROUGHPUT_BATCHES,
    device: str = "cpu",
    threads: int | Iterable[int] = 1,
    dtype: torch.dtype = torch.float64,
    repeats: int = 5,
    gamma: float = 1e-2,
    eps: float = 1e-4,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> str:
    """Throughput of the one-call loss and gradient (:func:`lcs_cvx.violation_value_and_grad`,
    :func:`lcs_cvx.prediction_value_and_grad`) against the batch size, on ``device`` in
    ``dtype``, with each count of ``threads`` (the compiled kernels' on the CPU, and torch's); a
    mid-training model as in :func:`run_bench`. The thread counts of one batch are timed side by
    side: each repeat times one call of each in turn (after a warm-up of each), and the median
    over at least ``repeats`` repeats and :data:`MIN_TIMED_S` is kept; ``× first`` is the speed-up
    over the first count. On a GPU each call is followed by ``torch.cuda.synchronize()``.
    Returns a markdown table (samples/s)."""
    from .value_and_grad import prediction_value_and_grad, violation_value_and_grad

    counts = [threads] if isinstance(threads, int) else list(threads)
    dev = torch.device(device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    lines = ["| (n_x, n_u, n_λ) | loss | device | dtype | threads | batch | samples/s | × first |",
             "|---|---|---|---|---:|---:|---:|---:|"]
    batches = sorted(batches)
    torch_threads = torch.get_num_threads()
    try:
        for n_x, n_u, n_lam in sizes:
            truth = random_lcs(n_x, n_u, n_lam, stiffness=0.5, seed=seed)
            data = make_dataset(truth, max(batches), noise=1e-2, seed=seed + 1)
            model = perturbed(truth, 0.05, seed + 2).to(device=dev, dtype=dtype)
            x_all, u_all, xn_all = (t.to(device=dev, dtype=dtype) for t in (data.x, data.u, data.x_next))
            for loss in losses:
                for batch in batches:
                    x, u, xn = x_all[:batch], u_all[:batch], xn_all[:batch]

                    def call(t: int, x=x, u=u, xn=xn, loss=loss, model=model) -> float:
                        torch.set_num_threads(t)
                        t0 = time.perf_counter()
                        if loss == "violation":
                            violation_value_and_grad(model, x, u, xn, gamma=gamma, eps=eps, threads=t)
                        else:
                            prediction_value_and_grad(model, x, u, xn, threads=t)
                        sync()
                        return time.perf_counter() - t0

                    times: dict[int, list[float]] = {t: [] for t in counts}
                    warm_until = time.perf_counter() + WARMUP_S
                    while time.perf_counter() < warm_until:
                        for t in counts:
                            call(t)
                    start = time.perf_counter()
                    while min(len(v) for v in times.values()) < repeats or time.perf_counter() - start < MIN_TIMED_S:
                        for t in counts:
                            times[t].append(call(t))
                    rates = {t: batch / statistics.median(v) for t, v in times.items()}
                    for t in counts:
                        lines.append(f"| ({n_x}, {n_u}, {n_lam}) | {loss} | {dev.type} | "
                                     f"{str(dtype).split('.')[-1]} | {t} | {batch:,} | {rates[t]:,.0f} | "
                                     f"{rates[t] / rates[counts[0]]:.2f} |")
                        if progress is not None:
                            progress(lines[-1])
    finally:
        torch.set_num_threads(torch_threads)
    return "\n".join(lines)


def run_rigid_body_bench(batch: int = 200, repeats: int = 5, gamma: float = 1e-2, eps: float = 1e-2,
                         friction_directions: int = 4, seed: int = 0, contact_only: bool = True,
                         progress: Callable[[str], None] | None = None) -> str:
    """Loss + gradient of a rigid body's per-sample LCSs (:class:`lcs_cvx.RigidBodyContact`, the
    ContactNets cube: 8 corners, ``friction_directions`` cone edges, ``n_lam = 32`` at 4) on
    ``batch`` transitions of the recorded cube tosses (:func:`lcs_cvx.datasets.cube_tosses`),
    drawn at random among those with a corner within 1 cm of the floor (``contact_only``; else
    among all), on the fast path and on the cvxpylayers reference, side by side; a call is
    ``loss(...).backward()`` as in a training step. Returns a markdown table."""
    from .datasets import CUBE_DT, CUBE_MASS, CUBE_SIDE, cube_tosses
    from .kinematics import rotation_matrix
    from .rigid_body import RigidBodyContact

    data = cube_tosses().to_transitions()
    model = RigidBodyContact(half_sizes=[CUBE_SIDE / 2] * 3, mass=CUBE_MASS, dt=CUBE_DT, mu=0.15,
                             ground=-0.0012, friction_directions=friction_directions)
    x = data.x
    with torch.no_grad():
        lowest = (x[:, 6:7] + (model.vertices @ rotation_matrix(x[:, :4]).mT)[..., 2]).amin(1)
    pool = torch.nonzero(lowest < 0.01 if contact_only else torch.ones_like(lowest, dtype=torch.bool)).flatten()
    idx = pool[torch.randperm(len(pool), generator=torch.Generator().manual_seed(seed))[:batch]]
    xb, ub, xnb = data.x[idx], data.u[idx], data.x_next[idx]
    lines = ["| loss | path | batch | n_λ | samples/s | × reference | rel. Δloss |", "|---|---|---:|---:|---:|---:|---:|"]
    for loss in LOSSES:
        fn = _loss_fn(loss, gamma, eps)
        ref = fn(model, xb, ub, xnb, "fast", True).loss.detach()
        rates: dict[str, tuple[float, float]] = {}
        for path in ("cvxpylayers", "fast"):
            def call(path: str = path, fn: Callable = fn) -> None:
                model.zero_grad()
                fn(model, xb, ub, xnb, path).backward()

            med = median_time(call, repeats)
            value = fn(model, xb, ub, xnb, path, True).loss.detach()
            rates[path] = (len(idx) / med, float((value - ref).abs() / (1.0 + ref.abs())))
            if progress is not None:
                progress(f"rigid body {loss:<10s} {path:<12s} {rates[path][0]:>10.0f} samples/s")
        for path in ("fast", "cvxpylayers"):
            rate, err = rates[path]
            lines.append(f"| {loss} | {path} | {len(idx)} | {model.n_lam} | {rate:,.0f} | "
                         f"{rate / rates['cvxpylayers'][0]:.1f} | {err:.1e} |")
    return "\n".join(lines)
