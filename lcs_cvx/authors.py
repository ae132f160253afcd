"""The paper's authors' learners beside the package's, side by side in one process: loss and
gradient throughput (``lcs-cvx bench --authors PATH``; the study
``studies/solvers/authors_speed.py`` writes every Fig. 1 size, resumably).

The authors' learners (DAIRLab/Learning-LCS, ``lcs/lcs_learning.py``: ``LCS_VN`` for the
violation loss, ``LCS_PN`` for the prediction loss; CasADi with qpOASES, one QP per sample) are
imported from a checkout the user names (:func:`load_authors`: the folder that holds their
``lcs`` package; nothing of theirs is in this package) and called as their training loops call
them: ``learner.step(x, u, x_next, theta)`` returns the mean loss and its gradient in ``theta``.
Beside it, the package's two ways to the same numbers: ``*_value_and_grad`` (the loss and its
gradient in one call) and ``*_loss`` followed by ``.backward()`` (through torch's autograd, as a
user's own training loop runs them). Their objectives differ from the package's by constant
factors (their (V) objective at ``(gamma, eps)`` is twice the package's at ``(gamma / 2, 2
eps)``, their prediction loss twice the package's): each row checks that ``lam``, the loss and
the gradient agree. The model is a random ground truth with every parameter perturbed by ``0.05
N(0, 1)`` and ``G`` made upper triangular (the authors' ``G`` is); ``theta`` its parameters in
their layout (``vec`` column-major). One torch thread; per repeat one authors' call, then each of
the package's calls for as long; medians.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch

from ._checks import LCSInputError
from .data import Dataset, make_dataset, random_lcs
from .losses import prediction_loss, prediction_loss_info, violation_loss, violation_loss_info
from .system import LCS
from .train import fit
from .value_and_grad import prediction_value_and_grad, violation_value_and_grad

__all__ = ["FIG1_SIZES", "N_X_10_SIZES", "load_authors", "run_authors", "run_row", "table"]

#: The sizes of Fig. 1 with ``n_x = 10``: panel (a).
N_X_10_SIZES = [(10, 4, n) for n in (1, 4, 8, 12, 16, 20)]
FIG1_SIZES = (
    N_X_10_SIZES
    + [(n, 4, 10) for n in (2, 8, 16, 32, 64, 128)]
    + [(8, 4, 10), (4, 4, 4)]
)
PAPER_SIZES = [(10, 4, 4), (10, 4, 10), (10, 4, 20), (128, 4, 10)]
LOSSES = ("violation", "prediction")
GAMMA, EPS = 1e-2, 1e-4  # the authors' (gamma, eps) of Fig. 1(a), (b)
#: The training-step timing: the data of one run, the authors' steps per repeat, fit's iterations
STEP_DATA, STEP_CALLS, STEP_ITERATIONS = 20_000, 5, 2000


def model_for(n_x: int, n_u: int, n_lam: int, seed: int = 0) -> tuple[LCS, Dataset]:
    """A mid-training model (truth + 0.05 N(0, 1), ``G`` upper triangular) and a batch of 50,000."""
    truth = random_lcs(n_x, n_u, n_lam, stiffness=0.5, seed=seed)
    data = make_dataset(truth, 50_000, noise=1e-2, seed=seed + 1)
    model = truth  # a fresh object: perturbed in place
    gen = torch.Generator().manual_seed(seed + 2)
    with torch.no_grad():
        for _, p in model.named_parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=gen, dtype=p.dtype))
        model.G.copy_(torch.triu(model.G))
    model.requires_grad_(True)
    return model, data


def authors_theta(model: LCS) -> np.ndarray:
    """The model's parameters in the authors' ``theta`` layout: ``vec`` (column-major) of ``A, B,
    C, d, D, E``, then ``G``'s upper triangle column by column, ``vec(H)``, ``c``."""
    def vec(t):
        return t.detach().numpy().reshape(-1, order="F") if t.dim() == 2 else t.detach().numpy()

    G = model.G.detach().numpy()
    g_para = np.concatenate([G[: j + 1, j] for j in range(G.shape[0])])
    return np.concatenate([vec(model.A), vec(model.B), vec(model.C), vec(model.d), vec(model.D),
                           vec(model.E), g_para, vec(model.H), vec(model.c)])


def package_gradient(model: LCS) -> np.ndarray:
    """The package's gradient in the authors' layout (as :func:`authors_theta`); ``d/dG_para`` is
    ``dG`` on the upper triangle (``G``'s strict lower part is held at 0)."""
    grads = {k: p.grad for k, p in model.named_parameters()}
    return authors_theta(SimpleNamespace(**{**grads, "G": torch.triu(grads["G"])}))


