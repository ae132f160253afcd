r"""The models the physics study compares, behind one interface: ``predict(x, u, contact=None)``
maps states ``(N, n_x)`` and inputs ``(N, n_u)`` (physical units, float64 numpy) to next states.

- :class:`LCSModel` -- a learned :class:`lcs_cvx.LCS` in physical units.
- :class:`AffineModel` -- ``x' = A x + B u + d`` by least squares.
- :class:`ModeAffineModel` -- the affine model fitted separately on each true contact mode
  (cart-pole: free / left wall / right wall; pusher-slider: separated / sticking / sliding either
  way) and told the true mode when it predicts: an oracle, the best a
  piecewise-affine model with known modes could do.
- :class:`MLPModel` -- a small MLP (torch), ``x' = x + f(x, u)``.
- :class:`PARCModel` -- PARC's piecewise-affine model (Bemporad's piecewise-affine regression
  and classification, :mod:`lcs_cvx.study.baselines.parc`), rebuilt from its pieces and its
  partition.

The LCS is learned by :func:`lcs_cvx.fit` in the library's normalised coordinates
(:class:`lcs_cvx.scaling.Scaling`) and comes back in physical units; the MLP learns on the same
normalised coordinates.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import torch

import lcs_cvx
from lcs_cvx import LCS, Dataset
from lcs_cvx.scaling import Scaling

__all__ = [
    "LCSModel",
    "AffineModel",
    "ModeAffineModel",
    "MLPModel",
    "PARCModel",
    "contact_mode",
    "encode",
    "fit_lcs",
    "fit_mlp",
    "fit_parc",
    "mlp_from_result",
    "parc_from_result",
]


def contact_mode(contact: np.ndarray) -> np.ndarray:
    """The mode label ``(N,)`` int64 of a contact state: ``(N, k)`` bool (one column per
    contact) -> ``sum_j 2^j contact_j`` (cart-pole: ``0`` free, ``1`` left, ``2`` right, ``3``
    both); an ``(N,)`` array of integer labels is returned as it is."""
    contact = np.asarray(contact)
    if contact.ndim == 1:
        if not np.issubdtype(contact.dtype, np.integer):
            raise ValueError(f"contact: expected integer mode labels, received dtype {contact.dtype}")
        return contact.astype(np.int64)
    bits = contact.astype(bool).astype(np.int64)
    return bits @ (2 ** np.arange(bits.shape[1], dtype=np.int64))


class LCSModel:
    """A learned LCS in physical units; ``lam(x, u)`` is its complementarity variable."""

    def __init__(self, lcs: LCS) -> None:
        self.lcs = lcs

    @classmethod
    def from_matrices(cls, matrices: dict[str, np.ndarray]) -> LCSModel:
        return cls(LCS.from_matrices(**matrices))

    def predict(self, x: np.ndarray, u: np.ndarray, contact: np.ndarray | None = None) -> np.ndarray:
        out = np.full(x.shape, np.nan)
        ok = np.isfinite(x).all(axis=1)  # a diverged rollout stays diverged
        with torch.no_grad():
            out[ok] = self.lcs.step(torch.from_numpy(np.ascontiguousarray(x[ok])),
                                    torch.from_numpy(np.ascontiguousarray(u[ok]))).numpy()
        return out

    def lam(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``lam = LCP(F, D x + E u + c)`` ``(N, n_lam)`` for states ``(N, n_x)``, inputs ``(N, n_u)``."""
        with torch.no_grad():
            return self.lcs.solve_lcp(torch.from_numpy(np.ascontiguousarray(x)),
                                      torch.from_numpy(np.ascontiguousarray(u))).lam.numpy()


def _lstsq(x: np.ndarray, u: np.ndarray, x_next: np.ndarray) -> np.ndarray:
    Z = np.hstack([x, u, np.ones((x.shape[0], 1))])
    W, *_ = np.linalg.lstsq(Z, x_next, rcond=None)
    return W


