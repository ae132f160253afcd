"""fit on trajectories (lcs_cvx.train.holdout and the simulation-error phase): whole trajectories
held out, the held-out scores of the LCS and of the affine map on the same split, the affine map
returned on request, rollout scores and early stopping on them, the simulation-error phase
(it lowers its loss; a killed run resumes exactly), select_n_lam on trajectories, and the named
errors of bad input."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from helpers import simulated_runs

import lcs_cvx
from lcs_cvx.metrics import affine_lstsq
from lcs_cvx.scaling import Scaling
from lcs_cvx.simulation_error import change_error, rollout_growth
from lcs_cvx.train.holdout import split_data
from lcs_cvx.train.phase_options import RunOptions


def make_trajectories(truth, K, T, seed=0, noise=0.0):
    return simulated_runs(truth, [T] * K, seed=seed, noise=noise, x_range=5.0, u_range=3.0)


@pytest.fixture(scope="module")
def truth():
    return lcs_cvx.random_lcs(2, 1, 2, seed=0)


@pytest.fixture(scope="module")
def data(truth):
    return make_trajectories(truth, 10, 25, seed=1)


def fit(data, seed=3, **kw):
    model = lcs_cvx.LCS(2, 1, 2, seed=seed)
    return model, lcs_cvx.fit(model, data, progress=False, **{"recipe": "plain", "iterations": 200, "rollout_iterations": 30, **kw})


def test_whole_trajectories_are_held_out(data):
    split = split_data(data, None, RunOptions(holdout=0.3, seed=2), None)
    assert isinstance(split.holdout, lcs_cvx.Trajectories)
    assert len(split.trajectories) == 7 and len(split.holdout) == 3
    firsts = {tuple(x[0].tolist()) for x in data.xs}
    train_firsts = {tuple(x[0].tolist()) for x in split.trajectories.xs}
    held_firsts = {tuple(x[0].tolist()) for x in split.holdout.xs}
    assert train_firsts | held_firsts == firsts and not train_firsts & held_firsts
    assert len(split.fit) == sum(split.trajectories.lengths)  # trains on the kept trajectories only


def test_heldout_scores_of_the_lcs_and_of_the_affine_map(data):
    """On held-out runs both are scored by the rollout error relative to the recorded change,
    each coordinate scaled by the spread of its one-step change on the training runs."""
    model, result = fit(data, holdout_horizon=5, holdout=0.3)
    split = split_data(data, None, RunOptions(holdout=0.3), None)
    scale = Scaling.fit(split.fit).sy
    assert result.heldout_error == pytest.approx(change_error(model, split.holdout, 5, scale), rel=1e-12)
    affine = affine_lstsq(split.fit)
    assert result.affine_heldout_error == pytest.approx(change_error(affine, split.holdout, 5, scale), rel=1e-12)
    assert result.heldout_score == "5-step rollout error relative to the recorded change"
    assert result.heldout_growth == pytest.approx(rollout_growth(model, split.holdout), rel=1e-12)
    assert result.beats_affine == (result.heldout_error < result.affine_heldout_error)
    assert "5-step rollout error" in result.verdict and f"{result.heldout_error:.4g}" in result.verdict


def test_the_judgement_shows_the_affine_maps_growth_and_the_per_run_spread(data):
    """Beside the scores: the affine map's rollout growth on the same held-out runs, and each
    held-out run's score alone (of the LCS and of the affine map), their range in the verdict."""
    model, result = fit(data, holdout_horizon=5, holdout=0.3)
    split = split_data(data, None, RunOptions(holdout=0.3), None)
    affine = affine_lstsq(split.fit)
    assert result.affine_heldout_growth == pytest.approx(rollout_growth(affine, split.holdout), rel=1e-12)
    runs = [lcs_cvx.Trajectories([x], [u]) for x, u in zip(split.holdout.xs, split.holdout.us, strict=True)]
    assert len(runs) == 3
    assert result.heldout_run_errors == pytest.approx([change_error(model, r, 5, split.scale) for r in runs],
                                                      rel=1e-12)
    assert result.affine_heldout_run_errors == pytest.approx(
        [change_error(affine, r, 5, split.scale) for r in runs], rel=1e-12)
    lo, hi = min(result.heldout_run_errors), max(result.heldout_run_errors)
    assert f"(per-run range {lo:.3g}-{hi:.3g})" in result.verdict
    assert len(result.verdict.splitlines()) == 5  # one item per line
    assert f"affine {result.affine_heldout_growth:.3g}" in result.verdict
    # one held-out run: no spread to show
    one = split_data(lcs_cvx.Trajectories(data.xs[:4], data.us[:4]), None, RunOptions(holdout=0.1), None)
    assert len(one.holdout) == 1 and one.run_scores(model) is None


