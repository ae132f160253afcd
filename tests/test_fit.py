"""Training (lcs_cvx.fit): recovery, second order vs Adam, recipes, checkpoints and resume."""

from __future__ import annotations

import ast
import dataclasses
import math
import signal
import subprocess
import sys
import textwrap

import pytest
import torch

import lcs_cvx
from lcs_cvx import LCSInputError
from lcs_cvx.system import PARAMETER_NAMES
from lcs_cvx.train import (
    FLAT_OPTIONS,
    AdamOptions,
    FitOptions,
    PolishOptions,
    RefineOptions,
    extra_units,
    resolve_options,
)
from lcs_cvx.train.holdout import Split


@pytest.fixture(scope="module")
def small():
    """A (2, 1, 2) ground truth, 2,000 noiseless training samples and 500 test samples."""
    truth = lcs_cvx.random_lcs(2, 1, 2, seed=0)
    train = lcs_cvx.make_dataset(truth, 2000, seed=1)
    test = lcs_cvx.make_dataset(truth, 500, seed=2)
    return truth, train, test


#: the optimisers in the data's own coordinates from the given model (the paper's protocol), so
#: that these tests measure the optimisers alone; normalisation has its own tests (test_scaling)
RAW = {"recipe": "plain", "normalize": False, "init": "model"}


def _first_below(history, level):
    return next((h["iteration"] for h in history if h["e_test"] is not None and h["e_test"] < level), None)


@pytest.mark.parametrize(
    "options",
    [
        {"optimizer": "adam", "iterations": 3000, "lr": 5e-3, "eval_every": 50, **RAW},
        {"optimizer": "adam", "loss": "prediction", "iterations": 3000, "lr": 5e-3, "eval_every": 50, **RAW},
        {"optimizer": "gauss-newton", "iterations": 20, **RAW},
        {"optimizer": "newton", "iterations": 60, **RAW},
        {"recipe": "best", "iterations": 1500},
    ],
    ids=["adam-violation", "adam-prediction", "gauss-newton", "newton", "best"],
)
def test_recovers_small_system(small, options):
    truth, train, test = small
    model = lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3)
    result = lcs_cvx.fit(model, train, test=test, progress=False, **options)
    assert result.model is model
    last = result.kept_history[-1]
    assert last["e_test"] < 1e-5
    assert lcs_cvx.relative_error(model, test) == pytest.approx(last["e_test"])


def test_second_order_needs_far_fewer_iterations_than_adam(small):
    _, train, test = small
    adam = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3), train, test=test, progress=False,
                       iterations=3000, lr=5e-3, eval_every=10, **RAW)
    gn = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3), train, test=test, progress=False,
                     optimizer="gauss-newton", iterations=20, **RAW)
    newton = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3), train, test=test, progress=False,
                         optimizer="newton", iterations=60, **RAW)
    k_adam, k_gn, k_newton = (_first_below(r.history, 1e-5) for r in (adam, gn, newton))
    assert None not in (k_adam, k_gn, k_newton)
    assert k_adam >= 20 * k_gn  # measured: Adam ~1,000+ steps, Gauss-Newton < 10
    assert k_adam >= 10 * k_newton


def test_history_records_and_settings(small):
    _, train, test = small
    seen = []
    result = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3), train, recipe="plain", test=test, progress=False,
                         iterations=200, eval_every=50, callbacks=[lambda rec, m: seen.append(rec)])
    assert [h["iteration"] for h in result.history] == [50, 100, 150, 200]
    assert seen == result.history
    assert all(h["phase"] == "adam" and h["e_test"] > 0 and h["loss"] > 0 for h in result.history)
    # keep_best=None is resolved: off for transitions
    assert result.settings == resolve_options(iterations=200, eval_every=50, keep_best=False)
    assert result.settings.adam.lr == 1e-3 and result.settings.adam.betas == (0.9, 0.9)


def test_callback_stops_training(small):
    _, train, _ = small
    result = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3), train, recipe="plain", progress=False, iterations=1000,
                         eval_every=10, callbacks=[lambda rec, m: rec["iteration"] >= 30])
    assert result.history[-1]["iteration"] == 30


