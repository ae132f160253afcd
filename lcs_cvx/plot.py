"""Plots of a fit: what a person would rather look at than read.

Each function draws with matplotlib (the ``plot`` extra) on a figure of its own or on the
``ax``/``axes`` it is given, returns the :class:`matplotlib.figure.Figure`, and writes a file only
when ``path`` is given (PNG, or any format matplotlib infers from the suffix). No function opens
a window or touches pyplot's global state: the figures are :class:`~matplotlib.figure.Figure`
objects, shown by a notebook or saved with ``fig.savefig``.

- :func:`history` -- the training loss and the held-out score against iterations, the phases
  (Adam, pruning, Gauss--Newton or Newton, polish, simulation error) as bands, the kept iterate
  marked (:meth:`lcs_cvx.FitResult.plot`).
- :func:`rollouts` -- recorded against predicted runs, per coordinate: the model's open-loop
  rollout (restarted from the recorded state every ``horizon`` steps) beside the least-squares
  affine map's and any other model's.
- :func:`modes` -- which complementarity units are active along each recorded run (a raster of
  the exact LCP's active sets, eq. (1)) and how many modes that makes.
- :func:`plan` -- a C3 plan (:class:`lcs_cvx.control.Plan`): planned states, inputs and forces
  against the model's own rollout under the planned inputs.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from ._checks import LCSInputError
from ._optional import require
from .data import Dataset
from .metrics import affine_lstsq
from .trajectories import Trajectories

__all__ = ["history", "rollouts", "modes", "plan", "PHASE_COLORS"]

#: The band colour of each training phase in :func:`history`.
PHASE_COLORS = {"adam": "#dde8f4", "prune": "#f4e3c9", "gauss-newton": "#dcefd9", "newton": "#dcefd9",
                "polish": "#efdcef", "rollout": "#f6dada"}


def _figure(axes: Any, rows: int, size: tuple[float, float]) -> tuple[Any, list[Any]]:
    """``(figure, a list of rows axes)``: the given axes (checked) or a new figure's, one column."""
    if axes is None:
        figure_cls = require("matplotlib.figure", "plot", "lcs_cvx.plot").Figure
        fig = figure_cls(figsize=size, layout="constrained")
        return fig, list(fig.subplots(rows, 1, squeeze=False, sharex=True)[:, 0])
    flat = list(np.atleast_1d(np.asarray(axes, dtype=object)).reshape(-1))
    if len(flat) != rows or not all(hasattr(a, "plot") for a in flat):
        raise LCSInputError(f"axes: expected {rows} matplotlib Axes, received {len(flat)} "
                            f"({type(axes).__name__})")
    return flat[0].figure, flat


def _save(fig: Any, path: str | os.PathLike | None) -> Any:
    if path is not None:
        fig.savefig(os.fspath(path), dpi=120)
    return fig


def _numpy(t: Any) -> np.ndarray:
    return t.detach().cpu().numpy() if isinstance(t, torch.Tensor) else np.asarray(t)


