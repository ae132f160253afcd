"""Tensors in and out of the compiled kernels (:mod:`.compiled`): when they run, the arrays
they take (views of the tensors' memory, a model's parameters kept between calls), the tensors
of what they return, and the loss as an autograd node whose backward is the kernel's gradient
(:class:`CompiledLoss`).

The fast losses (:mod:`lcs_cvx.losses`) and an ensemble's stack (:mod:`lcs_cvx.stacked`) call
the compiled kernels through :func:`call_on_model` and :func:`compiled_call`.
"""

from __future__ import annotations

import functools
import itertools
import operator
import os
import weakref
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import torch

from .._checks import LCSInputError, as_transitions
from ..system import LCS, PARAMETER_NAMES
from .pivoting import check_warm_start

__all__ = ["COLD", "MIN_CHUNK", "CompiledLoss", "as_arrays", "call_on_model", "chunks", "compiled",
           "compiled_call", "loss_on_model", "model_arrays", "parameter_arrays", "ready", "resolve_threads",
           "scalar", "use_compiled"]


def use_compiled(model: Any, x: torch.Tensor, arrays: str) -> bool:
    """Whether the fast losses run compiled (:mod:`.compiled`): one model's
    float64 tensors on the CPU, the default there (``arrays="auto"``); ``arrays="compiled"``
    asks for it and names what stands in the way."""
    if arrays not in ("auto", "compiled"):
        return False
    ok = x.device.type == "cpu" and x.dtype == torch.float64 and model.A.dim() == 2
    if arrays == "compiled" and not ok:
        raise LCSInputError(
            f"arrays: 'compiled' runs one model's float64 CPU tensors, received {x.dtype} on "
            f"{x.device} with parameters of shape {tuple(model.A.shape)}"
        )
    return ok


def as_arrays(*tensors: torch.Tensor | np.ndarray) -> list[np.ndarray]:
    """C-contiguous float64 arrays on the tensors' memory (a copy only where not contiguous);
    arrays pass through."""
    out = []
    for t in tensors:
        a = t if isinstance(t, np.ndarray) else t.detach().numpy() if t.requires_grad else t.numpy()
        out.append(a if a.flags.c_contiguous else np.ascontiguousarray(a))
    return out


def scalar(value: float) -> torch.Tensor:
    """A 0-dim float64 tensor of ``value`` (through NumPy: a third of ``torch.tensor``'s cost)."""
    return torch.from_numpy(np.array(value))


#: Per model: its parameters and ``stiffness`` buffer when last seen, their storage addresses,
#: arrays on their memory and the stiffness as a 0-dim array (an optimiser's step changes the
#: values in place, which the arrays see).
_PARAMETER_ARRAYS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

#: The compiled kernels (:mod:`.compiled`), imported on first use (numba's import and the
#: kernels' loading cost a fraction of a second, paid only by a program that runs them).
_COMPILED: Any = None

#: The cold start (an empty warm start) of the compiled kernels (:data:`.compiled.COLD`).
COLD = np.zeros((0, 0), dtype=np.bool_)


def compiled() -> Any:
    """The module :mod:`.compiled` (imported once)."""
    global _COMPILED
    if _COMPILED is None:
        from . import compiled as module

        _COMPILED = module
    return _COMPILED


def parameter_arrays(model: Any) -> tuple[list[torch.Tensor], list[np.ndarray]]:
    """The model's parameters (``A, B, C, d, D, E, G, H, c``) and arrays on their memory, made
    once per model and made again when a parameter is replaced or moved to other storage."""
    params, arrays, _ = model_arrays(model)
    return params, arrays


def model_arrays(model: Any) -> tuple[list[torch.Tensor], list[np.ndarray], np.ndarray]:
    """:func:`parameter_arrays` and the model's ``stiffness`` as a 0-dim array on its buffer."""
    table = model.__dict__.get("_parameters", {})  # a torch Module's own table: no __getattr__
    params = [table[k] if k in table else getattr(model, k) for k in PARAMETER_NAMES]
    buffers = model.__dict__.get("_buffers", {})
    stiffness = buffers["stiffness"] if "stiffness" in buffers else model.stiffness
    tensors = [*params, stiffness]
    pointers = [t.data_ptr() for t in tensors]
    seen = _PARAMETER_ARRAYS.get(model)
    if seen is not None and all(map(operator.is_, tensors, seen[0])) and pointers == seen[1]:
        return params, seen[2], seen[3]
    found = as_arrays(*params)
    s = stiffness.detach().numpy()
    _PARAMETER_ARRAYS[model] = (tensors, pointers, found, s)
    return params, found, s


