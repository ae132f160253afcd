"""C3's compiled path: a whole solve in one compiled call (:func:`lcs_cvx._kernels.c3_polish.
solve_states`) for float64 initial states on the CPU.

It applies where the QP step is the fast path's affine map (``qp_path="fast"``, with or without
box bounds), the decision vector carries ``eta`` (``"auto"``, ``"lcp"``, ``"c3+"``), the model
has contact forces, and the array back-end is ``"auto"`` or ``"compiled"`` (naming ``"numpy"``
or ``"torch"`` asks for the array kernels of :mod:`lcs_cvx._kernels.c3`). Everything that does
not depend on the initial state (the QP's affine maps, their bound sensitivities, the stacked
matrices, the projections' weights, the bounds) is laid out once, when the controller is built.
It plans what the array kernels plan (to round-off: the same arithmetic in another order); a
solve it cannot finish by itself (an LCP its pivoting leaves unsolved, a singular mode system, a
box QP that does not finish) returns None and runs on the array kernels, whose fallbacks and
errors then apply.

Shapes: ``x0 (n_x,)`` or ``(B, n_x)``; the plan's as :class:`lcs_cvx.control.Plan`.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import torch

from .._kernels.arrays import array_ops
from .._kernels.c3_polish import solve_states
from .._kernels.lcp import PIVOT_TOL
from .._kernels.pivoting import STALL
from .plan import MAX_SWEEPS, Plan

__all__ = ["CompiledSolve", "KINDS"]

#: the projections the compiled ADMM runs, by their index there
KINDS = {"lcp": 0, "c3+": 1}

#: the NumPy back-end, whose copies of the controller's arrays the compiled path reads
_NUMPY = array_ops(torch.zeros(0), "numpy")


class CompiledSolve:
    """The compiled path of the controller ``ctrl`` (a :class:`lcs_cvx.control.C3`), or None
    where it does not apply (:meth:`of`)."""

    @classmethod
    def of(cls, ctrl: Any) -> CompiledSolve | None:
        lay = ctrl.layout
        if (ctrl.qp.path != "fast" or not lay.with_eta or lay.n_lam == 0 or ctrl.arrays not in ("auto", "compiled")
                or any(p.kind not in KINDS for p in ctrl.projections)):
            return None
        return cls(ctrl)

    def __init__(self, ctrl: Any):
        hz, lay, qp = ctrl.horizon, ctrl.layout, ctrl.qp
        N, nl = hz.N, lay.n_lam
        self.ctrl = ctrl
        self.kinds = np.array([KINDS[p.kind] for p in ctrl.projections], dtype=np.int64)
        self.names = [p.kind for p in ctrl.projections]
        maps = qp._maps.on(_NUMPY, None)
        self.Yf, self.Yt, self.y0 = (np.ascontiguousarray(maps[k]) for k in ("Yf", "Yt", "y0"))
        levels, n_y = self.y0.shape
        S, lo, hi = qp._box
        self.S, self.lo, self.hi = np.ascontiguousarray(S, dtype=np.int64), lo.copy(), hi.copy()
        if S.size:
            self.P_SS = np.ascontiguousarray(np.stack([s[0] for s in qp._sensitivity]))
            self.P_ST = np.ascontiguousarray(np.stack([s[1] for s in qp._sensitivity]))
        else:
            self.P_SS, self.P_ST = np.zeros((levels, 0, 0)), np.zeros((levels, 0, n_y))
        sw = {"lam": np.zeros((N, nl)), "eta": np.zeros((N, nl))}
        for p in ctrl.projections:
            if p.kind == "c3+":
                sw = p._sqrt_w.on(_NUMPY, None)
        self.sw_lam, self.sw_eta = np.ascontiguousarray(sw["lam"]), np.ascontiguousarray(sw["eta"])
        self.mats = tuple(np.ascontiguousarray(getattr(hz, k)) for k in "ABCdDEFc")
        admm_hz = qp.horizon  # the ADMM's system (lam rescaled with scale_lcs)
        self.admm = tuple(np.ascontiguousarray(getattr(admm_hz, k)) for k in "DEc")
        self.weights = tuple(np.ascontiguousarray(w) for w in (ctrl.Q, ctrl.R, ctrl.QN))
        b = ctrl.bounds

        def box(v: Any, n: int) -> tuple[np.ndarray, np.ndarray]:
            return (np.full(n, -np.inf), np.full(n, np.inf)) if v is None else (v[0].copy(), v[1].copy())

        self.u_box = (np.tile(b.u[0], N), np.tile(b.u[1], N)) if b.u is not None else (np.zeros(0), np.zeros(0))
        self.xl_box = box(b.x, lay.n_x) + box(b.lam, nl)
        self.x_des = np.ascontiguousarray(ctrl.x_des.numpy())  # (1, N + 1, n_x)
        self.shape = (N, lay.n_z)

    def _initial_states(self, x0: Any) -> np.ndarray | None:
        """``x0`` as a C-contiguous ``(B, n_x)`` float64 array where it is one already (a NumPy
        array or a CPU tensor, finite), else None (the array path checks and converts it)."""
        if isinstance(x0, torch.Tensor):
            if x0.dtype != torch.float64 or x0.device.type != "cpu" or x0.requires_grad:
                return None
            x0 = x0.numpy()
        elif not isinstance(x0, np.ndarray) or x0.dtype != np.float64:
            return None
        nx = self.ctrl.horizon.n_x
        if x0.ndim == 1:
            x0 = x0.reshape(1, -1)
        if x0.ndim != 2 or x0.shape[1] != nx or x0.shape[0] == 0:
            return None
        if not math.isfinite(float(x0.sum())) and not np.isfinite(x0).all():
            return None
        return x0 if x0.flags.c_contiguous and x0.flags.writeable else x0.copy()

    def solve(self, x0: Any, x_des: Any, warm_start: Any, u_ref: Any) -> tuple[Plan, int] | None:
        """``(plan, qp_failures)`` from ``x0`` as :meth:`lcs_cvx.control.C3.solve` plans it, or
        None where the compiled path does not apply to this call."""
        t_start = time.perf_counter()
        X0 = self._initial_states(x0)
        if X0 is None:
            return None
        ctrl = self.ctrl
        single = np.ndim(x0) == 1
        Bn = X0.shape[0]
        N, nz = self.shape
        nx, nu, nl = X0.shape[1], ctrl.horizon.n_u, ctrl.horizon.n_lam
        like = torch.from_numpy(X0)
        xd = self.x_des if x_des is None else ctrl._target(x_des).numpy()
        XD = xd if Bn == 1 else np.ascontiguousarray(np.broadcast_to(xd, (Bn, N + 1, nx)))
        delta = None if warm_start is None else ctrl._start(warm_start, like)
        D0 = np.zeros((Bn, N, nz)) if delta is None else np.ascontiguousarray(delta.numpy(), dtype=np.float64)
        if ctrl.penalize_input_change and u_ref is not None:
            UR = np.ascontiguousarray(ctrl._input_reference(u_ref, like).numpy(), dtype=np.float64)
        else:
            UR = np.zeros((Bn, N, nu))
        out = {"x": np.empty((Bn, N + 1, nx)), "u": np.empty((Bn, N, nu)), "lam": np.empty((Bn, N, nl)),
               "delta": np.empty((Bn, N, nz)), "primal_residual": np.empty((Bn, ctrl.admm_iterations)),
               "dual_residual": np.empty((Bn, ctrl.admm_iterations)), "complementarity": np.empty(Bn),
               "x_model": np.empty((Bn, N + 1, nx)), "lam_model": np.empty((Bn, N, nl)), "cost": np.empty(Bn),
               "polished": np.empty(Bn, dtype=np.bool_)}
        chosen, gap = np.empty(Bn, dtype=np.int64), np.empty(Bn)
        t = time.perf_counter()
        failures, status = solve_states(
            X0, XD, UR, D0, self.kinds, self.Yf, self.Yt, self.y0, self.S, self.lo, self.hi, self.P_SS, self.P_ST,
            ctrl.admm_iterations, ctrl.rho_scale, self.sw_lam, self.sw_eta, *self.mats, *self.admm, *self.weights,
            ctrl.fix_lam0, ctrl.lam_scale, ctrl.polish, *self.u_box, *self.xl_box, PIVOT_TOL, MAX_SWEEPS, STALL,
            *out.values(), chosen, gap)
        t_kernel = time.perf_counter() - t
        if status != 0:
            return None
        times = {"qp": t_kernel, "projection": 0.0, "lcp": 0.0, "model": 0.0, "polish": 0.0}
        out["gap"] = gap
        if single:  # the batch axis dropped (a 1-D array's one entry as a 0-dim array)
            fields = {k: torch.from_numpy(v[0] if v.ndim > 1 else v.reshape(())) for k, v in out.items()}
            names: Any = self.names[int(chosen[0])]
        else:
            fields = {k: torch.from_numpy(v) for k, v in out.items()}
            names = [self.names[int(i)] for i in chosen]
        times["total"] = time.perf_counter() - t_start
        return Plan(**fields, times=times, qp_failures=failures, projection=names), failures