def test_keep_best_returns_the_best_iterate_on_the_heldout_part(small):
    _, train, test = small
    fit_part, val = train.split(0.8, seed=1)
    model = lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3)
    # a learning rate too large to settle: the last iterate is not the best one
    result = lcs_cvx.fit(model, fit_part, recipe="plain", validation=val, test=test, progress=False, iterations=400, lr=0.3,
                         eval_every=20, keep_best=True)
    best = min(h["heldout"] for h in result.history)
    assert best < result.history[-1]["heldout"]
    assert lcs_cvx.relative_error(model, val) == pytest.approx(best, rel=1e-12)
    assert all(h["e_test"] is not None for h in result.history)  # reported beside it


def test_the_test_set_drives_no_choice(small):
    """The same model, history of losses and held-out scores with and without ``test``: the
    kept iterate and the kept restart follow the held-out part only."""
    _, train, test = small
    kw = {"recipe": "plain", "iterations": 200, "lr": 0.3, "eval_every": 20, "keep_best": True, "restarts": 2,
          "progress": False}
    with_test = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3), train, test=test, **kw)
    without = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3), train, **kw)
    assert with_test.restart_scores == without.restart_scores
    for a, b in zip(with_test.history, without.history, strict=True):
        assert (a["loss"], a["heldout"]) == (b["loss"], b["heldout"])  # the same operations
        assert a["e_test"] is not None and b["e_test"] is None
    for name in PARAMETER_NAMES:
        assert torch.equal(getattr(with_test.model, name), getattr(without.model, name)), name


def test_keep_best_without_a_heldout_part_is_an_error(small):
    _, train, test = small
    with pytest.raises(lcs_cvx.LCSInputError, match=r"keep_best: expected a held-out part .* a test set is only "
                                                    r"reported.*received keep_best=True"):
        lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), train, recipe="plain", test=test, keep_best=True, iterations=5, progress=False)


def test_restarts_pick_the_best_on_holdout(small):
    _, train, _ = small
    result = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3), train, recipe="plain", progress=False,
                         optimizer="gauss-newton", iterations=3, restarts=3, holdout=0.2)
    assert len(result.restart_scores) == 3
    _, holdout = train.split(0.8, seed=0)
    assert lcs_cvx.relative_error(result.model, holdout) == pytest.approx(min(result.restart_scores))
    assert {h["restart"] for h in result.history} == {0, 1, 2}
    kept = result.kept_restart
    assert result.restart_scores[kept] == min(result.restart_scores)


def test_the_kept_restart_names_the_returned_models_records(small):
    _, train, test = small
    result = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3), train, recipe="plain", test=test,
                         progress=False, optimizer="gauss-newton", iterations=3, restarts=3)
    records = result.kept_history
    assert {h["restart"] for h in records} == {result.kept_restart}
    assert records[-1]["e_test"] == pytest.approx(lcs_cvx.relative_error(result.model, test))
    one = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3), train, recipe="plain", progress=False,
                      optimizer="gauss-newton", iterations=1, restarts=1)
    assert one.restart_scores == [] and one.kept_restart == 0 and one.kept_history == one.history


def test_kept_fit_compares_the_last_refined_loss_with_the_last_adam_loss():
    from lcs_cvx.train.driver import kept_fit

    h = [{"phase": "adam", "loss": 1e-4}, {"phase": "adam", "loss": 2e-5},
         {"phase": "gauss-newton", "loss": 9e-5}, {"phase": "gauss-newton", "loss": 5e-5}]
    assert kept_fit(h, 3.0) and not kept_fit(h, 2.0)
    assert kept_fit(h, None)
    assert kept_fit(h[:2], 1.0)  # no refinement: nothing could lose the fit
    assert kept_fit(h[2:], 1.0)  # no Adam phase: nothing to compare with
    assert not kept_fit(h + [{"phase": "polish", "loss": 1e-9}], 2.0)  # polish is not refinement


def test_restart_tolerance_runs_restarts_until_one_kept_its_fit(small, monkeypatch):
    from lcs_cvx.train import driver

    _, train, _ = small
    verdicts, tolerances = iter([False, True]), []

    def verdict(history, tolerance):
        tolerances.append(tolerance)
        return next(verdicts)

    monkeypatch.setattr(driver, "kept_fit", verdict)
    monkeypatch.setattr(Split, "affine_score", lambda self: math.inf)  # every run beats it
    result = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), train, recipe="plain", progress=False, iterations=20,
                         eval_every=10, refine="gauss-newton", refine_iterations=2, restarts=4,
                         restart_tolerance=3.0)
    assert tolerances == [3.0, 3.0]  # the second run kept its fit: restarts 2 and 3 never ran
    assert len(result.restart_scores) == 2
    assert {h["restart"] for h in result.history} == {0, 1}


