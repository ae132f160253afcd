r"""The PARC baseline: piecewise-affine regression and classification (A. Bemporad, "A
piecewise linear regression and classification algorithm with application to learning and
model predictive control of hybrid systems", IEEE TAC 2023; package ``pyparc``, extra
``baselines``).

PARC fits K affine maps and a piecewise-linear partition of the input space together,

    x' = A_j x + B_j u + d_j   for  [x; u] in P_j,   j = argmax_i  omega_i^T [x; u] + gamma_i,

by block-coordinate descent from a k-means++ clustering of ``[x; u]``: assign each sample to the
piece that fits it best (penalised by ``sigma`` times its distance to the piece's centroid, the
``"Voronoi"`` separation), refit each piece by ridge regression (``alpha``), until the cost drops
by less than ``cost_tol`` or ``maxiter`` iterations; clusters of fewer than ``min_number``
samples are merged away (if all are, as with K close to the number of samples over
``min_number``, PARC's fit raises: :class:`~lcs_cvx.study.baselines.BaselineFailed` here), and
with ``fit_on_partition`` the pieces are refitted on the final partition. It is called here as the authors of the paper called it in their comparison, on the
raw ``[x, u] -> x'`` data, with ``K`` the number of hybrid modes of the truth in the training
data (``K = "modes"``) unless a number is given.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from threadpoolctl import threadpool_limits

from ..._optional import require
from .failure import BaselineFailed

__all__ = ["PARCModel", "fit", "import_parc"]


def import_parc() -> Any:
    """The ``pyparc.parc`` module (imports scikit-learn, faiss, mip, pypoman and matplotlib);
    ``ModuleNotFoundError`` naming the extra ``baselines`` when it is missing."""
    return require("pyparc.parc", "baselines", "the PARC baseline (lcs_cvx.study.baselines.parc)")


class PARCModel:
    """A fitted ``pyparc.parc.PARC`` behind the interface of :meth:`lcs_cvx.LCS.step`."""

    dtype = torch.float64

    def __init__(self, predictor: Any) -> None:
        self.predictor = predictor

    def step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Next states ``(N, n_x)`` of states ``x`` ``(N, n_x)`` and inputs ``u`` ``(N, n_u)``."""
        X = np.hstack([x.detach().cpu().numpy(), u.detach().cpu().numpy()]).astype(np.float64)
        n = X.shape[0]
        if n == self.predictor.nx:  # PARC.predict reads an (nx, nx) array as one sample: pad
            X = np.vstack([X, X[:1]])
        yhat, _ = self.predictor.predict(X)
        return torch.from_numpy(np.asarray(yhat[:n], dtype=np.float64))


def fit(train: Any, options: dict[str, Any], *, seed: int, modes: int
        ) -> tuple[PARCModel, dict[str, Any]]:
    """Fit PARC to ``train`` (an :class:`lcs_cvx.Dataset`) with ``options`` (keys of
    ``OPTIONS["parc"]``); ``seed`` seeds numpy's global generator, which PARC's k-means draws
    from; ``modes`` is K when ``options["K"] == "modes"``. One thread (scikit-learn's and faiss'
    thread pools limited to one).

    Returns the model and ``{"K": K asked, "K_final": pieces kept, "iterations": descent
    iterations, "cost": final cost}``.

    Raises:
        BaselineFailed: ``pyparc``'s fit raised (any exception of ``PARC.fit``, chained as
            ``__cause__``; e.g. ``ValueError: attempt to get argmax of an empty sequence`` when
            every cluster has fewer than ``min_number`` samples and all are merged away).
    """
    parc = import_parc()
    K = modes if options["K"] == "modes" else options["K"]
    if K < 1:
        raise ValueError(f"modes: PARC needs K >= 1 pieces, received {K!r}")
    X = np.hstack([train.x.detach().cpu().numpy(), train.u.detach().cpu().numpy()]).astype(np.float64)
    Y = train.x_next.detach().cpu().numpy().astype(np.float64)
    predictor = parc.PARC(
        K=int(K), alpha=options["alpha"], sigma=options["sigma"], separation=options["separation"],
        maxiter=options["maxiter"], cost_tol=options["cost_tol"], min_number=options["min_number"],
        fit_on_partition=options["fit_on_partition"], softmax_maxiter=options["softmax_maxiter"],
        beta=options["beta"], initialization=("kmeans", options["kmeans_init"]), verbose=0)
    state = np.random.get_state()
    np.random.seed(seed)
    try:
        with threadpool_limits(1):
            try:
                predictor.fit(X, Y, categorical=[False] * Y.shape[1], weights=np.ones(Y.shape[1]))
            except Exception as exc:  # PARC's own algorithm, not our code: a result
                raise BaselineFailed(f"PARC failed: {type(exc).__name__}: {exc}") from exc
    finally:
        np.random.set_state(state)
    cost = np.asarray(predictor.cost, dtype=np.float64).ravel()
    return PARCModel(predictor), {"K": int(K), "K_final": int(predictor.K),
                                  "iterations": int(predictor.iters),
                                  "cost": float(cost[-1]) if cost.size else None}
