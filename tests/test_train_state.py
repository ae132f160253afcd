"""lcs_cvx.train.state: the trainer's state between steps (its minibatches)."""

from __future__ import annotations

import torch

import lcs_cvx
from lcs_cvx.bench import perturbed
from lcs_cvx.system import PARAMETER_NAMES
from lcs_cvx.train import state as train_state


def test_a_whole_large_minibatch_is_taken_in_storage_order(monkeypatch):
    """A minibatch of every training sample, from ``IN_ORDER_FROM`` samples on, is the samples
    in storage order; the permutation is drawn all the same (the run's random numbers are those
    of a smaller batch) and a smaller whole batch keeps the permutation's order. A full-batch
    fit then differs from the permuted one only by the order of its sums (to round-off)."""
    truth = lcs_cvx.random_lcs(3, 1, 2, seed=0)
    data = lcs_cvx.make_dataset(truth, 300, noise=1e-2, seed=1)
    options = lcs_cvx.train.resolve_options(recipe="paper", batch_size=300, iterations=6)

    def first_batches(threshold):
        monkeypatch.setattr(train_state, "IN_ORDER_FROM", threshold)
        st = train_state.TrainState(perturbed(truth, 0.3, 3), data, options, 0)
        return [st.next_batch(300) for _ in range(2)], st.perm, st.generator.get_state()

    (in_order, perm, gen) = first_batches(300)
    (permuted, perm2, gen2) = first_batches(301)
    for idx in in_order:
        assert torch.equal(idx, torch.arange(300))
    assert not torch.equal(permuted[1], torch.arange(300)) and torch.equal(permuted[1], perm2)
    assert torch.equal(perm, perm2) and torch.equal(gen, gen2)  # the same draws either way

    fits = {}
    for threshold in (1, 10**9):  # every whole batch in storage order, none
        monkeypatch.setattr(train_state, "IN_ORDER_FROM", threshold)
        model = perturbed(truth, 0.3, 3)
        lcs_cvx.fit(model, data, options, progress=False)
        fits[threshold] = model
    for name in PARAMETER_NAMES:
        a, b = getattr(fits[1], name).detach(), getattr(fits[10**9], name).detach()
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)