def test_restart_tolerance_runs_one_restart_when_the_first_keeps_its_fit(small, monkeypatch):

    monkeypatch.setattr(Split, "affine_score", lambda self: math.inf)
    _, train, _ = small
    options = dict(recipe="plain", progress=False, iterations=20, eval_every=10, refine="gauss-newton",
                   refine_iterations=2, restarts=3)
    once = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), train, restart_tolerance=1e9, **options)
    every = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), train, **options)
    assert len(once.restart_scores) == 1 and len(every.restart_scores) == 3
    assert once.restart_scores[0] == every.restart_scores[0]  # the same first run


def test_restart_tolerance_runs_restarts_until_one_beats_the_affine_map(small, monkeypatch):
    """A run that kept its fit but whose held-out error is not below AFFINE_MARGIN times the
    affine map's has not succeeded: the next restart runs."""
    from lcs_cvx.train import driver

    _, train, _ = small
    options = dict(recipe="plain", progress=False, iterations=20, eval_every=10, refine="gauss-newton",
                   refine_iterations=2, restarts=3, restart_tolerance=1e9, holdout=0.2)
    every = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=4), train, **{**options, "restart_tolerance": None})
    scores = every.restart_scores
    fit_part, holdout = train.split(0.8, seed=0)
    calls = []

    def level(split):  # an affine error that run 1 beats and run 0 does not
        calls.append((len(split.fit), len(split.holdout)))
        return scores[1] / driver.AFFINE_MARGIN * 1.0001

    assert scores[0] > scores[1]  # the fixture's runs: the first is the worse
    monkeypatch.setattr(Split, "affine_score", level)
    result = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=4), train, **options)
    assert result.restart_scores == scores[:2]  # run 0 did not beat it, run 1 did: run 2 skipped
    assert calls == [(len(fit_part), len(holdout))]  # computed once, on the fit and held-out parts


def test_init_tuple_starts_restart_k_from_its_kth_entry(small, monkeypatch):
    from lcs_cvx.train import driver

    _, train, _ = small
    kinds = []
    real = driver.start

    def spy(base, init, scaling, data, exact):
        kinds.append((init, exact))
        return real(base, init, scaling, data, exact)

    monkeypatch.setattr(driver, "start", spy)
    lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), train, recipe="plain", progress=False, iterations=10, restarts=3,
                init=("increment", "model"))
    assert kinds == [("increment", True), ("model", False), ("increment", False)]
    assert resolve_options(init=["affine", "model"]).run.init == ("affine", "model")  # TOML lists


@pytest.mark.parametrize("value", [(), ["model", "random"], ("increment", 3)])
def test_init_tuple_is_checked(value):
    with pytest.raises(LCSInputError, match="init: expected one of"):
        resolve_options(init=value)


@pytest.mark.parametrize("value", [0.5, float("nan"), "3", True])
def test_restart_tolerance_is_checked(value):
    with pytest.raises(LCSInputError, match="restart_tolerance"):
        resolve_options(restarts=2, restart_tolerance=value)


def test_restart_tolerance_is_refused_with_restarts_trained_together(small):
    _, train, _ = small
    with pytest.raises(LCSInputError, match="restart_tolerance.*ensemble=True"):
        lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), train, recipe="plain", progress=False, iterations=5,
                    restarts=2, restart_tolerance=3.0, ensemble=True)


def test_polish_lowers_the_prediction_loss(small):
    """A final polish on the prediction loss: recorded as its own phase, counted in the
    iterations, and it lowers L_pred on the training data from where Adam on L_eps left it."""
    truth, train, test = small
    model = lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3)
    kw = {"iterations": 300, "lr": 5e-3, "progress": False, "eval_every": 50, **RAW}
    plain = lcs_cvx.fit(model, train, test=test, **kw)
    with torch.no_grad():
        before = float(lcs_cvx.prediction_loss(plain.model, train.x, train.u, train.x_next))
    polished = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3), train, test=test, polish_iterations=200,
                           polish_lr=1e-3, **kw)
    with torch.no_grad():
        after = float(lcs_cvx.prediction_loss(polished.model, train.x, train.u, train.x_next))
    phases = [h["phase"] for h in polished.history]
    assert phases.count("polish") == 4 and phases[-1] == "polish"
    assert polished.history[-1]["iteration"] == 500
    assert after < 0.9 * before  # measured: 0.051 -> 0.042


