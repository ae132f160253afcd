r"""Metrics of the cube study (:mod:`studies.cube.study`) on held-out tosses.

Every model is a *stepper*: a function ``x (N, 13) float64 tensor -> x' (N, 13)`` (no input: the
tosses have ``n_u = 0``). State columns: :data:`lcs_cvx.datasets.CUBE_COLUMNS`.

- :func:`one_step`: per state group (:data:`GROUPS`), the relative error of the predicted change
  ``Delta = x' - x`` with each coordinate scaled by the spread (standard deviation) of its change
  on the evaluated set,

      rel_g = sum_t sum_{j in g} ((Delta_hat_tj - Delta_tj) / s_j)^2 / sum_t sum_{j in g} (Delta_tj / s_j)^2,

  (0: perfect, 1: as bad as predicting no change), and the plain RMS error of ``x'`` in the
  group's units ``sqrt(mean_{t, j in g} (x_hat'_tj - x'_tj)^2)``.
- :func:`rollouts`: open-loop rollouts (the model fed its own predictions) from the first state
  of each toss to its end, and from every state ``s`` of each toss with ``s + H <= T`` over ``H``
  steps (windows). Per rollout of ``L`` steps: the position error
  ``sqrt(mean_{h=1..L} ||p_hat_h - p_h||^2)`` (m), the rotation error ``mean_{h=1..L}
  angle(q_h, q_hat_h)`` (rad, :func:`geodesic_angle`) and the growth
  ``max_h ||x_hat_h|| / max_t ||x_t||`` (the denominator over the whole recorded toss). A rollout
  *diverges* when it produces NaN/inf or its growth exceeds :data:`DIVERGED_GROWTH`; a state
  beyond :data:`CUTOFF_GROWTH` is replaced by NaN (so that no overflow or failed LCP solve
  stops the evaluation) and its rollout counted as diverged. Diverged rollouts are never dropped:
  the mean errors over all rollouts are then ``inf``, and the means over the rollouts that did
  not diverge are reported beside the count.
- :func:`dair_pll_errors`: dair_pll's whole-toss metrics (``pos_int_traj``, ``angle_int_traj``
  of ``dair_pll/experiment.py``): per toss the mean over the rollout's steps of the Euclidean
  position error and of the rotation angle, averaged over the tosses.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from lcs_cvx.kinematics import quaternion_product, up_in_body

__all__ = ["GROUPS", "DIVERGED_GROWTH", "CUTOFF_GROWTH", "geodesic_angle", "atan2_angle", "one_step", "rollout",
           "rollouts", "dair_pll_errors", "whole_toss_errors", "Stepper"]

#: A model: next states of a batch of states (float64 tensors ``(N, 13)``).
Stepper = Callable[[torch.Tensor], torch.Tensor]

#: The state groups: name -> column indices of :data:`lcs_cvx.datasets.CUBE_COLUMNS`.
GROUPS: dict[str, tuple[int, ...]] = {
    "quaternion": (0, 1, 2, 3),
    "position": (4, 5, 6),
    "angular velocity": (7, 8, 9),
    "linear velocity": (10, 11, 12),
}
#: Units of the plain RMS error of each group.
UNITS = {"quaternion": "1", "position": "m", "angular velocity": "rad/s", "linear velocity": "m/s"}
#: A rollout whose state norm exceeds this multiple of the toss's largest has diverged.
DIVERGED_GROWTH = 10.0
#: Beyond this multiple a predicted state is replaced by NaN (and the rollout has diverged).
CUTOFF_GROWTH = 1e3
Q, P = slice(0, 4), slice(4, 7)


def geodesic_angle(q: Any, q_hat: Any) -> np.ndarray:
    """The rotation angle (rad) between unit quaternions ``q`` and ``q_hat`` (``(..., 4)``,
    ``w, x, y, z``): ``2 acos |<q, q_hat / ||q_hat||>|``, in ``[0, pi]``; the same for ``q`` and
    ``-q`` (one rotation). ``q_hat`` is normalised here (a model's prediction need not be a unit
    quaternion); a non-finite or zero ``q_hat`` gives NaN."""
    q = np.asarray(q, dtype=np.float64)
    q_hat = np.asarray(q_hat, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        q_hat = q_hat / np.linalg.norm(q_hat, axis=-1, keepdims=True)
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
        dot = np.abs(np.sum(q * q_hat, axis=-1))
    return 2.0 * np.arccos(np.clip(dot, 0.0, 1.0)) + np.where(np.isfinite(dot), 0.0, np.nan)


def atan2_angle(q: Any, q_hat: Any) -> np.ndarray:
    """dair_pll's rotation angle (rad) between unit quaternions ``q`` and ``q_hat`` (``(..., 4)``,
    ``w, x, y, z``): ``2 atan2(||v||, w)`` of ``(w, v) = q^-1 q_hat`` (``q_hat`` normalised), with no
    choice between ``q_hat`` and ``-q_hat``: in ``[0, 2 pi)``, above pi where ``w < 0``
    (:func:`geodesic_angle` is the shorter of the two)."""
    q = np.asarray(q, dtype=np.float64)
    q_hat = np.asarray(q_hat, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        q_hat = q_hat / np.linalg.norm(q_hat, axis=-1, keepdims=True)
        inv = q * np.array([1.0, -1.0, -1.0, -1.0]) / np.sum(q * q, axis=-1, keepdims=True)
    rel = quaternion_product(torch.from_numpy(inv), torch.from_numpy(q_hat)).numpy()
    return 2.0 * np.arctan2(np.linalg.norm(rel[..., 1:], axis=-1), rel[..., 0])


def one_step(step: Stepper, xs: Sequence[torch.Tensor]) -> dict[str, float]:
    """One-step errors of ``step`` on every transition of the tosses ``xs`` (float64 ``(T+1, 13)``
    each): ``{"<group> rel": ..., "<group> rms": ...}`` for each of :data:`GROUPS` (see the module
    docstring) and ``"all rel"`` over the 13 coordinates. A non-finite prediction makes its
    groups' errors ``inf``."""
    x = torch.cat([t[:-1] for t in xs])
    x_next = torch.cat([t[1:] for t in xs])
    with torch.no_grad():
        pred = _safe_step(step, x)
    delta, delta_hat = (x_next - x).numpy(), (pred - x).numpy()
    s = delta.std(axis=0)
    s = np.where(s > 0, s, 1.0)
    err = (delta_hat - delta) / s
    ref = delta / s
    out: dict[str, float] = {}
    for g, cols in {**GROUPS, "all": tuple(range(13))}.items():
        c = list(cols)
        e = err[:, c]
        if not np.isfinite(e).all():
            out[f"{g} rel"] = math.inf
            out[f"{g} rms"] = math.inf
            continue
        out[f"{g} rel"] = float((e**2).sum() / (ref[:, c] ** 2).sum())
        if g != "all":
            out[f"{g} rms"] = float(np.sqrt(((pred.numpy()[:, c] - x_next.numpy()[:, c]) ** 2).mean()))
    return out


