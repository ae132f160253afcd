"""The matrices of a kernel call: one model's, shared by every sample, or one per model of a stack.

A kernel call solves a batch of per-sample problems whose matrices (``F``; (V)'s ``L^T L`` and
``K``) belong to a model. With one model (:class:`Shared`) every sample uses the same matrices,
kept as they are (``(n, n)``, a flat row ``(1, n * n)``). A stack of ``M`` models
(:class:`Stacked`, :mod:`lcs_cvx.stacked`) has them along a leading model axis (``(M, n, n)``,
``(M, n * n)``) and its samples model-major: ``B`` per model, sample ``t`` of model ``t // B``.

The pivoting (:mod:`.pivoting`) calls its ``solve(free, idx)`` on the whole batch or on a work
set ``idx`` (sorted sample indices). :meth:`Shared.select` / :meth:`Stacked.select` give the
operations of that call on the selected samples:

- ``rows(M)``: the per-sample rows of a flat matrix ``M`` (for ``ArrayOps.free_block``);
- ``rmul(a, M)``: every sample's row of ``a`` times its model's matrix ``M``;
- ``solve(M, rhs, spd)``: ``ArrayOps.solve`` of the per-sample systems.

A stacked call does, for each model, the arithmetic of that model's own call: a product on
the whole batch is a product per model (NumPy's stacked ``@``, one BLAS call per model on the
model's rows), a product on a work set is one product per model on the rows of the model in it,
and the choice of linear-solve library (:meth:`ArrayOps.solve`) is made on one model's number
of systems. Each model therefore gets the numbers of its own call.
"""

from __future__ import annotations

from typing import Any

from .arrays import NUMPY_SOLVE_WORK, ArrayOps

__all__ = ["Shared", "Stacked", "matrices"]


class Shared:
    """One model: every sample uses the same matrices (the kernels' plain arithmetic)."""

    def __init__(self, xp: ArrayOps) -> None:
        self.xp = xp

    def select(self, idx: Any) -> Shared:
        """The operations on the samples ``idx`` (None: all); the matrices do not depend on it."""
        return self

    def rows(self, M: Any) -> Any:
        """``M`` ``(1, p)``, which broadcasts over the samples."""
        return M

    def rmul(self, a: Any, M: Any) -> Any:
        """``a @ M`` for ``a`` ``(b, m)`` and ``M`` ``(m, p)``."""
        return a @ M

    def solve(self, M: Any, rhs: Any, spd: bool) -> tuple[Any, Any | None]:
        return self.xp.solve(M, rhs, spd)


class Stacked:
    """``n_models`` models of ``per_model`` samples each (model-major); matrices ``(n_models, ...)``."""

    def __init__(self, xp: ArrayOps, n_models: int, per_model: int, like: Any) -> None:
        self.xp, self.K, self.B = xp, n_models, per_model
        #: the model of every sample, ``(K * B,)``
        self.group = xp.repeat(xp.arange(n_models, like), per_model)
        self.starts = xp.arange(n_models + 1, like) * per_model

    def select(self, idx: Any) -> _Selection:
        """The operations on the samples ``idx`` (sorted; None: all)."""
        if idx is None:
            return _Selection(self, None, None)
        return _Selection(self, idx, self.xp.to_list(self.xp.searchsorted(idx, self.starts)))


class _Selection:
    """:class:`Stacked`'s operations on the whole batch (``idx`` None) or on the sorted samples
    ``idx``, whose model ``k`` holds positions ``bounds[k]:bounds[k + 1]``."""

    def __init__(self, stack: Stacked, idx: Any, bounds: list[int] | None) -> None:
        self.stack, self.idx, self.bounds = stack, idx, bounds

    def _parts(self) -> list[tuple[int, int, int]]:
        """``(model, start, stop)`` of the models with samples in the selection."""
        b = self.bounds
        return [(k, b[k], b[k + 1]) for k in range(self.stack.K) if b[k] < b[k + 1]]

    def rows(self, M: Any) -> Any:
        """The rows ``M[model(t)]`` of the selected samples, ``(b, p)``, for ``M`` ``(K, p)``."""
        g = self.stack.group
        return M[g if self.idx is None else g[self.idx]]

    def rmul(self, a: Any, M: Any) -> Any:
        """Each selected sample's row of ``a`` ``(b, m)`` times its model's ``M[k]`` ``(m, p)``."""
        s = self.stack
        if self.idx is None:
            return (a.reshape(s.K, s.B, a.shape[-1]) @ M).reshape(s.K * s.B, M.shape[-1])
        if s.B == 1:  # a model per sample (lcs_cvx.per_sample): one batched product
            return (a[:, None, :] @ M[self.idx])[:, 0, :]
        out = s.xp.empty((a.shape[0], M.shape[-1]), a)
        for k, i, j in self._parts():
            out[i:j] = a[i:j] @ M[k]
        return out

    def solve(self, M: Any, rhs: Any, spd: bool) -> tuple[Any, Any | None]:
        """``ArrayOps.solve`` with the library chosen per model (on its number of systems)."""
        s, xp = self.stack, self.stack.xp
        if self.idx is None or not xp.np:
            return xp.solve(M, rhs, spd, batch=s.B)
        if s.B == 1:  # a model per sample: each system its own model's, the library of one system
            return xp.solve(M, rhs, spd, batch=1)
        n = rhs.shape[1]
        parts = self._parts()
        small = [(j - i) * n * n <= NUMPY_SOLVE_WORK for _, i, j in parts]
        if all(small) or not any(small):
            return xp.solve(M, rhs, spd, batch=max(j - i for _, i, j in parts))
        x, failed = xp.empty(rhs.shape, rhs), None
        for want in (True, False):  # NumPy's systems, then torch's
            spans = [(i, j) for (_, i, j), sm in zip(parts, small, strict=True) if sm == want]
            sel = xp.concat_index(spans, rhs)
            x_sel, f_sel = xp.solve(M[sel], rhs[sel], spd, batch=1 if want else NUMPY_SOLVE_WORK + 1)
            x[sel] = x_sel
            if f_sel is not None:
                if failed is None:
                    failed = xp.zeros_bool(rhs.shape[0], rhs)
                failed[sel] = f_sel
        return x, failed


def matrices(xp: ArrayOps, M: Any, n_samples: int) -> Shared | Stacked:
    """:class:`Shared` for one model's matrix ``M`` ``(n, n)``; :class:`Stacked` for a stack
    ``(K, n, n)`` whose ``n_samples`` samples come model-major, ``n_samples / K`` per model."""
    if M.ndim == 2:
        return Shared(xp)
    K = M.shape[0]
    return Stacked(xp, K, n_samples // K, M)