def test_recipes_and_option_resolution():
    paper = resolve_options("paper")
    assert (paper.optimizer, paper.adam.lr, paper.adam.lr_schedule, paper.refine.method) == (
        "adam", 1e-3, "constant", None)
    best = resolve_options("best", lr=2e-2)
    assert best.adam.lr == 2e-2 and best.adam.eps_start == 1e-2 and best.refine.method == "gauss-newton"
    assert best.adam.extra_units == "auto" and best.prune.repair == 1
    assert [extra_units("auto", n) for n in (1, 4, 8, 20)] == [1, 2, 4, 4]
    gn = resolve_options(optimizer="gauss-newton")
    assert gn.optimizer == "gauss-newton" and gn.adam.iterations == 0
    assert gn.refine.iterations == 100 and gn.refine.batch_size == 5000 and gn.run.eval_every == 1
    assert gn.run.restarts == 3 and gn.replace(optimizer="adam").run.restarts == 1
    assert resolve_options(optimizer="gauss-newton", iterations=7).refine.iterations == 7
    # the recipes are values: options=RECIPES[...] with overrides is the recipe with keywords
    assert lcs_cvx.RECIPES["best"].replace(lr=2e-2) == best
    assert lcs_cvx.RECIPES["paper"] == paper and paper.recipe == "paper"
    # the flat keywords are a faithful view of the groups
    for opts in (paper, best, gn, resolve_options(polish_iterations=5, restarts=2)):
        flat = opts.flat()
        assert resolve_options(flat.pop("recipe"), **flat) == opts


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"learning_rate": 1e-3}, r"unknown option\(s\) \['learning_rate'\]"),
        ({"optimizer": "sgd"}, r"optimizer: expected one of .*received 'sgd'"),
        ({"loss": "mse"}, r"loss: expected one of .*received 'mse'"),
        ({"lr": -1.0}, r"lr: expected a finite number > 0, received -1.0"),
        ({"iterations": 2.5}, r"iterations: expected an integer >= 0, received 2.5"),
        ({"eps_start": 1e-6}, r"eps_start: expected None or a number >= eps"),
        ({"loss": "prediction", "optimizer": "newton"}, r"second-order methods are for the violation loss"),
        ({"recipe": "fast"}, r"recipe: expected one of \('paper', 'best', 'plain'\), received 'fast'"),
        ({"extra_units": 2}, r"extra_units: the pruned model needs a refinement phase"),
        ({"extra_units": "many"}, r"extra_units: expected an integer >= 0 or 'auto', received 'many'"),
        ({"extra_units": -1}, r"extra_units: expected an integer >= 0 or 'auto', received -1"),
        ({"polish_iterations": -3}, r"polish_iterations: expected an integer >= 0, received -3"),
        ({"polish_lr": 0.0}, r"polish_lr: expected a finite number > 0, received 0.0"),
    ],
)
def test_invalid_options(small, kwargs, match):
    _, train, _ = small
    with pytest.raises(LCSInputError, match=match):
        lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2), train, progress=False, **{"recipe": "plain", **kwargs})


def test_invalid_data(small):
    _, train, _ = small
    x = train.x.clone()
    x[3, 1] = float("nan")
    with pytest.raises(LCSInputError, match=r"train: expected finite real values in x, received NaN/inf"):
        lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2), lcs_cvx.Dataset(x, train.u, train.x_next), recipe="plain", progress=False)
    with pytest.raises(LCSInputError, match=r"train: expected n_x=3, n_u=1 \(the model's\), received n_x=2"):
        lcs_cvx.fit(lcs_cvx.LCS(3, 1, 2), train, recipe="plain", progress=False)
    with pytest.raises(LCSInputError, match="train: expected an lcs_cvx.Dataset"):
        lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2), (train.x, train.u), recipe="plain", progress=False)
    with pytest.raises(LCSInputError, match="model: expected an lcs_cvx.LCS"):
        lcs_cvx.fit(torch.nn.Linear(2, 2), train, recipe="plain", progress=False)


