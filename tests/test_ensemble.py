"""Ensembles (lcs_cvx.stacked, lcs_cvx.fit_ensemble): K models in one batched loop, each with
the numbers of its own run -- bit for bit on CPU tensors (the NumPy kernels), to round-off on the
torch kernels."""

from __future__ import annotations

import copy
import warnings

import pytest
import torch

import lcs_cvx
from lcs_cvx import LCSInputError
from lcs_cvx.losses import prediction_fast, regularizer, violation_fast
from lcs_cvx.stacked import StackedLCS, prediction_losses, violation_losses
from lcs_cvx.system import PARAMETER_NAMES

F64 = torch.float64
GAMMA, EPS = 5e-3, 2e-4


def _cells(K, n_lam, n=400, n_x=5, n_u=2, seed=0):
    """``K`` cells of their own: truth, noisy training set, noiseless test set, learner."""
    out = []
    for k in range(K):
        truth = lcs_cvx.random_lcs(n_x, n_u, n_lam, stiffness=0.5, seed=seed + 10 * k)
        out.append((lcs_cvx.make_dataset(truth, n, noise=0.01, seed=seed + 10 * k + 1),
                    lcs_cvx.make_dataset(truth, 100, seed=seed + 10 * k + 2),
                    lcs_cvx.LCS(n_x, n_u, n_lam, stiffness=1.0, init_scale=0.3, seed=seed + 10 * k + 3)))
    return out


def _stack(cells, B, offset=0):
    """Each cell's samples ``offset:offset + B`` as ``(K, B, .)`` tensors."""
    return [torch.stack([getattr(c[0], f)[offset:offset + B] for c in cells]) for f in ("x", "u", "x_next")]


def _grads(params):
    return [None if p.grad is None else p.grad.clone() for p in params]


@pytest.mark.parametrize("loss", ["violation", "prediction"])
@pytest.mark.parametrize("n_lam", [1, 4, 10])
@pytest.mark.parametrize("arrays", ["numpy", "torch"])
def test_stacked_losses_are_each_models_own(loss, n_lam, arrays):
    """Model k's value, gradient and active sets are those of its own fast loss on its own
    minibatch: bit for bit with the NumPy kernels, to round-off with the torch kernels. Half
    of the models start from a warm start (the active sets of a first call), half cold."""
    K, B = 4, 60
    cells = _cells(K, n_lam)
    x, u, xn = _stack(cells, B)
    ens = StackedLCS([c[2] for c in cells])
    kw = {"gamma": GAMMA, "eps": EPS} if loss == "violation" else {}
    stacked_fn, own_fn = ((violation_losses, violation_fast) if loss == "violation"
                          else (prediction_losses, prediction_fast))
    first = stacked_fn(ens, x, u, xn, arrays=arrays, **kw)
    warm = torch.tensor([True, False, True, False])
    info = stacked_fn(ens, x, u, xn, warm_start=first.active, warm=warm, arrays=arrays, **kw)
    (info.loss + 1e-5 * (ens.C**2).sum((1, 2))).sum().backward()  # the sum of the models' objectives
    assert info.loss.shape == (K,) and info.n_fallback == [0] * K
    exact = arrays == "numpy"
    for k, (_, _, model) in enumerate(cells):
        own = own_fn(model, x[k], u[k], xn[k], warm_start=first.active[k] if warm[k] else None,
                     arrays=arrays, **kw)
        (own.loss + regularizer(model, 1e-5)).backward()
        assert torch.equal(info.active[k], own.active)
        if exact:
            assert torch.equal(info.loss[k], own.loss)
        else:
            torch.testing.assert_close(info.loss[k], own.loss, rtol=1e-12, atol=0.0)
        for name in PARAMETER_NAMES:
            g, g_own = getattr(ens, name).grad[k], getattr(model, name).grad
            if exact:
                assert torch.equal(g, g_own), name
            else:
                # the violation gradients carry w / (gamma eps B): round-off of w times ~1e6
                torch.testing.assert_close(g, g_own, rtol=1e-7, atol=1e-9 * float(g_own.abs().max()))