#: A compiled call of ``N >= 2 * MIN_CHUNK`` samples is solved in ``N // MIN_CHUNK`` parts of
#: ``MIN_CHUNK`` to ``2 MIN_CHUNK - 1`` consecutive samples: a part's arrays stay in the caches
#: and in memory the allocator reuses (one call of 1,000,000 samples ran at half the rate of
#: calls of 50,000), and the parts are shared among the threads. The parts depend on ``N`` only,
#: so every thread count gives the same numbers, bit for bit; a smaller call is one part.
MIN_CHUNK = 4096

#: The pool the chunks of a call run on (made on first use; the compiled kernels release the
#: GIL, so the threads run in parallel).
_POOL: ThreadPoolExecutor | None = None


def resolve_threads(threads: int | None) -> int:
    """``threads``, or by default ``torch.get_num_threads()`` (``torch.set_num_threads``, or
    ``OMP_NUM_THREADS`` when the process started); an :class:`LCSInputError` names anything but
    an integer >= 1."""
    if threads is None:
        return torch.get_num_threads()
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise LCSInputError(f"threads: expected an integer >= 1 (or None: torch.get_num_threads()), "
                            f"received {threads!r}")
    return int(threads)


def chunks(N: int) -> list[tuple[int, int]]:
    """The row ranges ``[(start, stop), ...]`` of the parts of a call of ``N`` samples
    (:data:`MIN_CHUNK`): ``max(1, N // MIN_CHUNK)`` of them, of equal sizes to one sample."""
    k = max(1, N // MIN_CHUNK)
    bounds = [N * i // k for i in range(k + 1)]
    return list(zip(bounds[:-1], bounds[1:], strict=True))


@functools.cache
def _kernel_blas() -> list[Any]:
    """threadpoolctl's controllers of the BLAS the compiled kernels' matrix products call
    (numba's ``np.dot`` goes through SciPy's BLAS: the one in SciPy's wheel, else every BLAS)."""
    import scipy
    from threadpoolctl import ThreadpoolController

    libs = ThreadpoolController().select(user_api="blas").lib_controllers
    home = os.path.dirname(os.path.abspath(scipy.__file__))
    own = [lib for lib in libs if os.path.abspath(lib.filepath).startswith(home)]
    return own or list(libs)


class _OneBlasThread:
    """The kernels' BLAS on one thread while a large call runs: its products are a small part of
    the call, and a BLAS that spreads them over every core (as OpenBLAS does above a size) costs
    more in hand-offs than it saves, and competes with the call's own threads (measured: one
    call of 50,000 samples at (10, 4, 4) took 18 ms with SciPy's OpenBLAS on 2 threads, 10 ms
    on 1). Restored on exit."""

    def __enter__(self) -> None:
        self.changed = [(lib, lib.get_num_threads()) for lib in _kernel_blas()]
        for lib, before in self.changed:
            if before != 1:
                lib.set_num_threads(1)

    def __exit__(self, *exc: object) -> None:
        for lib, before in self.changed:
            if before != 1:
                lib.set_num_threads(before)


def _pool() -> ThreadPoolExecutor:
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=max(1, (os.cpu_count() or 1) - 1),
                                   thread_name_prefix="lcs_cvx")
    return _POOL


#: How the counts of one kernel's parts combine, by position after its per-sample arrays: the
#: unconverged samples (added; -1, non-finite data, wins), the sweeps (their maximum) and, for the
#: prediction loss, the degenerate samples (added).
_COUNTS = {"violation": (sum, max), "prediction": (sum, max, sum)}


def _combine(name: str, outs: list[tuple], sizes: list[int], rows: list[np.ndarray | None]) -> tuple:
    """One call's outputs from its parts' (``sizes`` samples each, in order; their per-sample
    arrays already in ``rows``; each part's value and gradients flattened into one row,
    ``out[0]``): the mean value and its gradients as the parts' means weighted by their shares
    of the batch, summed in the parts' order (:func:`.rows.weighted_rows`; equal to one whole
    call's to round-off: the sums are taken in another order), and the counts."""
    N = sum(sizes)
    w = np.array([n / N for n in sizes])
    flat = _rows_kernels().weighted_rows(w, np.stack([out[0] for out in outs]))
    shapes = outs[0][1]
    grads, at = [], 1
    for shape in shapes:
        size = int(np.prod(shape))
        grads.append(flat[at:at + size].reshape(shape))
        at += size
    counts = [rule([out[2 + i] for out in outs]) for i, rule in enumerate(_COUNTS[name])]
    if any(out[2] < 0 for out in outs):
        counts[0] = -1
    return (float(flat[0]), tuple(grads), *rows, *counts)


def _rows_kernels() -> Any:
    """The module :mod:`.rows` (compiled; imported with the kernels)."""
    from . import rows

    return rows


def _share(work: Any, n_parts: int, threads: int) -> None:
    """``work(i)`` for every part ``i < n_parts``, on ``threads`` threads (this one and the
    pool's): each takes the next part not yet taken, so a thread slowed by the machine (a
    virtual core shared with another guest, a busy neighbour) takes fewer parts instead of
    holding up the call; what a part computes does not depend on the thread that runs it."""
    taken = itertools.count()  # its next() is atomic under the GIL

    def loop() -> None:
        for i in iter(taken.__next__, None):
            if i >= n_parts:
                return
            work(i)

    k = min(threads, n_parts)
    with _OneBlasThread():
        pending = [_pool().submit(loop) for _ in range(k - 1)]
        try:
            loop()
        finally:
            for p in pending:
                p.result()


def compiled_call(fn: Any, params: Sequence[np.ndarray], stiffness: float, x: torch.Tensor | np.ndarray,
                  u: torch.Tensor | np.ndarray, x_next: torch.Tensor | np.ndarray,
                  warm_start: torch.Tensor | np.ndarray | None, width: int, *options: Any,
                  threads: int | None = None, tensors: bool = True, rows: np.ndarray | None = None,
                  store: tuple[np.ndarray, np.ndarray] | None = None, per_sample: bool = True) -> tuple[int, tuple]:
    """``fn`` (:func:`.compiled.violation` or ``.prediction``) on one model's
    parameter arrays ``params`` (``A, B, C, d, D, E, G, H, c``) and a batch; returns its status
    (0; 1: a sample did not converge, and the caller runs the array kernels, which end it with
    the reference solvers; -1: the data are not finite) and its outputs, the gradients as
    tensors (``tensors=False``: as the kernel's arrays; the data and ``warm_start`` may then be
    arrays too, the trainer's one-call step). A batch of at least ``2 * MIN_CHUNK`` samples is
    solved in parts (:func:`chunks`), shared among ``threads`` threads (:func:`_share`) and
    combined in their order (:func:`_combine`): the same numbers for every ``threads``.

    ``rows``: the batch is the rows ``rows`` of ``x``, ``u``, ``x_next`` (arrays of all the
    data) and of ``warm_start`` (then a table of every sample's active sets, or None), each
    part's gathered by its thread (:mod:`.rows`; the same numbers as gathering first);
    ``store``: then a trainer's tables ``(active (N, width), seen (N,))``, into which each part
    writes its samples' active sets (by its thread, as it ends). ``per_sample=False``: no
    per-sample outputs (a training step's: ``lam``, ``phi``/``w`` and the active sets None)."""
    A, B, C, d, D, E, G, H, c = params
    warm = COLD
    if isinstance(warm_start, np.ndarray):
        warm = warm_start
    elif warm_start is not None:
        check_warm_start(warm_start, (x.shape[0], width))
        warm = np.ascontiguousarray(warm_start.numpy())
    xa, ua, xna = as_arrays(x, u, x_next)
    N = x.shape[0] if rows is None else rows.shape[0]
    if rows is None and N < 2 * MIN_CHUNK:  # one part, the common call: no more to arrange
        out = fn(A, B, C, d, D, E, c, G, H, stiffness, xa, ua, xna, *options, warm)
        if out[5]:
            return (-1 if out[5] < 0 else 1), out
        grads = tuple(map(torch.from_numpy, out[1])) if tensors else out[1]
        return 0, (out[0], grads, *(out[2:] if per_sample else (None, None, None) + out[5:]))
    parts = chunks(N)
    kernels = _rows_kernels() if rows is not None else None

    def run(a: int, b: int) -> tuple:
        if kernels is None:
            own = warm[a:b] if warm.shape[0] else warm
            return fn(A, B, C, d, D, E, c, G, H, stiffness, xa[a:b], ua[a:b], xna[a:b], *options, own)
        r = rows[a:b]
        xs, us, xns, own = kernels.take_batch(xa, ua, xna, warm, r)
        out = fn(A, B, C, d, D, E, c, G, H, stiffness, xs, us, xns, *options, own)
        if store is not None:
            kernels.put_rows(*store, r, out[4])
        return out

    if len(parts) == 1:
        out = run(*parts[0])
        if not per_sample:
            out = out[:2] + (None, None, None) + out[5:]
    else:
        n = C.shape[1]
        widths = ((n, np.float64), (n, np.float64), (width, np.bool_))  # lam, phi or w, the active sets
        rows_out = [np.empty((N, k), dtype=t) if per_sample else None for k, t in widths]
        outs: list[Any] = [None] * len(parts)

        def work(i: int) -> None:
            """Part ``i``: its per-sample arrays copied into ``rows_out`` and dropped, its value
            and gradients flattened into one row (for :func:`_combine`)."""
            a, b = parts[i]
            out = run(a, b)
            for j in range(3):
                if rows_out[j] is not None:
                    rows_out[j][a:b] = out[2 + j]
            outs[i] = (np.concatenate(([out[0]], *(g.reshape(-1) for g in out[1]))),
                       [g.shape for g in out[1]], *out[5:])

        _share(work, len(parts), resolve_threads(threads))
        out = _combine(fn.__name__, outs, [b - a for a, b in parts], rows_out)
    status = out[5]
    if status:
        return (-1 if status < 0 else 1), out
    return 0, (out[0], tuple(map(torch.from_numpy, out[1]))) + out[2:] if tensors else out


def call_on_model(name: str, model: Any, x: torch.Tensor, u: torch.Tensor, x_next: torch.Tensor,
                  warm_start: torch.Tensor | None, width: int, *options: Any,
                  gamma: float | None = None, threads: int | None = None, per_sample: bool = True) -> tuple | None:
    """:func:`compiled_call` of the kernel ``name`` (``"violation"`` or ``"prediction"``) on the
    model: ``(params, outputs)``, or None where the array kernels take over. Non-finite data
    raise :func:`lcs_cvx._checks.as_transitions`'s error (the kernel checks them: the public
    losses skip that check for tensors ready for it). ``gamma``: also check Lemma 2's
    ``gamma < sigma_min(F + F^T)`` (:func:`lcs_cvx._checks.check_gamma`, needed only from
    ``2 s`` on); ``threads``, ``per_sample``: as :func:`compiled_call`'s."""
    params, arrays, stiffness = model_arrays(model)
    s = float(stiffness)
    if gamma is not None and not gamma < 2.0 * s:  # F + F^T >= 2 s I: below, nothing to check
        from ..problems import check_gamma

        check_gamma(model.F, gamma)
    status, out = compiled_call(getattr(compiled(), name), arrays, s, x, u, x_next, warm_start, width,
                                *options, threads=threads, per_sample=per_sample)
    if status < 0:
        as_transitions(model, x, u, x_next)  # names the non-finite input
    return None if status else (params, out)


def loss_on_model(name: str, model: Any, x: torch.Tensor, u: torch.Tensor, x_next: torch.Tensor,
                  warm_start: Any, threads: Any, *options: Any, gamma: float | None = None) -> torch.Tensor | None:
    """The loss ``name`` (``"violation"`` or ``"prediction"``) of one :class:`lcs_cvx.LCS` on the
    compiled kernel as an autograd node (:class:`CompiledLoss`), without the diagnostics of the
    losses' ``*_info`` variants (no per-sample tensors): the value and gradients of those, by the
    same call; None where it does not run (a subclass of the LCS, or the kernel hands the batch
    to the array kernels: the caller then takes its ``*_info`` path). ``options``, ``gamma``:
    :func:`call_on_model`'s."""
    if type(model) is not LCS:
        return None
    resolve_threads(threads)
    width = 2 * model.n_lam if name == "violation" else model.n_lam
    done = call_on_model(name, model, x, u, x_next, warm_start, width, *options, gamma=gamma, threads=threads,
                         per_sample=False)
    if done is None:
        return None
    params, out = done
    return CompiledLoss.apply(scalar(out[0]), out[1], *params)


def ready(model: Any, x: Any, u: Any, x_next: Any, one_model: bool = False) -> bool:
    """Whether ``(x, u, x_next)`` are already what :func:`lcs_cvx._checks.as_transitions` returns
    for the compiled kernels: float64 CPU tensors of the right shapes for a float64 model
    (their finiteness is then the kernel's check); ``one_model``: and the model is one LCS (its
    ``A`` is 2-D), not a stack."""
    table = model.__dict__.get("_parameters", {})  # a torch Module's own table: no __getattr__
    try:
        A = table["A"] if "A" in table else model.A
        return (x.dtype is u.dtype is x_next.dtype is A.dtype is torch.float64
                and x.is_cpu and u.is_cpu and x_next.is_cpu and x.dim() == 2
                and x.shape == x_next.shape and x.shape[1] == model.n_x
                and u.shape == (x.shape[0], model.n_u) and (not one_model or A.dim() == 2))
    except AttributeError:  # not tensors
        return False


class CompiledLoss(torch.autograd.Function):
    """``apply(value, grads, *params)``: the value of a compiled loss
    (:mod:`lcs_cvx._kernels.compiled`, which computes the loss and its closed-form gradients in
    one call) with those gradients ``grads`` (in ``params`` order) as its backward; a stack's
    values ``(K,)`` scale their models' slices of the gradients."""

    @staticmethod
    def forward(ctx, value, grads, *params):  # noqa: D102
        ctx.grads = grads
        return value

    @staticmethod
    def backward(ctx, grad):  # noqa: D102
        need = ctx.needs_input_grad[2:]
        return (None, None) + tuple(
            None if not n else g * (grad if grad.dim() == 0 else grad.reshape((-1,) + (1,) * (g.dim() - 1)))
            for g, n in zip(ctx.grads, need, strict=True))
