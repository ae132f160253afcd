"""Every optimizer recovers a small LCS from the default model (``LCS(2, 1, 2, seed=...)``, no
stiffness argument) with its default options.

The system: ``random_lcs(2, 1, 2, stiffness=0.5, seed=21)``, 2,000 training samples with noise
1e-3, 1,000 noiseless test samples; the models ``LCS(2, 1, 2, seed=100 + k)``, ``k = 0, 1, 2``.
A single second-order run from such a start ends in a local minimum of the violation loss about
half the time, which is why the second-order optimizers make three runs by default
(:data:`lcs_cvx.train.options.OPTIMIZER_DEFAULTS`): with one run of 50 steps, Newton ended at
e_test ~1e-3 on all three seeds here. Adam runs 2,000 of its 10,000 default steps, for time; its
minibatch noise floor at lr 1e-3 is a few 1e-7. Bounds, not values: trajectories differ across
machines in round-off.
"""

from __future__ import annotations

import pytest
import torch

import lcs_cvx
from lcs_cvx.metrics import relative_error

#: the keywords of each run (beyond the defaults) and the bound on its e_test
RUNS = {
    "adam": ({"recipe": "plain", "iterations": 2000}, 3e-6),
    "gauss-newton": ({}, 1e-6),
    "newton": ({}, 1e-6),
}


@pytest.fixture(scope="module")
def system():
    truth = lcs_cvx.random_lcs(2, 1, 2, stiffness=0.5, seed=21)
    train = lcs_cvx.make_dataset(truth, 2000, noise=1e-3, seed=22)
    test = lcs_cvx.make_dataset(truth, 1000, noise=0.0, seed=23)
    return train, test


@pytest.mark.parametrize("k", [0, 1, 2])
@pytest.mark.parametrize("optimizer", list(RUNS))
def test_default_model_recovers_the_system(system, optimizer, k):
    train, test = system
    keywords, bound = RUNS[optimizer]
    model = lcs_cvx.LCS(2, 1, 2, seed=100 + k)
    assert float(model.stiffness) == lcs_cvx.system.DEFAULT_STIFFNESS
    result = lcs_cvx.fit(model, train, optimizer=optimizer, progress=False, **keywords)
    assert result.n_fallback == 0
    e_test = relative_error(model, test)
    assert e_test <= bound, f"{optimizer}, seed {100 + k}: e_test {e_test:.3g} > {bound:g}"
    assert all(bool(torch.isfinite(p).all()) for p in model.parameters())