@pytest.mark.parametrize("loss", ["violation", "prediction"])
def test_stacked_fallbacks_are_each_models_own(loss, monkeypatch):
    """With no pivoting sweeps allowed, the samples whose first guess is wrong fall back to the
    reference solver model by model: the same answers, counts and warnings as each model's own
    call."""
    monkeypatch.setattr(lcs_cvx.losses, "MAX_ITER", 0)
    cells = _cells(3, 5)  # (at n_lam = 3 the cold guess is right on every sample of a model)
    x, u, xn = _stack(cells, 40)
    ens = StackedLCS([c[2] for c in cells])
    kw = {"gamma": GAMMA, "eps": EPS} if loss == "violation" else {}
    stacked_fn, own_fn = ((violation_losses, violation_fast) if loss == "violation"
                          else (prediction_losses, prediction_fast))
    with pytest.warns(lcs_cvx.FallbackWarning) as caught_stacked:
        info = stacked_fn(ens, x, u, xn, **kw)
    messages = []
    for k, (_, _, model) in enumerate(cells):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            own = own_fn(model, x[k], u[k], xn[k], **kw)
        messages += [str(w.message) for w in caught]
        assert own.n_fallback > 0 and info.n_fallback[k] == own.n_fallback
        assert info.fallback_residual[k] == own.fallback_residual
        torch.testing.assert_close(info.loss[k], own.loss, rtol=1e-12, atol=0.0)
        assert torch.equal(info.active[k], own.active)
    assert sorted(str(w.message) for w in caught_stacked) == sorted(messages)


def test_ensemble_stacks_and_checks_its_models():
    models = [lcs_cvx.LCS(3, 1, 2, seed=k) for k in range(3)]
    ens = StackedLCS(models)
    assert len(ens) == 3 and ens.A.shape == (3, 3, 3) and ens.c.shape == (3, 2)
    for k, m in enumerate(models):
        assert torch.equal(ens.F[k], m.F.detach())
    other = ens.copy_to(2, lcs_cvx.LCS(3, 1, 2, seed=9))
    assert all(torch.equal(getattr(other, n), getattr(models[2], n)) for n in PARAMETER_NAMES)
    sub = ens.select([2, 0])
    assert torch.equal(sub.G[0], ens.G[2]) and torch.equal(sub.stiffness, ens.stiffness[[2, 0]])
    with pytest.raises(LCSInputError, match=r"models\[1\]: expected \(n_x, n_u, n_lam, dtype, device\)"):
        StackedLCS([models[0], lcs_cvx.LCS(3, 1, 3)])
    with pytest.raises(LCSInputError, match=r"models\[1\]: expected an lcs_cvx.LCS, received str"):
        StackedLCS([models[0], "model"])
    with pytest.raises(LCSInputError, match=r"models: expected a non-empty list"):
        StackedLCS([])
    with pytest.raises(LCSInputError, match=r"models\[1\]: expected a model without masks"):
        StackedLCS([models[0], lcs_cvx.LCS(3, 1, 2).mask(A=torch.eye(3, dtype=torch.bool))])
    fixed = lcs_cvx.LCS(3, 1, 2)
    fixed.A.requires_grad_(False)
    with pytest.raises(LCSInputError, match=r"models\[1\]: expected the fixed parameters of models\[0\] \(\[\]\), received \['A'\]"):
        StackedLCS([models[0], fixed])


def _fit_both(cells, seeds, **options):
    """``fit_ensemble`` on copies of the cells' learners, and ``fit`` on each alone."""
    ens_models = [copy.deepcopy(c[2]) for c in cells]
    own_models = [copy.deepcopy(c[2]) for c in cells]
    trains, tests = [c[0] for c in cells], [c[1] for c in cells]
    stacked = lcs_cvx.fit_ensemble(ens_models, trains, tests=tests, seeds=seeds, progress=False, **options)
    own = [lcs_cvx.fit(m, trains[k], test=tests[k], seed=seeds[k], progress=False, **options)
           for k, m in enumerate(own_models)]
    return stacked, own


def _strip(history):
    return [{k: v for k, v in h.items() if k != "wall_time"} for h in history]


