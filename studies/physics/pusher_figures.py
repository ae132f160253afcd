r"""Figures of the pusher-slider study: the learning curve (error against the training size) and
one open-loop rollout through the contact modes. The error-against-horizon figure is
:func:`studies.physics.evaluation.plot_error_vs_horizon`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .evaluation import draw_rollout_panels, pyplot, rollout
from .pusher_plant import MODES

__all__ = ["plot_learning_curve", "plot_rollout"]

_MODE_COLOURS = ("none", "tab:green", "tab:orange", "tab:purple")


def plot_learning_curve(per_size: dict[str, Any], H: int, path: str) -> None:
    """One row per test set, columns: one-step error in contact and ``H``-step rollout error,
    against the training size (log-log), one line per model."""
    plt = pyplot()
    sizes = sorted(per_size, key=int)
    set_names = list(per_size[sizes[0]]["sets"])
    fig, axes = plt.subplots(len(set_names), 2, figsize=(12, 4.2 * len(set_names)), squeeze=False)
    for i, set_name in enumerate(set_names):
        names = list(dict.fromkeys(r["name"] for n in sizes for r in per_size[n]["sets"][set_name]))
        for j, (label, value) in enumerate((("one-step error in contact", lambda r: r["one_step"]["contact"]),
                                            (f"{H}-step rollout error", lambda r: r["rollout"][str(H)]))):
            ax = axes[i, j]
            for name in names:
                ys = []
                for n in sizes:
                    row = next((r for r in per_size[n]["sets"][set_name] if r["name"] == name), None)
                    failed = row is None or row["error"] is not None  # a failed fit: no point
                    ys.append(np.nan if failed or not np.isfinite(value(row)) else value(row))
                ax.plot([int(n) for n in sizes], ys, "o-" if name.startswith("LCS") else "s:", lw=1.6, ms=4, label=name)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("training samples")
            ax.set_title(f"{set_name}: {label}")
            ax.grid(True, which="both", alpha=0.3)
    axes[0, 1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_rollout(models: dict[str, Any], data: Any, start: int, horizon: int, physics: Any, path: str) -> None:
    """True vs each model's open-loop rollout of one test window: the pusher's position on the
    face and its gap, the slider's velocity; the true contact mode of each period shaded."""
    plt = pyplot()
    t = np.arange(horizon + 1) * physics.control_period
    true = np.concatenate([data.x[start : start + 1], data.x_next[start : start + horizon]])
    panels = (("pusher on the face p_y (cm)", lambda xs: xs[:, 1]),
              ("gap p_x − p_x,touch (cm)", lambda xs: xs[:, 0] - physics.touching_x),
              ("slider velocity v_x (cm/s)", lambda xs: xs[:, 2]),
              ("slider velocity v_y (cm/s)", lambda xs: xs[:, 3]))
    preds = {name: rollout(model, data, np.array([start]), horizon)[0] for name, model in models.items()}
    shade = [(k, _MODE_COLOURS[mode]) for k, mode in enumerate(data.contact[start : start + horizon]) if mode]
    fig, axes = plt.subplots(1, len(panels), figsize=(18, 4.2))
    draw_rollout_panels(axes, panels, t, true, preds, shade)
    axes[-1].legend(fontsize=7, loc="best")
    shading = ", ".join(f"{c.removeprefix('tab:')}: {m}" for c, m in zip(_MODE_COLOURS[1:], MODES[1:], strict=True))
    fig.suptitle(f"Open-loop rollout of {horizon} steps (test window {start}; shaded, the true mode: {shading})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