def learners(lcs_learning, n_x: int, n_u: int, n_lam: int, stiffness: float):
    """The authors' two learners, set up as their Fig. 1 scripts do (no regulariser here)."""
    vn = lcs_learning.LCS_VN(n_state=n_x, n_control=n_u, n_lam=n_lam, F_stiffness=stiffness)
    vn.diff(gamma=GAMMA, epsilon=EPS, w_C=0.0, C_ref=0, w_F=0.0, F_ref=0)
    pn = lcs_learning.LCS_PN(n_state=n_x, n_control=n_u, n_lam=n_lam, F_stiffness=stiffness)
    pn.diff(w_C=0.0, C_ref=0, w_F=0.0, F_ref=0)
    return {"violation": vn, "prediction": pn}


def training_steps(lcs_learning, optim, model: LCS, data, loss: str, batch: int,
                   repeats: int) -> dict:
    """Seconds per training step, medians of ``repeats`` interleaved repeats: one step of the
    authors' training loop as their Fig. 1 scripts run it (a minibatch of ``batch`` drawn by a
    permutation, ``learner.step``, their ``Adam.step`` on ``theta``), timed over
    :data:`STEP_CALLS` steps, against one step of :func:`lcs_cvx.fit` with ``recipe="paper"`` on
    :data:`STEP_DATA` samples (a fit's wall time over its :data:`STEP_ITERATIONS` iterations:
    its checks, minibatches, warm starts, loss and gradient, Adam and records)."""
    train = Dataset(data.x[:STEP_DATA], data.u[:STEP_DATA], data.x_next[:STEP_DATA])
    xa, ua, xna = (t.numpy() for t in (train.x, train.u, train.x_next))
    learner = learners(lcs_learning, model.n_x, model.n_u, model.n_lam, float(model.stiffness))[loss]
    adam = optim.Adam()
    theta = [authors_theta(model)]
    rng = np.random.default_rng(0)

    def theirs():  # the body of their training loop
        rows = rng.permutation(len(xa))[:batch]
        out = learner.step(xa[rows], ua[rows], xna[rows], theta[0])
        theta[0] = adam.step(theta[0], out[1])

    kw = {"gamma": GAMMA / 2, "eps": 2 * EPS} if loss == "violation" else {}

    def ours() -> float:
        start = LCS(model.n_x, model.n_u, model.n_lam, stiffness=float(model.stiffness))
        start.load_state_dict(model.state_dict())
        t0 = time.perf_counter()
        fit(start, train, recipe="paper", loss=loss, iterations=STEP_ITERATIONS, batch_size=batch,
            progress=False, **kw)
        return (time.perf_counter() - t0) / STEP_ITERATIONS

    theirs(), ours()
    t_theirs, t_ours = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(STEP_CALLS):
            theirs()
        t_theirs.append((time.perf_counter() - t0) / STEP_CALLS)
        t_ours.append(ours())
    authors, package = statistics.median(t_theirs), statistics.median(t_ours)
    return {"authors_step_s": authors, "fit_step_s": package, "step_ratio": authors / package}


