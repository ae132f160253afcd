"""lcs_cvx/authors.py without the authors' code (which is not in this repository): the layout of
their ``theta``, the package's gradient in it, and the named error for a folder without their
learners (``lcs-cvx bench --authors``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lcs_cvx import LCSInputError
from lcs_cvx.authors import authors_theta, load_authors, model_for, package_gradient
from lcs_cvx.cli import main


def test_theta_is_the_authors_layout():
    """``vec`` column-major of A, B, C, d, D, E, then G's upper triangle column by column, vec(H), c."""
    model, _ = model_for(3, 2, 2)
    theta = authors_theta(model)
    n_x, n_u, n = 3, 2, 2
    sizes = [n_x * n_x, n_x * n_u, n_x * n, n_x, n * n_x, n * n_u, n * (n + 1) // 2, n * n, n]
    assert theta.shape == (sum(sizes),)
    parts = np.split(theta, np.cumsum(sizes)[:-1])
    A = model.A.detach().numpy()
    assert np.array_equal(parts[0], A.reshape(-1, order="F"))  # column-major
    G = model.G.detach().numpy()
    assert np.array_equal(parts[6], np.array([G[0, 0], G[0, 1], G[1, 1]]))  # upper triangle by columns
    assert np.array_equal(parts[8], model.c.detach().numpy())
    assert np.array_equal(np.tril(G, -1), np.zeros_like(G))  # the authors' G is upper triangular


def test_package_gradient_takes_gs_upper_triangle():
    model, _ = model_for(3, 2, 2)
    for name, p in model.named_parameters():
        p.grad = torch.full_like(p, float(len(name)))
    model.G.grad = torch.arange(4.0, dtype=torch.float64).reshape(2, 2)
    g = package_gradient(model)
    assert g.shape == authors_theta(model).shape
    assert np.array_equal(g[-(2 + 4 + 3):-(2 + 4)], np.array([0.0, 1.0, 3.0]))  # G's upper triangle


def test_a_folder_without_their_learners_is_named(tmp_path, capsys):
    with pytest.raises(LCSInputError, match="authors: expected a folder with lcs/lcs_learning.py"):
        load_authors(tmp_path)
    assert main(["bench", "--authors", str(tmp_path)]) == 2
    assert "lcs/lcs_learning.py" in capsys.readouterr().err
