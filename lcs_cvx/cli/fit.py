"""``lcs-cvx fit`` and ``lcs-cvx predict``: learn an LCS from a data file and save it; evaluate
a saved model on a data file."""

from __future__ import annotations

import argparse
import os
import time
from typing import Any

import numpy as np
import torch

from .. import LCSInputError, count_modes, rollout_error, select_n_lam
from ._args import (
    Columns,
    add_column_options,
    candidates,
    check_dims,
    check_target,
    fraction,
    horizons,
    jsonable,
    kinematics_spec,
    n_lam_or_auto,
    nonnegative_float,
    positive_float,
    positive_int,
    read_table,
    relative_error_for,
    require,
    reraise_for,
    seed,
)

__all__ = ["configure_fit", "run_fit", "configure_predict", "run_predict"]


def configure_fit(p: argparse.ArgumentParser) -> None:
    # required, but checked by run_fit: every command parses with no arguments (test_cli)
    p.add_argument("--data", help="training set: an .npz with x, u, x_next, a .csv of transitions "
                   "or a trajectory file (.npz with offsets, .csv with a trajectory column) (required)")
    p.add_argument("--n-lam", type=n_lam_or_auto, metavar="K|auto",
                   help="number of complementarity variables of the learned LCS, or 'auto': one "
                   "model per --candidates, the smallest within --tolerance of the lowest held-out "
                   "error (required)")
    p.add_argument("--out", help="model file to write, with lcs_cvx.save_model (required)")
    p.add_argument("--test", default=None, help="test set (as --data); its e_test is printed")
    p.add_argument("--candidates", type=candidates, default=None, metavar="K,K,...",
                   help="with --n-lam auto: the n_lam to try (default: 1,2,4,8)")
    p.add_argument("--validation", default=None, metavar="FILE",
                   help="with --n-lam auto: held-out set (as --data) the candidates are compared on "
                   "(default: --holdout of --data)")
    p.add_argument("--holdout", type=fraction, default=None,
                   help="with --n-lam auto and no --validation: fraction of --data held out "
                   "(default: 0.2)")
    p.add_argument("--tolerance", type=nonnegative_float, default=None,
                   help="with --n-lam auto: relative slack of the choice (default: 0.1)")
    add_column_options(p)
    p.add_argument("--stiffness", type=positive_float, default=1.0,
                   help="s in F = G G^T + H - H^T + s I of the learned LCS (default: 1.0)")
    p.add_argument("--kinematics", type=kinematics_spec, default=None, metavar="SPEC",
                   help="known kinematics, integrated rather than learned (lcs_cvx.Kinematics), as "
                        "'dt=0.01 positions=0:2,1:3' (configuration:velocity column indices) and "
                        "'quaternions=q0:w0 frame=body|world' for unit quaternions (scalar first), 'up=g0:q0' for "
                        "the vertical in the body frame")
    # None = not given: lcs_cvx.fit's own defaults and recipes decide
    p.add_argument("--loss", choices=("violation", "prediction"), default=None)
    p.add_argument("--optimizer", choices=("adam", "gauss-newton", "newton"), default=None)
    p.add_argument("--recipe", choices=("best", "paper", "plain"), default=None,
                   help="the options' starting point (default: best, the recommended recipe; plain: "
                        "lcs_cvx.FitOptions' own defaults, and the default with --optimizer "
                        "gauss-newton or newton)")
    p.add_argument("--iterations", type=positive_int, default=None)
    p.add_argument("--lr", type=positive_float, default=None, help="learning rate")
    p.add_argument("--batch-size", type=positive_int, default=None)
    p.add_argument("--gamma", type=positive_float, default=None,
                   help="gamma of the violation loss, 0 < gamma < sigma_min(F + F^T)")
    p.add_argument("--eps", type=positive_float, default=None, help="epsilon of the violation loss")
    p.add_argument("--seed", type=seed, default=None,
                   help="seed of the initialisation (default: 0) and of the training")
    p.add_argument("--init", choices=("model", "increment", "affine"), default=None,
                   help="where training starts (lcs_cvx.fit's init; default: the recipe's)")
    p.add_argument("--normalize", action=argparse.BooleanOptionalAction, default=None,
                   help="learn in normalised coordinates and fold the result back into the "
                   "data's units (default: the recipe's; on except with --recipe paper)")
    p.add_argument("--rollout-horizon", type=_horizon_or_none, default=None, metavar="H|none",
                   help="with a trajectory file: the simulation-error phase's H-step rollouts "
                   "(lcs_cvx.fit's rollout_horizon; default: 10 steps with a trajectory file, "
                   "'none': no such phase)")
    p.add_argument("--rollout-iterations", type=positive_int, default=None,
                   help="steps of that refinement (default: 300)")
    p.add_argument("--holdout-horizon", type=positive_int, default=None, metavar="H",
                   help="with a trajectory file: score the held-out trajectories by the H-step "
                   "rollout error relative to the recorded change (default: 10 steps, at most the "
                   "longest held-out trajectory's)")
    p.add_argument("--affine-if-better", action="store_true", default=None,
                   help="write the least-squares affine map (an LCS with C = 0) when it scores at "
                   "least as well on held-out data")
    p.add_argument("--checkpoint", default=None, help="checkpoint file written during training")
    p.add_argument("--resume", action="store_true", default=None,
                   help="continue from --checkpoint")
    p.add_argument("--threads", type=positive_int, default=1, help="torch CPU threads (default: 1)")
    p.add_argument("--plots", default=None, metavar="DIR",
                   help="write the training history, the rollouts of the first trajectory (trajectory files) "
                        "and the modes along the data as PNG files to DIR (created; the plot extra)")


