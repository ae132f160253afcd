"""Differentiable solver paths: loss + gradient of both losses through every installed path.

For the violation loss (``lcs_cvx.violation_loss``, eq. (9): the batch mean of the optimal value
of (V)) and the prediction loss (``lcs_cvx.prediction_loss``, eq. (6): the LCP solved, then
``1/2 ||x'_theta - x'||^2``), one timed call is the loss on a batch followed by ``.backward()``
to the model's parameters ``A, B, C, d, D, E, G, H, c`` (``F = G G^T + H - H^T + s I``), as in
a training step. The paths:

- ``fast``: the package's kernels (``solver="fast"``, the default; compiled for float64 CPU
  tensors, as a training step runs them, without the diagnostics of ``*_loss_info``): exact pivoting,
  the envelope gradient of Lemma 3 for (V), the implicit function theorem on the active set
  (Lemma 1) for (P);
- ``cvxpylayers`` / ``cvxpylayers-scs``: the package's ``solver=`` paths, diffcp with Clarabel
  / SCS over the declared CVXPY problems (:func:`lcs_cvx.violation_problem`,
  :func:`lcs_cvx.convex_lcp_problem`);
- ``cvxpylayers-ecos``: the same layers with diffcp's third cone solver, ECOS (diffcp accepts
  ``solve_method`` ``"SCS"``, ``"ECOS"`` and ``"Clarabel"``; cvxpylayers' other backends --
  Moreau, CuClarabel, MPAX -- need packages or GPUs that are not installed), built here from
  the package's layers (``lcs_cvx.layers.violation_layer``/``lcp_layer``) as
  ``lcs_cvx.losses`` builds the other two;
- ``qpth``: ``qpth.qp.QPFunction`` (batched primal-dual interior point, implicit
  differentiation of its KKT system); every input is passed with the batch dimension, because
  qpth averages the gradient of an input without one over the batch instead of summing it
  (``Q``, ``G``, ``h`` shared by the batch would get gradients ``B`` times too small);
- ``qplayer``: ProxSuite's ``proxsuite.torch.qplayer.QPFunction`` (ProxQP per sample, its own
  backward);
- ``qpoases``: qpOASES through CasADi's conic interface (``casadi.conic(..., "qpoases")``
  mapped over the batch) for the forward solve, with the closed-form gradients written here:
  for (V) the envelope theorem (Lemma 3: the objective of (V) evaluated at the detached
  optimum, :meth:`lcs_cvx.problems.ViolationProblem.objective`, differentiated), for (P) the
  implicit function theorem on the active set that qpOASES found (Lemma 1:
  ``lam_I = -F_II^{-1} q_I`` through :func:`lcs_cvx.lcp.active_set_solve`, differentiated).

The QPs handed to ``qpth``, ``qplayer`` and ``qpoases``, in ``min 1/2 z^T Q z + p^T z``:

- (P), ``z = lam``: ``Q = F + F^T``, ``p = q``, subject to ``lam >= 0`` and ``F lam + q >= 0``
  (the LCP with ``F + F^T > 0`` is this convex QP; its optimal value is 0);
- (V), ``z = (lam, phi)``: eq. (9b) times ``eps`` (the same minimiser, a better-scaled QP)::

      Q = [[eps C^T C + F^T F / gamma, I - F^T / gamma], [I - F / gamma, I / gamma]],
      p = [eps C^T r + F^T q / gamma, -q / gamma],   z >= 0,

  positive definite for ``gamma < sigma_min(F + F^T)`` (Lemma 2).

On every path the loss is then evaluated by the package's formula at the path's solution
(:meth:`~lcs_cvx.problems.ViolationProblem.objective` of (V); the prediction error for (P)),
and autograd carries the gradient through the layer.

Measured per (loss, size, path, batch): samples/s = batch / median time of one call (median of
at least 5 repeats after a warm-up, one thread; :func:`lcs_cvx.bench.median_time` for calls
under a second, else one warm-up call and 5 timed calls), at batch 1, 200 and 50,000. A path is
not run at 50,000 when one call would take more than 60 s (estimated from its rate at 200, for
the batched ``qpth`` from one call at 5,000; or found by the warm-up call): the row says
"skipped: > 60 s per call" and gives the rate measured at 200. Agreement with the fast path on the same batch (the last timed call):
max |Δlam|, relative Δloss ``|L - L_fast| / (1 + |L_fast|)`` and relative Δgradient
``max_params max|g - g_fast| / (1 + max_params max|g_fast|)``. A path that raises is recorded
with its error, never dropped.

Data: sizes ``(n_x, n_u, n_lam) = (10, 4, 4)`` and ``(10, 4, 20)``; ground truth
``lcs_cvx.random_lcs(stiffness=0.5, seed=0)``, 50,000 transitions
``lcs_cvx.make_dataset(noise=1e-2, seed=1)`` (a batch of ``B`` is their first ``B``), the
model is the truth with every parameter plus ``0.05 N(0, 1)`` (``lcs_cvx.bench``'s setting);
``gamma = 1e-2``, ``eps = 1e-4``.

    python -m studies.solvers.differentiable_paths --out studies/results/solvers [--smoke]

Writes ``OUT/differentiable_paths.jsonl`` (one line per (loss, size, path, batch); a rerun skips
finished rows), ``OUT/differentiable_paths.md`` and ``OUT/differentiable_paths.png``
(``--smoke``: ``differentiable_paths_smoke.*``: n_lam = 3, batches 1 and 20, a few seconds per
path).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from . import records  # noqa: E402
from .differentiable_paths_cells import (  # noqa: E402
    BATCHES,
    EPS,
    GAMMA,
    LOSSES,
    N_DATA,
    PATHS,
    SIZES,
    SMOKE_BATCHES,
    SMOKE_SIZES,
    agreement,
    call,
    run_row,
    setup,
    terms,
    violation_qp,
)
from .differentiable_paths_report import cell_text, fmt_err, report  # noqa: E402

__all__ = ["EPS", "GAMMA", "LOSSES", "PATHS", "agreement", "call", "main", "run", "setup", "terms", "violation_qp"]


# -- the run --------------------------------------------------------------------------------------
def plan(smoke: bool):
    if smoke:
        return SMOKE_SIZES, SMOKE_BATCHES, max(SMOKE_BATCHES)
    return SIZES, BATCHES, N_DATA


def load(path: Path) -> dict[tuple, dict]:
    return records.load(path, lambda r: (r["loss"], (r["n_x"], r["n_u"], r["n_lam"]), r["path"], r["batch"]))


def run(out: Path, smoke: bool = False, paths: tuple[str, ...] = PATHS,
        log: Callable[[str], None] = print) -> dict[tuple, dict]:
    torch.set_num_threads(1)
    out.mkdir(parents=True, exist_ok=True)
    stem = "differentiable_paths_smoke" if smoke else "differentiable_paths"
    jpath = out / f"{stem}.jsonl"
    done = load(jpath)
    sizes, batches, n_data = plan(smoke)
    big = max(batches)
    for size in sizes:
        for loss in LOSSES:
            for path in paths:
                for batch in batches:
                    key = (loss, size, path, batch)
                    if key in done:
                        continue
                    r200 = done.get((loss, size, path, 200), {}).get("samples_per_s")
                    row = run_row(loss, size, path, batch, n_data, r200, big)
                    with jpath.open("a") as fh:
                        fh.write(json.dumps(row) + "\n")
                    done[key] = row
                    log(f"{loss:10s} {size} {path:17s} B={batch:<6d} {cell_text(row):>28s} "
                        f"dlam {fmt_err(row.get('max_dlam'))} dgrad {fmt_err(row.get('rel_dgrad'))} "
                        f"[{row['row_seconds']:.1f} s]")
    report(done, out, stem, sizes, batches, paths, smoke)
    return done


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("studies/results/solvers"))
    ap.add_argument("--smoke", action="store_true", help="n_lam = 3, batches 1 and 20")
    ap.add_argument("--paths", nargs="+", default=list(PATHS), choices=PATHS)
    args = ap.parse_args(argv)
    run(args.out, smoke=args.smoke, paths=tuple(args.paths), log=lambda s: print(s, flush=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
