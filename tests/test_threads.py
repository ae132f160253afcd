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
