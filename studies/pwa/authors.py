"""The authors' published numbers of their PWA regression comparison (the paper's authors'
repository, ``compare/``: their violation-based method against PARC).

Their protocol: n_x = 4, n_u = 2, a random LCS of stiffness 1 (``F = G G^T + H - H^T + I``),
N = 5,000 training samples (x ~ U[-10, 10], u ~ U[-5, 5], noise 1e-2), 1,000 noiseless test
samples; one run per mode count. The violation loss: gamma = 1e-2, eps = 1e-2, Adam lr 1e-3,
50 epochs of batch 100, in their loss scaling. PARC: K = the number of modes in the training
data, ``separation = "Voronoi"``, ``sigma = 1``, ``alpha = beta = 1e-3``, ``maxiter = 15``,
``cost_tol = 1e-4``, ``min_number = 10``, ``fit_on_partition = True``. Training times are wall
seconds of their scripts on their machine; PARC failed at 2,021 modes (n_lambda = 16).
"""

from __future__ import annotations

__all__ = ["PUBLISHED", "SOURCE"]

SOURCE = ("the authors' published numbers (the paper's repository, compare/: violation-based "
          "method vs PARC, one run per mode count)")

#: ``(modes, violation time s, PARC time s, violation e_test, PARC e_test)``; None: PARC failed.
PUBLISHED: tuple[tuple[int, float, float | None, float, float | None], ...] = (
    (16, 9.0, 32.0, 0.0049, 0.0046),
    (32, 11.0, 73.0, 0.0038, 0.010),
    (60, 14.0, 120.0, 0.0043, 0.0036),
    (105, 16.0, 227.0, 0.0022, 0.0016),
    (267, 22.0, 534.0, 0.003, 0.003),
    (1074, 48.0, 2340.0, 0.004, 0.006),
    (2021, 59.0, None, 0.003, None),
)