# -- training ---------------------------------------------------------------------------------
def history(result: Any, ax: Any = None, path: str | os.PathLike | None = None) -> Any:
    """The training of :func:`lcs_cvx.fit`: the mean training loss of each record (log scale)
    and, on the right axis, the held-out score (``heldout``, with ``keep_best``) and the test
    error (``e_test``, with ``test``; reported only), against the iteration; the phases as
    bands and the kept iterate (the lowest held-out score of the kept restart) marked. Other
    restarts' losses are drawn thin.

    Args:
        result: a :class:`lcs_cvx.FitResult`.
        ax: a matplotlib ``Axes`` to draw on (default: a new figure).
        path: write the figure there (default: nothing is written).
    """
    records = getattr(result, "history", None)
    if not isinstance(records, list) or not records:
        raise LCSInputError("result: expected an lcs_cvx.FitResult with at least one history record, received "
                            + (f"{type(result).__name__}" if records is None else "an empty history"))
    fig, (ax,) = _figure(ax, 1, (7.5, 5.0))
    kept = result.kept_restart
    mine = [h for h in records if h.get("restart", 0) == kept]
    for r in sorted({h.get("restart", 0) for h in records} - {kept}):
        other = [h for h in records if h.get("restart", 0) == r]
        ax.semilogy([h["iteration"] for h in other], [h["loss"] for h in other], color="0.6", lw=0.8,
                    label=f"training loss, restart {r}")
    it = [h["iteration"] for h in mine]
    ax.semilogy(it, [h["loss"] for h in mine], color="C0", lw=1.6, label="training loss"
                + (f", restart {kept} (kept)" if len(result.restart_scores) > 1 else ""))
    lo, bands = 0, {}
    for phase, group in itertools.groupby(mine, key=lambda h: h["phase"]):  # a band per phase
        hi = list(group)[-1]["iteration"]
        band = ax.axvspan(lo, hi, color=PHASE_COLORS.get(phase, "#eeeeee"), zorder=0, lw=0)
        bands.setdefault(f"phase: {phase}", band)
        lo = hi
    ax.set_xlabel("iteration")
    ax.set_ylabel("mean regularised training loss")
    right = None
    for key, label, color in (("heldout", "held-out score (chooses the kept iterate)", "C3"),
                              ("e_test", "test error e_test (reported only)", "C2")):
        pts = [(h["iteration"], h[key]) for h in mine if h.get(key) is not None and np.isfinite(h[key])]
        if pts:
            right = right if right is not None else ax.twinx()
            right.semilogy(*zip(*pts, strict=True), "o-", ms=3, lw=1.0, color=color, label=label)
    best = [h for h in mine if h.get("heldout") is not None and np.isfinite(h["heldout"])]
    if best and result.settings.run.keep_best:
        h = min(best, key=lambda h: h["heldout"])
        right.plot([h["iteration"]], [h["heldout"]], "*", ms=14, color="C3", label="kept iterate")
    if right is not None:
        right.set_ylabel("score")
    handles = [a.get_legend_handles_labels() for a in (ax, right) if a is not None]
    handles.append((list(bands.values()), list(bands)))
    ax.legend(sum((h for h, _ in handles), []), sum((lab for _, lab in handles), []), fontsize=8,
              loc="upper center", bbox_to_anchor=(0.5, -0.15), ncols=3, frameon=False)
    ax.set_title(f"fit: {len(mine)} records" + (f", {len(result.restart_scores)} restarts"
                                                 if len(result.restart_scores) > 1 else ""))
    return _save(fig, path)


# -- recorded runs ----------------------------------------------------------------------------
def _windows(model: Any, x: torch.Tensor, u: torch.Tensor, horizon: int) -> np.ndarray:
    """The rollout of ``model`` along one run ``x`` ``(T + 1, n_x)``, ``u`` ``(T, n_u)``,
    restarted from the recorded state every ``horizon`` steps: ``(T + 1, n_x)``, NaN where a
    rollout left the finite numbers."""
    T = u.shape[0]
    dtype = getattr(model, "dtype", torch.float64)
    device = getattr(model, "device", x.device)
    out = np.full((T + 1, x.shape[1]), np.nan)
    out[0] = _numpy(x[0])
    with torch.no_grad():
        for s in range(0, T, horizon):
            state = x[s : s + 1].to(dtype=dtype, device=device)
            for t in range(s, min(s + horizon, T)):
                state = model.step(state, u[t : t + 1].to(dtype=dtype, device=device))
                if not bool(torch.isfinite(state).all()):
                    break
                out[t + 1] = _numpy(state[0])
    return out


def _baselines(baselines: Any, trajectories: Trajectories) -> dict[str, Any]:
    """``{label: model}``: ``"affine"`` is the least-squares affine map fitted on the runs shown."""
    if isinstance(baselines, Mapping):
        return dict(baselines)
    out = {}
    for b in baselines or ():
        if b == "affine":
            out["affine least squares (fitted on these runs)"] = affine_lstsq(trajectories.to_transitions())
        elif callable(getattr(b, "step", None)):
            out[type(b).__name__] = b
        else:
            raise LCSInputError(f"baselines: expected 'affine', models with a step(x, u) or a mapping "
                                f"label -> model, received {b!r}")
    return out


def _coordinates(coordinates: Any, n_x: int, names: Sequence[str] | None) -> list[int]:
    if coordinates is None:
        return list(range(n_x))
    out = []
    for c in ([coordinates] if isinstance(coordinates, (int, str)) else coordinates):
        if isinstance(c, str):
            if names is None or c not in names:
                raise LCSInputError(f"coordinates: expected a state index or one of the data's names "
                                    f"{list(names) if names else '(none: the data has no names)'}, received {c!r}")
            c = list(names).index(c)
        if not isinstance(c, (int, np.integer)) or not 0 <= c < n_x:
            raise LCSInputError(f"coordinates: expected indices in [0, {n_x}), received {c!r}")
        out.append(int(c))
    return out