def _horizon_or_none(text: str) -> int | str:
    """``--rollout-horizon``: an integer >= 1, or ``none`` (kept as the string until passed on)."""
    return "none" if text.strip().lower() == "none" else positive_int(text)


#: The options of lcs-cvx fit that only --n-lam auto uses.
_AUTO_ONLY = ("candidates", "validation", "holdout", "tolerance")


def run_fit(args: argparse.Namespace) -> int:
    """Learn an LCS from ``--data`` with :func:`lcs_cvx.fit` (or, with ``--n-lam auto``,
    :func:`lcs_cvx.select_n_lam`) and write it to ``--out``."""

    from .. import LCS
    from .. import fit as fit_lcs  # looked up at run time: tests replace lcs_cvx.fit
    from ..io import save_model

    require(args, "data", "n_lam", "out")
    auto = args.n_lam == "auto"
    if not auto:
        given = [name for name in _AUTO_ONLY if getattr(args, name) is not None]
        if given:
            raise LCSInputError(
                f"{given[0]}: only with --n-lam auto, received --n-lam {args.n_lam}"
                + (" (use --test for a test set)" if given[0] == "validation" else "")
            )
    elif args.checkpoint is not None or args.resume:
        raise LCSInputError(
            f"{'checkpoint' if args.checkpoint is not None else 'resume'}: expected none with "
            "--n-lam auto (one training run per candidate; checkpoint a run of a fixed --n-lam)"
        )
    if auto and args.validation is not None and args.holdout is not None:
        raise LCSInputError(
            f"holdout: expected none with --validation (nothing is held out of --data), "
            f"received {args.holdout:g}"
        )
    cols = Columns.from_args(args)
    train, trajectories = read_table("data", args.data, cols)
    test = validation = None
    if args.test is not None:
        test, _ = read_table("test", args.test, cols)
        check_dims("test", args.test, test, train.n_x, train.n_u, f"as in {args.data!r}")
    validation_runs = None
    if auto and args.validation is not None:
        validation, validation_runs = read_table("validation", args.validation, cols)
        check_dims("validation", args.validation, validation, train.n_x, train.n_u,
                   f"as in {args.data!r}")
        if (trajectories is None) != (validation_runs is None):
            raise LCSInputError(
                f"validation: expected {'a trajectory file' if trajectories is not None else 'transitions'}, "
                f"as --data is, received {args.validation!r}")
    check_target("out", args.out)  # fail before training, not after
    check_target("checkpoint", args.checkpoint)
    if args.resume and args.checkpoint is None:
        raise LCSInputError("resume: expected --checkpoint PATH to resume from, received none")
    seed = 0 if args.seed is None else args.seed
    # passed on to lcs_cvx.fit only when given: fit's defaults and recipes decide the rest
    passed = ("loss", "optimizer", "recipe", "iterations", "lr", "batch_size", "gamma", "eps",
              "seed", "init", "normalize", "checkpoint", "resume", "rollout_horizon",
              "rollout_iterations", "holdout_horizon", "affine_if_better")
    options = {k: getattr(args, k) for k in passed if getattr(args, k) is not None}
    if options.get("rollout_horizon") == "none":
        options["rollout_horizon"] = None
    print(
        f"data: {len(train)} samples (n_x={train.n_x}, n_u={train.n_u})"
        + (f", test {len(test)} samples" if test is not None else "")
        + (f", validation {len(validation)} samples" if validation is not None else "")
    )

    t0 = time.perf_counter()
    selection = None
    if auto:
        cands = args.candidates or (1, 2, 4, 8)
        holdout = 0.2 if args.holdout is None else args.holdout
        tolerance = 0.1 if args.tolerance is None else args.tolerance
        print(f"model: n_lam auto among {', '.join(map(str, sorted(cands)))}, stiffness "
              f"{args.stiffness:g}, init seed {seed}", flush=True)
        options.pop("seed", None)  # select_n_lam's own, passed on to fit
        # a trajectory file is passed whole: whole runs are held out
        selection = _train(args, lambda: select_n_lam(
            trajectories if trajectories is not None else train, cands,
            validation_runs if validation_runs is not None else validation, holdout=holdout, tolerance=tolerance,
            stiffness=args.stiffness, kinematics=args.kinematics, seed=seed, progress=True, test=test,
            **options))
        result, n_lam = selection.results[selection.n_lam], selection.n_lam
        print("\n".join(selection.summary().splitlines()[:-1]))
        where = (f"--validation {args.validation!r}" if validation is not None
                 else f"{100 * holdout:g}% of --data's runs held out" if trajectories is not None
                 else f"{100 * holdout:g}% of --data held out")
        print(f"chosen n_lam: {n_lam} (the smallest within {100 * tolerance:g}% of the lowest "
              f"{result.heldout_score if trajectories is not None else 'relative error'} on {where})")
    else:
        n_lam = args.n_lam
        model = LCS(train.n_x, train.n_u, n_lam, stiffness=args.stiffness, seed=seed, kinematics=args.kinematics)
        print(f"model: n_lam={n_lam}, stiffness {args.stiffness:g}, init seed {seed}"
              + (f", kinematics {args.kinematics}" if args.kinematics is not None else ""), flush=True)
        # a trajectory file is passed whole: fit holds out whole trajectories
        data = trajectories if trajectories is not None else train
        result = _train(args, lambda: fit_lcs(model, data, test=test, progress=True, **options))
    wall = time.perf_counter() - t0

    metadata = {
        "fit": jsonable(result.settings.flat()),
        "init": {"n_lam": n_lam, "stiffness": args.stiffness, "seed": seed,
                 **({"kinematics": str(args.kinematics)} if args.kinematics is not None else {})},
        "data": {"train": args.data, "test": args.test, "n_train": len(train)},
    }
    if selection is not None:
        metadata["data"]["validation"] = args.validation
        metadata["selection"] = jsonable({
            "n_lam": n_lam, "candidates": [row["n_lam"] for row in selection.table],
            "tolerance": selection.tolerance,
            "holdout": None if validation is not None else holdout,
            "table": selection.table,
        })
    try:
        save_model(result.model, args.out, metadata=metadata)
    except LCSInputError as exc:
        raise reraise_for("out", exc) from None
    if result.n_fallback:
        print(f"fallbacks: {result.n_fallback} training samples were solved by the reference "
              f"solver (worst relative KKT residual {result.fallback_residual:.2e})")
    if test is not None:
        print(f"e_test: {relative_error_for('test', result.model, test):.6g}")
    print(f"train relative error: {relative_error_for('data', result.model, train):.6g}")
    if result.beats_affine is not None:
        print(result.verdict)
    print(f"wall time: {wall:.2f} s")
    print(f"saved: {args.out}")
    if args.plots is not None:
        _plots(args.plots, result.model, trajectories if trajectories is not None else train, result)
    return 0