def test_options_are_frozen():
    import dataclasses

    with pytest.raises(dataclasses.FrozenInstanceError):
        FitOptions().adam.lr = 1.0  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        FitOptions().adam = None  # type: ignore[misc]


def test_checkpoint_mismatch_is_refused(small, tmp_path):
    _, train, _ = small
    ckpt = tmp_path / "run.ckpt"
    lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3), train, recipe="plain", progress=False, iterations=20,
                checkpoint_every=10, checkpoint=ckpt)
    with pytest.raises(LCSInputError, match=r"checkpoint: .* other options \(differing: \['lr'\]\)"):
        lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3), train, recipe="plain", progress=False, iterations=20,
                    checkpoint_every=10, checkpoint=ckpt, resume=True, lr=1e-2)


_SCRIPT = textwrap.dedent(
    """
    import os, signal, sys, torch, lcs_cvx
    torch.set_num_threads(1)
    truth = lcs_cvx.random_lcs(2, 1, 2, seed=0)
    train = lcs_cvx.make_dataset(truth, 2000, seed=1)
    test = lcs_cvx.make_dataset(truth, 200, seed=2)
    model = lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3)

    def kill(record, model):  # SIGKILL at the first record from iteration KILL on
        if record["iteration"] >= int(sys.argv[2]):
            os.kill(os.getpid(), signal.SIGKILL)

    lcs_cvx.fit(model, train, test=test, progress=False, checkpoint=sys.argv[1], resume=True,
                callbacks=[kill], **OPTIONS)
    """
)


@pytest.mark.parametrize(
    "options, kill",
    [
        ({"recipe": "plain", "iterations": 2500, "eval_every": 100, "checkpoint_every": 100, "lr": 5e-3,
          "reinit_saturated": True, "eps_start": 1e-2, "lr_schedule": "cosine",
          "refine": "gauss-newton", "refine_iterations": 3, "refine_batch": 1000,
          "extra_units": 1, "polish_iterations": 150}, 1250),
        ({"optimizer": "newton", "iterations": 40, "batch_size": 1000}, 20),
    ],
    ids=["adam+refine", "newton"],
)
def test_resume_after_kill_equals_uninterrupted(small, tmp_path, options, kill):
    """A training subprocess killed mid-run (SIGKILL, sent by itself at its first record from
    iteration ``kill`` on: after its last checkpoint, before the next), resumed in this process:
    the final model and history (wall times aside) equal an uninterrupted run's."""
    _, train, _ = small
    test = lcs_cvx.make_dataset(lcs_cvx.random_lcs(2, 1, 2, seed=0), 200, seed=2)
    ckpt = tmp_path / "run.ckpt"
    script = tmp_path / "train.py"
    script.write_text(_SCRIPT.replace("**OPTIONS", f"**{options!r}"))
    proc = subprocess.run([sys.executable, str(script), str(ckpt), str(kill)])
    assert proc.returncode == -signal.SIGKILL
    partial = torch.load(ckpt, weights_only=True)
    assert partial["run"] is not None  # killed mid-run: there is something left to do
    resumed_model = lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3)
    resumed = lcs_cvx.fit(resumed_model, train, test=test, progress=False, checkpoint=ckpt,
                          resume=True, **options)
    clean_model = lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3)
    clean = lcs_cvx.fit(clean_model, train, test=test, progress=False, **options)
    for name, p in clean_model.named_parameters():
        assert torch.equal(p, getattr(resumed_model, name)), name

    def strip(history):
        return [{k: v for k, v in h.items() if k != "wall_time"} for h in history]

    assert strip(resumed.history) == strip(clean.history)
    # resuming a finished run does nothing more and returns the same model
    again_model = lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3)
    again = lcs_cvx.fit(again_model, train, test=test, progress=False, checkpoint=ckpt,
                        resume=True, **options)
    assert strip(again.history) == strip(clean.history)
    for name, p in clean_model.named_parameters():
        assert torch.equal(p, getattr(again_model, name)), name


def test_divergence_is_reported_not_silent(small):
    _, train, _ = small
    with pytest.raises(lcs_cvx.SolverError, match=r"training diverged at iteration \d+: loss = .*not finite; lower lr"):
        lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, stiffness=1.0, seed=3), train, recipe="plain", progress=False, iterations=500, lr=1e200)