def _affine(W: np.ndarray, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    return np.hstack([x, u, np.ones((x.shape[0], 1))]) @ W


class AffineModel:
    """``x' = A x + B u + d`` fitted by least squares."""

    def __init__(self, W: np.ndarray) -> None:
        self.W = W

    @classmethod
    def fit(cls, x: np.ndarray, u: np.ndarray, x_next: np.ndarray) -> AffineModel:
        return cls(_lstsq(x, u, x_next))

    def predict(self, x: np.ndarray, u: np.ndarray, contact: np.ndarray | None = None) -> np.ndarray:
        return _affine(self.W, x, u)


class ModeAffineModel:
    """One affine least-squares model per true contact mode (:func:`contact_mode`); a mode with
    fewer than ``min_samples`` training samples uses the model fitted on all of them."""

    def __init__(self, weights: dict[int, np.ndarray], fallback: np.ndarray) -> None:
        self.weights, self.fallback = weights, fallback

    @classmethod
    def fit(cls, x: np.ndarray, u: np.ndarray, x_next: np.ndarray, contact: np.ndarray,
            min_samples: int = 50) -> ModeAffineModel:
        mode = contact_mode(contact)
        weights = {}
        for k in np.unique(mode):
            sel = mode == k
            if sel.sum() >= min_samples:
                weights[int(k)] = _lstsq(x[sel], u[sel], x_next[sel])
        return cls(weights, _lstsq(x, u, x_next))

    def predict(self, x: np.ndarray, u: np.ndarray, contact: np.ndarray | None = None) -> np.ndarray:
        if contact is None:
            raise ValueError("contact: the mode oracle needs the true contact state of every sample")
        mode = contact_mode(contact)
        out = _affine(self.fallback, x, u)
        for k, W in self.weights.items():
            sel = mode == k
            if sel.any():
                out[sel] = _affine(W, x[sel], u[sel])
        return out


def encode(scaling: Scaling, x: np.ndarray, u: np.ndarray, x_next: np.ndarray | None = None
           ) -> tuple[np.ndarray, ...]:
    """``(z, v)``, or ``(z, v, y)`` with ``x_next``, in the normalised coordinates of ``scaling``."""
    xt, ut = torch.from_numpy(np.ascontiguousarray(x)), torch.from_numpy(np.ascontiguousarray(u))
    xn = torch.from_numpy(np.ascontiguousarray(x_next)) if x_next is not None else xt
    d = scaling.encode(Dataset(xt, ut, xn))
    out = (d.x.numpy(), d.u.numpy()) + ((d.x_next.numpy(),) if x_next is not None else ())
    return out


class MLPModel:
    """``x' = x + m_y + S_y f(z, v)`` with ``f`` a tanh MLP on the normalised coordinates."""

    def __init__(self, net: torch.nn.Module, scaling: Scaling) -> None:
        self.net, self.scaling = net, scaling

    def predict(self, x: np.ndarray, u: np.ndarray, contact: np.ndarray | None = None) -> np.ndarray:
        z, v = encode(self.scaling, x, u)
        with torch.no_grad():
            y = self.net(torch.from_numpy(np.hstack([z, v]))).numpy()
        s = self.scaling
        return s.k.numpy() * x + s.my.numpy() + s.sy.numpy() * y


def _mlp(n_in: int, n_out: int, hidden: list[int], seed: int) -> torch.nn.Module:
    torch.manual_seed(seed)
    layers: list[torch.nn.Module] = []
    for h in hidden:
        layers += [torch.nn.Linear(n_in, h), torch.nn.Tanh()]
        n_in = h
    layers.append(torch.nn.Linear(n_in, n_out))
    return torch.nn.Sequential(*layers).to(torch.float64)


def fit_mlp(job: dict[str, Any]) -> dict[str, Any]:
    """Train the MLP baseline (a process-pool job; plain data in, plain data out).

    ``job``: ``z, v, y`` (normalised training data), ``z_val, v_val, y_val`` (validation),
    ``hidden``, ``iterations``, ``batch_size``, ``lr``, ``weight_decay``, ``seed``. Adam on the
    mean squared error of ``y`` with a cosine learning rate; the iterate with the lowest
    validation error (checked every 250 iterations) is kept. Returns ``state`` (the state dict as
    numpy), ``hidden``, ``history`` and ``wall_time``.
    """
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    Xt = torch.from_numpy(np.hstack([job["z"], job["v"]]))
    Yt = torch.from_numpy(job["y"])
    Xh = torch.from_numpy(np.hstack([job["z_val"], job["v_val"]]))
    Yh = torch.from_numpy(job["y_val"])
    gen = torch.Generator().manual_seed(job["seed"])
    net = _mlp(Xt.shape[1], Yt.shape[1], list(job["hidden"]), job["seed"])
    opt = torch.optim.Adam(net.parameters(), lr=job["lr"], weight_decay=job["weight_decay"])
    iters, bs = job["iterations"], min(job["batch_size"], Xt.shape[0])
    best, best_state, history = math.inf, None, []
    for it in range(iters):
        for g in opt.param_groups:
            g["lr"] = job["lr"] * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * it / iters)))
        idx = torch.randint(0, Xt.shape[0], (bs,), generator=gen)
        loss = ((net(Xt[idx]) - Yt[idx]) ** 2).sum(-1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if (it + 1) % 250 == 0 or it + 1 == iters:
            with torch.no_grad():
                h = float(((net(Xh) - Yh) ** 2).sum(-1).mean())
            history.append({"iteration": it + 1, "val_mse": h})
            if h < best:
                best = h
                best_state = {n: p.detach().clone() for n, p in net.state_dict().items()}
    if best_state is not None:
        net.load_state_dict(best_state)
    return {"state": {n: p.numpy() for n, p in net.state_dict().items()}, "hidden": list(job["hidden"]),
            "history": history, "val_mse": best, "wall_time": time.perf_counter() - t0}


def mlp_from_result(result: dict[str, Any], scaling: Scaling, n_in: int, n_out: int) -> MLPModel:
    net = _mlp(n_in, n_out, result["hidden"], 0)
    net.load_state_dict({n: torch.from_numpy(np.asarray(p)) for n, p in result["state"].items()})
    return MLPModel(net, scaling)


def fit_lcs(job: dict[str, Any]) -> dict[str, Any]:
    """Learn one LCS (a process-pool job; plain data in, plain data out).

    ``job``: ``x, u, x_next`` (training, physical units) and ``x_val, u_val, x_next_val``
    (validation: with ``keep_best`` in the options the held-out part the kept iterate and restart
    are chosen on, else monitored only; scored at the end), ``n_lam``, ``loss``, ``recipe``, ``options``
    (more :func:`lcs_cvx.fit` options), ``stiffness``, ``init_scale``, ``init`` (the
    :func:`lcs_cvx.fit` option: ``"increment"``, ``"affine"`` or ``"model"``), ``seed``. The fit
    normalises the data itself and returns the model in physical units. Returns its
    ``matrices``, ``val_error`` (relative error on the validation set), ``history``, ``settings``
    and ``wall_time``; a run that fails with :class:`lcs_cvx.SolverError` returns
    ``matrices = None``, ``val_error = inf`` and ``error``.
    """
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    train = Dataset.from_arrays(job["x"], job["u"], job["x_next"])
    val = Dataset.from_arrays(job["x_val"], job["u_val"], job["x_next_val"])
    model = LCS(train.n_x, train.n_u, job["n_lam"], stiffness=job["stiffness"],
                init_scale=job["init_scale"], seed=job["seed"])
    try:
        # with keep_best the validation set is the held-out part the iterate is chosen on; else it
        # is monitored only (e_test) and the restarts are chosen on fit's own held-out fraction
        held = {"validation": val} if job["options"].get("keep_best") else {"test": val}
        result = lcs_cvx.fit(model, train, recipe=job["recipe"], loss=job["loss"], seed=job["seed"],
                             init=job["init"], progress=False, **held, **job["options"])
    except lcs_cvx.SolverError as exc:  # a diverged run: reported, never selected
        return {"matrices": None, "val_error": math.inf, "history": [], "settings": None,
                "wall_time": time.perf_counter() - t0, "error": str(exc)}
    settings = result.settings.flat()
    return {
        "matrices": result.model.to_matrices(),
        "val_error": lcs_cvx.relative_error(result.model, val),
        "history": result.history,
        "settings": settings,
        "wall_time": time.perf_counter() - t0,
    }


class PARCModel:
    r"""A piecewise-affine model with a piecewise-linear partition, as PARC fits it
    (``pyparc.parc.PARC.predict`` with numerical targets): for ``z = [x, u]`` ``(n_z,)``,

        j = argmax_i  omega_i^T z + gamma_i,    x' = coef_j^T z + intercept_j,

    ``omega`` ``(K, n_z)``, ``gamma`` ``(K,)``, ``coef`` ``(K, n_z, n_x)``, ``intercept`` ``(K, n_x)``.
    """

    def __init__(self, omega: np.ndarray, gamma: np.ndarray, coef: np.ndarray, intercept: np.ndarray) -> None:
        K, n_z = omega.shape
        if gamma.shape != (K,) or coef.shape[:2] != (K, n_z) or intercept.shape != (K, coef.shape[2]):
            raise ValueError(f"omega, gamma, coef, intercept: expected shapes (K, n_z), (K,), (K, n_z, n_x), "
                             f"(K, n_x), received {omega.shape}, {gamma.shape}, {coef.shape}, {intercept.shape}")
        self.omega, self.gamma, self.coef, self.intercept = omega, gamma, coef, intercept

    @classmethod
    def from_predictor(cls, predictor: Any) -> PARCModel:
        """The arrays of a fitted ``pyparc.parc.PARC`` (numerical targets, every feature used)."""
        p = predictor
        if any(p.categorical) or list(p.coeff_index) != list(range(p.ny)) or not np.all(p.feature_selection):
            raise ValueError("predictor: expected a PARC fit with numerical targets and every feature "
                             f"selected, received categorical={p.categorical}, coeff_index={p.coeff_index}")
        return cls(*(np.array(a, dtype=np.float64) for a in (p.omega, np.ravel(p.gamma), p.coef_, p.intercept_)))

    def piece(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The piece ``j`` ``(N,)`` of every sample."""
        return np.argmax(np.hstack([x, u]) @ self.omega.T + self.gamma, axis=1)

    def predict(self, x: np.ndarray, u: np.ndarray, contact: np.ndarray | None = None) -> np.ndarray:
        z = np.hstack([x, u])
        j = np.argmax(z @ self.omega.T + self.gamma, axis=1)
        return np.einsum("nz,nzx->nx", z, self.coef[j]) + self.intercept[j]


def fit_parc(job: dict[str, Any]) -> dict[str, Any]:
    """Fit the PARC baseline (a process-pool job; plain data in, plain data out) through
    :func:`lcs_cvx.study.baselines.parc.fit` on the raw ``[x, u] -> x'`` data.

    ``job``: ``x, u, x_next`` (training, physical units), ``options`` (the complete options of
    ``lcs_cvx.study.baselines.OPTIONS["parc"]``), ``modes`` (K where ``options["K"] == "modes"``),
    ``seed``. Returns the :class:`PARCModel` arrays ``omega, gamma, coef, intercept``, ``info``
    (K asked, pieces kept, iterations, final cost) and ``wall_time``; a fit in which ``pyparc``
    raises returns ``omega = None`` and ``error`` (the exception's type and message).
    """
    from lcs_cvx.study.baselines import BaselineFailed
    from lcs_cvx.study.baselines.parc import fit, import_parc

    import_parc()  # a missing extra is an error of the set-up, not a failed fit
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    train = Dataset.from_arrays(job["x"], job["u"], job["x_next"])
    try:
        model, info = fit(train, job["options"], seed=job["seed"], modes=job["modes"])
    except BaselineFailed as exc:  # pyparc's own fit failed: a result, reported in the tables
        cause = exc.__cause__ or exc  # name pyparc's exception, which BaselineFailed wraps
        return {"omega": None, "gamma": None, "coef": None, "intercept": None, "info": None,
                "wall_time": time.perf_counter() - t0, "error": f"{type(cause).__name__}: {cause}"}
    arrays = PARCModel.from_predictor(model.predictor)
    return {"omega": arrays.omega, "gamma": arrays.gamma, "coef": arrays.coef, "intercept": arrays.intercept,
            "info": info, "wall_time": time.perf_counter() - t0, "error": None}


def parc_from_result(result: dict[str, Any]) -> PARCModel:
    """The :class:`PARCModel` of a :func:`fit_parc` result that did not fail."""
    if result.get("error") is not None:
        raise ValueError(f"result: expected a PARC fit that succeeded, received the error {result['error']!r}")
    return PARCModel(*(np.asarray(result[k], dtype=np.float64) for k in ("omega", "gamma", "coef", "intercept")))
