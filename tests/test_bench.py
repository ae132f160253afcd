"""The solver-comparison benchmark runs end to end on a tiny size (timings are not asserted)."""

import math

import pytest

from lcs_cvx.bench import format_table, run_bench


@pytest.fixture
def short_timing(monkeypatch):
    """The benchmark's warm-up and minimum timed window off: these tests check what it computes,
    not how fast."""
    from lcs_cvx import bench

    monkeypatch.setattr(bench, "WARMUP_S", 0.0)
    monkeypatch.setattr(bench, "MIN_TIMED_S", 0.0)


def test_bench_tiny_runs_and_paths_agree(short_timing):
    rows = run_bench([(3, 1, 2)], paths=("fast", "cvxpylayers"), batch=8, repeats=1)
    assert len(rows) == 4  # 2 losses x 2 paths
    for r in rows:
        assert r.samples_per_s > 0 and math.isfinite(r.samples_per_s)
        # every path solves the same problem: lam and loss agree with the fast path (loosely:
        # diffcp-Clarabel reaches |d lam| ~ 1e-6 here, and lam_i ~ 1e-6 on an active bound costs
        # a first-order amount of the loss; tight agreement is tested in test_losses.py)
        assert r.lam_err < 1e-4, r
        assert r.loss_err < 1e-4, r
    fast = [r for r in rows if r.path == "fast"]
    assert all(r.lam_err == 0.0 and r.loss_err == 0.0 for r in fast)
    table = format_table(rows)
    assert table.splitlines()[0].startswith("| (n_x, n_u, n_λ)")
    assert "| fast |" in table and "| cvxpylayers |" in table


def test_lcp_bench_tiny(short_timing):
    from lcs_cvx.bench import run_lcp_bench

    table = run_lcp_bench(n_lams=(2,), batches=(50,), repeats=1, n_reference=5)
    lines = table.splitlines()
    assert lines[0].startswith("| n_λ | batch | fast samples/s")
    row = [c.strip() for c in lines[2].strip("|").split("|")]
    assert row[0] == "2" and row[1] == "50"
    assert float(row[2].replace(",", "")) > 0 and float(row[3].replace(",", "")) > 0
    assert float(row[5]) < 1e-6  # fast and Clarabel agree


class VirtualClock:
    """Stands in for the ``time`` module of :mod:`lcs_cvx.bench`: ``perf_counter()`` reads a
    clock that only the timed function advances, so these tests count calls, not seconds. The
    steps are powers of two: the clock's sums are exact."""

    def __init__(self) -> None:
        self.now = 0.0

    def perf_counter(self) -> float:
        return self.now


def test_time_warms_up_to_a_steady_state(monkeypatch):
    """A fast path is called for WARMUP_S before it is timed (the first few hundred calls of a
    process ran slower here), and a repeat averages as many calls as fill MIN_REPEAT_S."""
    from lcs_cvx import bench

    clock, step = VirtualClock(), 2.0**-10  # one call takes ~1 ms of the virtual clock
    monkeypatch.setattr(bench, "time", clock)
    monkeypatch.setattr(bench, "WARMUP_S", 50 * step)
    monkeypatch.setattr(bench, "MIN_REPEAT_S", 10 * step)
    monkeypatch.setattr(bench, "MIN_TIMED_S", 0.0)
    stamps = []

    def fn():
        stamps.append(clock.now)
        clock.now += step

    t = bench.median_time(fn, repeats=2)
    assert t == step  # the mean time of one call
    # one set-up call, >= WARMUP_S of warm-up calls, then 2 repeats of MIN_REPEAT_S each
    warm = [s for s in stamps[1:] if s - stamps[1] < 50 * step]
    assert len(warm) == 50
    assert len(stamps) - 1 - len(warm) == 2 * 10


def test_time_fills_the_minimum_timed_window(monkeypatch):
    """Short repeats continue until MIN_TIMED_S is filled (slow phases of the machine are then a
    minority of the repeats whose median is kept)."""
    from lcs_cvx import bench

    clock, step = VirtualClock(), 2.0**-14  # one call takes ~61 us of the virtual clock
    monkeypatch.setattr(bench, "time", clock)
    monkeypatch.setattr(bench, "WARMUP_S", 0.0)
    monkeypatch.setattr(bench, "MIN_REPEAT_S", 0.001)
    monkeypatch.setattr(bench, "MIN_TIMED_S", 0.1)
    calls = []

    def fn():
        calls.append(clock.now)
        clock.now += step

    bench.median_time(fn, repeats=2)
    assert len(calls) > 100  # ~0.1 s of calls, not 2 repeats of a few
    assert clock.now - calls[2] >= 0.1  # the repeats after the set-up and warm-up calls


def test_throughput_tiny(short_timing):
    """The batch-size curve: a row per (loss, batch) with a positive rate, threads and dtype as
    asked (a batch large enough to be split across the two threads included)."""
    import torch

    from lcs_cvx._kernels.calls import MIN_CHUNK
    from lcs_cvx.bench import run_throughput

    threads = torch.get_num_threads()
    try:
        table = run_throughput([(3, 1, 2)], batches=(16, 2 * MIN_CHUNK), threads=(1, 2), repeats=1)
    finally:
        torch.set_num_threads(threads)
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in table.splitlines()[2:]]
    big = f"{2 * MIN_CHUNK:,}"
    assert [(r[1], r[5], r[4]) for r in rows] == [
        (loss, batch, t) for loss in ("violation", "prediction") for batch in ("16", big) for t in ("1", "2")]
    assert all(r[2] == "cpu" and r[3] == "float64" for r in rows)
    assert all(float(r[6].replace(",", "")) > 0 for r in rows)
    assert all(r[7] == "1.00" for r in rows if r[4] == "1") and torch.get_num_threads() == threads


def test_cli_throughput_and_its_device_errors(capsys, monkeypatch):
    """``lcs-cvx bench --throughput`` prints the table; ``--device`` names what it expected where
    the machine has no such device or the solver comparison cannot run there (exit 2)."""
    import torch

    from lcs_cvx import bench
    from lcs_cvx.cli import main

    monkeypatch.setattr(bench, "WARMUP_S", 0.0)
    monkeypatch.setattr(bench, "MIN_TIMED_S", 0.0)
    threads = torch.get_num_threads()
    try:
        assert main(["bench", "--throughput", "--sizes", "3,1,2", "--batches", "8,16", "--repeats", "1",
                     "--losses", "violation"]) == 0
    finally:
        torch.set_num_threads(threads)
    out = capsys.readouterr().out
    assert out.count("| (3, 1, 2) | violation | cpu | float64 | 1 |") == 2 * 2  # progress lines and table
    assert main(["bench", "--throughput", "--sizes", "3,1,2", "--batches", "8", "--repeats", "1",
                 "--losses", "prediction", "--threads", "1,2"]) == 0
    assert capsys.readouterr().out.count("| (3, 1, 2) | prediction | cpu | float64 |") == 2 * 2
    if not torch.cuda.is_available():
        assert main(["bench", "--throughput", "--device", "cuda"]) == 2
        assert "--device: expected a device this machine has" in capsys.readouterr().err
    assert main(["bench", "--device", "cuda"]) == 2
    assert "--device: the solver comparison runs on the CPU" in capsys.readouterr().err
    assert main(["bench", "--throughput", "--device", "tpu"]) == 2
