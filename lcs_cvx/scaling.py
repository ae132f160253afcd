r"""Learning in normalised coordinates: an exact change of coordinates of an LCS.

Data come in metres, radians, newtons and millimetres; the losses' constants (``gamma``,
``eps``), the initialisation and Adam's step sizes are all calibrated for data of unit scale.
:class:`Scaling` maps a transition ``(x, u, x')`` to normalised coordinates

    z = S_x^{-1} (x - m_x),    v = S_u^{-1} (u - m_u),    y = S_y^{-1} (x' - K x - m_y),

with means ``m``, diagonal scales ``S`` and ``K`` the 0/1 diagonal that makes ``y`` the
*increment* ``x' - x`` (``K_ii = 1``) where the model allows it. The scales give ``z`` and ``v``
the spread of the paper's benchmark data (Sec. 5: ``x ~ U[-10, 10]``, ``u ~ U[-5, 5]``, standard
deviations :data:`X_SPREAD` and :data:`U_SPREAD`), where the recipes' learning rates, ``eps`` and
``gamma`` were tuned, and ``y`` a unit standard deviation; a constant column gets scale 1.
The paper's spread rather than a unit one because those constants were tuned at it: with unit
spreads more runs of ``recipe="best"`` stay stuck far above the noise floor (the documentation's
Benchmarks page, "Measurements behind the training defaults", has the runs).
An LCS on ``(z, v) -> y``,

    y = Â z + B̂ v + Ĉ lam + d̂,     0 <= lam  _|_  D̂ z + Ê v + F lam + ĉ >= 0,

is exactly the LCS of eq. (1) in the user's units with the same ``lam`` and ``F``
(:meth:`Scaling.to_physical`)::

    A = K + S_y Â S_x^{-1}        B = S_y B̂ S_u^{-1}        C = S_y Ĉ
    d = m_y + S_y (d̂ - Â S_x^{-1} m_x - B̂ S_u^{-1} m_u)
    D = D̂ S_x^{-1}                E = Ê S_u^{-1}             c = ĉ - D m_x - E m_u

and :meth:`Scaling.to_normalised` is its inverse. Known structure survives the change: every map
above is diagonal in each parameter's entries except for ``d`` and ``c``, so a sparsity mask keeps
its pattern. A fixed or masked entry of ``d`` (of ``c``) stays constant through learning when
the rest of its row of ``A - K`` and ``B`` (of ``D`` and ``E``) is fixed or masked too (the
configuration rows of :class:`lcs_cvx.Kinematics`); otherwise ``x`` and ``u`` are not centred
(``m_x = m_u = 0``), and no row of ``y`` whose ``d`` is constrained is (then ``d = S_y d̂`` there
and ``c = ĉ``). ``K_ii = 0`` where a mask holds ``A_ii`` at 0.
A fixed parameter is copied back bit for bit after the fold-back.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch

from .data import Dataset
from .parameter_constraints import project_
from .system import LCS, PARAMETER_NAMES

__all__ = ["Scaling", "X_SPREAD", "U_SPREAD", "in_user_coordinates", "fold_back"]

#: The standard deviation of ``z`` (``U[-10, 10]``'s) and of ``v`` (``U[-5, 5]``'s).
X_SPREAD = 10.0 / 3.0**0.5
U_SPREAD = 5.0 / 3.0**0.5


def _constrained_entries(model: LCS, name: str) -> torch.Tensor:
    """Bool, the parameter's shape (CPU): True where the entry is fixed or masked."""
    p = getattr(model, name)
    if not p.requires_grad:
        return torch.ones(p.shape, dtype=torch.bool)
    mask = model.masks.get(name)
    return torch.zeros(p.shape, dtype=torch.bool) if mask is None else ~mask