@pytest.mark.parametrize(("count", "holdout", "held"), [
    (2, 0.1, 1), (3, 0.1, 1), (4, 0.1, 1), (4, 0.5, 2), (5, 0.1, 2), (10, 0.1, 2), (19, 0.1, 2),
    (25, 0.1, 2), (26, 0.1, 3), (10, 0.3, 3), (10, 0.95, 9)])
def test_at_least_two_runs_are_held_out_of_five_or_more(data, truth, count, holdout, held):
    """A score on one held-out run is that run's noise: of five or more runs at least two are
    held out; of two to four, one (before, the default holdout of 0.1 raised a 'frac' error on
    two to four runs); always one left to train on."""
    runs = data if count == 10 else make_trajectories(truth, count, 25, seed=1)
    split = split_data(runs, None, RunOptions(holdout=holdout), None)
    assert (len(split.trajectories), len(split.holdout)) == (count - held, held)


def test_a_model_whose_rollouts_grow_more_is_never_better(data):
    """A lower held-out error does not make the LCS better when its held-out rollouts grow past
    GROWTH_SLACK times the larger of the data's (1) and the affine map's growth; NaN growth
    counts as growing."""
    from lcs_cvx.train.result import GROWTH_SLACK

    _, result = fit(data, iterations=20, rollout_horizon=None)
    lower = dataclasses.replace(result, heldout_error=0.5 * result.affine_heldout_error, affine_heldout_growth=1.2)
    assert lower.beats_affine and not lower.grows_more
    assert "the LCS is better" in dataclasses.replace(lower, heldout_growth=GROWTH_SLACK * 1.2).verdict
    grown = dataclasses.replace(lower, heldout_growth=GROWTH_SLACK * 1.2 * 1.01)
    assert grown.grows_more and grown.beats_affine is False
    assert "NOT better than the affine map (lower error, but its rollouts leave the data's range)" in grown.verdict
    # the data's own growth (1) is the floor of the reference: an affine map that shrinks does not tighten it
    shrinking = dataclasses.replace(lower, affine_heldout_growth=0.5, heldout_growth=1.4)
    assert shrinking.beats_affine
    assert dataclasses.replace(lower, heldout_growth=math.nan).beats_affine is False
    # a diverging affine map licenses nothing: the data's own range is the reference then
    assert dataclasses.replace(lower, affine_heldout_growth=math.inf, heldout_growth=1.4).beats_affine
    assert dataclasses.replace(lower, affine_heldout_growth=math.inf, heldout_growth=2.0).grows_more


def test_choices_never_keep_a_model_whose_rollouts_leave_the_data_range(truth, data, monkeypatch):
    """The choice score is the held-out score where the held-out rollouts stay within the growth
    bound (the verdict's rule) and inf past it; keep_best and the restarts then never return an
    iterate that grows past it when an earlier one did not."""
    from lcs_cvx.train.holdout import Split
    from lcs_cvx.train.result import GROWTH_SLACK

    split = split_data(data, None, RunOptions(), "auto")
    assert split.growth_bound == GROWTH_SLACK * max(1.0, split.affine_growth())
    stable = lcs_cvx.random_lcs(2, 1, 2, seed=0)
    assert split.choice_score(stable) == split.score(stable) < math.inf
    exploding = lcs_cvx.random_lcs(2, 1, 2, seed=0)
    with torch.no_grad():
        exploding.A.mul_(3.0)
    assert split.growth(exploding) > split.growth_bound and math.isfinite(split.score(exploding))
    assert split.choice_score(exploding) == math.inf
    # every iterate after the first grows (a stand-in growth): the start is kept, and reported as such
    calls = []
    real = Split.growth

    def growth(self, model):
        calls.append(1)
        return real(self, model) if len(calls) == 1 else 100.0

    monkeypatch.setattr(Split, "growth", growth)
    model = lcs_cvx.random_lcs(2, 1, 2, seed=0).requires_grad_(True)
    with torch.no_grad():
        model.A.add_(0.01)  # a start training improves on
    start = {k: v.detach().clone() for k, v in model.state_dict().items()}
    result = lcs_cvx.fit(model, data, recipe="plain", init="model", normalize=False, iterations=30, eval_every=10,
                         rollout_horizon=None, holdout_horizon=4, progress=False)
    assert len(result.history) >= 3 and [h["heldout"] for h in result.history] == [math.inf] * len(result.history)
    for k, v in model.state_dict().items():
        assert torch.equal(v, start[k]), k