def _safe_step(step: Stepper, x: torch.Tensor) -> torch.Tensor:
    """``step`` on the finite rows of ``x`` only; the other rows stay NaN. A step that raises
    (e.g. an LCP solve that fails on a huge state) makes every row NaN."""
    out = torch.full_like(x, math.nan)
    ok = torch.isfinite(x).all(dim=1)
    if bool(ok.any()):
        try:
            out[ok] = step(x[ok]).to(torch.float64)
        except Exception:  # noqa: BLE001 - a failed step is a diverged rollout, counted
            pass
    return out


def rollout(step: Stepper, x0: torch.Tensor, steps: int, scale: torch.Tensor | None = None) -> torch.Tensor:
    """``(N, steps + 1, 13)``: the open-loop rollouts of ``step`` from the states ``x0``
    ``(N, 13)`` (row 0 is ``x0``). With ``scale`` ``(N,)`` (each rollout's largest true state
    norm), a state beyond :data:`CUTOFF_GROWTH` times it is replaced by NaN."""
    traj = [x0.to(torch.float64)]
    x = traj[0]
    with torch.no_grad():
        for _ in range(steps):
            x = _safe_step(step, x)
            if scale is not None:
                big = torch.linalg.vector_norm(x, dim=1) > CUTOFF_GROWTH * scale
                x[big] = math.nan
            traj.append(x)
    return torch.stack(traj, dim=1)


def _summary(pos: np.ndarray, rot: np.ndarray, growth: np.ndarray) -> dict[str, float]:
    """Means over the rollouts of their errors; see the module docstring."""
    diverged = ~np.isfinite(pos) | ~np.isfinite(rot) | ~np.isfinite(growth) | (growth > DIVERGED_GROWTH)
    ok = ~diverged
    nan = math.nan
    return {
        "rollouts": int(pos.size),
        "diverged": int(diverged.sum()),
        "pos": float(pos.mean()) if ok.all() else math.inf,
        "rot": float(rot.mean()) if ok.all() else math.inf,
        "pos_ok": float(pos[ok].mean()) if ok.any() else nan,
        "rot_ok": float(rot[ok].mean()) if ok.any() else nan,
        "pos_median": float(np.median(np.where(ok, pos, np.inf))),
        "rot_median": float(np.median(np.where(ok, rot, np.inf))),
        "growth_max": float(np.nanmax(np.where(np.isfinite(growth), growth, np.inf))) if growth.size else nan,
        "growth_median": float(np.median(np.where(np.isfinite(growth), growth, np.inf))),
    }


