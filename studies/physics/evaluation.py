r"""Metrics, figures and the results table of the physics study.

Every model is evaluated in physical units on :class:`~studies.physics.plant.Transitions`
through ``predict(x, u, contact)`` (``contact`` is used by the mode oracle only).

- One-step relative error, the paper's ``e_test`` (Sec. 5) on a subset ``S`` of the samples:
  ``sum_{t in S} ||x'_model(x_t, u_t) - x'_t||^2 / sum_{t in S} ||x'_t||^2``, for the free
  samples (no wall pushed during the control period), the in-contact ones and all of them.
- Open-loop rollout error at horizon ``h``: from the true state at the start of every window of
  ``H`` consecutive samples of one trajectory, the model is stepped ``h`` times under the recorded
  inputs, ``sum ||x_hat_{t+h} - x_{t+h}||^2 / sum ||x_{t+h}||^2`` over the windows (the same
  windows for every ``h <= H``; the oracle is given the true contact mode of every step).
- Contact agreement: the learned ``lam_i > tol`` against the true contact state of each wall,
  after the best assignment of ``lam``'s coordinates to the walls -- each coordinate to the left
  wall, the right wall or neither, a wall predicted in contact when any of its coordinates is
  active (for ``n_lam = 2`` this includes the two permutations). Reported as the mean over the two
  walls of the fraction of samples that agree, next to the trivial "never in contact" level.
  An LCS can also encode a wall by a coordinate that is active *off* contact (the complementary
  description of the same piecewise-affine map), which that measure does not credit; the
  "either sign" variant identifies each wall with one coordinate, distinct for the two walls,
  taken as ``lam_i > tol`` or as ``lam_i <= tol``, whichever agrees more.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = [
    "relative_error",
    "one_step_errors",
    "mode_errors",
    "rollout",
    "rollout_errors",
    "contact_agreement",
    "pyplot",
    "draw_rollout_panels",
    "plot_rollouts",
    "plot_error_vs_horizon",
    "markdown_table",
    "fmt",
]


def relative_error(pred: np.ndarray, target: np.ndarray) -> float:
    """``sum ||pred - target||^2 / sum ||target||^2`` (NaN for an empty set)."""
    if target.shape[0] == 0:
        return float("nan")
    num = float(((pred - target) ** 2).sum())
    return num / float((target**2).sum()) if np.isfinite(num) else float("inf")


def one_step_errors(model: Any, data: Any) -> dict[str, float]:
    """One-step relative errors ``{"free", "contact", "all"}`` on ``data`` (Transitions)."""
    pred = model.predict(data.x, data.u, data.contact)
    c = data.in_contact
    return {
        "free": relative_error(pred[~c], data.x_next[~c]),
        "contact": relative_error(pred[c], data.x_next[c]),
        "all": relative_error(pred, data.x_next),
    }


def mode_errors(model: Any, data: Any, modes: Sequence[str]) -> dict[str, float]:
    """One-step relative errors per true contact mode: ``{modes[k]: error on the samples whose
    label (``data.contact``, ``(N,)`` int) is k}``, and ``"contact"`` (every label but 0) and
    ``"all"``; NaN for a mode without samples."""
    pred = model.predict(data.x, data.u, data.contact)
    out = {name: relative_error(pred[data.contact == k], data.x_next[data.contact == k])
           for k, name in enumerate(modes)}
    c = data.in_contact
    out["contact"] = relative_error(pred[c], data.x_next[c])
    out["all"] = relative_error(pred, data.x_next)
    return out


def rollout(model: Any, data: Any, starts: np.ndarray, horizon: int) -> np.ndarray:
    """Open-loop predictions ``(len(starts), horizon + 1, n_x)`` from the true states at
    ``starts`` under the recorded inputs (a diverging model gives inf/NaN, not an error)."""
    x = data.x[starts].copy()
    out = [x]
    with np.errstate(all="ignore"):
        for h in range(horizon):
            idx = starts + h
            x = model.predict(x, data.u[idx], data.contact[idx])
            x = np.where(np.isfinite(x), x, np.nan)
            out.append(x)
    return np.stack(out, axis=1)


def rollout_errors(model: Any, data: Any, horizon: int) -> np.ndarray:
    """``(horizon,)`` open-loop rollout errors at ``h = 1 .. horizon`` (one set of windows)."""
    starts = data.windows(horizon)
    pred = rollout(model, data, starts, horizon)
    errs = []
    for h in range(1, horizon + 1):
        target = data.x_next[starts + h - 1]
        p = pred[:, h]
        errs.append(relative_error(p, target) if np.isfinite(p).all() else float("inf"))
    return np.asarray(errs)


def contact_agreement(active: np.ndarray, contact: np.ndarray) -> dict[str, Any]:
    """Agreement between learned ``active`` ``(N, n_lam)`` and true ``contact`` ``(N, 2)``.

    Returns ``agreement`` (mean over the walls, best assignment), ``per_wall``, ``assignment``
    (for each coordinate ``"left"``, ``"right"`` or ``None``), ``any_contact`` (any coordinate
    active vs any wall pushing) and ``trivial`` (the agreement of "never in contact").
    """
    active = np.asarray(active, dtype=bool)
    contact = np.asarray(contact, dtype=bool)
    n, n_lam = active.shape
    codes = (active.astype(np.int64) << np.arange(n_lam)).sum(axis=1)
    subsets = np.arange(2**n_lam)
    # agree[w, S]: samples where "some coordinate of S active" equals wall w's contact
    predicted = (codes[None, :] & subsets[:, None]) != 0  # (2^n_lam, N)
    agree = np.stack([(predicted == contact[None, :, w]).mean(axis=1) for w in range(2)])
    best, arg = -1.0, (0, 0)
    for s_left, s_right in itertools.product(subsets, subsets):
        if s_left & s_right:
            continue
        score = 0.5 * (agree[0, s_left] + agree[1, s_right])
        if score > best:
            best, arg = score, (int(s_left), int(s_right))
    assignment = [("left" if arg[0] >> i & 1 else "right" if arg[1] >> i & 1 else None)
                  for i in range(n_lam)]
    # either sign: one coordinate per wall (distinct), active or inactive as the indicator
    unit = np.stack([[np.maximum((active[:, i] == contact[:, w]).mean(), (active[:, i] != contact[:, w]).mean())
                      for i in range(n_lam)] for w in range(2)])  # (2, n_lam)
    pairs = [(i, j) for i in range(n_lam) for j in range(n_lam) if i != j or n_lam == 1]
    i_best, j_best = max(pairs, key=lambda p: unit[0, p[0]] + unit[1, p[1]])
    return {
        "agreement": float(best),
        "either_sign": float(0.5 * (unit[0, i_best] + unit[1, j_best])),
        "either_sign_units": [int(i_best), int(j_best)],
        "per_wall": [float(agree[0, arg[0]]), float(agree[1, arg[1]])],
        "assignment": assignment,
        "any_contact": float((active.any(axis=1) == contact.any(axis=1)).mean()) if n else float("nan"),
        "trivial": float(1.0 - contact.mean()),
    }


# -- figures ---------------------------------------------------------------------------------
def pyplot():
    """``matplotlib.pyplot`` on the non-interactive Agg backend (figures go to files)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def pick_contact_window(data: Any, horizon: int) -> int | None:
    """The first window whose true trajectory is free for its first 3 steps, then has a wall
    contact that ends within the window; else the first window with any contact; else None."""
    fallback = None
    for s in data.windows(horizon):
        c = data.in_contact[s : s + horizon]
        if not c.any():
            continue
        if fallback is None:
            fallback = int(s)
        first = int(np.argmax(c))
        if first >= 3 and not c[first:].all():
            return int(s)
    return fallback


