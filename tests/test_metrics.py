"""lcs_cvx.metrics: e_test of the least-squares affine map (the one-mode reference)."""

from __future__ import annotations

import pytest
import torch

import lcs_cvx
from lcs_cvx import Dataset, LCSInputError
from lcs_cvx.metrics import affine_error, affine_lstsq


def _affine_data(n: int, seed: int) -> tuple[Dataset, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    W = torch.randn(3 + 2 + 1, 3, generator=g, dtype=torch.float64)
    x = torch.randn(n, 3, generator=g, dtype=torch.float64)
    u = torch.randn(n, 2, generator=g, dtype=torch.float64)
    xn = torch.cat([x, u, torch.ones(n, 1, dtype=torch.float64)], 1) @ W
    return Dataset(x, u, xn), W


def test_affine_lstsq_recovers_an_affine_map_and_its_error_is_zero():
    train, W = _affine_data(200, 0)
    test, _ = _affine_data(50, 1)
    assert torch.allclose(affine_lstsq(train).W, W, atol=1e-10)
    # test was drawn with another affine map: W is far from it
    same, _ = _affine_data(50, 0)
    assert affine_error(train, same) < 1e-20
    assert affine_error(train, test) > 0.1


def test_affine_error_is_the_relative_error_of_the_least_squares_map():
    truth = lcs_cvx.random_lcs(3, 1, 2, seed=0)
    train = lcs_cvx.make_dataset(truth, 500, seed=1)
    test = lcs_cvx.make_dataset(truth, 200, seed=2)
    W = affine_lstsq(train).W
    pred = torch.cat([test.x, test.u, torch.ones(len(test), 1, dtype=test.x.dtype)], 1).double() @ W
    direct = float(((pred - test.x_next.double()) ** 2).sum() / (test.x_next.double() ** 2).sum())
    assert affine_error(train, test) == pytest.approx(direct, rel=1e-12)
    # the truth, with its complementarity units, predicts better than the best affine map
    assert lcs_cvx.relative_error(truth, test) < affine_error(train, test)


def test_affine_error_refuses_an_empty_test_set():
    train, _ = _affine_data(20, 0)
    with pytest.raises(LCSInputError, match="dataset: expected at least one sample"):
        affine_error(train, Dataset(train.x[:0], train.u[:0], train.x_next[:0]))