@pytest.mark.parametrize(
    "options",
    [
        {"recipe": "paper", "loss": "violation", "lr": 5e-3, "gamma": GAMMA, "eps": EPS},
        {"recipe": "paper", "loss": "prediction", "lr": 1e-3},
        {"recipe": "plain", "loss": "violation", "lr_schedule": "cosine", "lr": 1e-2, "eps_start": 1e-2},
    ],
    ids=["paper-violation", "paper-prediction", "normalised-schedules"],
)
def test_fit_ensemble_is_fit_model_by_model(options):
    """Every model's history (losses, e_test, fallbacks) and final parameters are those of its
    own ``fit`` with the same options and seed, bit for bit -- over several epochs, so that warm
    starts, fresh permutations and (third case) normalisation and the schedules are all
    exercised."""
    cells = _cells(3, 3, n=300)
    stacked, own = _fit_both(cells, [7, 8, 9], iterations=40, batch_size=50, eval_every=10, **options)
    for r_stacked, r_own in zip(stacked, own, strict=True):
        assert _strip(r_stacked.history) == _strip(r_own.history)
        assert len(r_own.history) == 4 and r_stacked.settings == r_own.settings
        for name in PARAMETER_NAMES:
            assert torch.equal(getattr(r_stacked.model, name), getattr(r_own.model, name)), name
        assert (r_stacked.scaling is None) == (r_own.scaling is None)


def test_fit_ensemble_on_the_torch_kernels_agrees_to_round_off(monkeypatch):
    """The torch kernels (the CUDA path, here on CPU tensors) give each model its own run's
    numbers to round-off amplified by a short training."""
    import lcs_cvx.stacked as ensemble_module

    def with_torch(fn):
        return lambda *a, **kw: fn(*a, **{**kw, "arrays": "torch"})

    cells = _cells(2, 4, n=200)
    options = {"recipe": "paper", "loss": "violation", "lr": 5e-3, "gamma": GAMMA, "eps": EPS,
               "iterations": 20, "batch_size": 50, "eval_every": 10}
    monkeypatch.setattr("lcs_cvx.train.ensemble.violation_losses", with_torch(ensemble_module.violation_losses))
    stacked, own = _fit_both(cells, [1, 2], **options)
    for r_stacked, r_own in zip(stacked, own, strict=True):
        for a, b in zip(r_stacked.history, r_own.history, strict=True):
            assert a["loss"] == pytest.approx(b["loss"], rel=1e-9)
            assert a["e_test"] == pytest.approx(b["e_test"], rel=1e-7)


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")
def test_a_diverging_model_leaves_the_ensemble():
    """With ``throw=False`` a model whose training diverges gets its error as its result and the
    others go on, each still equal to its own run; with ``throw=True`` the error is raised."""
    cells = _cells(3, 2, n=200)
    blown = cells[1][0]  # inputs of 1e200: the loss overflows at once
    cells[1] = (lcs_cvx.Dataset(blown.x * 1e200, blown.u, blown.x_next), cells[1][1], cells[1][2])
    options = {"recipe": "paper", "iterations": 20, "batch_size": 50, "eval_every": 10}
    models = [copy.deepcopy(c[2]) for c in cells]
    results = lcs_cvx.fit_ensemble(models, [c[0] for c in cells], tests=[c[1] for c in cells],
                                   seeds=[0, 1, 2], throw=False, progress=False, **options)
    assert isinstance(results[1], lcs_cvx.SolverError)
    assert "models[1]: training diverged at iteration 1" in str(results[1])
    with pytest.raises(lcs_cvx.SolverError, match=r"training diverged at iteration 1"):
        lcs_cvx.fit(copy.deepcopy(cells[1][2]), cells[1][0], progress=False, seed=1, **options)
    for k in (0, 2):
        own = lcs_cvx.fit(copy.deepcopy(cells[k][2]), cells[k][0], test=cells[k][1], seed=k,
                          progress=False, **options)
        assert _strip(results[k].history) == _strip(own.history)
    with pytest.raises(lcs_cvx.SolverError, match=r"models\[1\]: training diverged"):
        lcs_cvx.fit_ensemble([copy.deepcopy(c[2]) for c in cells], [c[0] for c in cells],
                             progress=False, **options)


