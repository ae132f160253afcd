"""Training on the model's device and dtype: every random draw of :mod:`lcs_cvx.train` (the
re-initialisation of saturated units, the extra units of :func:`lcs_cvx.resizing.add_units`, the
restarts' fresh models) is taken on the run's CPU generator in float64 -- the same numbers on every
device, CPU runs bit-identical to before -- and then moved to the parameter's device and dtype.

Every held-out score, the affine reference and the rollouts compute on the model's device
whatever the data's (a CUDA model with CPU data, or CUDA data with a default model). The CUDA
tests run where a GPU is present (skipped otherwise); the others run everywhere, with the meta
device standing in for a GPU.
"""

from __future__ import annotations

import math
import warnings

import pytest
import torch
from helpers import simulated_runs

import lcs_cvx
import lcs_cvx.train.phases as phases
from lcs_cvx.metrics import AffineMap, affine_lstsq
from lcs_cvx.simulation_error import affine_rollout_error
from lcs_cvx.system import PARAMETER_NAMES
from lcs_cvx.train.phases import draw

F64 = torch.float64

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")

#: ``recipe="best"`` cut down to a few seconds: every phase runs (Adam with re-initialisation,
#: extra units and pruning, the Gauss--Newton refinement, two restarts)
SHORT_BEST = {"recipe": "best", "iterations": 40, "reinit_every": 10, "prune_batch": 200,
              "refine_iterations": 2, "refine_batch": 200, "progress": False}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_draw_is_on_the_parameters_device_and_dtype(dtype):
    like = torch.zeros(3, 2, dtype=dtype)
    out = draw((4, 2), torch.Generator().manual_seed(5), like)
    assert out.shape == (4, 2) and out.dtype == dtype and out.device == like.device
    # the numbers of before (0.1 N(0, 1) drawn in float64 on the CPU generator): bit-identical
    expected = (0.1 * torch.randn((4, 2), generator=torch.Generator().manual_seed(5), dtype=F64)).to(dtype)
    assert torch.equal(out, expected)
    # another device: moved there (the meta device stands in for a GPU on any machine)
    meta = draw((4, 2), torch.Generator().manual_seed(5), torch.empty(1, dtype=dtype, device="meta"))
    assert meta.device.type == "meta" and meta.dtype == dtype and meta.shape == (4, 2)
    assert torch.equal(draw((3,), torch.Generator().manual_seed(1), like, scale=2.0),
                       (2.0 * torch.randn(3, generator=torch.Generator().manual_seed(1), dtype=F64)).to(dtype))


def _saturated_start(device: str | torch.device, dtype: torch.dtype) -> lcs_cvx.LCS:
    model = lcs_cvx.LCS(2, 1, 2, seed=3, dtype=dtype).to(device)
    with torch.no_grad():
        model.c[0] = -1e3  # unit 0 active on every sample: saturated, so it is re-drawn
    return model


def _spy_reinit(monkeypatch) -> list[bool]:
    """Record, for each call of ``reinit_saturated``, whether it changed the model."""
    changed: list[bool] = []
    real = phases.reinit_saturated

    def spy(state):
        before = [getattr(state.work, k).detach().clone() for k in "CDEc"]
        real(state)
        after = [getattr(state.work, k).detach() for k in "CDEc"]
        assert all(a.device == b.device and a.dtype == b.dtype for a, b in zip(before, after, strict=True))
        changed.append(any(not torch.equal(a, b) for a, b in zip(before, after, strict=True)))

    monkeypatch.setattr(phases, "reinit_saturated", spy)
    return changed


def test_best_recipe_in_float32_redraws_in_the_models_dtype(monkeypatch):
    truth = lcs_cvx.random_lcs(2, 1, 2, seed=0)
    train = lcs_cvx.make_dataset(truth, 600, seed=1)
    changed = _spy_reinit(monkeypatch)
    model = _saturated_start("cpu", torch.float32)
    with warnings.catch_warnings():  # float32 pivoting may miss PIVOT_TOL on a few samples
        warnings.simplefilter("ignore", lcs_cvx.FallbackWarning)
        lcs_cvx.fit(model, train, **SHORT_BEST, restarts=1, init="model")
    assert True in changed  # a unit was re-drawn
    assert all(getattr(model, k).dtype == torch.float32 for k in PARAMETER_NAMES)
    assert all(bool(torch.isfinite(getattr(model, k)).all()) for k in PARAMETER_NAMES)