def draw_rollout_panels(axes: Any, panels: Sequence[tuple[str, Any]], t: np.ndarray, true: np.ndarray,
                        preds: dict[str, np.ndarray], shade: Sequence[tuple[int, str]]) -> None:
    """On each axis, the panel ``(label, f)``: ``f`` of the true states ``(H + 1, n_x)`` and of
    each model's rollout (LCSs dashed, the others dotted) against the times ``t``, and the
    periods ``k`` of ``shade = [(k, colour)]`` shaded."""
    for ax, (label, f) in zip(axes, panels, strict=True):
        ax.plot(t, f(true), "k-", lw=3, label="MuJoCo (true)")
        for name, pred in preds.items():
            ax.plot(t, f(pred), "--" if "LCS" in name else ":", lw=1.6, label=name)
        for k, colour in shade:
            ax.axvspan(t[k], t[k + 1], color=colour, alpha=0.15, lw=0)
        ax.set_xlabel("time (s)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)


def plot_rollouts(models: dict[str, Any], data: Any, start: int, horizon: int, physics: Any,
                  path: str, title: str) -> None:
    """True vs each model's open-loop rollout of one window: tip position (with the walls) and
    pole angular velocity."""
    plt = pyplot()
    t = np.arange(horizon + 1) * physics.control_period
    idx = np.array([start])
    true = np.concatenate([data.x[start : start + 1], data.x_next[start : start + horizon]])
    L = physics.pole_length
    tip = lambda xs: xs[:, 0] + L * np.sin(xs[:, 1])  # noqa: E731
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    preds = {name: rollout(model, data, idx, horizon)[0] for name, model in models.items()}
    shade = [(int(k), "orange") for k in np.nonzero(data.in_contact[start : start + horizon])[0]]
    draw_rollout_panels(axes, [("pole tip x (m)", tip), ("pole angle θ (rad)", lambda xs: xs[:, 1]),
                               ("θ' (rad/s)", lambda xs: xs[:, 3])], t, true, preds, shade)
    inner = physics.wall_distance - physics.tip_radius
    for s in (-1, 1):
        axes[0].axhline(s * inner, color="gray", lw=1)
    lo, hi = axes[0].get_ylim()
    axes[0].set_ylim(max(lo, -2 * inner), min(hi, 2 * inner))
    axes[1].set_ylim(*np.clip(axes[1].get_ylim(), -1.5, 1.5))
    axes[2].legend(fontsize=7, loc="best")
    fig.suptitle(title + " (shaded: a wall pushes during the period; grey lines: contact surfaces)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_error_vs_horizon(curves: dict[str, dict[str, np.ndarray]], path: str, period: float = 0.04) -> None:
    """``curves[test_set][model] = (H,)`` rollout errors; one panel per test set; ``period``:
    the control period (s), for the axis label."""
    plt = pyplot()
    fig, axes = plt.subplots(1, len(curves), figsize=(6.5 * len(curves), 4.5), sharey=True)
    axes = np.atleast_1d(axes)
    for ax, (set_name, per_model) in zip(axes, curves.items(), strict=True):
        for name, errs in per_model.items():
            h = np.arange(1, len(errs) + 1)
            ax.plot(h, np.where(np.isfinite(errs), errs, np.nan), "o-" if "LCS" in name else "s:",
                    ms=3, lw=1.4, label=name)
        ax.set_yscale("log")
        ax.set_xticks([1, *range(5, len(errs) + 1, 5)])
        ax.set_xlabel(f"horizon H (control periods of {period:g} s)")
        ax.set_title(set_name)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("open-loop relative error at H")
    axes[-1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# -- table -------------------------------------------------------------------------------------
def fmt(v: Any) -> str:
    """A number for a markdown table: ``1.23e-04`` below 0.01 and from 1,000 on, else four
    decimals; "–" for None, "diverged" for inf/NaN."""
    if v is None:
        return "–"
    if isinstance(v, str):
        return v
    if not np.isfinite(v):
        return "diverged"
    return f"{v:.2e}" if abs(v) < 1e-2 or abs(v) >= 1e3 else f"{v:.4f}"


def markdown_table(rows: Sequence[dict[str, Any]], horizons: Sequence[int]) -> str:
    """Rows: ``name``, ``one_step`` ({free, contact, all}), ``rollout`` ({h: err}),
    ``agreement`` (dict or None), ``train_s``."""
    head = (["model", "1-step free", "1-step contact", "1-step all"]
            + [f"rollout H={h}" for h in horizons]
            + ["λ/contact agreement", "agreement, either sign", "train (s)"])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        ag = r.get("agreement")
        ag_s = ["–", "–"] if ag is None else [f"{ag['agreement']:.3f}", f"{ag['either_sign']:.3f}"]
        cells = [r["name"], fmt(r["one_step"]["free"]), fmt(r["one_step"]["contact"]),
                 fmt(r["one_step"]["all"])] + [fmt(r["rollout"][str(h)]) for h in horizons]
        cells += [*ag_s, "–" if r.get("train_s") is None else f"{r['train_s']:.0f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