def test_fit_takes_options_and_overrides(small):
    """``fit(model, data, options, **overrides)`` is ``fit(model, data, recipe=..., **kw)``."""
    _, train, test = small
    kw = {"iterations": 300, "refine_iterations": 2, "progress": False}
    a = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), train, test=test, recipe="best", **kw)
    b = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), train, lcs_cvx.RECIPES["best"], test=test, **kw)
    assert a.settings == b.settings
    assert [h["e_test"] for h in a.history] == [h["e_test"] for h in b.history]
    with pytest.raises(LCSInputError, match=r"options: expected an lcs_cvx.FitOptions .*received dict"):
        lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2), train, {"lr": 1e-3}, progress=False)
    with pytest.raises(LCSInputError, match=r"recipe: expected None when options are given"):
        lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2), train, lcs_cvx.RECIPES["paper"], recipe="best", progress=False)
    # a whole group as an override
    c = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), train, recipe="plain", progress=False,
                    adam=lcs_cvx.AdamOptions(iterations=40, lr=5e-3), run=lcs_cvx.RunOptions(eval_every=20))
    assert [h["iteration"] for h in c.history] == [20, 40] and c.settings.adam.lr == 5e-3


def test_fallbacks_are_recorded(small, monkeypatch):
    """Every record carries the samples the fast solver handed to a reference solver in its
    stretch and their worst residual, and the result sums them: with no pivoting sweeps allowed,
    every sample whose first guess is not its solution falls back, for real, in every phase."""
    _, train, _ = small
    clean = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), train, recipe="plain", progress=False, iterations=30,
                        eval_every=10, optimizer="adam")
    assert clean.n_fallback == 0 and clean.fallback_residual == 0.0
    assert all(h["n_fallback"] == 0 for h in clean.history)
    monkeypatch.setattr(lcs_cvx.losses, "MAX_ITER", 0)
    best = {"recipe": "best", "iterations": 20, "eval_every": 10, "prune_batch": 100,
            "refine_iterations": 1, "refine_batch": 100}  # Adam, pruning with repair, refinement
    for options in ({"recipe": "plain", "iterations": 30, "eval_every": 10}, {"optimizer": "gauss-newton", "iterations": 2,
                                                          "batch_size": 300}, best):
        with pytest.warns(lcs_cvx.FallbackWarning) as caught:  # and said so
            result = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), train, progress=False, **options)
        assert any("solved them with enumeration of the 4^" in str(w.message) for w in caught)
        counts = [h["n_fallback"] for h in result.history]
        assert result.n_fallback == sum(counts) > 0
        for phase in {h["phase"] for h in result.history}:  # (a stretch may start every sample right)
            assert any(h["n_fallback"] > 0 for h in result.history if h["phase"] == phase), phase
        assert 0.0 < result.fallback_residual <= 1e-13  # enumeration (n_lam = 2): exact to round-off
        assert result.fallback_residual == max(h["fallback_residual"] for h in result.history)


def test_old_checkpoint_format_is_refused(small, tmp_path):
    _, train, _ = small
    ckpt = tmp_path / "old.ckpt"
    torch.save({"format": 3, "options": {}, "done": []}, ckpt)
    with pytest.raises(LCSInputError, match=r"checkpoint: .* has format 3, expected 4 \(written by another version"):
        lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2), train, recipe="plain", progress=False, checkpoint=ckpt, resume=True)


# -- the flat keywords are aliases of fields: replace changes exactly what it names -------------
def _changed(a: FitOptions, b: FitOptions) -> set[tuple[str, str]]:
    """The fields (group, name) in which ``a`` and ``b`` differ, compared field by field."""
    out = {("recipe", "")} if a.recipe != b.recipe else set()
    for group in ("objective", "adam", "prune", "refine", "polish", "rollout", "run"):
        ga, gb = getattr(a, group), getattr(b, group)
        out |= {(group, f.name) for f in dataclasses.fields(ga)
                if getattr(ga, f.name) != getattr(gb, f.name)}
    return out