def rollouts(model: Any, trajectories: Trajectories, horizon: int | None = None, coordinates: Any = None,
             baselines: Any = ("affine",), run: int = 0, dt: float | None = None, axes: Any = None,
             path: str | os.PathLike | None = None) -> Any:
    """Run ``run`` of ``trajectories`` as recorded against the open-loop predictions of ``model``
    and of the baselines, one panel per state coordinate.

    Args:
        model: an :class:`lcs_cvx.LCS` (or any model with ``step(x, u)``).
        trajectories: :class:`lcs_cvx.Trajectories` (their ``names``, when they have them, label
            the panels).
        horizon: steps of each open-loop rollout: every ``horizon`` steps the prediction starts
            again from the recorded state (the held-out score's windows); None: one rollout over
            the whole run.
        coordinates: the state coordinates to draw (indices or names; default: all).
        baselines: ``"affine"`` (the least-squares affine map fitted on ``trajectories``: a
            reference that has seen the runs), other models with ``step(x, u)``, or a mapping
            ``{label: model}`` (an MLP, say).
        run: which trajectory.
        dt: seconds per step: the time axis in seconds (default: steps).
        axes: one matplotlib ``Axes`` per coordinate (default: a new figure).
        path: write the figure there.
    """
    if not isinstance(trajectories, Trajectories):
        raise LCSInputError(f"trajectories: expected lcs_cvx.Trajectories, received {type(trajectories).__name__}")
    if not isinstance(run, (int, np.integer)) or not 0 <= run < len(trajectories):
        raise LCSInputError(f"run: expected an index in [0, {len(trajectories)}), received {run!r}")
    T = trajectories.lengths[run]
    if horizon is not None and (isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or horizon < 1):
        raise LCSInputError(f"horizon: expected None or an integer >= 1, received {horizon!r}")
    names = getattr(trajectories, "names", None)
    coords = _coordinates(coordinates, trajectories.n_x, names)
    x, u = trajectories.xs[run], trajectories.us[run]
    H = T if horizon is None else int(horizon)
    predicted = {"model": _windows(model, x, u, H)}
    for label, b in _baselines(baselines, trajectories).items():
        predicted[label] = _windows(b, x, u, H)
    fig, axs = _figure(axes, len(coords), (7.0, 1.0 + 1.8 * len(coords)))
    t = np.arange(T + 1) * (1.0 if dt is None else dt)
    for ax, c in zip(axs, coords, strict=True):
        ax.plot(t, _numpy(x[:, c]), color="k", lw=1.8, label="recorded")
        for k, (label, xs) in enumerate(predicted.items()):
            ax.plot(t, xs[:, c], lw=1.2, ls="-" if k == 0 else "--", color=f"C{k}",
                    label=type(model).__name__ if label == "model" else label)
        if horizon is not None and H < T:
            for s in range(H, T, H):
                ax.axvline(t[s], color="0.85", lw=0.6, zorder=0)
        ax.set_ylabel(names[c] if names else f"x[{c}]")
    axs[-1].set_xlabel("time [s]" if dt is not None else "step")
    axs[0].legend(fontsize=8, loc="best")
    axs[0].set_title(f"run {run}: " + ("open-loop rollout over the whole run" if horizon is None or H >= T
                                        else f"{H}-step open-loop rollouts from the recorded states"))
    return _save(fig, path)