def _errors(pred: np.ndarray, true: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per rollout (rows of ``pred``/``true`` ``(N, L + 1, 13)``, row 0 the start): position
    RMS, mean rotation angle and growth over steps ``1..L``, NaN where non-finite."""
    p, t = pred[:, 1:], true[:, 1:]
    with np.errstate(invalid="ignore", over="ignore"):
        pos = np.sqrt(np.mean(np.sum((p[..., P] - t[..., P]) ** 2, axis=-1), axis=1))
        rot = np.mean(geodesic_angle(t[..., Q], p[..., Q]), axis=1)
        norms = np.linalg.norm(p, axis=-1)
        growth = np.max(np.where(np.isfinite(norms), norms, np.inf), axis=1) / scale
    finite = np.isfinite(p).all(axis=(1, 2))
    pos = np.where(finite, pos, np.nan)
    rot = np.where(finite, rot, np.nan)
    growth = np.where(finite, growth, np.inf)
    return pos, rot, growth


def rollouts(step: Stepper, xs: Sequence[torch.Tensor], horizons: Sequence[int] = (10, 30),
             stride: int = 1) -> dict[str, dict[str, float]]:
    """Open-loop rollout errors of ``step`` on the tosses ``xs``: ``{"H10": {...}, "H30": {...},
    "end": {...}}`` (:func:`_summary`'s keys; module docstring). ``"end"``: one rollout per toss
    from its first state to its last; ``"H<n>"``: every window of ``n`` steps starting at a
    multiple of ``stride`` within a toss."""
    out: dict[str, dict[str, float]] = {}
    maxnorm = [float(torch.linalg.vector_norm(t, dim=1).max()) for t in xs]
    # from the first state to the end: all tosses together, each cut at its own length
    T = max(t.shape[0] for t in xs)
    x0 = torch.stack([t[0] for t in xs])
    scale = torch.tensor(maxnorm, dtype=torch.float64)
    pred = rollout(step, x0, T - 1, scale).numpy()
    pos, rot, growth = [], [], []
    for i, t in enumerate(xs):
        n = t.shape[0]
        a, b, c = _errors(pred[i:i + 1, :n], t.numpy()[None], np.array([maxnorm[i]]))
        pos.append(a[0]), rot.append(b[0]), growth.append(c[0])
    out["end"] = _summary(np.array(pos), np.array(rot), np.array(growth))
    for H in horizons:
        starts = [(i, s) for i, t in enumerate(xs) for s in range(0, t.shape[0] - 1 - H + 1, stride)]
        if not starts:
            continue
        x0 = torch.stack([xs[i][s] for i, s in starts])
        sc = np.array([maxnorm[i] for i, _ in starts])
        pred = rollout(step, x0, H, torch.from_numpy(sc)).numpy()
        true = np.stack([xs[i][s:s + H + 1].numpy() for i, s in starts])
        out[f"H{H}"] = _summary(*_errors(pred, true, sc))
    return out


def dair_pll_errors(step: Stepper, xs: Sequence[torch.Tensor]) -> dict[str, float]:
    """Whole-toss open-loop rollouts of ``step`` from each toss's first state, scored by
    :func:`whole_toss_errors`."""
    T = max(t.shape[0] for t in xs)
    maxnorm = torch.tensor([float(torch.linalg.vector_norm(t, dim=1).max()) for t in xs], dtype=torch.float64)
    pred = rollout(step, torch.stack([t[0] for t in xs]), T - 1, maxnorm).numpy()
    return whole_toss_errors([pred[i, :t.shape[0]] for i, t in enumerate(xs)], xs)


def whole_toss_errors(preds: Sequence[Any], xs: Sequence[torch.Tensor]) -> dict[str, float]:
    """dair_pll's whole-toss errors of the predicted tosses ``preds`` (each ``(T_i, 13)``, row 0
    the first recorded state) against the recorded ``xs``: its position error (m; the mean over
    steps of ``||p_hat - p||``, averaged over tosses), its rotation error (rad; the mean angle),
    ours beside them (``pos_rms``: the RMS position error, averaged), the count of rollouts
    that diverged (their errors are then inf), and ``end_tilt``: the mean over tosses of the last
    predicted state's tilt from resting on a face, ``acos max_k |g_k|`` with ``g = R(q)^T e_z``
    (rad; the recorded tosses end at rest on a face, within about 1°). ``rot`` is the shorter
    angle (:func:`geodesic_angle`), ``rot_atan2`` dair_pll's own (:func:`atan2_angle`)."""
    dist, rms, rot, rot2, tilt = [], [], [], [], []
    for p, t in zip(preds, xs, strict=True):
        p, true = np.asarray(p, dtype=np.float64), t.numpy()
        with np.errstate(invalid="ignore", over="ignore"):
            d = np.linalg.norm(p[1:, P] - true[1:, P], axis=-1)
            a = geodesic_angle(true[1:, Q], p[1:, Q])
            a2 = atan2_angle(true[1:, Q], p[1:, Q])
        ok = np.isfinite(p[1:]).all()
        dist.append(d.mean() if ok else math.inf)
        rms.append(np.sqrt((d ** 2).mean()) if ok else math.inf)
        rot.append(a.mean() if ok else math.inf)
        rot2.append(a2.mean() if ok else math.inf)
        g = up_in_body(torch.as_tensor(p[-1:, Q] / np.linalg.norm(p[-1, Q]))) if ok else None
        tilt.append(math.acos(min(1.0, float(g.abs().max()))) if ok else math.inf)
    return {"pos": float(np.mean(dist)), "rot": float(np.mean(rot)), "rot_atan2": float(np.mean(rot2)),
            "pos_rms": float(np.mean(rms)),
            "diverged": int(np.sum(~np.isfinite(dist))), "end_tilt": float(np.mean(tilt))}
