"""lcs_cvx.plot: each figure written as a PNG and opened again (its size, not blank), the
axes a caller gives drawn on, bad input named; the CLI's --plots."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import lcs_cvx
from lcs_cvx import LCSInputError, plot

image = pytest.importorskip("matplotlib.image")
figure = pytest.importorskip("matplotlib.figure")


def truth_runs(k=6, T=30, seed=1):
    truth = lcs_cvx.random_lcs(2, 1, 2, seed=0)
    g = torch.Generator().manual_seed(seed)
    us = [torch.randn(T, 1, generator=g, dtype=torch.float64) for _ in range(k)]
    xs = [truth.rollout(torch.randn(2, generator=g, dtype=torch.float64), u) for u in us]
    return truth, lcs_cvx.Trajectories(xs, us, names=["p [m]", "v [m/s]"])


@pytest.fixture(scope="module")
def fitted():
    _, runs = truth_runs()
    model = lcs_cvx.LCS(2, 1, 2, seed=3)
    result = lcs_cvx.fit(model, runs, recipe="plain", iterations=200, eval_every=40, rollout_iterations=40,
                         progress=False)
    return model, runs, result


def opened(path, min_size=(300, 200)):
    """The PNG at ``path`` as pixels: at least ``min_size`` (w, h) and not one colour."""
    px = image.imread(path)
    assert px.shape[1] >= min_size[0] and px.shape[0] >= min_size[1], px.shape
    assert np.unique(px.reshape(-1, px.shape[-1]), axis=0).shape[0] > 20  # lines and text, not blank
    return px


def test_the_three_plots_and_the_fit_shortcut_write_pngs(fitted, tmp_path):
    model, runs, result = fitted
    figs = {"history": result.plot(path=tmp_path / "history.png"),
            "rollouts": plot.rollouts(model, runs, horizon=10, path=tmp_path / "rollouts.png"),
            "modes": plot.modes(model, runs, path=tmp_path / "modes.png")}
    for name, fig in figs.items():
        assert isinstance(fig, figure.Figure), name
        opened(tmp_path / f"{name}.png")
    # the rollouts' panels carry the data's names; the history marks the kept iterate
    assert [ax.get_ylabel() for ax in figs["rollouts"].axes] == ["p [m]", "v [m/s]"]
    labels = [t.get_text() for t in figs["history"].axes[0].get_legend().get_texts()]
    assert "kept iterate" in labels and any("held-out score" in s for s in labels)
    assert "distinct modes" in figs["modes"].axes[0].get_title()
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.MonkeyPatch.context() as mp:  # without a path nothing is written, not even in the cwd
        mp.chdir(tmp_path)
        assert isinstance(plot.history(result), figure.Figure)
        plot.rollouts(model, runs)
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_a_plot_draws_on_the_axes_it_is_given(fitted):
    model, runs, _ = fitted
    fig = figure.Figure()
    axes = fig.subplots(2, 1)
    assert plot.rollouts(model, runs, coordinates=["p [m]", 1], axes=axes, baselines={}) is fig
    assert len(axes[0].lines) == 2  # recorded and the model: no baseline asked for
    with pytest.raises(LCSInputError, match=r"axes: expected 1 matplotlib Axes, received 2"):
        plot.rollouts(model, runs, coordinates=[0], axes=axes)


def test_the_rollouts_are_the_models_own(fitted):
    """Over the whole run, the model's line is its rollout from the recorded first state."""
    model, runs, _ = fitted
    fig = plot.rollouts(model, runs, run=2, baselines=())
    drawn = fig.axes[1].lines[1].get_ydata()
    with torch.no_grad():
        want = model.rollout(runs.xs[2][0], runs.us[2])[:, 1].numpy()
    assert np.abs(drawn - want).max() <= 1e-12


def test_a_c3_plan_is_drawn_against_the_models_rollout(fitted, tmp_path):
    model, _, _ = fitted
    ctrl = lcs_cvx.control.C3(model, horizon=5, Q=np.eye(2), R=np.eye(1))
    p = ctrl.solve(np.array([0.5, -0.2]))
    fig = plot.plan(p, path=tmp_path / "plan.png")
    opened(tmp_path / "plan.png")
    assert len(fig.axes) == 3 and "gap" in fig.axes[0].get_title()


def test_bad_input_is_named(fitted):
    model, runs, _ = fitted
    with pytest.raises(LCSInputError, match=r"coordinates: expected a state index or one of the data's names"):
        plot.rollouts(model, runs, coordinates=["z"])
    with pytest.raises(LCSInputError, match=r"run: expected an index in \[0, 6\), received 6"):
        plot.rollouts(model, runs, run=6)
    with pytest.raises(LCSInputError, match=r"horizon: expected None or an integer >= 1, received 0"):
        plot.rollouts(model, runs, horizon=0)
    with pytest.raises(LCSInputError, match=r"baselines: expected 'affine', models with a step"):
        plot.rollouts(model, runs, baselines=("mlp",))
    with pytest.raises(LCSInputError, match=r"result: expected an lcs_cvx.FitResult"):
        plot.history("result")
    with pytest.raises(LCSInputError, match=r"plan: expected an lcs_cvx.control.Plan, received str"):
        plot.plan("plan")


def test_the_cli_writes_the_plots(tmp_path, capsys):
    from lcs_cvx.cli import main

    _, runs = truth_runs()
    runs.save(tmp_path / "runs.npz")
    out = tmp_path / "plots"
    assert main(["fit", "--data", str(tmp_path / "runs.npz"), "--n-lam", "2", "--recipe", "plain", "--iterations",
                 "40", "--out", str(tmp_path / "m.npz"), "--plots", str(out)]) == 0
    assert f"plots: {out / 'history.png'}, {out / 'rollouts.png'}, {out / 'modes.png'}" in capsys.readouterr().out
    for name in ("history", "rollouts", "modes"):
        opened(out / f"{name}.png")
    assert main(["predict", "--model", str(tmp_path / "m.npz"), "--data", str(tmp_path / "runs.npz"),
                 "--plots", str(tmp_path / "again")]) == 0
    assert sorted(p.name for p in (tmp_path / "again").iterdir()) == ["modes.png", "rollouts.png"]