def modes(model: Any, trajectories: Trajectories | Dataset, ax: Any = None, tol: float | None = None,
          path: str | os.PathLike | None = None) -> Any:
    """Which units of ``model`` are active (``lam_i > tol`` at the exact LCP solution) at each
    recorded ``(x_t, u_t)`` of every run: a raster, runs side by side, with the number of
    distinct active sets (hybrid modes) in the title.

    Args:
        model: an :class:`lcs_cvx.LCS` (anything with ``active_set(x, u)``).
        trajectories: :class:`lcs_cvx.Trajectories` (or a :class:`lcs_cvx.Dataset`: its
            samples in order, as one run).
        ax: a matplotlib ``Axes`` (default: a new figure).
        tol: the activity threshold (default: :data:`lcs_cvx.system.ACTIVE_TOL`).
        path: write the figure there.
    """
    if isinstance(trajectories, Dataset):
        pairs = [(trajectories.x, trajectories.u)]
    elif isinstance(trajectories, Trajectories):
        pairs = [(x[:-1], u) for x, u in zip(trajectories.xs, trajectories.us, strict=True)]
    else:
        raise LCSInputError(f"trajectories: expected lcs_cvx.Trajectories or an lcs_cvx.Dataset, received "
                            f"{type(trajectories).__name__}")
    kw = {} if tol is None else {"tol": tol}
    dtype = getattr(model, "dtype", torch.float64)
    device = getattr(model, "device", None)
    active = [_numpy(model.active_set(x.to(dtype=dtype, device=device), u.to(dtype=dtype, device=device), **kw))
              for x, u in pairs]
    raster = np.concatenate(active, axis=0).T.astype(float)  # (n_lam, sum T_i)
    distinct = len({row.tobytes() for row in np.concatenate(active, axis=0)})
    fig, (ax,) = _figure(ax, 1, (7.0, 2.0 + 0.25 * raster.shape[0]))
    ax.imshow(raster, aspect="auto", interpolation="nearest", cmap="Greys", vmin=0, vmax=1,
              extent=(0, raster.shape[1], raster.shape[0] - 0.5, -0.5))
    edge = 0
    for a in active[:-1]:
        edge += a.shape[0]
        ax.axvline(edge, color="C3", lw=0.8)
    ax.set_yticks(range(raster.shape[0]))
    ax.set_ylabel("unit i (black: active)")
    ax.set_xlabel(f"recorded step, runs side by side ({len(active)} runs)")
    ax.set_title(f"{distinct} distinct modes (active sets) of {2 ** raster.shape[0]} possible")
    return _save(fig, path)


# -- control ----------------------------------------------------------------------------------
def plan(plan: Any, axes: Any = None, dt: float | None = None, path: str | os.PathLike | None = None) -> Any:
    """A C3 plan: the planned states, inputs and forces (solid) against the model's own
    rollout under the planned inputs and its forces there (dashed: ``x_model``, ``lam_model``),
    three panels. For a batch of plans, the first.

    Args:
        plan: a :class:`lcs_cvx.control.Plan` (``C3.solve``'s).
        axes: three matplotlib ``Axes`` (default: a new figure).
        dt: seconds per step (default: steps).
        path: write the figure there.
    """
    if not all(hasattr(plan, k) for k in ("x", "u", "lam")):
        raise LCSInputError(f"plan: expected an lcs_cvx.control.Plan, received {type(plan).__name__}")
    x, u, lam = (_numpy(getattr(plan, k)) for k in ("x", "u", "lam"))
    x_model = None if plan.x_model is None else _numpy(plan.x_model)
    lam_model = None if plan.lam_model is None else _numpy(plan.lam_model)
    if x.ndim == 3:  # a batch: the first plan
        x, u, lam = x[0], u[0], lam[0]
        x_model = None if x_model is None else x_model[0]
        lam_model = None if lam_model is None else lam_model[0]
    fig, axs = _figure(axes, 3, (7.0, 6.0))
    t = np.arange(x.shape[0]) * (1.0 if dt is None else dt)
    for i in range(x.shape[1]):
        axs[0].plot(t, x[:, i], color=f"C{i % 10}", lw=1.4, label=f"x[{i}]")
        if x_model is not None:
            axs[0].plot(t, x_model[:, i], color=f"C{i % 10}", lw=1.0, ls="--")
    axs[0].set_ylabel("state\n(dashed: the model's rollout)")
    for i in range(u.shape[1]):
        axs[1].step(t[:-1], u[:, i], where="post", color=f"C{i % 10}", label=f"u[{i}]")
    axs[1].set_ylabel("input")
    for i in range(lam.shape[1]):
        axs[2].plot(t[:-1], lam[:, i], color=f"C{i % 10}", lw=1.4, label=f"lam[{i}]")
        if lam_model is not None:
            axs[2].plot(t[:-1], lam_model[:, i], color=f"C{i % 10}", lw=1.0, ls="--")
    axs[2].set_ylabel("force\n(dashed: the model's)")
    axs[2].set_xlabel("time [s]" if dt is not None else "step")
    for ax in axs:
        if ax.get_legend_handles_labels()[0] and len(ax.get_legend_handles_labels()[0]) <= 8:
            ax.legend(fontsize=7, loc="upper right")
    gap = getattr(plan, "gap", None)
    axs[0].set_title("C3 plan" + ("" if gap is None else f": largest gap to the model's rollout "
                                                       f"{float(np.max(_numpy(gap))):.3g}"))
    return _save(fig, path)