def _held_rows_vary(model: LCS, name: str, others: tuple[str, ...]) -> bool:
    """Whether a constrained entry of the offset ``name`` (``d`` or ``c``) sits in a row in which
    ``others`` have free entries: its normalised value would then move with them unless ``x``
    and ``u`` are not centred."""
    rows = _constrained_entries(model, name)
    free = torch.zeros_like(rows)
    for other in others:
        free |= ~_constrained_entries(model, other).all(1)
    return bool((rows & free).any())


def _moments(a: torch.Tensor, center: bool | torch.Tensor, spread: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean (0 without centring; ``center`` per column or for all) and scale of each column: its
    standard deviation (RMS without centring) over ``spread``; a column whose deviation is at
    round-off level of its magnitude (a constant column) gets 1."""
    m = a.mean(0) * torch.as_tensor(center, dtype=a.dtype)
    s = (a - m).pow(2).mean(0).sqrt()
    floor = 1e-12 * a.abs().amax(0) if a.shape[0] else torch.zeros_like(s)
    return m, torch.where(s > floor, s / spread, torch.ones_like(s))


@dataclass(frozen=True)
class Scaling:
    """The affine change of coordinates of the module docstring; every field ``(n,)`` float64.

    Attributes:
        mx, sx: mean and scale of ``x`` ``(n_x,)``.
        mu, su: of ``u`` ``(n_u,)``.
        my, sy: of the target ``x' - K x`` ``(n_x,)``.
        k: the diagonal of ``K`` ``(n_x,)`` (1.0: the target is the increment ``x' - x``).

    Example:
        >>> import lcs_cvx
        >>> from lcs_cvx.scaling import Scaling
        >>> truth = lcs_cvx.random_lcs(3, 1, 2, seed=0)
        >>> data = lcs_cvx.make_dataset(truth, 200, seed=1)
        >>> scaling = Scaling.fit(data)
        >>> back = scaling.to_physical(scaling.to_normalised(truth))
        >>> bool(torch.allclose(back.step(data.x, data.u), truth.step(data.x, data.u)))
        True
    """

    mx: torch.Tensor
    sx: torch.Tensor
    mu: torch.Tensor
    su: torch.Tensor
    my: torch.Tensor
    sy: torch.Tensor
    k: torch.Tensor

    @classmethod
    def fit(cls, data: Dataset, model: LCS | None = None) -> Scaling:
        """The scaling of ``data`` (statistics in float64) for learning ``model``'s structure
        (its fixed and masked parameters decide centring and ``K``; None: none)."""
        x, u, xn = (t.detach().to("cpu", torch.float64) for t in (data.x, data.u, data.x_next))
        center_xu, center_y = True, torch.ones(x.shape[1], dtype=torch.bool)
        k = torch.ones(x.shape[1], dtype=torch.float64)
        if model is not None:
            held_A = model.held.get("A")  # NaN where learned
            if held_A is not None:  # K_ii = 0 where A_ii is held at 0
                k = (held_A.diagonal() != 0).to(torch.float64)
            center_xu = not (_held_rows_vary(model, "d", ("A", "B")) or _held_rows_vary(model, "c", ("D", "E")))
            center_y = ~_constrained_entries(model, "d")
        mx, sx = _moments(x, center_xu, X_SPREAD)
        mu, su = _moments(u, center_xu, U_SPREAD)
        my, sy = _moments(xn - k * x, center_y, 1.0)
        return cls(mx, sx, mu, su, my, sy, k)

    def _on(self, like: torch.Tensor) -> Scaling:
        kw = {"dtype": like.dtype, "device": like.device}
        return Scaling(*(getattr(self, f).to(**kw) for f in ("mx", "sx", "mu", "su", "my", "sy", "k")))

    # -- data ---------------------------------------------------------------------------
    def encode(self, data: Dataset) -> Dataset:
        """``data`` in normalised coordinates ``(z, v, y)`` (``lam`` kept as it is)."""
        s = self._on(data.x)
        z = (data.x - s.mx) / s.sx
        v = (data.u - s.mu) / s.su
        y = (data.x_next - s.k * data.x - s.my) / s.sy
        return Dataset(z, v, y, data.lam)

    # -- models -------------------------------------------------------------------------
    def to_normalised(self, model: LCS) -> LCS:
        """A new LCS: ``model`` in normalised coordinates (same ``lam`` and ``F``), with its fixed
        parameters fixed and its masks."""
        with torch.no_grad():
            p = {name: getattr(model, name).detach() for name in PARAMETER_NAMES}
            s = self._on(p["A"])
            Ak = p["A"] - torch.diag(s.k)
            values = {
                "A": Ak * s.sx / s.sy[:, None],
                "B": p["B"] * s.su / s.sy[:, None],
                "C": p["C"] / s.sy[:, None],
                "d": (Ak @ s.mx + p["B"] @ s.mu + p["d"] - s.my) / s.sy,
                "D": p["D"] * s.sx,
                "E": p["E"] * s.su,
                "c": p["c"] + p["D"] @ s.mx + p["E"] @ s.mu,
                "G": p["G"], "H": p["H"],
            }
        return _like(model, values)

    def to_physical(self, normalised: LCS, out: LCS | None = None) -> LCS:
        """The LCS in the user's units of a model learned in normalised coordinates: written into
        ``out`` in place (its fixed parameters kept bit for bit) when given, else a new LCS."""
        with torch.no_grad():
            p = {name: getattr(normalised, name).detach() for name in PARAMETER_NAMES}
            s = self._on(p["A"])
            A_hat_x = p["A"] / s.sx  # Â S_x^{-1}
            B_hat_u = p["B"] / s.su
            D = p["D"] / s.sx
            E = p["E"] / s.su
            values = {
                "A": torch.diag(s.k) + s.sy[:, None] * A_hat_x,
                "B": s.sy[:, None] * B_hat_u,
                "C": s.sy[:, None] * p["C"],
                "d": s.my + s.sy * (p["d"] - A_hat_x @ s.mx - B_hat_u @ s.mu),
                "D": D, "E": E,
                "c": p["c"] - D @ s.mx - E @ s.mu,
                "G": p["G"], "H": p["H"],
            }
            if out is None:
                return _like(normalised, values)
            for name, value in values.items():
                param = getattr(out, name)
                if param.requires_grad:  # a fixed parameter keeps the user's exact value
                    param.copy_(value)
            project_(out)
        return out


def _like(model: LCS, values: dict[str, torch.Tensor]) -> LCS:
    """A new LCS of ``model``'s sizes, stiffness, dtype and device with these parameter values,
    and ``model``'s fixed parameters and masks."""
    new = LCS(model.n_x, model.n_u, model.n_lam, stiffness=float(model.stiffness), init_scale=0.0,
              dtype=model.dtype).to(model.device)
    with torch.no_grad():
        for name, value in values.items():
            getattr(new, name).copy_(value)
    for name in PARAMETER_NAMES:  # the flags and masks, not the values: those are mapped
        getattr(new, name).requires_grad_(getattr(model, name).requires_grad)
    if model.masks:  # held at the mapped values (entrywise maps: no centring where d, c are held)
        new.replace_masks(model.masks, zero=False)
    return new


def in_user_coordinates(scaling: Scaling | None, learner: LCS, like: LCS) -> LCS:
    """``learner`` (a model in the coordinates of learning) in the user's coordinates: a copy of
    ``like`` (its fixed parameters bit for bit) when the sizes agree, else a new LCS; ``learner``
    itself without a scaling."""
    if scaling is None:
        return learner
    out = scaling.to_physical(learner, out=copy.deepcopy(like) if learner.n_lam == like.n_lam else None)
    out._kinematics = like.kinematics
    return out


def fold_back(scaling: Scaling | None, learner: LCS, model: LCS) -> None:
    """Write ``learner`` into ``model`` (in place), in the user's coordinates."""
    if scaling is not None:
        scaling.to_physical(learner, out=model)
    elif learner is not model:
        model.load_state_dict(learner.state_dict())