def _plots(directory: str, model: Any, data: Any, result: Any = None) -> None:
    """``--plots DIR``: the fit's history (with a result), the rollouts of the first run (with
    trajectories) and the modes along the data, as PNG files in ``directory`` (created)."""
    from .. import plot
    from ..trajectories import Trajectories

    os.makedirs(directory, exist_ok=True)
    written = []
    if result is not None:
        written.append(os.path.join(directory, "history.png"))
        plot.history(result, path=written[-1])
    if isinstance(data, Trajectories):
        written.append(os.path.join(directory, "rollouts.png"))
        plot.rollouts(model, data, path=written[-1])
    written.append(os.path.join(directory, "modes.png"))
    plot.modes(model, data, path=written[-1])
    print(f"plots: {', '.join(written)}")


def _train(args: argparse.Namespace, run: Any) -> Any:
    """``run()``, with the library's name of the training set, ``train``, as ``--data``."""
    try:
        return run()
    except LCSInputError as exc:  # fit names the training set "train"; here it is --data
        if str(exc).startswith("train: "):
            raise reraise_for("data", LCSInputError(str(exc).removeprefix("train: "))) from None
        raise


def configure_predict(p: argparse.ArgumentParser) -> None:
    # required, but checked by run_predict: every command parses with no arguments (test_cli)
    p.add_argument("--model", help="model file written by lcs-cvx fit / save_model (required)")
    p.add_argument("--data", help="data set, an .npz with x, u, x_next, a .csv of transitions or a "
                   "trajectory file (Trajectories.save's .npz, a .csv with a trajectory column) "
                   "(required)")
    p.add_argument("--out", default=None,
                   help="also write the predictions (arrays x_next_pred, lam) to this .npz")
    p.add_argument("--horizons", type=horizons, default=None,
                   help="rollout horizons for trajectory files (default: 1,5,20)")
    add_column_options(p)
    p.add_argument("--threads", type=positive_int, default=1, help="torch CPU threads (default: 1)")
    p.add_argument("--plots", default=None, metavar="DIR",
                   help="write the rollouts of the first trajectory and the modes along the data as PNG "
                        "files to DIR (created; the plot extra)")