#: a valid value other than the default for every flat keyword
_NEW_VALUES = {
    "optimizer": "gauss-newton", "iterations": 33, "batch_size": 77, "loss": "prediction",
    "gamma": 0.02, "eps": 2e-4, "reg": 0.0, "lr": 5e-3, "betas": (0.8, 0.95), "adam_eps": 1e-7,
    "lr_schedule": "cosine", "lr_floor": 0.1, "eps_start": 1e-2, "eps_fraction": 0.5,
    "reinit_saturated": True, "reinit_every": 100, "extra_units": 2, "prune_repair": 2,
    "prune_batch": 300, "prune_lookahead": 2, "refine": "newton", "refine_iterations": 3,
    "refine_batch": 100, "damping": 1e-2, "polish_iterations": 10, "polish_lr": 1e-3,
    "restarts": 3, "holdout": 0.2, "restart_tolerance": 2.0, "seed": 5, "eval_every": 7,
    "checkpoint_every": 11, "keep_best": True, "normalize": False, "init": ("affine", "model"),
    "rollout_horizon": 7, "rollout_iterations": 12, "rollout_lr": 2e-3, "rollout_batch": 9,
    "holdout_horizon": 4, "affine_if_better": True,
}


def test_replace_keeps_fields_no_keyword_names():
    """Regression: replace() went through the flat keywords and back, which have no slot for the
    polish's batch size or the refinement's record interval, so both fell back to their
    defaults (batch 200, record_every 1) on any replace."""
    opts = FitOptions(polish=PolishOptions(iterations=100, batch_size=1000),
                      refine=RefineOptions(method="gauss-newton", record_every=5))
    new = opts.replace(lr=2e-3)
    assert new.polish.batch_size == 1000 and new.refine.record_every == 5
    assert new == dataclasses.replace(opts, adam=dataclasses.replace(opts.adam, lr=2e-3))
    assert _changed(opts, new) == {("adam", "lr")}


def test_fit_overrides_keep_fields_no_keyword_names(small):
    _, train, _ = small
    opts = FitOptions(adam=AdamOptions(iterations=4), polish=PolishOptions(iterations=2, batch_size=1000),
                      refine=RefineOptions(method="gauss-newton", iterations=1, record_every=5))
    result = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), train, options=opts, lr=2e-3, progress=False)
    assert result.settings.polish.batch_size == 1000 and result.settings.refine.record_every == 5
    assert result.settings == dataclasses.replace(opts, adam=dataclasses.replace(opts.adam, lr=2e-3),
                                                  run=dataclasses.replace(opts.run, keep_best=False))


@pytest.mark.parametrize("keyword", FLAT_OPTIONS)
def test_replace_with_a_keyword_changes_exactly_its_fields(keyword):
    aliases = lcs_cvx.train.options.FLAT_ALIASES
    assert set(_NEW_VALUES) == set(FLAT_OPTIONS) and FLAT_OPTIONS == ("optimizer", *aliases)
    if keyword == "optimizer":  # the optimizer's fields and its documented defaults
        base = FitOptions()
        new = base.replace(optimizer="gauss-newton")
        assert new == resolve_options(optimizer="gauss-newton")
        assert _changed(base, new) == {  # refine.batch_size and record_every: 5000 and 1 already
            ("adam", "iterations"), ("refine", "method"), ("refine", "iterations"),
            ("adam", "batch_size"), ("polish", "batch_size"), ("run", "eval_every"),
            ("run", "checkpoint_every"), ("run", "restarts")}
        return
    # a refinement for extra_units to prune into; none with the prediction loss (Lemma 4)
    base = FitOptions() if keyword == "loss" else FitOptions(refine=RefineOptions(method="gauss-newton"))
    new = base.replace(**{keyword: _NEW_VALUES[keyword]})
    assert _changed(base, new) == set(aliases[keyword])
    assert all(getattr(getattr(new, g), f) == _NEW_VALUES[keyword] for g, f in aliases[keyword])
    assert new.flat()[keyword] == (list if keyword == "betas" else lambda v: v)(_NEW_VALUES[keyword])


