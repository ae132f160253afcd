"""Data (:mod:`lcs_cvx.data`) and metrics (:mod:`lcs_cvx.metrics`): the paper's generator
(Sec. 5: x ~ U[-10, 10], u ~ U[-5, 5], N(0, noise^2) on x'), the Dataset container, e_test and
the number of hybrid modes."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from zoo import decoupled

import lcs_cvx
from lcs_cvx import LCS, Dataset, count_modes, make_dataset, random_lcs, relative_error
from lcs_cvx.lcp import solve_lcp_brute
from lcs_cvx.system import ACTIVE_TOL

F64 = torch.float64


@pytest.fixture(scope="module")
def truth():
    return random_lcs(4, 2, 3, seed=3)


@pytest.fixture(scope="module")
def data(truth):
    return make_dataset(truth, 2000, seed=1)


# -- make_dataset --------------------------------------------------------------------------


@pytest.mark.parametrize("x_scale, u_scale", [(10.0, 5.0), (2.0, 0.5)])
def test_make_dataset_ranges(truth, x_scale, u_scale):
    ds = make_dataset(truth, 3000, seed=0, x_scale=x_scale, u_scale=u_scale)
    assert len(ds) == 3000
    assert ds.x.shape == (3000, 4) and ds.u.shape == (3000, 2) and ds.x_next.shape == (3000, 4)
    assert ds.lam.shape == (3000, 3)
    assert all(t.dtype == F64 for t in (ds.x, ds.u, ds.x_next, ds.lam))
    assert float(ds.x.abs().max()) <= x_scale
    assert float(ds.u.abs().max()) <= u_scale
    # uniform: fills the box (every coordinate gets near both ends) and is centred
    assert bool((ds.x.amin(0) < -0.99 * x_scale).all()) and bool((ds.x.amax(0) > 0.99 * x_scale).all())
    assert bool((ds.u.amin(0) < -0.99 * u_scale).all()) and bool((ds.u.amax(0) > 0.99 * u_scale).all())
    assert float(ds.x.mean(0).abs().max()) < 0.05 * x_scale
    # U[-a, a] has std a / sqrt(3)
    assert torch.allclose(ds.x.std(0), torch.full((4,), x_scale / 3**0.5, dtype=F64), rtol=0.05)


def test_make_dataset_reproducible(truth):
    a = make_dataset(truth, 500, noise=0.1, seed=5)
    b = make_dataset(truth, 500, noise=0.1, seed=5)
    c = make_dataset(truth, 500, noise=0.1, seed=6)
    for name in ("x", "u", "x_next", "lam"):
        assert torch.equal(getattr(a, name), getattr(b, name))
        assert not torch.equal(getattr(a, name), getattr(c, name))
    # the noise level changes x' only, not the sampled (x, u)
    clean = make_dataset(truth, 500, noise=0.0, seed=5)
    assert torch.equal(clean.x, a.x) and torch.equal(clean.u, a.u) and torch.equal(clean.lam, a.lam)
    assert not torch.equal(clean.x_next, a.x_next)
    # chunking does not change the data
    chunked = make_dataset(truth, 500, noise=0.1, seed=5, batch_size=7)
    assert torch.allclose(chunked.x_next, a.x_next, rtol=0, atol=1e-12)


def test_make_dataset_noise_statistics(truth):
    noise, N = 0.01, 20_000
    ds = make_dataset(truth, N, noise=noise, seed=2)
    resid = ds.x_next - truth.step(ds.x, ds.u)
    assert resid.shape == (N, 4)
    # per coordinate and overall: std within 3 % (its standard error is ~0.5 %), mean within
    # 5 standard errors of 0
    assert torch.allclose(resid.std(0), torch.full((4,), noise, dtype=F64), rtol=0.03)
    assert float(resid.mean(0).abs().max()) < 5 * noise / N**0.5
    assert float(resid.std()) == pytest.approx(noise, rel=0.01)
    # Gaussian: ~68.3 % within one sigma, ~95.4 % within two
    assert float((resid.abs() < noise).double().mean()) == pytest.approx(0.6827, abs=0.01)
    assert float((resid.abs() < 2 * noise).double().mean()) == pytest.approx(0.9545, abs=0.005)
    # independent coordinates
    corr = torch.corrcoef(resid.T)
    assert float((corr - torch.eye(4, dtype=F64)).abs().max()) < 0.04


def test_make_dataset_noiseless_is_exact(truth, data):
    assert torch.allclose(data.x_next, truth.step(data.x, data.u), rtol=0, atol=1e-12)


def test_make_dataset_lam_is_the_exact_lcp(truth, data):
    q = truth.lcp_offset(data.x, data.u)
    brute = solve_lcp_brute(truth.F, q)
    assert float((data.lam - brute.lam).abs().max()) <= 1e-10 * (1 + float(brute.lam.abs().max()))
    w = data.lam @ truth.F.mT + q
    assert float(torch.minimum(data.lam, w).abs().max()) <= 1e-10
    # and it is the lam that produced x'
    xn = data.x @ truth.A.mT + data.u @ truth.B.mT + data.lam @ truth.C.mT + truth.d
    assert torch.allclose(xn, data.x_next, rtol=0, atol=1e-12)
    assert bool((data.lam > 0).any(0).all())  # every unit is active somewhere


def test_make_dataset_float32_system_gives_float64_data():
    sys32 = random_lcs(3, 1, 2, seed=0, dtype=torch.float32)
    ds = make_dataset(sys32, 100, seed=0)
    assert ds.x.dtype == ds.x_next.dtype == ds.lam.dtype == F64
    ref = make_dataset(random_lcs(3, 1, 2, seed=0), 100, seed=0)
    assert torch.equal(ds.x, ref.x)
    assert torch.allclose(ds.x_next, ref.x_next, rtol=1e-5, atol=1e-4)


# -- Dataset -------------------------------------------------------------------------------


def test_dataset_len_and_indexing(data):
    assert len(data) == 2000 and data.n_x == 4 and data.n_u == 2
    part = data[10:25]
    assert isinstance(part, Dataset) and len(part) == 15
    assert torch.equal(part.x, data.x[10:25]) and torch.equal(part.u, data.u[10:25])
    assert torch.equal(part.x_next, data.x_next[10:25]) and torch.equal(part.lam, data.lam[10:25])
    one = data[7]
    assert len(one) == 1 and one.x.shape == (1, 4) and torch.equal(one.x[0], data.x[7])
    assert torch.equal(data[-1].x[0], data.x[-1])
    assert torch.equal(data[-2000].x[0], data.x[0])
    assert torch.equal(data[np.int64(3)].x[0], data.x[3])
    idx = torch.tensor([5, 1, 1999])
    picked = data[idx]
    assert len(picked) == 3 and torch.equal(picked.x_next, data.x_next[idx])
    mask = data.x[:, 0] > 0
    assert len(data[mask]) == int(mask.sum())
    assert len(data[2000:]) == 0
    assert "N=2000" in repr(data)


@pytest.mark.parametrize("i", [2000, 2001, -2001])
def test_dataset_index_out_of_range(data, i):
    with pytest.raises(IndexError, match="out of range"):
        data[i]


def test_dataset_iterates_over_its_samples():
    ds = make_dataset(random_lcs(2, 1, 1, seed=0), 5, seed=0)
    samples = list(ds)  # the sequence protocol stops at the IndexError
    assert len(samples) == 5
    assert all(len(s) == 1 for s in samples)
    assert torch.equal(torch.cat([s.x for s in samples]), ds.x)


def test_dataset_split(data):
    a, b = data.split(0.8, seed=3)
    assert len(a) == 1600 and len(b) == 400
    # disjoint and together the whole set: the rows of x are distinct random floats
    rows = lambda d: {tuple(r) for r in d.x.tolist()}  # noqa: E731
    assert len(rows(data)) == 2000
    assert rows(a).isdisjoint(rows(b))
    assert rows(a) | rows(b) == rows(data)
    # rows stay together: x_next and lam follow their x
    i = int(torch.nonzero((data.x == a.x[0]).all(1))[0])
    assert torch.equal(a.x_next[0], data.x_next[i]) and torch.equal(a.lam[0], data.lam[i])
    # reproducible, seed-dependent, shuffled
    a2, _ = data.split(0.8, seed=3)
    a3, _ = data.split(0.8, seed=4)
    assert torch.equal(a.x, a2.x)
    assert not torch.equal(a.x, a3.x)
    assert not torch.equal(a.x, data.x[:1600])
    # rounding of the size
    small = data[:7]
    assert [len(p) for p in small.split(0.5)] == [round(3.5), 7 - round(3.5)]
    assert [len(p) for p in small.split(0.3)] == [2, 5]


@pytest.mark.parametrize("frac", [0.0, 1.0, -0.2, 1.5])
def test_dataset_split_rejects_bad_fraction(data, frac):
    with pytest.raises(lcs_cvx.LCSInputError, match=r"frac: expected a fraction in \(0, 1\), received"):
        data.split(frac)


@pytest.mark.parametrize("with_lam", [True, False])
def test_dataset_save_load_round_trip(tmp_path, data, with_lam):
    ds = data[:100] if with_lam else Dataset(data.x[:100], data.u[:100], data.x_next[:100])
    path = tmp_path / "d.npz"
    ds.save(path)
    # a plain .npz, readable without pickle
    with np.load(path, allow_pickle=False) as f:
        assert sorted(f.files) == sorted(["x", "u", "x_next"] + (["lam"] if with_lam else []))
        assert f["x"].dtype == np.float64
        assert np.array_equal(f["x_next"], ds.x_next.numpy())
    back = Dataset.load(path)
    assert len(back) == 100
    for name in ("x", "u", "x_next"):
        assert torch.equal(getattr(back, name), getattr(ds, name))
    if with_lam:
        assert torch.equal(back.lam, ds.lam)
    else:
        assert back.lam is None
    back_str = Dataset.load(str(path))
    assert torch.equal(back_str.x, ds.x)


def test_dataset_save_is_atomic_and_uses_the_path_as_given(tmp_path, data):
    """The path exactly as given (np.savez would append .npz), via lcs_cvx.io.atomic_write: no
    temporary file is left behind, and a missing directory is an LCSInputError."""
    path = tmp_path / "plain"
    data[:10].save(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plain"]
    with np.load(path, allow_pickle=False) as f:
        assert np.array_equal(f["x"], data.x[:10].numpy())
    with pytest.raises(lcs_cvx.LCSInputError, match="path: expected a file in an existing directory"):
        data[:10].save(tmp_path / "missing" / "d.npz")


def test_dataset_from_arrays():
    g = np.random.default_rng(0)
    x, u, xn = g.standard_normal((6, 3)), g.standard_normal(6), g.standard_normal((6, 3))
    ds = Dataset.from_arrays(x, u, xn)
    assert len(ds) == 6 and ds.n_x == 3 and ds.n_u == 1  # 1-D u is one input per sample
    assert ds.u.shape == (6, 1) and ds.lam is None
    assert all(t.dtype == F64 for t in (ds.x, ds.u, ds.x_next))
    assert np.array_equal(ds.x.numpy(), x) and np.array_equal(ds.u.numpy()[:, 0], u)
    ds2 = Dataset.from_arrays(x.astype(np.float32).tolist(), u[:, None], xn, lam=np.abs(xn[:, :2]))
    assert ds2.x.dtype == F64 and ds2.lam.shape == (6, 2)
    # torch float64 tensors go through unchanged
    ds3 = Dataset.from_arrays(torch.tensor(x), torch.tensor(u[:, None]), torch.tensor(xn))
    assert torch.equal(ds3.x, ds.x)
    with pytest.raises(lcs_cvx.LCSInputError, match=r"x_next: expected 6 rows to match the other inputs, received 5"):
        Dataset.from_arrays(x, u, xn[:5])
    with pytest.raises(lcs_cvx.LCSInputError, match=r"x_next: expected shape \(N, 3\) or \(3,\), received shape \(6, 2\)"):
        Dataset.from_arrays(x, u, xn[:, :2])
    with pytest.raises(lcs_cvx.LCSInputError, match=r"x: expected finite values, received 1 NaN/inf entries"):
        Dataset.from_arrays(np.where(np.arange(18).reshape(6, 3) == 4, np.nan, x), u, xn)
    with pytest.raises(lcs_cvx.LCSInputError, match=r"x: expected shape \(N, n_x\), received shape \(6,\)"):
        Dataset.from_arrays(x[:, 0], u, xn)


# -- count_modes ---------------------------------------------------------------------------


def inputs(x, u) -> Dataset:
    """The inputs ``(x, u)`` as a data set (count_modes reads only them)."""
    return Dataset(x, u, torch.zeros_like(x))


def test_count_modes_known_systems():
    g = np.random.default_rng(0)
    sys2 = decoupled(2)
    x = torch.tensor(g.uniform(-1, 1, (400, 2)), dtype=F64)
    u = torch.zeros(400, 0, dtype=F64)
    assert torch.equal(sys2.active_set(x, u), x < 0)
    assert count_modes(sys2, inputs(x, u)) == 4
    # data in fewer quadrants: fewer modes
    assert count_modes(sys2, inputs(x.abs(), u)) == 1
    assert count_modes(sys2, inputs(torch.stack([x[:, 0], x[:, 1].abs()], 1), u)) == 2
    # one unit: two modes
    sys1 = decoupled(1)
    x1 = torch.tensor(g.uniform(-1, 1, (100, 1)), dtype=F64)
    assert count_modes(sys1, inputs(x1, torch.zeros(100, 0, dtype=F64))) == 2
    assert count_modes(sys1, inputs(x1.abs() + 0.1, torch.zeros(100, 0, dtype=F64))) == 1
    # three decoupled units with all sign patterns: 8
    sys3 = decoupled(3)
    x3 = torch.tensor(g.uniform(-1, 1, (2000, 3)), dtype=F64)
    assert count_modes(sys3, inputs(x3, torch.zeros(2000, 0, dtype=F64))) == 8
    # no samples, no modes
    assert count_modes(sys2, inputs(x[:0], u[:0])) == 0


def test_count_modes_tolerance():
    sys = decoupled(1)
    x = torch.tensor([[-1e-7], [-1.0], [1.0]], dtype=F64)  # lam = 1e-7, 1, 0
    u = torch.zeros(3, 0, dtype=F64)
    assert ACTIVE_TOL == 1e-5  # the default of count_modes and LCS.active_set
    assert count_modes(sys, inputs(x, u)) == 2  # default tol 1e-5: 1e-7 counts as inactive
    assert count_modes(sys, inputs(x, u), tol=1e-9) == 2
    assert count_modes(sys, inputs(x[:1], u[:1]), tol=1e-9) == 1
    assert count_modes(sys, inputs(x[:1], u[:1])) == 1
    assert bool(sys.active_set(x[:1], u[:1], tol=1e-9)[0, 0])
    assert not bool(sys.active_set(x[:1], u[:1], tol=1e-5)[0, 0])
    assert not bool(sys.active_set(x[:1], u[:1])[0, 0])


def test_count_modes_random_system_matches_brute_force(truth, data):
    modes = count_modes(truth, data)
    brute = solve_lcp_brute(truth.F, truth.lcp_offset(data.x, data.u))
    assert modes == torch.unique(brute.lam > 1e-5, dim=0).shape[0]
    assert 2 <= modes <= 2**3


# -- relative_error (e_test) ---------------------------------------------------------------


def test_relative_error_zero_for_truth_positive_for_perturbed(truth, data):
    assert relative_error(truth, data) <= 1e-24
    errs = []
    for delta in (1e-4, 1e-3, 1e-2):
        model = LCS.from_matrices(**{**truth.to_matrices(), "A": truth.A.numpy() + delta})
        errs.append(relative_error(model, data))
    assert all(e > 0 for e in errs)
    assert errs[0] < errs[1] < errs[2]
    # a perturbation of the LCP part only also shows
    mats = truth.to_matrices()
    mats["c"] = mats["c"] + 0.1
    assert relative_error(LCS.from_matrices(**mats), data) > 1e-8
    # definition: sum |x'_model - x'|^2 / sum |x'|^2
    model = LCS.from_matrices(**{**truth.to_matrices(), "d": truth.d.numpy() + 0.01})
    pred = model.step(data.x, data.u).detach()
    expected = float(((pred - data.x_next) ** 2).sum() / (data.x_next**2).sum())
    assert relative_error(model, data) == pytest.approx(expected, rel=1e-12)


def test_relative_error_on_noisy_data_is_the_noise_floor(truth):
    noise = 0.01
    ds = make_dataset(truth, 5000, noise=noise, seed=4)
    expected = ds.x_next.numel() * noise**2 / float((ds.x_next**2).sum())
    assert relative_error(truth, ds) == pytest.approx(expected, rel=0.05)


def test_relative_error_float32_model(truth, data):
    m32 = LCS.from_matrices(**truth.to_matrices(), dtype=torch.float32)
    e = relative_error(m32, data)
    assert 0 <= e <= 1e-10


def test_from_arrays_takes_tensors_without_their_autograd_history(truth):
    """A Dataset built from a model's own predictions holds data, not a graph: no grad, and
    .numpy() works on every column."""
    x = torch.randn(5, truth.n_x, dtype=torch.float64)
    u = torch.randn(5, truth.n_u, dtype=torch.float64)
    x_next = LCS(truth.n_x, truth.n_u, truth.n_lam, seed=0).step(x, u)  # a learnable model's prediction
    assert x_next.requires_grad
    data = lcs_cvx.Dataset.from_arrays(x, u, x_next)
    assert not any(t.requires_grad for t in (data.x, data.u, data.x_next))
    assert np.array_equal(data.x_next.numpy(), x_next.detach().numpy())