def run_predict(args: argparse.Namespace) -> int:
    """e_test and the number of hybrid modes of a saved model on a data set."""
    from ..io import atomic_write, load_model

    require(args, "model", "data")
    check_target("out", args.out)
    try:
        model = load_model(args.model)
    except LCSInputError as exc:
        raise reraise_for("model", exc) from None
    data, trajs = read_table("data", args.data, Columns.from_args(args))
    if trajs is None and args.horizons is not None:
        raise LCSInputError(
            f"horizons: only for trajectory files (an .npz with offsets, a .csv with a trajectory "
            f"column), received --data {args.data!r}"
        )
    check_dims("data", args.data, data, model.n_x, model.n_u, f"the model's, {args.model!r}")
    model.requires_grad_(False)
    x, u = data.x.to(model.dtype), data.u.to(model.dtype)
    print(f"model: n_x={model.n_x}, n_u={model.n_u}, n_lam={model.n_lam} ({args.model})")
    if trajs is None:
        print(f"data: {len(data)} samples ({args.data})")
    else:
        print(f"data: {len(data)} samples in {len(trajs)} trajectories ({args.data})")
    print(f"e_test: {relative_error_for('data', model, data):.6g}")
    print(f"modes: {count_modes(model, data)}")
    if trajs is not None:
        longest = max(trajs.lengths)
        hs = [h for h in dict.fromkeys(args.horizons or (1, 5, 20)) if h <= longest]
        if hs:
            errs = rollout_error(model, trajs, hs)
            print(f"rollout error (H={', '.join(map(str, hs))}): "
                  + ", ".join(f"{errs[h]:.6g}" for h in hs))
        else:
            print(f"rollout error: none (every horizon is longer than the longest trajectory, {longest} steps)")
    if args.out is not None:
        with torch.no_grad():
            lam = model.solve_lcp(x, u).lam
            x_next = x @ model.A.mT + u @ model.B.mT + lam @ model.C.mT + model.d
        arrays = {"x_next_pred": x_next.cpu().numpy(), "lam": lam.cpu().numpy()}
        try:
            atomic_write(args.out, lambda f: np.savez(f, **arrays), name="out")
        except LCSInputError as exc:
            raise reraise_for("out", exc) from None
        print(f"predictions: {args.out}")
    if args.plots is not None:
        _plots(args.plots, model, trajs if trajs is not None else data)
    return 0