def run_row(lcs_learning, size, loss: str, batch: int, repeats: int, seed: int = 0,
            optim=None) -> dict:
    """One row of :func:`table`: at ``size`` ``(n_x, n_u, n_lam)`` and ``loss``, the samples per
    second of the authors' ``step`` (module ``lcs_learning``), of ``*_value_and_grad`` and of the
    loss + ``backward()`` on ``batch`` samples (medians of ``repeats`` interleaved repeats), the
    agreement of ``lam``, loss and gradient, and with the authors' ``optim`` the training steps'
    times (:func:`training_steps`)."""
    n_x, n_u, n_lam = size
    model, data = model_for(n_x, n_u, n_lam, seed)
    x, u, xn = data.x[:batch], data.u[:batch], data.x_next[:batch]
    learner = learners(lcs_learning, n_x, n_u, n_lam, float(model.stiffness))[loss]
    theta = authors_theta(model)
    xa, ua, xna = x.numpy(), u.numpy(), xn.numpy()

    def theirs():
        return learner.step(xa, ua, xna, theta)

    def ours():  # what a user's training step runs: the loss, then autograd
        model.zero_grad(set_to_none=True)
        if loss == "violation":
            value = violation_loss(model, x, u, xn, gamma=GAMMA / 2, eps=2 * EPS)
        else:
            value = prediction_loss(model, x, u, xn)
        value.backward()
        return value

    def ours_vg():  # the loss and its gradient in one call (the authors' step returns both)
        if loss == "violation":
            return violation_value_and_grad(model, x, u, xn, gamma=GAMMA / 2, eps=2 * EPS)
        return prediction_value_and_grad(model, x, u, xn)

    # the same computation: lam, loss and gradient
    out = theirs()
    their_loss, their_grad, their_lam = out[0], out[1], out[-1]
    value = ours()
    info = (violation_loss_info(model, x, u, xn, gamma=GAMMA / 2, eps=2 * EPS)
            if loss == "violation" else prediction_loss_info(model, x, u, xn))
    our_grad = 2.0 * package_gradient(model)
    vg_value, vg_grads = ours_vg()
    agreement = {
        "lam_err": float(np.abs(info.lam.numpy() - their_lam).max()),
        "loss_rel_err": abs(2.0 * float(value) - their_loss) / (1.0 + abs(their_loss)),
        "grad_rel_err": float(np.abs(our_grad - their_grad).max() / (1.0 + np.abs(their_grad).max())),
        "value_and_grad_equal": float(vg_value) == float(value) and all(
            bool(torch.equal(vg_grads[k], p.grad)) for k, p in model.named_parameters()),
    }

    # interleaved timing: per repeat one authors' call, then each package call for as long
    for _ in range(3):
        theirs(), ours(), ours_vg()
    t_theirs, t_ours, t_vg = [], [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        theirs()
        dt = time.perf_counter() - t0
        t_theirs.append(dt)
        for fn, times in ((ours, t_ours), (ours_vg, t_vg)):
            n, t0 = 0, time.perf_counter()
            while True:
                fn()
                n += 1
                el = time.perf_counter() - t0
                if el >= max(dt, 0.02):
                    break
            times.append(el / n)
    authors = batch / statistics.median(t_theirs)
    package, package_vg = batch / statistics.median(t_ours), batch / statistics.median(t_vg)
    steps = training_steps(lcs_learning, optim, model, data, loss, batch, repeats) if optim else {}
    return {"n_x": n_x, "n_u": n_u, "n_lam": n_lam, "loss": loss, "batch": batch,
            "authors_samples_per_s": authors, "package_samples_per_s": package,
            "ratio": package / authors, "value_and_grad_samples_per_s": package_vg,
            "value_and_grad_ratio": package_vg / authors, **agreement, **steps}


def _step_cells(r: dict) -> str:
    if "step_ratio" not in r:
        return "– | – | –"
    return f"{1e3 * r['authors_step_s']:.2f} | {1e3 * r['fit_step_s']:.3f} | {r['step_ratio']:,.0f}×"


def table(rows: list[dict]) -> str:
    lines = ["| (n_x, n_u, n_λ) | loss | authors (`step`) | lcs_cvx `*_value_and_grad` | ratio | "
             "lcs_cvx loss + `backward()` | ratio | max Δλ | rel. Δloss | rel. Δgradient | "
             "training step: authors (ms) | `fit` (ms) | ratio |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| ({r['n_x']}, {r['n_u']}, {r['n_lam']}) | {r['loss']} | "
                     f"{r['authors_samples_per_s']:,.0f} | {r['value_and_grad_samples_per_s']:,.0f} | "
                     f"{r['value_and_grad_ratio']:,.0f}× | {r['package_samples_per_s']:,.0f} | "
                     f"{r['ratio']:,.0f}× | {r['lam_err']:.1e} | {r['loss_rel_err']:.1e} | "
                     f"{r['grad_rel_err']:.1e} | {_step_cells(r)} |")
    return "\n".join(lines)


def load_authors(path: str | Path) -> tuple[Any, Any]:
    """The authors' modules ``(lcs_learning, optim)`` from the checkout ``path`` (the folder that
    holds their ``lcs`` package); an :class:`LCSInputError` names anything else."""
    path = Path(path)
    if not (path / "lcs" / "lcs_learning.py").is_file():
        raise LCSInputError(f"authors: expected a folder with lcs/lcs_learning.py (a DAIRLab/Learning-LCS "
                            f"checkout), received {str(path)!r}")
    sys.path.insert(0, str(path))
    from lcs import (
        lcs_learning,  # the authors' code, from the user's checkout
        optim,
    )

    return lcs_learning, optim


def run_authors(path: str | Path, sizes: list[tuple[int, int, int]] = N_X_10_SIZES,
                losses: tuple[str, ...] = LOSSES, batch: int = 200, repeats: int = 7, steps: bool = False,
                progress: Any = None) -> str:
    """:func:`run_row` for every size and loss against the checkout ``path``, on one torch
    thread; returns the markdown :func:`table`."""
    lcs_learning, optim = load_authors(path)
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    rows = []
    try:
        for loss in losses:
            for size in sizes:
                rows.append(run_row(lcs_learning, size, loss, batch, repeats, optim=optim if steps else None))
                if progress is not None:
                    progress(table(rows[-1:]).splitlines()[-1])
    finally:
        torch.set_num_threads(before)
    return table(rows)
