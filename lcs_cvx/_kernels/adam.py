r"""Adam's update compiled (numba): one call updates every parameter of a model in place.

The update of :class:`torch.optim.Adam` (no weight decay, no AMSGrad; Kingma and Ba, ICLR 2015,
Algorithm 1), element by element, in the order of operations of torch's single-tensor
implementation, on arrays that share memory with the parameters and the optimiser's state:

$$
m \leftarrow m + (1 - \beta_1)(g - m), \qquad
v \leftarrow \beta_2 v + (1 - \beta_2)\, g\, g, \qquad
p \leftarrow p - \alpha_t\, \frac{m}{\sqrt{v} / \sqrt{1 - \beta_2^t} + \epsilon},
\qquad \alpha_t = \frac{\mathrm{lr}}{1 - \beta_1^t}.
$$

(``lerp`` with a weight of at least 1/2 is written ``g - (g - m) beta_1``, as torch writes it.)
torch may fuse a multiply and an add into one instruction on some processors and not on others,
so the two agree to round-off, not bit for bit. The step counts ``t`` are the optimiser's
own (one float32 per parameter), advanced here; the bias corrections are computed by the caller
from ``t`` as torch computes them (Python floats).
"""

from __future__ import annotations

import math

import numba

from .dense import JIT

__all__ = ["adam_update"]


@numba.njit(**JIT)
def adam_update(params, grads, exp_avgs, exp_avg_sqs, steps, beta1, beta2, eps, step_size,
                bias_correction2_sqrt, step):  # pragma: no cover - compiled
    """Adam's step on the flat (1-D, contiguous) views ``params[k]``, ``grads[k]``, moments
    ``exp_avgs[k]``, ``exp_avg_sqs[k]`` and step counts ``steps[k]`` (``(1,)`` float32) of every
    parameter ``k`` (tuples of arrays), in place. ``step`` is the count after this step, for which
    ``step_size = lr / (1 - beta1^step)`` and ``bias_correction2_sqrt = (1 - beta2^step)^0.5``
    were computed; returns False (and changes nothing) if a parameter's count is not
    ``step - 1``."""
    for k in range(len(params)):
        if steps[k][0] + 1.0 != step:
            return False
    w = 1.0 - beta1
    small = w < 0.5
    for k in range(len(params)):
        p, g, m, v = params[k], grads[k], exp_avgs[k], exp_avg_sqs[k]
        steps[k][0] += 1.0
        for i in range(p.shape[0]):
            gi = g[i]
            mi = m[i] + w * (gi - m[i]) if small else gi - (gi - m[i]) * (1.0 - w)
            vi = v[i] * beta2 + (1.0 - beta2) * gi * gi
            m[i] = mi
            v[i] = vi
            p[i] = p[i] + -step_size * mi / (math.sqrt(vi) / bias_correction2_sqrt + eps)
    return True