def test_affine_if_better_returns_the_affine_map_for_a_growing_model(data, monkeypatch):
    """The driver asks the same judgement: a model whose held-out rollouts grow past the slack
    (here made so by a stand-in growth of 100) is replaced by the affine map with
    ``affine_if_better``, however low its error."""
    from lcs_cvx.train.holdout import Split

    monkeypatch.setattr(Split, "growth", lambda self, model: 100.0)
    model, result = fit(data, iterations=200, affine_if_better=True)
    assert result.grows_more and result.returned_affine and torch.count_nonzero(model.C) == 0
    assert "DIVERGE" in result.verdict and "the affine map is returned" in result.verdict


def test_the_verdict_says_when_rollouts_diverge(data):
    _, result = fit(data, iterations=20, rollout_horizon=None)
    grown = dataclasses.replace(result, heldout_growth=math.inf)
    assert "(its open-loop rollouts DIVERGE)" in grown.verdict
    assert "DIVERGE" not in dataclasses.replace(result, heldout_growth=1.2).verdict


def test_affine_if_better_returns_the_affine_map_and_keeps_the_learned_model(data):
    """A run of two Adam steps leaves the LCS far above the affine map: with affine_if_better the
    returned model is the affine map (C = 0), scoring exactly its held-out error."""
    model, result = fit(data, iterations=2, affine_if_better=True)
    assert result.beats_affine is False and result.returned_affine
    assert torch.count_nonzero(model.C) == 0
    assert result.learned is not None and torch.count_nonzero(result.learned.C) > 0
    split = split_data(data, None, RunOptions(), None)
    assert change_error(model, split.holdout, split.horizon, split.scale) == pytest.approx(
        result.affine_heldout_error, rel=1e-10)
    assert "the affine map is returned" in result.verdict
    _, kept = fit(data, iterations=2)  # without the option: said, not done
    assert kept.beats_affine is False and not kept.returned_affine and kept.learned is None
    assert "affine_if_better=True" in kept.verdict


def test_a_dataset_keeps_its_old_behaviour(truth):
    """Transitions with one run: nothing held out, no comparison; the training is unchanged."""
    train = lcs_cvx.make_dataset(truth, 500, seed=1)
    _, result = fit(train)
    assert result.heldout_error is None and result.beats_affine is None
    assert result.verdict.startswith("no held-out data")


def test_validation_trajectories_replace_the_split(truth, data):
    val = make_trajectories(truth, 3, 25, seed=9)
    model, result = fit(data, validation=val, holdout_horizon=3)
    scale = Scaling.fit(data.to_transitions()).sy
    assert result.heldout_error == pytest.approx(change_error(model, val, 3, scale), rel=1e-12)


def test_keep_best_follows_the_heldout_score(data):
    model, result = fit(data, keep_best=True, holdout_horizon=4, eval_every=20, lr=3e-2)
    scores = [h["heldout"] for h in result.history]
    assert all(s is not None and math.isfinite(s) for s in scores)
    assert result.heldout_error == pytest.approx(min(scores), rel=1e-9)


def test_keep_best_is_on_by_default_where_trajectories_are_held_out(truth, data):
    _, runs = fit(data, holdout_horizon=4, iterations=40, eval_every=10, rollout_iterations=20)
    assert runs.settings.run.keep_best is True
    scores = [h["heldout"] for h in runs.history]
    assert all(s is not None for s in scores)
    assert runs.heldout_error <= min(scores) * (1 + 1e-9)  # the best iterate (or the start)
    _, off = fit(data, keep_best=False, iterations=20, eval_every=10, rollout_iterations=10)
    assert off.settings.run.keep_best is False and all(h["heldout"] is None for h in off.history)
    _, transitions = fit(lcs_cvx.make_dataset(truth, 300, seed=1), iterations=20, eval_every=10)
    assert transitions.settings.run.keep_best is False
    with pytest.raises(lcs_cvx.LCSInputError, match="keep_best: expected True, False or None"):
        fit(data, keep_best="yes")


