"""Large batches in parts and across threads (lcs_cvx/_kernels/calls.py): a compiled call of at
least ``2 * MIN_CHUNK`` samples is solved in parts of ``MIN_CHUNK`` to ``2 MIN_CHUNK - 1``
samples, shared among the threads and combined in their order. The parts depend on the batch
only, so every thread count gives the same numbers bit for bit (the same operations in the same
order); against one whole call, each sample is solved by the same operations except the batch
products (BLAS blocks a part otherwise than the whole), and the mean loss and its gradients are
the parts' means weighted back together (another order of the sums): equal to round-off."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import make_problem, rel_err

import lcs_cvx
from lcs_cvx import LCSInputError
from lcs_cvx._kernels import calls
from lcs_cvx._kernels.calls import MIN_CHUNK, chunks, resolve_threads
from lcs_cvx.losses import prediction_fast, violation_fast
from lcs_cvx.system import PARAMETER_NAMES

GAMMA, EPS = 1e-2, 1e-3


def test_chunks_split_rows_evenly_above_the_threshold():
    assert chunks(2 * MIN_CHUNK) == [(0, MIN_CHUNK), (MIN_CHUNK, 2 * MIN_CHUNK)]
    assert chunks(2 * MIN_CHUNK - 1) == [(0, 2 * MIN_CHUNK - 1)]  # a part below MIN_CHUNK: one
    assert chunks(5) == [(0, 5)]
    parts = chunks(10 * MIN_CHUNK + 3)
    sizes = [b - a for a, b in parts]
    assert len(parts) == 10 and parts[0][0] == 0 and parts[-1][1] == 10 * MIN_CHUNK + 3
    assert max(sizes) - min(sizes) <= 1 and all(parts[i][1] == parts[i + 1][0] for i in range(9))


def test_threads_default_to_torchs_and_bad_counts_are_named():
    assert resolve_threads(None) == torch.get_num_threads() and resolve_threads(3) == 3
    model, data = make_problem(n_lam=2, n=10, seed=0)
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(LCSInputError, match="^threads: expected an integer >= 1"):
            lcs_cvx.violation_loss(model, data.x, data.u, data.x_next, threads=bad)
    with pytest.raises(LCSInputError, match="^threads:"):
        lcs_cvx.prediction_value_and_grad(model, data.x, data.u, data.x_next, threads=0)
    with pytest.raises(LCSInputError, match="^threads:"):
        lcs_cvx.fit(model, data, recipe="plain", iterations=1, progress=False, threads=0)


@pytest.mark.parametrize("loss", ["violation", "prediction"])
def test_every_thread_count_gives_the_same_numbers_and_a_whole_calls(loss, monkeypatch):
    """A batch of ``3 MIN_CHUNK + 37`` samples (three parts) on one, two and three threads: the
    same solutions, active sets, value and gradients, bit for bit; against the batch solved as
    one part, the same active sets and the rest to round-off."""
    model, data = make_problem(n_lam=4, n=3 * MIN_CHUNK + 37, model="perturbed", seed=3)
    fn = violation_fast if loss == "violation" else prediction_fast
    kw = {"gamma": GAMMA, "eps": EPS} if loss == "violation" else {}

    def run(threads):
        model.zero_grad()
        info = fn(model, data.x, data.u, data.x_next, threads=threads, **kw)
        info.loss.backward()
        return info, {k: getattr(model, k).grad.clone() for k in PARAMETER_NAMES}

    one, g1 = run(1)
    for threads in (2, 3):
        other, g = run(threads)
        assert torch.equal(other.active, one.active) and torch.equal(other.lam, one.lam)
        assert torch.equal(other.loss.detach(), one.loss.detach())
        assert all(torch.equal(g[k], g1[k]) for k in PARAMETER_NAMES)
    monkeypatch.setattr(calls, "chunks", lambda N: [(0, N)])  # one whole call
    whole, gw = run(2)
    assert torch.equal(whole.active, one.active)
    assert float((whole.lam - one.lam).abs().max()) <= 1e-12 * (1 + float(one.lam.abs().max()))
    assert float(whole.loss.detach()) == pytest.approx(float(one.loss.detach()), rel=1e-12, abs=0)
    for name in PARAMETER_NAMES:
        assert rel_err(gw[name], g1[name]) <= 1e-11, name
    # the one-call API: value and gradients, the same way
    vg = getattr(lcs_cvx, f"{loss}_value_and_grad")
    v1, d1 = vg(model, data.x, data.u, data.x_next, threads=1, **kw)
    v2, d2 = vg(model, data.x, data.u, data.x_next, threads=2, **kw)
    assert torch.equal(v1, v2) and all(torch.equal(d1[k], d2[k]) for k in PARAMETER_NAMES)


def test_a_part_that_does_not_converge_hands_the_whole_batch_over(monkeypatch):
    """With no pivoting sweep allowed, a split call reports its unconverged samples like a
    whole one: the array kernels end them with the reference (FallbackWarning), the same counts."""
    from lcs_cvx import FallbackWarning
    from lcs_cvx import losses as losses_module

    model, data = make_problem(n_lam=4, n=2 * MIN_CHUNK, model="perturbed", seed=1)
    monkeypatch.setattr(losses_module, "MAX_ITER", 0)
    counts = []
    for threads in (1, 2):
        with pytest.warns(FallbackWarning):
            counts.append(violation_fast(model, data.x, data.u, data.x_next, gamma=GAMMA, eps=EPS,
                                         threads=threads).n_fallback)
    assert counts[0] == counts[1] > 0


def test_non_finite_data_in_a_later_part_are_named():
    model, data = make_problem(n_lam=3, n=2 * MIN_CHUNK + 5, seed=4)
    x = data.x.clone()
    x[-1, 0] = float("nan")
    with pytest.raises(LCSInputError, match="^x: expected finite values"):
        lcs_cvx.violation_value_and_grad(model, x, data.u, data.x_next, threads=2)
    assert np.isfinite(float(lcs_cvx.violation_loss(model, data.x, data.u, data.x_next, threads=2).detach()))


def test_row_kernels_are_numpys_take_and_put():
    """The gathers and write-back of a minibatch's rows (lcs_cvx/_kernels/rows.py) against
    NumPy's indexing, the weighted sum of a call's parts against Python's ``sum``, bit for bit."""
    from lcs_cvx._kernels.rows import AHEAD, all_seen, put_rows, take_batch, weighted_rows

    rng = np.random.default_rng(0)
    N = 3 * AHEAD + 50
    x, u, xn = rng.normal(size=(N, 5)), rng.normal(size=(N, 2)), rng.normal(size=(N, 5))
    warm = rng.random((N, 6)) < 0.5
    for rows in (rng.permutation(N), rng.permutation(N)[:AHEAD - 3], np.zeros(0, dtype=np.int64)):
        got = take_batch(x, u, xn, warm, rows)
        for a, b in zip(got, (x, u, xn, warm), strict=True):
            assert a.dtype == b.dtype and np.array_equal(a, b[rows])
        assert take_batch(x, u, xn, calls.COLD, rows)[3] is not None  # the cold start passes through
    table, seen = np.zeros((N, 6), dtype=np.bool_), np.zeros(N, dtype=np.bool_)
    rows = rng.permutation(N)[: N // 2]
    assert not all_seen(seen, rows)
    put_rows(table, seen, rows, warm[: len(rows)])
    assert np.array_equal(table[rows], warm[: len(rows)]) and all_seen(seen, rows)
    assert seen.sum() == len(rows) and not table[~seen].any()
    w, parts = rng.random(7), rng.normal(size=(7, 11))
    assert np.array_equal(weighted_rows(w, parts), sum(wk * p for wk, p in zip(w, parts, strict=True)))


@pytest.mark.parametrize("loss", ["violation", "prediction"])
def test_a_call_on_rows_is_the_call_on_the_gathered_batch(loss):
    """``compiled_call(..., rows=)`` (a minibatch read where it lies, the warm start read from a
    table and the active sets written back, a training step's) against the batch gathered first:
    the same value and gradients, bit for bit, on one part and on several, on 1 and 2 threads."""
    from lcs_cvx import losses

    model, data = make_problem(n_lam=3, n=5 * MIN_CHUNK, model="perturbed", seed=6)
    params, arrays, s = calls.model_arrays(model)
    n = model.n_lam
    if loss == "violation":
        fn, width, opts = calls.compiled().violation, 2 * n, (GAMMA, EPS, losses.VIOLATION_TOL, losses.MAX_ITER,
                                                              losses.STALL)
    else:
        fn, width, opts = calls.compiled().prediction, n, (losses.LCP_TOL, losses.MAX_ITER, losses.STALL,
                                                           losses.DEGENERATE_TOL)
    xa, ua, xna = (t.numpy() for t in (data.x, data.u, data.x_next))
    rng = np.random.default_rng(1)
    for size in (MIN_CHUNK // 2, 3 * MIN_CHUNK + 11):
        rows = rng.permutation(len(xa))[:size]
        _, first = calls.compiled_call(fn, arrays, float(s), xa[rows], ua[rows], xna[rows], None, width, *opts,
                                       tensors=False)
        table = np.zeros((len(xa), width), dtype=np.bool_)
        table[rows] = ~first[4]  # a warm start other than the answer
        seen = np.zeros(len(xa), dtype=np.bool_)
        for threads in (1, 2):
            status, want = calls.compiled_call(fn, arrays, float(s), xa[rows], ua[rows], xna[rows], table[rows],
                                               width, *opts, tensors=False, threads=threads)
            store = (table.copy(), seen.copy())
            status2, got = calls.compiled_call(fn, arrays, float(s), xa, ua, xna, table, width, *opts, tensors=False,
                                               threads=threads, rows=rows, store=store, per_sample=False)
            assert status == status2 == 0
            assert got[0] == want[0] and all(np.array_equal(a, b) for a, b in zip(got[1], want[1], strict=True))
            assert got[2] is got[3] is got[4] is None
            assert np.array_equal(store[0][rows], want[4]) and store[1][rows].all() and store[1].sum() == size


def test_the_lean_loss_is_the_loss_of_the_info_path():
    """``violation_loss`` / ``prediction_loss`` on the compiled kernel without the diagnostics:
    the value and gradients of the ``*_info`` call, bit for bit (the same kernel call)."""
    model, data = make_problem(n_lam=4, n=300, model="perturbed", seed=8)
    for plain, info in ((lcs_cvx.violation_loss, lcs_cvx.violation_loss_info),
                        (lcs_cvx.prediction_loss, lcs_cvx.prediction_loss_info)):
        grads = []
        for fn in (lambda plain=plain: plain(model, data.x, data.u, data.x_next),
                   lambda info=info: info(model, data.x, data.u, data.x_next).loss):
            model.zero_grad()
            value = fn()
            value.backward()
            grads.append((value.detach(), [getattr(model, k).grad.clone() for k in PARAMETER_NAMES]))
        assert torch.equal(grads[0][0], grads[1][0])
        assert all(torch.equal(a, b) for a, b in zip(grads[0][1], grads[1][1], strict=True))


def test_parts_go_to_whichever_thread_is_free():
    """The calling thread is held up on its first part until the other thread has run every
    other part: each part runs once, the calling thread runs one (a fixed split would have given
    it half, and the other thread could not finish the rest)."""
    import threading

    main = threading.get_ident()
    ran: list[tuple[int, bool]] = []
    rest_done = threading.Event()

    def work(i):
        on_main = threading.get_ident() == main
        if on_main:
            rest_done.wait(10)
        ran.append((i, on_main))
        if sum(not m for _, m in ran) == 11:
            rest_done.set()

    calls._share(work, 12, 2)
    assert sorted(i for i, _ in ran) == list(range(12))
    assert sum(on_main for _, on_main in ran) == 1
