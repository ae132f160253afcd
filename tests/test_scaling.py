"""Learning in normalised coordinates (lcs_cvx.scaling, RunOptions.normalize / init)."""

from __future__ import annotations

import pytest
import torch

import lcs_cvx
from lcs_cvx import Dataset
from lcs_cvx.scaling import U_SPREAD, X_SPREAD, Scaling
from lcs_cvx.train.starts import affine_start_

SX = torch.tensor([1e3, 1.0, 1e-2, 10.0], dtype=torch.float64)
SU = torch.tensor([1e-2, 1e2], dtype=torch.float64)


@pytest.fixture(scope="module")
def system():
    truth = lcs_cvx.random_lcs(4, 2, 3, seed=0)
    train = lcs_cvx.make_dataset(truth, 3000, noise=1e-2, seed=1)
    test = lcs_cvx.make_dataset(truth, 1000, seed=2)
    return truth, train, test


def rescaled(data: Dataset) -> Dataset:
    return Dataset(data.x * SX, data.u * SU, data.x_next * SX, data.lam)


def test_statistics_of_the_normalised_data(system):
    _, train, _ = system
    s = Scaling.fit(train)
    z = s.encode(train)
    assert torch.allclose(z.x.mean(0), torch.zeros(4, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(z.x.std(0, unbiased=False), torch.full((4,), X_SPREAD, dtype=torch.float64))
    assert torch.allclose(z.u.std(0, unbiased=False), torch.full((2,), U_SPREAD, dtype=torch.float64))
    assert torch.allclose(z.x_next.std(0, unbiased=False), torch.ones(4, dtype=torch.float64))
    # the increment: y = (x' - x - m_y) / s_y
    assert torch.allclose(z.x_next * s.sy + s.my, train.x_next - train.x)


def test_a_rescaling_leaves_the_normalised_data_unchanged(system):
    _, train, _ = system
    a, b = Scaling.fit(train).encode(train), Scaling.fit(rescaled(train)).encode(rescaled(train))
    for field in ("x", "u", "x_next"):
        assert torch.allclose(getattr(a, field), getattr(b, field), rtol=1e-10, atol=1e-10)


def test_the_fold_back_is_exact(system):
    """The normalised model and its fold-back predict the same x' and lam, up to round-off."""
    truth, train, test = system
    s = Scaling.fit(rescaled(train))
    model = lcs_cvx.LCS(4, 2, 3, seed=5, init_scale=0.5)
    back = s.to_physical(model)
    data = rescaled(test)
    z = s.encode(data)
    with torch.no_grad():
        y = model.step(z.x, z.u)
        x_next = back.step(data.x, data.u)
        assert torch.allclose(x_next, data.x + s.my + s.sy * y, rtol=1e-10, atol=1e-9 * float(SX.max()))
        lam_n, lam_p = model.solve_lcp(z.x, z.u).lam, back.solve_lcp(data.x, data.u).lam
    assert torch.allclose(lam_n, lam_p, rtol=1e-9, atol=1e-10)
    # and to_normalised inverts it
    again = s.to_normalised(back)
    for name in lcs_cvx.system.PARAMETER_NAMES:
        assert torch.allclose(getattr(again, name), getattr(model, name), rtol=1e-9, atol=1e-12), name


def test_a_constant_column_gets_scale_one():
    x = torch.randn(200, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    x[:, 1] = 7.0
    u = torch.zeros(200, 1, dtype=torch.float64)
    data = Dataset(x, u, x + 1.0)
    s = Scaling.fit(data)
    assert s.sx[1] == 1.0 and s.su[0] == 1.0 and bool((s.sy == 1.0).all())
    z = s.encode(data)
    assert bool(torch.isfinite(z.x).all()) and bool((z.x[:, 1] == 0).all())


def test_fit_in_other_units_is_the_same_problem(system):
    """The units experiment in small: rescaled state and input, same seeds, e_test in each
    run's own units at the same level (the metric weights the states differently)."""
    truth, train, test = system
    errors = []
    for tr, te in ((train, test), (rescaled(train), rescaled(test))):
        model = lcs_cvx.LCS(4, 2, 3, seed=0)
        result = lcs_cvx.fit(model, tr, test=te, recipe="best", progress=False)
        assert result.scaling is not None
        # e_test in the history is in the user's units: the returned model's error
        last = result.kept_history[-1]
        assert last["e_test"] == pytest.approx(lcs_cvx.relative_error(model, te), rel=1e-6)
        errors.append(lcs_cvx.relative_error(model, te))
    assert max(errors) < 3e-7  # the noise floor of this data is ~1e-7
    assert max(errors) / min(errors) < 4.0
    # without normalisation the rescaled problem is far from the floor
    model = lcs_cvx.LCS(4, 2, 3, seed=0)
    lcs_cvx.fit(model, rescaled(train), recipe="best", normalize=False, init="model", progress=False)
    assert lcs_cvx.relative_error(model, rescaled(test)) > 1e3 * max(errors)


def test_callbacks_see_the_model_in_the_users_units(system):
    _, train, test = system
    data, held = rescaled(train), rescaled(test)
    seen = []

    def cb(record, model):
        seen.append((record["e_test"], lcs_cvx.relative_error(model, held)))

    lcs_cvx.fit(lcs_cvx.LCS(4, 2, 3), data, recipe="plain", test=held, iterations=200, eval_every=100,
                callbacks=[cb], progress=False)
    assert len(seen) == 2
    for recorded, recomputed in seen:
        assert recorded == pytest.approx(recomputed, rel=1e-9)


@pytest.mark.parametrize("init", ["model", "increment", "affine"])
def test_starts(system, init):
    truth, train, _ = system
    model = lcs_cvx.LCS(4, 2, 3, seed=1)
    before = {k: v.detach().clone() for k, v in model.state_dict().items()}
    result = lcs_cvx.fit(model, rescaled(train), recipe="plain", init=init, iterations=1, eval_every=1, progress=False)
    assert result.settings.run.init == init
    assert any(not torch.equal(before[k], v) for k, v in model.state_dict().items())


def test_the_affine_start_is_the_least_squares_fit(system):
    _, train, _ = system
    model = lcs_cvx.LCS(4, 2, 3, seed=1)
    affine_start_(model, train)
    phi = torch.cat([train.x, train.u, torch.ones(len(train), 1, dtype=torch.float64)], 1)
    W = torch.linalg.lstsq(phi, train.x_next).solution.T
    assert torch.allclose(torch.cat([model.A, model.B, model.d[:, None]], 1), W, rtol=1e-8, atol=1e-10)


def test_the_paper_recipe_learns_in_the_datas_own_coordinates():
    opts = lcs_cvx.RECIPES["paper"]
    assert opts.run.normalize is False and opts.run.init == "model"
    assert lcs_cvx.RECIPES["best"].run.normalize is True


def test_bad_options_are_named():
    with pytest.raises(lcs_cvx.LCSInputError, match="init: expected one of"):
        lcs_cvx.train.resolve_options(init="zeros")
    with pytest.raises(lcs_cvx.LCSInputError, match="normalize: expected True or False"):
        lcs_cvx.train.resolve_options(normalize="yes")


def test_resume_under_normalisation_gives_the_uninterrupted_result(system, tmp_path):
    _, train, test = system
    data = rescaled(train)
    kw = {"recipe": "plain", "iterations": 300, "eval_every": 50, "checkpoint_every": 50, "progress": False}
    full = lcs_cvx.LCS(4, 2, 3, seed=2)
    lcs_cvx.fit(full, data, **kw)
    path = tmp_path / "ckpt.pt"
    part = lcs_cvx.LCS(4, 2, 3, seed=2)
    lcs_cvx.fit(part, data, checkpoint=path, callbacks=[lambda rec, m: rec["iteration"] >= 150], **kw)
    resumed = lcs_cvx.LCS(4, 2, 3, seed=2)
    lcs_cvx.fit(resumed, data, checkpoint=path, resume=True, **kw)
    for name in lcs_cvx.system.PARAMETER_NAMES:
        assert torch.equal(getattr(resumed, name), getattr(full, name)), name


def test_structure_survives_the_change_of_coordinates(system):
    """Masks keep their pattern (an A_ii masked to 0 drops the identity from that row's
    target), a fixed or masked d or c switches centring off, fixed values come back bit for bit."""
    truth, train, test = system
    mask_A = torch.ones(4, 4, dtype=torch.bool)
    mask_A[0, 0] = mask_A[2, 1] = False
    mask_C = torch.tensor([[1, 0, 0], [1, 1, 0], [0, 1, 1], [0, 0, 1]], dtype=torch.bool)
    model = lcs_cvx.LCS(4, 2, 3, seed=4, mask={"A": mask_A, "C": mask_C}).fix(c=truth.c, B=truth.B)
    data = rescaled(train)
    s = Scaling.fit(data, model)
    assert s.k.tolist() == [0.0, 1.0, 1.0, 1.0]
    assert bool((s.mx == 0).all()) and bool((s.mu == 0).all())  # c is fixed: no centring
    normalised = s.to_normalised(model)
    assert not normalised.B.requires_grad and not normalised.c.requires_grad
    assert normalised.A[0, 0] == 0 and normalised.A[2, 1] == 0
    assert bool((normalised.C[~mask_C] == 0).all())
    lcs_cvx.fit(model, data, recipe="plain", iterations=200, eval_every=100, progress=False)
    assert torch.equal(model.B, truth.B) and torch.equal(model.c, truth.c)
    assert model.A[0, 0].item() == 0.0 and model.A[2, 1].item() == 0.0
    assert bool((model.C[~mask_C] == 0).all())
    assert model.masks.keys() == {"A", "C"}