def test_keep_best_returns_the_start_when_training_only_makes_it_worse(truth, data):
    """The start is a candidate: from the truth itself, steps of a huge learning rate only
    raise the held-out error, and the returned model is the start, bit for bit."""
    model = lcs_cvx.random_lcs(2, 1, 2, seed=0).requires_grad_(True)
    start = {k: v.detach().clone() for k, v in model.state_dict().items()}
    result = lcs_cvx.fit(model, data, recipe="plain", init="model", normalize=False, lr=0.5, iterations=30, eval_every=10,
                         rollout_horizon=None, holdout_horizon=4, progress=False)
    assert all(h["heldout"] > result.heldout_error for h in result.history)
    for k, v in model.state_dict().items():
        assert torch.equal(v, start[k]), k


def test_with_keep_best_the_simulation_error_phase_refines_the_best_iterate(truth):
    """The phase starts from the best iterate so far, not the last: with a vanishing step its
    first record scores as the best Adam record, which here is not the last one."""
    noisy = make_trajectories(truth, 10, 25, seed=1, noise=0.05)
    _, result = fit(noisy, seed=5, keep_best=True, holdout_horizon=4, eval_every=10, lr=2e-1, iterations=90,
                    rollout_horizon=5, rollout_iterations=20, rollout_lr=1e-12)
    adam = [h["heldout"] for h in result.history if h["phase"] == "adam"]
    rollout = [h["heldout"] for h in result.history if h["phase"] == "rollout"]
    assert adam[-1] > min(adam) * 1.01  # the last Adam iterate is not the best
    assert rollout[0] == pytest.approx(min(adam), rel=1e-6)
    assert result.heldout_error <= min(adam) * (1 + 1e-9)


def test_the_simulation_error_phase_runs_last_and_lowers_its_loss(truth):
    noisy = make_trajectories(truth, 10, 25, seed=1, noise=0.05)
    _, result = fit(noisy, rollout_horizon=5, rollout_iterations=120, eval_every=20, rollout_lr=3e-3)
    phases = [h["phase"] for h in result.history]
    assert phases[-6:] == ["rollout"] * 6 and "rollout" not in phases[:-6]
    losses = [h["loss"] for h in result.history if h["phase"] == "rollout"]
    assert losses[-1] < losses[0]


def test_the_phase_runs_by_default_on_trajectories_only(truth, data):
    _, runs = fit(data, iterations=20, eval_every=10, rollout_iterations=20)
    assert [h["phase"] for h in runs.history].count("rollout") == 2
    assert runs.refinement_kept is not None  # decided on the held-out runs
    _, transitions = fit(lcs_cvx.make_dataset(truth, 300, seed=1), iterations=20, eval_every=10)
    assert "rollout" not in [h["phase"] for h in transitions.history] and transitions.refinement_kept is None
    paper = lcs_cvx.RECIPES["paper"]
    assert paper.rollout.horizon is None  # the paper's protocol has no such phase
    with pytest.raises(lcs_cvx.LCSInputError, match="rollout_horizon: restarts trained together run the Adam phase only"):
        lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), data, recipe="plain", progress=False, restarts=2, ensemble=True, iterations=10)


def test_a_refinement_that_does_not_pay_is_undone(data):
    """A learning rate that wrecks the model: the held-out score rises, the model before the
    phase comes back, bit for bit the model of the same run without the phase."""
    model, result = fit(data, iterations=60, rollout_horizon=5, rollout_iterations=5, rollout_lr=5.0)
    assert result.refinement_kept is False
    assert [h["phase"] for h in result.history].count("rollout") == 1
    without, _ = fit(data, iterations=60, rollout_horizon=None)
    for name, p in without.named_parameters():
        assert torch.equal(p, getattr(model, name)), name


def test_a_stopped_simulation_error_phase_resumes_exactly(data, tmp_path):
    kw = dict(recipe="plain", iterations=40, eval_every=10, checkpoint_every=10, rollout_horizon=4,
              rollout_iterations=40)
    ckpt = tmp_path / "run.ckpt"
    stopped = lcs_cvx.LCS(2, 1, 2, seed=3)
    lcs_cvx.fit(stopped, data, progress=False, checkpoint=ckpt,
                callbacks=[lambda rec, m: rec["phase"] == "rollout" and rec["iteration"] == 60], **kw)
    resumed_model = lcs_cvx.LCS(2, 1, 2, seed=3)
    resumed = lcs_cvx.fit(resumed_model, data, progress=False, checkpoint=ckpt, resume=True, **kw)
    clean_model = lcs_cvx.LCS(2, 1, 2, seed=3)
    clean = lcs_cvx.fit(clean_model, data, progress=False, **kw)
    for name, p in clean_model.named_parameters():
        assert torch.equal(p, getattr(resumed_model, name)), name
    strip = lambda hist: [{k: v for k, v in h.items() if k != "wall_time"} for h in hist]  # noqa: E731
    assert strip(resumed.history) == strip(clean.history)


