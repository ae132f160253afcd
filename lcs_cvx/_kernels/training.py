r"""Adam's minibatch steps of eq. (4) compiled: many steps of a run in one call.

One step takes the next minibatch (its rows of the training data), the samples' active sets from
their last visit as the warm start (when every one of them was seen), the loss and its gradient
from the compiled kernel (:func:`.compiled.violation`, Lemma 3, or :func:`.compiled.prediction`,
Lemma 1), adds the regulariser ``reg ||C||_F^2`` and its gradient ``reg (2 C)``, zeroes the
gradient of masked entries, and makes Adam's update (:mod:`.adam`, the same arithmetic) on every
trainable parameter; then it remembers the samples' active sets. These are the operations of
:func:`lcs_cvx.train.onecall.adam_step` in the same order, so a run gets the same parameters bit
for bit whether its steps are taken one call each or many in one call.

The caller (:class:`lcs_cvx.train.phases.AdamPhase`) draws the minibatches and the learning
rates, ``eps`` and bias corrections of each step in Python, as for one step. A step whose
minibatch the kernel leaves unconverged (or whose data are not finite) ends the call before
it, with nothing of it done: the caller takes that step on the path that ends such samples with
the reference solvers. A step after which the loss or ``F`` is no longer finite ends the call
after it (``diverged``).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .compiled import prediction, violation
from .dense import JIT
from .products import stiffness_matrix

__all__ = ["VIOLATION", "PREDICTION", "adam_steps"]

#: ``kind`` of :func:`adam_steps`.
VIOLATION, PREDICTION = 0, 1


@numba.njit(**JIT)
def adam_steps(kind, A, B, C, d, D, E, c, G, H, stiffness, X, U, XN, rows, active, seen, gamma, eps_k,
               tol, max_iter, stall, degenerate_tol, reg, masks, trainable, exp_avgs, exp_avg_sqs, steps,
               beta1, beta2, adam_eps, step_sizes, bias_corrections2_sqrt, step0):  # pragma: no cover
    """Steps ``s = 0 .. K - 1`` on the minibatches ``rows[s]`` ``(K, B)`` of the data ``X (N, n_x)``,
    ``U (N, n_u)``, ``XN (N, n_x)``, in place on the parameters (``A .. H`` as the compiled
    kernels take them), the tables ``active (N, width)`` and ``seen (N,)``, and Adam's state
    (``exp_avgs``, ``exp_avg_sqs``: flat views per parameter in ``A, B, C, d, D, E, G, H, c``
    order; ``steps``: each one's ``(1,)`` float32 count, all ``step0`` on entry). ``kind``:
    :data:`VIOLATION` (``gamma`` and ``eps_k[s]``) or :data:`PREDICTION`; ``masks``: flat bool
    views (False: held at 0), ``trainable`` ``(9,)`` bool; step ``s``'s Adam step size and
    ``(1 - beta2^t)^0.5`` in ``step_sizes[s]``, ``bias_corrections2_sqrt[s]``.

    Returns ``(done, losses, diverged)``: the steps made, their regularised losses ``(K,)`` (the
    first ``done``), and whether the last of them left the loss or ``F`` not finite."""
    K, batch = rows.shape
    losses = np.zeros(K)
    params = (A.reshape(-1), B.reshape(-1), C.reshape(-1), d.reshape(-1), D.reshape(-1), E.reshape(-1),
              G.reshape(-1), H.reshape(-1), c.reshape(-1))
    w = 1.0 - beta1
    small = w < 0.5
    for s in range(K):
        r = rows[s]
        x, u, xn = X[r], U[r], XN[r]
        all_seen = True
        for i in range(batch):
            if not seen[r[i]]:
                all_seen = False
                break
        warm = active[r] if all_seen else np.zeros((0, 0), dtype=np.bool_)
        if kind == VIOLATION:
            out_v = violation(A, B, C, d, D, E, c, G, H, stiffness, x, u, xn, gamma, eps_k[s], tol, max_iter,
                              stall, warm)
            value, grads, act, bad = out_v[0], out_v[1], out_v[4], out_v[5]
        else:
            out_p = prediction(A, B, C, d, D, E, c, G, H, stiffness, x, u, xn, tol, max_iter, stall,
                               degenerate_tol, warm)
            value, grads, act, bad = out_p[0], out_p[1], out_p[4], out_p[5]
        if bad != 0:
            return s, losses, False
        if reg != 0.0:
            value += reg * np.sum(C * C)
        g = (grads[0].reshape(-1), grads[1].reshape(-1), (grads[2] + reg * (2.0 * C)).reshape(-1),
             grads[3].reshape(-1), grads[4].reshape(-1), grads[5].reshape(-1), grads[6].reshape(-1),
             grads[7].reshape(-1), grads[8].reshape(-1))
        step = step0 + 1.0 + s
        step_size, bc2 = step_sizes[s], bias_corrections2_sqrt[s]
        for k in range(9):
            if not trainable[k]:
                continue
            p, gk, m, v, mask = params[k], g[k], exp_avgs[k], exp_avg_sqs[k], masks[k]
            steps[k][0] = step
            for i in range(p.shape[0]):
                gi = gk[i] if mask[i] else 0.0
                mi = m[i] + w * (gi - m[i]) if small else gi - (gi - m[i]) * (1.0 - w)
                vi = v[i] * beta2 + (1.0 - beta2) * gi * gi
                m[i] = mi
                v[i] = vi
                if mask[i]:  # a masked entry keeps its held value
                    p[i] = p[i] + -step_size * mi / (math.sqrt(vi) / bc2 + adam_eps)
        for i in range(batch):
            active[r[i]] = act[i]
            seen[r[i]] = True
        losses[s] = value
        if not math.isfinite(value) or not np.isfinite(stiffness_matrix(G, H, stiffness)).all():
            return s + 1, losses, True
    return K, losses, False