def test_keywords_with_a_second_order_optimizer():
    """iterations, batch_size and eval_every alias the refinement's fields (which is then the
    optimizer); refine, refine_iterations and refine_batch alias none."""
    gn = resolve_options(optimizer="gauss-newton")
    assert _changed(gn, gn.replace(iterations=7)) == {("refine", "iterations")}
    assert _changed(gn, gn.replace(batch_size=64)) == {
        ("refine", "batch_size"), ("adam", "batch_size"), ("polish", "batch_size")}
    assert _changed(gn, gn.replace(eval_every=3)) == {("run", "eval_every"), ("refine", "record_every")}
    assert _changed(gn, gn.replace(lr=5e-3)) == {("adam", "lr")}
    assert gn.replace(refine=None, refine_iterations=3, refine_batch=100, optimizer="gauss-newton") == gn
    assert _changed(gn, gn.replace(optimizer="newton")) == {("refine", "method")}
    with pytest.raises(LCSInputError, match=r"refine: a refinement follows the Adam phase"):
        gn.replace(refine="newton")
    # back to Adam: no refinement, Adam's defaults; named keywords win over the defaults
    assert gn.replace(optimizer="adam") == resolve_options()
    assert gn.replace(optimizer="adam", iterations=9).adam.iterations == 9
    assert FitOptions().replace(optimizer="newton", iterations=7) == resolve_options(optimizer="newton", iterations=7)
    with pytest.raises(LCSInputError, match=r"refine: a refinement follows the Adam phase"):
        lcs_cvx.RECIPES["best"].replace(optimizer="gauss-newton")  # the recipe refines after Adam


def test_batch_size_sets_the_polish_batch_too():
    """The polish has no keyword for its batch: batch_size sets Adam's and the polish's (as fit
    always has); the polish's own survives a replace that does not name batch_size."""
    assert resolve_options(batch_size=300).polish.batch_size == 300
    opts = FitOptions(polish=PolishOptions(iterations=5, batch_size=1000))
    assert opts.replace(iterations=50).polish.batch_size == 1000
    assert _changed(opts, opts.replace(batch_size=300)) == {("adam", "batch_size"), ("polish", "batch_size")}


@pytest.mark.parametrize("call", [
    lambda: FitOptions().replace(learning_rate=1e-3),
    lambda: resolve_options("best", learning_rate=1e-3),
    lambda: lcs_cvx.RECIPES["paper"].replace(lr=1e-3, learning_rate=1e-3),
])
def test_unknown_keyword_is_named_with_the_valid_ones(call):
    with pytest.raises(LCSInputError, match=r"unknown option\(s\) \['learning_rate'\]; valid options are") as info:
        call()
    assert all(repr(k) in str(info.value) for k in FLAT_OPTIONS)


def test_a_misspelt_keyword_gets_the_nearest_valid_one():
    with pytest.raises(LCSInputError, match=r"unknown option\(s\) \['iteration'\]; valid options are .*; "
                                            r"did you mean 'iterations' for 'iteration'\?$"):
        resolve_options("best", iteration=10)


def test_recipes_are_read_only_and_options_do_not_import_recipes():
    with pytest.raises(TypeError):
        lcs_cvx.RECIPES["paper"] = FitOptions()  # type: ignore[index]
    with pytest.raises(TypeError):
        lcs_cvx.train.recipes.RECIPE_VERSIONS["best"] = 1  # type: ignore[index]
    with open(lcs_cvx.train.options.__file__) as f:
        tree = ast.parse(f.read())
    imported = [n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    imported += [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    assert not any("recipes" in (m or "") for m in imported), imported


def test_the_recommended_recipe_is_the_default(small):
    """Without ``options`` or ``recipe`` an LCS trained by Adam gets ``"best"`` (the recipe's
    options, the call's overrides on top); ``"plain"`` names FitOptions' own defaults, which a
    second-order optimiser keeps as its default."""
    _, train, _ = small
    kw = {"iterations": 20, "refine_iterations": 1, "prune_batch": 100, "refine_batch": 100, "progress": False}
    default = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), train, **kw)
    assert default.settings == resolve_options("best", keep_best=False, **{k: v for k, v in kw.items() if k != "progress"})
    assert lcs_cvx.train.DEFAULT_RECIPE == "best" and default.settings.recipe == "best"
    plain = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), train, recipe="plain", iterations=20, progress=False)
    assert plain.settings == resolve_options(iterations=20, keep_best=False) and plain.settings.recipe is None
    gn = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), train, optimizer="gauss-newton", iterations=2, progress=False)
    assert gn.settings.recipe is None and gn.settings.optimizer == "gauss-newton"
    # the prediction loss takes the recipe without its violation-only parts
    pred = resolve_options("best", loss="prediction")
    assert pred.refine.method is None and pred.adam.extra_units == 0 and pred.adam.lr == 1e-2