def test_select_n_lam_on_trajectories_scores_by_fit(data):
    sel = lcs_cvx.select_n_lam(data, [1, 2], recipe="plain", iterations=100, progress=False, holdout=0.3, holdout_horizon=3)
    for row in sel.table:
        assert row["validation_error"] == sel.results[row["n_lam"]].heldout_error
    assert "trajectories" in sel.validation


def test_select_n_lam_passes_over_a_candidate_whose_rollouts_grow_more(data, monkeypatch):
    """A candidate that grows past the bound is not chosen while another is not, however low its
    error; when every candidate grows, the errors alone choose (the verdicts say it)."""
    from lcs_cvx.train.result import FitResult

    kw = {"recipe": "plain", "iterations": 50, "progress": False, "holdout": 0.3, "holdout_horizon": 3,
          "tolerance": 1e9}
    assert lcs_cvx.select_n_lam(data, [1, 2], **kw).n_lam == 1  # the huge tolerance takes the smallest
    monkeypatch.setattr(FitResult, "grows_more", property(lambda self: self.model.n_lam == 1))
    sel = lcs_cvx.select_n_lam(data, [1, 2], **kw)
    assert sel.n_lam == 2 and [r["grows_more"] for r in sel.table] == [True, False]
    monkeypatch.setattr(FitResult, "grows_more", property(lambda self: True))
    assert lcs_cvx.select_n_lam(data, [1, 2], **kw).n_lam == 1


@pytest.mark.parametrize("kw, match", [
    ({"rollout_horizon": 3}, "rollout_horizon: the simulation-error phase rolls out windows of trajectories"),
    ({"holdout_horizon": 3}, "holdout_horizon: a rollout score needs held-out trajectories"),
])
def test_trajectory_options_with_transitions_are_named(truth, kw, match):
    with pytest.raises(lcs_cvx.LCSInputError, match=match):
        fit(lcs_cvx.make_dataset(truth, 100, seed=1), **kw)


def test_horizons_longer_than_the_trajectories_are_named(data):
    with pytest.raises(lcs_cvx.LCSInputError, match=r"rollout_horizon: expected at most 25 steps .* received 30"):
        fit(data, rollout_horizon=30)
    with pytest.raises(lcs_cvx.LCSInputError, match=r"holdout_horizon: expected at most 25 steps .* received 26"):
        fit(data, holdout_horizon=26)


def test_a_non_finite_log_entry_is_named_with_its_row():
    x = np.zeros((5, 2))
    x[3, 1] = np.nan
    with pytest.raises(lcs_cvx.LCSInputError, match=r"xs\[0\]: expected finite values, .* row 3, column 1"):
        lcs_cvx.Trajectories([x], [np.zeros((4, 1))])


def test_uneven_time_steps_are_reported(tmp_path):
    path = tmp_path / "log.csv"
    rows = ["trajectory,t,x_0,u_0"] + [f"a,{t},{i},0" for i, t in enumerate([0.0, 0.01, 0.02, 0.035, 0.045])]
    path.write_text("\n".join(rows) + "\n")
    with pytest.warns(UserWarning, match=r"time: trajectory 'a' .* uneven steps: from 0.01 to 0.015 \(spread 0.005"):
        tr = lcs_cvx.Trajectories.load(path, columns={"x": ["x_0"], "u": ["u_0"]}, time="t")
    assert tr.lengths == (4,)


@pytest.mark.parametrize("holdout_horizon, expected", [("auto", 10), (1, 10), (4, 4), (20, 20), (25, 25)])
def test_the_simulation_error_window_follows_a_named_holdout_horizon(data, holdout_horizon, expected):
    """rollout_horizon="auto": the held-out horizon where holdout_horizon names one (> 1), else
    10 steps; at most the longest training run (25 transitions here)."""
    split = split_data(data, None, RunOptions(holdout=0.3, holdout_horizon=holdout_horizon), "auto")
    assert split.rollout_horizon == min(expected, max(split.trajectories.lengths))
    assert max(split.trajectories.lengths) == 25
    assert split_data(data, None, RunOptions(holdout=0.3, holdout_horizon=holdout_horizon), 7).rollout_horizon == 7