def test_fit_ensemble_refuses_what_it_does_not_run():
    cells = _cells(2, 2, n=100)
    models, trains = [c[2] for c in cells], [c[0] for c in cells]
    with pytest.raises(LCSInputError, match=r"extra_units: fit_ensemble runs the Adam phase only; expected 0"):
        lcs_cvx.fit_ensemble(models, trains, recipe="best", progress=False)
    with pytest.raises(LCSInputError, match=r"refine: .*expected None, received 'gauss-newton'"):
        lcs_cvx.fit_ensemble(models, trains, refine="gauss-newton", progress=False)
    with pytest.raises(LCSInputError, match=r"polish_iterations: .*expected 0, received 5"):
        lcs_cvx.fit_ensemble(models, trains, polish_iterations=5, progress=False)
    with pytest.raises(LCSInputError, match=r"keep_best: .*expected False, received True"):
        lcs_cvx.fit_ensemble(models, trains, tests=trains, keep_best=True, progress=False)
    with pytest.raises(LCSInputError, match=r"tests: expected one per model \(2\), received 1"):
        lcs_cvx.fit_ensemble(models, trains, tests=trains[:1], progress=False)
    with pytest.raises(LCSInputError, match=r"trains: expected the same minibatch size .*\[50, 100\]"):
        lcs_cvx.fit_ensemble(models, [trains[0], lcs_cvx.Dataset(*(getattr(trains[1], f)[:50] for f in ("x", "u", "x_next")))],
                             batch_size=200, progress=False)
    with pytest.raises(LCSInputError, match=r"models: expected at least one"):
        lcs_cvx.fit_ensemble([], [], progress=False)
    with pytest.raises(LCSInputError, match=r"trains\[1\]: expected an lcs_cvx.Dataset"):
        lcs_cvx.fit_ensemble(models, [trains[0], "data"], progress=False)


@pytest.mark.parametrize("options", [{"recipe": "paper", "lr": 5e-3}, {"recipe": "plain", "keep_best": True}],
                         ids=["paper", "normalised-keep-best"])
def test_fit_restarts_together_are_the_restarts_one_after_another(options, tmp_path):
    """``fit(restarts=3, ensemble=True)`` trains the restarts in one batched loop: the same
    model, history, held-out scores and settings as one after the other; its checkpoint, written
    at the end, resumes to the same result."""
    train, test, model = _cells(1, 3, n=300)[0]
    kw = {"restarts": 3, "iterations": 30, "batch_size": 50, "eval_every": 10, "seed": 4,
          "progress": False, **options}
    one_by_one = lcs_cvx.fit(copy.deepcopy(model), train, test=test, **kw)
    ckpt = tmp_path / "run.ckpt"
    together = lcs_cvx.fit(copy.deepcopy(model), train, test=test, ensemble=True, checkpoint=ckpt, **kw)
    assert _strip(together.history) == _strip(one_by_one.history) and len(together.history) == 9
    assert together.restart_scores == one_by_one.restart_scores and together.settings == one_by_one.settings
    for name in PARAMETER_NAMES:
        assert torch.equal(getattr(together.model, name), getattr(one_by_one.model, name)), name
    again = lcs_cvx.fit(copy.deepcopy(model), train, test=test, ensemble=True, checkpoint=ckpt,
                        resume=True, **kw)
    assert _strip(again.history) == _strip(together.history)
    assert torch.equal(again.model.G, together.model.G)


def test_fit_restarts_together_refuse_what_they_do_not_run():
    train, _, model = _cells(1, 2, n=100)[0]
    with pytest.raises(LCSInputError, match=r"callbacks: expected none with ensemble=True"):
        lcs_cvx.fit(model, train, recipe="plain", restarts=2, ensemble=True, callbacks=[lambda rec, m: None], progress=False)
    with pytest.raises(LCSInputError, match=r"extra_units: fit_ensemble runs the Adam phase only"):
        lcs_cvx.fit(model, train, recipe="best", restarts=2, restart_tolerance=None, ensemble=True, progress=False)
