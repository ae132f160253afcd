r"""The linear complementarity system, eq. (1), as a ``torch.nn.Module``.

    x' = A x + B u + C lam + d
    0 <= lam  _|_  D x + E u + F lam + c >= 0,      F = G G^T + H - H^T + s I

The parameterisation of F (paper Sec. 5, :mod:`lcs_cvx.parameters`) makes ``F + F^T >= 2 s I >
0`` for every value of the learnable ``G`` and ``H`` and the fixed ``stiffness`` ``s > 0`` --
Assumption 1 holds by construction, so the LCP has a unique solution for every ``(x, u)``.

:class:`LCS` and :func:`lcs_cvx.data.random_lcs` share their defaults (``stiffness`` :data:`DEFAULT_STIFFNESS`,
``seed`` 0): a default model's set of ``F`` contains every default ground truth's ``F``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from torch import nn

from ._checks import LCSInputError, as_batch, as_held, as_matrix, as_pattern, check_positive
from .lcp import LCPSolution, active_set_solve, solve_lcp_unchecked
from .parameters import (
    MASKABLE,
    MATRIX_NAMES,
    PARAMETER_NAMES,
    F_matrix,
    factor_F,
    lcs_sizes,
    parameter_shapes,
    split_F,
)
from .problems import sym_min_eig
from .rollout import rollout

__all__ = ["LCS", "PARAMETER_NAMES", "MATRIX_NAMES", "ACTIVE_TOL", "DEFAULT_STIFFNESS", "MASKABLE",
           "C3_NAMES", "parameter_shapes", "F_matrix", "split_F"]

#: ``lam_i > ACTIVE_TOL`` marks unit ``i`` active (:meth:`LCS.active_set`,
#: :func:`lcs_cvx.count_modes`, the studies' mode counts). The fast solver's inactive ``lam_i`` are
#: exactly 0; an interior-point reference leaves ~1e-10 on them, which must not count as a mode.
#: The mode counts of the demo's data and of the Fig. 1 studies' training sets are the same for
#: every tolerance from 0 to 1e-5.
ACTIVE_TOL = 1e-5

#: The default ``stiffness`` ``s`` of :class:`LCS` and :func:`random_lcs`.
DEFAULT_STIFFNESS = 0.5


#: C3's name of each matrix -> ours (C3 writes ``x' = A x + B u + D lam + d``,
#: ``0 <= lam _|_ E x + F lam + H u + c >= 0``).
C3_NAMES = {"A": "A", "B": "B", "D": "C", "d": "d", "E": "D", "F": "F", "H": "E", "c": "c"}


class LCS(nn.Module):
    r"""A linear complementarity system (eq. (1)) with learnable
    ``theta = {A, B, C, d, D, E, G, H, c}``:

    $$
    \begin{aligned}
    x' &= A x + B u + C \lambda + d, \qquad
    0 \le \lambda \perp D x + E u + F \lambda + c \ge 0, \\
    F &= G G^\top + H - H^\top + s I.
    \end{aligned}
    $$

    Args:
        n_x, n_u, n_lam: state, input and complementarity dimensions (``n_u`` may be 0).
        stiffness: ``s > 0`` in ``F = G G^T + H - H^T + s I``; ``sigma_min(F + F^T) >= 2 s``
            (default :data:`DEFAULT_STIFFNESS`, as :func:`random_lcs`).
        init_scale: parameters are drawn as ``init_scale * N(0, 1)``.
        seed: seed of the initialisation (default 0; None: torch's global generator).
        dtype: floating dtype of the parameters (float64 recommended: the LCPs can be stiff).
        mask: optional ``{name: pattern}``, applied with :meth:`mask` after the initialisation.
        kinematics: optional :class:`lcs_cvx.Kinematics`, attached with :meth:`with_kinematics`.

    Batched methods take ``x`` ``(N, n_x)`` and ``u`` ``(N, n_u)``; a 1-D input is one sample.

    Known structure. A parameter is *fixed* iff it does not require grad (the torch convention:
    ``model.A.requires_grad_(False)`` fixes ``A``; :meth:`fix` sets values and fixes them). A
    *mask* (:meth:`mask`, :attr:`masks`) holds chosen entries of ``A, B, C, d, D, E, c`` at
    exactly 0, and :meth:`hold` at given values (gravity in ``d``, a known integration step in
    ``A``; :attr:`held`). :func:`lcs_cvx.fit` and every optimiser, pruning and re-initialisation
    leave fixed parameters and held entries bit-identical. :func:`random_lcs` returns a model with every
    parameter fixed (a ground truth); ``.requires_grad_(True)`` makes all of it learnable.

    Example:
        >>> import lcs_cvx
        >>> sys = lcs_cvx.random_lcs(4, 2, 3, seed=0)
        >>> x, u = torch.zeros(5, 4, dtype=torch.float64), torch.ones(5, 2, dtype=torch.float64)
        >>> sys.step(x, u).shape
        torch.Size([5, 4])
    """

    def __init__(
        self,
        n_x: int,
        n_u: int,
        n_lam: int,
        stiffness: float = DEFAULT_STIFFNESS,
        init_scale: float = 0.1,
        seed: int | None = 0,
        dtype: torch.dtype = torch.float64,
        mask: Mapping[str, Any] | None = None,
        kinematics: Any = None,
    ) -> None:
        super().__init__()
        # name -> CPU bool tensor (True: learnable entry); a plain attribute, not a buffer, so
        # state dicts are the same with and without masks
        self._masks: dict[str, torch.Tensor] = {}
        # name -> CPU tensor of the parameter's shape: the values of its masked entries (0 at
        # the learned ones); restored by every optimiser step (parameter_constraints.project_)
        self._held: dict[str, torch.Tensor] = {}
        self._kinematics: Any = None  # a Kinematics: the configuration rows integrated in step
        self.n_x = check_positive("n_x", n_x, integer=True)
        if isinstance(n_u, bool) or not isinstance(n_u, (int, np.integer)) or n_u < 0:
            raise LCSInputError(f"n_u: expected an integer >= 0, received {n_u!r}")
        self.n_u = int(n_u)
        self.n_lam = check_positive("n_lam", n_lam, integer=True)
        check_positive("stiffness", stiffness)
        if isinstance(init_scale, bool) or not isinstance(init_scale, (int, float)) or init_scale < 0:
            raise LCSInputError(f"init_scale: expected a number >= 0, received {init_scale!r}")
        if dtype not in (torch.float32, torch.float64):
            raise LCSInputError(f"dtype: expected torch.float32 or torch.float64, received {dtype}")
        self.register_buffer("stiffness", torch.tensor(float(stiffness), dtype=dtype))
        gen = torch.Generator().manual_seed(seed) if seed is not None else None
        for name in PARAMETER_NAMES:
            shape = parameter_shapes(self.n_x, self.n_u, self.n_lam)[name]
            value = torch.randn(shape, generator=gen, dtype=torch.float64) * float(init_scale)
            setattr(self, name, nn.Parameter(value.to(dtype)))
        if mask is not None:
            if not isinstance(mask, Mapping) or not all(isinstance(k, str) for k in mask):
                raise LCSInputError(
                    f"mask: expected a dict {{parameter name: pattern}} or None, received {mask!r}"
                )
            self.mask(**mask)
        if kinematics is not None:
            self.with_kinematics(kinematics)

    # -- known structure ----------------------------------------------------------------
    def fix(self, **values: Any) -> LCS:
        """Set parameters to known values and fix them (``requires_grad_(False)``); returns
        ``self``.

        Keywords are names of :data:`PARAMETER_NAMES` or ``F``. ``F`` sets ``G`` and ``H`` with
        :func:`split_F` at the model's ``stiffness`` ``s`` and fixes both: its symmetric part
        must be ``>= s I`` (else the model cannot represent it). Values are copied (arrays or
        tensors of the parameter's exact shape; tensors of the model's dtype); a value must be 0
        at the entries its parameter's mask holds at 0. Nothing changes unless every value is
        valid.

        Example:
            >>> m = LCS(2, 1, 1).fix(A=[[1.0, 0.1], [0.0, 1.0]], B=[[0.0], [0.1]])
            >>> m.A.requires_grad, m.C.requires_grad
            (False, True)
        """
        shapes = parameter_shapes(self.n_x, self.n_u, self.n_lam)
        unknown = [k for k in values if k not in shapes]
        if unknown:
            raise LCSInputError(
                f"{unknown[0]}: expected a parameter name among {PARAMETER_NAMES + ('F',)}, "
                f"received {unknown[0]!r}"
            )
        if "F" in values and ("G" in values or "H" in values):
            both = [k for k in ("G", "H") if k in values]
            raise LCSInputError(
                f"F: expected F alone or G and H, received F together with {', '.join(both)}"
            )
        kw = {"dtype": self.dtype, "device": self.device}
        new = {k: as_matrix(k, v, shapes[k], **kw) for k, v in values.items()}
        for k, v in new.items():
            m = self._masks.get(k)
            if m is None:
                continue
            held = self._held[k].to(v)
            off = v[~m.to(v.device)] != held[~m.to(v.device)]
            if bool(off.any()):
                raise LCSInputError(
                    f"{k}: expected the held values at the entries its mask holds (0 for mask, "
                    f"the given ones for hold), received {int(off.sum())} other values there"
                )
        if "F" in new:
            new["G"], new["H"] = split_F(new.pop("F"), float(self.stiffness), strict=True)
        with torch.no_grad():
            for k, v in new.items():
                getattr(self, k).copy_(v)
                getattr(self, k).requires_grad_(False)
        return self

    def mask(self, **patterns: Any) -> LCS:
        """Hold entries of parameters at exactly 0; returns ``self``.

        Keywords are names of :data:`MASKABLE` (``A, B, C, d, D, E, c``); each pattern is a bool
        or 0/1 array or tensor of the parameter's exact shape, True/1 where the entry may be
        nonzero (is learned), False/0 where it is held at 0. The masked entries are set to 0
        now and stay 0 through :func:`lcs_cvx.fit`. ``None`` removes a parameter's mask.
        Nothing changes unless every pattern is valid.

        Example:
            >>> m = LCS(2, 1, 1).mask(A=[[1, 1], [0, 1]])
            >>> m.A[1, 0].item(), m.masks["A"].tolist()
            (0.0, [[True, True], [False, True]])
        """
        others = {k: v for k, v in self._held.items() if k not in patterns}  # held as they were
        return self.replace_masks({**self._masks, **patterns}, held=others)

    def hold(self, **values: Any) -> LCS:
        """Hold entries of parameters at given values; returns ``self``.

        Keywords are names of :data:`MASKABLE`; each value is an array or tensor of the
        parameter's exact shape, NaN where the entry is learned and the value to hold elsewhere
        (e.g. gravity's increment in ``d``); entries held before (``mask``, ``hold``, the
        kinematics) stay held. The held entries are set now and stay bit-identical
        through :func:`lcs_cvx.fit` (their gradients are zeroed, every step restores them);
        :attr:`masks` shows them as masked, :attr:`held` their values. Nothing changes unless
        every value is valid.

        Example:
            >>> import math
            >>> m = LCS(2, 1, 1).hold(d=[math.nan, -0.0981])
            >>> held, pattern = m.held["d"], m.masks["d"]
            >>> m.d.tolist()[1], pattern.tolist(), held.tolist()[1]
            (-0.0981, [True, False], -0.0981)
        """
        shapes = parameter_shapes(self.n_x, self.n_u, self.n_lam)
        unknown = [k for k in values if k not in MASKABLE]
        if unknown:
            raise LCSInputError(f"{unknown[0]}: expected a name among {MASKABLE} to hold entries of, "
                                f"received {unknown[0]!r}")
        given = {k: as_held(k, v, shapes[k]) for k, v in values.items()}
        for k in given:  # entries held before stay held (unless given again); the caller's array untouched
            if k in self._masks:
                given[k] = torch.where(torch.isnan(given[k]) & ~self._masks[k], self._held[k], given[k])
        with torch.no_grad():
            for k, t in given.items():
                p = getattr(self, k)
                p.copy_(torch.where(~torch.isnan(t).to(p.device), t.to(p), p))
        others = {k: v for k, v in self._held.items() if k not in given}
        return self.replace_masks({**self._masks, **{k: torch.isnan(t) for k, t in given.items()}}, zero=False,
                                  held=others)

    @property
    def held(self) -> dict[str, torch.Tensor]:
        """``{name: tensor}`` (copies, on the CPU, the parameter's dtype) of the masked
        parameters: the value each masked entry is held at (0 for :meth:`mask`), NaN where the
        entry is learned."""
        return {k: torch.where(m, torch.full_like(self._held[k], float("nan")), self._held[k])
                for k, m in self._masks.items()}

    def replace_masks(self, masks: dict[str, Any], *, zero: bool = True,
                      held: dict[str, torch.Tensor] | None = None) -> LCS:
        """Replace every mask by ``masks`` (patterns as in :meth:`mask`, validated; a parameter
        not named, or named with None, has no mask); returns ``self``. The masked entries are
        held at 0 (``zero=True``), at ``held[name]``'s values where given (tensors of the
        parameter's shape, read at the masked entries), or else at the values they have now
        (``zero=False``: for models derived from another one, a unit eliminated, whose masked
        entries are checked afterwards rather than set).
        """
        shapes = parameter_shapes(self.n_x, self.n_u, self.n_lam)
        new: dict[str, torch.Tensor] = {}
        for k, v in masks.items():
            if k not in MASKABLE:
                why = (" (G and H parameterise F = G G^T + H - H^T + s I as a whole: fix them, "
                       "or F, instead)") if k in ("G", "H", "F") else ""
                raise LCSInputError(
                    f"{k}: expected a maskable parameter name among {MASKABLE}, received "
                    f"{k!r}{why}"
                )
            if v is not None:
                new[k] = as_pattern(k, v, shapes[k])
        self._masks = new
        with torch.no_grad():
            for k, m in new.items():
                p = getattr(self, k)
                if held is not None and k in held:
                    p.copy_(torch.where(m.to(p.device), p, held[k].to(p)))
                elif zero:
                    p.masked_fill_(~m.to(p.device), 0.0)
        self._held = {k: getattr(self, k).detach().cpu().clone().masked_fill_(m, 0.0) for k, m in new.items()}
        return self

    def with_kinematics(self, kinematics: Any) -> LCS:
        """Attach known kinematics (:class:`lcs_cvx.Kinematics`); returns ``self``. The
        configuration rows of ``A, B, C, d`` are held at ``x'_q = x_q`` (:meth:`hold`, other
        held entries kept) and :meth:`step` integrates them from the predicted velocities."""
        from .kinematics import attach

        return attach(self, kinematics)

    @property
    def kinematics(self) -> Any:
        """The attached :class:`lcs_cvx.Kinematics`, or None."""
        return self._kinematics

    def as_lcs(self, about: Any = None, u: Any = None) -> LCS:
        """The model as a plain LCS (:meth:`lcs_cvx.Kinematics.to_lcs`: exact with positions,
        a quaternion block linearised about the state ``about`` and input ``u``); ``self``
        without kinematics."""
        return self if self._kinematics is None else self._kinematics.to_lcs(self, about, u)

    @property
    def masks(self) -> dict[str, torch.Tensor]:
        """``{name: bool tensor}`` (copies, on the CPU) of the masked parameters: True where
        the entry is learned, False where it is held at 0 (:meth:`mask`)."""
        return {k: m.clone() for k, m in self._masks.items()}

    # -- construction -------------------------------------------------------------------
    @classmethod
    def from_matrices(cls, *, A: Any, B: Any, C: Any, d: Any, D: Any, E: Any, F: Any, c: Any,
                      dtype: torch.dtype = torch.float64) -> LCS:
        """Build a system from explicit matrices (``F`` given directly).

        ``F`` must satisfy Assumption 1 (``F + F^T`` positive definite); it is stored as
        ``G G^T + H - H^T + s I`` with ``s = sigma_min(F + F^T) / 4``, ``H = (F - F^T) / 4`` and
        ``G`` the Cholesky factor of the rest, so ``model.F`` reproduces ``F`` to round-off.
        """
        n_x, n_u, n_lam = lcs_sizes(A, B, C)
        shapes = parameter_shapes(n_x, n_u, n_lam)
        given = {"A": A, "B": B, "C": C, "d": d, "D": D, "E": E, "F": F, "c": c}
        mats = {k: as_matrix(k, v, shapes[k], dtype=torch.float64) for k, v in given.items()}
        s, G, H = factor_F(mats["F"])
        model = cls(n_x, n_u, n_lam, stiffness=s, init_scale=0.0, dtype=dtype)
        with torch.no_grad():
            for k in ("A", "B", "C", "d", "D", "E", "c"):
                getattr(model, k).copy_(mats[k])
            model.G.copy_(G)
            model.H.copy_(H)
        return model

    # -- the matrices -------------------------------------------------------------------
    @property
    def F(self) -> torch.Tensor:
        """``F = G G^T + H - H^T + s I`` ``(n_lam, n_lam)``."""
        return F_matrix(self.G, self.H, self.stiffness)

    @property
    def sigma_min(self) -> float:
        """``sigma_min(F + F^T)``: the smallest eigenvalue of ``F + F^T`` (Lemma 2's bound on gamma)."""
        with torch.no_grad():
            return float(sym_min_eig(self.F))

    @property
    def dtype(self) -> torch.dtype:
        return self.A.dtype

    @property
    def device(self) -> torch.device:
        return self.A.device

    def _xu(self, x: Any, u: Any) -> tuple[torch.Tensor, torch.Tensor]:
        kw = {"dtype": self.dtype, "device": self.device}
        x = as_batch("x", x, self.n_x, **kw)
        u = as_batch("u", u, self.n_u, batch=x.shape[0], **kw)
        return x, u

    def lcp_offset(self, x: Any, u: Any) -> torch.Tensor:
        """``q = D x + E u + c`` ``(N, n_lam)`` (eq. (2))."""
        x, u = self._xu(x, u)
        return x @ self.D.mT + u @ self.E.mT + self.c

    def solve_lcp(self, x: Any, u: Any, method: str = "fast") -> LCPSolution:
        """The LCP ``lam = LCP(F, D x + E u + c)`` of every sample, exact: an
        :class:`lcs_cvx.LCPSolution` (``lam`` ``(N, n_lam)``, ``w``, ``free``, ...).

        ``method`` is ``"fast"`` (batched pivoting), ``"cvxpy"`` (declared problem (P) with
        Clarabel) or ``"brute"``. When autograd is recording and the parameters require grad,
        ``lam`` (and ``w``) are re-expressed on the solution's free set, so gradients are those
        of the implicit function theorem (Lemma 1); a degenerate index (``lam_i = w_i = 0``) is
        held at zero (one-sided derivative).
        """
        # finite values checked as lcs_cvx.solve_lcp does; Assumption 1 holds by construction
        # (F = G G^T + H - H^T + s I), so its eigenvalue check is skipped
        kw = {"dtype": self.dtype, "device": self.device}
        F = as_matrix("F", self.F, (self.n_lam, self.n_lam), **kw)
        q = as_batch("q", self.lcp_offset(x, u), self.n_lam, **kw)
        sol = solve_lcp_unchecked(F, q, method=method)
        if torch.is_grad_enabled() and (F.requires_grad or q.requires_grad):
            lam = active_set_solve(F, q, sol.free)
            return dataclasses.replace(sol, lam=lam, w=lam @ F.mT + q)
        return sol

    def step(self, x: Any, u: Any, method: str = "fast") -> torch.Tensor:
        """``x' = A x + B u + C lam + d`` with ``lam`` from the exact LCP, ``(N, n_x)`` (``(n_x,)``
        for one state ``x`` ``(n_x,)``); with :attr:`kinematics`, its configuration rows then
        integrated from the velocities."""
        single = np.ndim(x) == 1
        x, u = self._xu(x, u)
        lam = self.solve_lcp(x, u, method=method).lam
        out = x @ self.A.mT + u @ self.B.mT + lam @ self.C.mT + self.d
        out = out if self._kinematics is None else self._kinematics.integrate(x, out)
        return out[0] if single else out

    def forward(self, x: Any, u: Any) -> torch.Tensor:
        """Same as :meth:`step`."""
        return self.step(x, u)

    def rollout(self, x0: Any, us: Any) -> torch.Tensor:
        """Simulate from ``x0`` ``(N, n_x)`` under inputs ``us`` ``(N, T, n_u)`` (:func:`rollout`).

        A single trajectory may be given as ``x0`` ``(n_x,)`` and ``us`` ``(T, n_u)``.
        Returns ``(N, T + 1, n_x)`` (``(T + 1, n_x)`` for a single trajectory).
        """
        return rollout(self, x0, us)

    def active_set(self, x: Any, u: Any, tol: float = ACTIVE_TOL) -> torch.Tensor:
        """Bool ``(N, n_lam)``: ``lam_i > tol`` at the LCP solution (the hybrid mode)."""
        with torch.no_grad():
            return self.solve_lcp(x, u).lam > tol

    def to_matrices(self) -> dict[str, np.ndarray]:
        """The LCS as numpy arrays, keys ``"A", "B", "C", "d", "D", "E", "F", "c"`` (with
        :attr:`kinematics`, the stored rows: :meth:`as_lcs` for the model's step)."""
        with torch.no_grad():
            out = {k: getattr(self, k).detach().cpu().numpy().copy() for k in MATRIX_NAMES if k != "F"}
            out["F"] = self.F.detach().cpu().numpy().copy()
        return {k: out[k] for k in MATRIX_NAMES}

    def extra_repr(self) -> str:
        kin = "" if self._kinematics is None else f", kinematics={self._kinematics}"
        return (f"n_x={self.n_x}, n_u={self.n_u}, n_lam={self.n_lam}, "
                f"stiffness={float(self.stiffness):.3g}, dtype={self.dtype}{kin}")

    def to_c3(self) -> dict[str, np.ndarray]:
        """The LCS (:meth:`as_lcs`) in the convention of the C3 MPC code, as numpy arrays: C3 writes
        ``x' = A x + B u + D lam + d``, ``0 <= lam _|_ E x + F lam + H u + c >= 0``, eq. (1) with
        our ``C, D, E`` renamed ``D, E, H`` (:data:`C3_NAMES`); same shapes."""
        m = self.as_lcs().to_matrices()
        return {c3: m[ours] for c3, ours in C3_NAMES.items()}

    @classmethod
    def from_c3(cls, matrices: dict[str, Any], dtype: torch.dtype = torch.float64) -> LCS:
        """The inverse of :meth:`to_c3`: a system from matrices in C3's naming (keys ``"A", "B",
        "D", "d", "E", "F", "H", "c"``; C3's ``D, E, H`` are our ``C, D, E``)."""
        missing = [k for k in C3_NAMES if k not in matrices]
        if missing:
            raise LCSInputError(f"matrices: expected C3's keys {tuple(C3_NAMES)}, missing {missing}")
        return cls.from_matrices(**{ours: matrices[c3] for c3, ours in C3_NAMES.items()}, dtype=dtype)

