"""Shared fixtures and helpers of the test suite (float64 throughout, one torch thread).

The helpers are plain functions (``from conftest import random_p_matrix``) so that hypothesis
tests can call them with drawn arguments.
"""

from __future__ import annotations

import importlib.util
import os
import sys

import numpy as np
import pytest
import torch

from lcs_cvx import random_lcs

# Oversubscribing the 2 shared cores made batched solves ~100x slower (DESIGN.md).
torch.set_num_threads(1)

#: The repository root; on the import path, because the studies (``studies.physics``) are a
#: package there, not installed.
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

#: Skips a test of the physics studies where MuJoCo (the ``physics`` extra) is not installed.
needs_mujoco = pytest.mark.skipif(
    importlib.util.find_spec("mujoco") is None,
    reason="mujoco is not installed (the physics extra: pip install 'lcs_cvx[physics]')",
)

F64 = torch.float64


def random_p_matrix(
    n: int,
    smin: float = 1.0,
    seed: int = 0,
    skew: float = 1.0,
    min_dir: np.ndarray | None = None,
) -> torch.Tensor:
    """A random ``(n, n)`` float64 ``F`` with ``F + F^T`` positive definite and
    ``sigma_min(F + F^T) = smin`` exactly (to round-off).

    ``F = S + K``: ``S`` symmetric with eigenvalues ``smin/2`` and ``smin/2 + U[0.1, 2]``
    (random eigenvectors; ``min_dir``, if given, is the eigenvector of ``smin/2``), ``K`` skew
    with ``N(0, 2 skew^2)`` entries. The skew part does not change ``F + F^T = 2 S``; a small
    ``skew`` makes ``F`` itself ill-conditioned when ``smin`` is small.
    """
    g = np.random.default_rng(seed)
    X = g.standard_normal((n, n))
    if min_dir is not None:
        X[:, 0] = min_dir
    Q, _ = np.linalg.qr(X)
    eig = np.concatenate([[smin / 2.0], smin / 2.0 + g.uniform(0.1, 2.0, n - 1)])
    S = (Q * eig) @ Q.T
    S = 0.5 * (S + S.T)
    M = g.standard_normal((n, n))
    return torch.tensor(S + skew * (M - M.T), dtype=F64)


def random_q(batch: int, n: int, seed: int = 0, scale: float = 1.0) -> torch.Tensor:
    """``(batch, n)`` float64 LCP offsets ``scale * N(0, 1)``."""
    g = np.random.default_rng(seed)
    return torch.tensor(scale * g.standard_normal((batch, n)), dtype=F64)


def strictly_complementary_lcp(
    F: torch.Tensor, batch: int, seed: int = 0, margin: float = 0.5
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(q, lam*)`` with a known solution whose every index is strictly complementary:
    either ``lam_i >= margin, w_i = 0`` or ``lam_i = 0, w_i >= margin``."""
    n = F.shape[0]
    g = np.random.default_rng(seed)
    free = g.random((batch, n)) < 0.5
    lam = np.where(free, margin + g.random((batch, n)), 0.0)
    w = np.where(free, 0.0, margin + g.random((batch, n)))
    lam_t = torch.tensor(lam, dtype=F64)
    q = torch.tensor(w, dtype=F64) - lam_t @ F.mT
    return q, lam_t


@pytest.fixture
def small_system():
    """A paper-style random ground truth with n_x = 4, n_u = 2, n_lam = 3 (float64)."""
    return random_lcs(4, 2, 3, seed=7)