@needs_cuda
def test_best_recipe_runs_on_cuda(monkeypatch):
    """``fit(recipe="best")`` of a model on the GPU, data on the CPU (moved by ``fit``): every
    phase runs, a saturated unit is re-drawn, and the model stays on its device."""
    truth = lcs_cvx.random_lcs(2, 1, 2, seed=0)
    train = lcs_cvx.make_dataset(truth, 600, seed=1)
    test = lcs_cvx.make_dataset(truth, 200, seed=2)
    changed = _spy_reinit(monkeypatch)
    model = _saturated_start("cuda", F64)
    result = lcs_cvx.fit(model, train, test=test, **SHORT_BEST)
    assert True in changed
    assert model.device.type == "cuda"
    assert all(getattr(model, k).device.type == "cuda" for k in PARAMETER_NAMES)
    assert {h["phase"] for h in result.history} >= {"adam", "gauss-newton"}
    assert all(bool(torch.isfinite(getattr(model, k)).all()) for k in PARAMETER_NAMES)
    # a second run from the default start (extra units grown on the GPU as well)
    again = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=4).to("cuda"), train, **SHORT_BEST)
    assert again.model.device.type == "cuda"


@needs_cuda
@pytest.mark.parametrize("projection", ["c3+", "auto"])
def test_c3_plans_on_cuda_as_on_the_cpu(projection):
    """C3's fast path on CUDA tensors (the default ``"auto"``, which runs the ``"lcp"``
    projection too, and ``"c3+"``): the whole solve on the GPU, the plans of the CPU. Plans of
    ``"c3+"`` that disagree with the model are this test's data, not its subject (``gap_tol``
    off)."""
    import numpy as np

    from lcs_cvx.control import C3, c3_cartpole

    P = c3_cartpole()
    G, U = P.weights["c3+"]
    ctrl = C3(P.model, P.horizon, Q=P.Q, R=P.R, G=G, U=U, projection=projection, gap_tol=None)
    X0 = torch.tensor(np.random.default_rng(0).uniform(-0.4, 0.4, (64, 4)))
    cpu, gpu = ctrl.solve(X0), ctrl.solve(X0.to("cuda"))
    assert gpu.u.device.type == "cuda" and gpu.x_model.device.type == "cuda"
    assert torch.allclose(gpu.u.cpu(), cpu.u, rtol=0, atol=1e-9)
    assert torch.allclose(gpu.cost.cpu(), cpu.cost, rtol=1e-9, atol=1e-12)


def test_the_affine_reference_steps_on_the_device_of_its_states():
    """The least-squares affine map fitted on the CPU scores states held on another device (a
    CUDA model's held-out data): it steps there, ``W`` moved to them. The meta device stands in
    for the GPU; before, this was ``RuntimeError: ... mat2 is on cpu``."""
    truth = lcs_cvx.random_lcs(2, 1, 2, seed=0)
    data = lcs_cvx.make_dataset(truth, 50, seed=1)
    affine = affine_lstsq(data)
    assert affine.W.device.type == "cpu"
    out = affine.step(data.x.to("meta"), data.u.to("meta"))
    assert out.device.type == "meta" and out.shape == (50, 2) and out.dtype == F64
    # on the CPU, the same operations as before: bit-identical
    assert torch.equal(affine.step(data.x, data.u), AffineMap.features(data.x, data.u) @ affine.W)
    # a second least-squares fit of the same data: LAPACK may block it otherwise (a few ulps)
    assert lcs_cvx.relative_error(affine, data) == pytest.approx(lcs_cvx.affine_error(data, data), rel=1e-12)


def test_held_out_scores_are_on_the_model_device_whatever_the_datas(monkeypatch):
    """``fit`` scores the held-out part and builds the affine reference from the training data
    it moved to the model's device, not from the user's: every dataset the affine map is fitted
    on, or scored on, is on the model's device (and dtype)."""
    import lcs_cvx.train.holdout as holdout

    seen = []
    real = holdout.affine_lstsq
    monkeypatch.setattr(holdout, "affine_lstsq", lambda d: seen.append(d.x.dtype) or real(d))
    truth = lcs_cvx.random_lcs(2, 1, 2, seed=0)
    train = lcs_cvx.make_dataset(truth, 300, seed=1)  # float64, the model float32
    model = lcs_cvx.LCS(2, 1, 2, seed=2, dtype=torch.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", lcs_cvx.FallbackWarning)
        result = lcs_cvx.fit(model, train, recipe="plain", iterations=20, restarts=2, progress=False)
    assert seen == [torch.float32]
    assert math.isfinite(result.heldout_error) and math.isfinite(result.affine_heldout_error)


def _runs():
    truth = lcs_cvx.random_lcs(2, 1, 2, seed=0)
    return simulated_runs(truth, [25] * 10, seed=1, x_range=5.0, u_range=3.0)


@needs_cuda
def test_fit_on_trajectories_with_validation_and_the_simulation_error_phase_on_cuda():
    """A CUDA model learned from CPU trajectories with held-out runs: Adam, the simulation-error
    phase, the held-out scores of the model and of the affine map, the rollout growth."""
    runs = _runs()
    train, validation = runs.split(0.8, seed=0)
    model = lcs_cvx.LCS(2, 1, 2, seed=3).to("cuda")
    result = lcs_cvx.fit(model, train, recipe="plain", validation=validation, iterations=100, rollout_horizon=5,
                         rollout_iterations=20, holdout_horizon=3, progress=False)
    assert model.device.type == "cuda"
    assert {h["phase"] for h in result.history} >= {"adam", "rollout"}
    assert math.isfinite(result.heldout_error) and math.isfinite(result.affine_heldout_error)
    assert result.heldout_growth is not None and math.isfinite(result.heldout_growth)
    errors = lcs_cvx.rollout_error(model, validation, horizons=(1, 3))
    assert all(math.isfinite(e) for e in errors.values())
    assert math.isfinite(affine_rollout_error(affine_lstsq(train.to_transitions().to("cuda")), validation, 3))
    print("cuda fit on trajectories:", result.verdict)


@needs_cuda
def test_select_n_lam_with_data_on_cuda():
    """``select_n_lam`` of a dataset on the GPU: the candidates are built there and scored there
    (before: a device mismatch in ``relative_error``)."""
    truth = lcs_cvx.random_lcs(2, 1, 2, seed=0)
    data = lcs_cvx.make_dataset(truth, 500, seed=1).to("cuda")
    selection = lcs_cvx.select_n_lam(data, candidates=(1, 2), recipe="plain", iterations=50, progress=False)
    assert selection.model.device.type == "cuda"
    assert all(math.isfinite(row["validation_error"]) for row in selection.table)
    traj = lcs_cvx.select_n_lam(_runs(), candidates=(2,), recipe="plain", iterations=50, progress=False,
                                make_model=lambda n: lcs_cvx.LCS(2, 1, n, seed=0).to("cuda"))
    assert traj.model.device.type == "cuda" and math.isfinite(traj.table[0]["validation_error"])
    print("cuda select_n_lam:", [(r["n_lam"], r["validation_error"]) for r in selection.table])


@needs_cuda
def test_fit_draws_and_warm_starts_on_the_data_device_as_on_the_cpu(tmp_path, monkeypatch):
    """A CUDA fit keeps its epoch permutation and warm-start tables on the GPU (no copy through
    the host per step), draws the minibatches of a CPU fit (the permutation comes from the CPU
    generator), ends where the CPU fit ends (to round-off), and resumes from its checkpoint;
    ``fit_ensemble`` likewise."""
    from lcs_cvx.train.state import TrainState

    seen_devices: set[str] = set()
    real = TrainState.remember

    def spy(self, idx, active):
        real(self, idx, active)
        seen_devices.update({self.perm.device.type, self.active.device.type, self.seen.device.type})

    monkeypatch.setattr(TrainState, "remember", spy)
    truth = lcs_cvx.random_lcs(2, 1, 2, seed=0)
    train = lcs_cvx.make_dataset(truth, 400, noise=1e-3, seed=1)
    options = {"recipe": "plain", "iterations": 60, "batch_size": 100, "lr": 1e-2, "progress": False}
    cpu = lcs_cvx.LCS(2, 1, 2, seed=3)
    lcs_cvx.fit(cpu, train, **options)
    gpu = lcs_cvx.LCS(2, 1, 2, seed=3).to("cuda")
    lcs_cvx.fit(gpu, train.to("cuda"), checkpoint=tmp_path / "run.ckpt", checkpoint_every=30, **options)
    assert seen_devices == {"cpu", "cuda"}
    for name in PARAMETER_NAMES:
        assert torch.allclose(getattr(gpu, name).detach().cpu(), getattr(cpu, name).detach(),
                              rtol=1e-8, atol=1e-10), name
    again = lcs_cvx.LCS(2, 1, 2, seed=3).to("cuda")  # resumed from the finished run's checkpoint
    lcs_cvx.fit(again, train.to("cuda"), checkpoint=tmp_path / "run.ckpt", checkpoint_every=30,
                resume=True, **options)
    assert again.device.type == "cuda"
    assert all(torch.equal(getattr(again, k), getattr(gpu, k)) for k in PARAMETER_NAMES)
    models = [lcs_cvx.LCS(2, 1, 2, seed=s).to("cuda") for s in (3, 4)]
    results = lcs_cvx.fit_ensemble(models, [train.to("cuda")] * 2, **options)
    assert all(math.isfinite(r.history[-1]["loss"]) for r in results)
