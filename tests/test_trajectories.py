"""`Trajectories` (validation, transitions, .npz and .csv files, split) and `rollout_error`
(batched open-loop windows against e_test, the true system and a hand-computed linear case)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import lcs_cvx
from lcs_cvx import LCS, LCSInputError, Trajectories, random_lcs, relative_error, rollout_error

F64 = torch.float64


def _simulate(system: LCS, lengths, seed: int = 0) -> Trajectories:
    """Noiseless trajectories of ``system`` stepped with ``LCS.step``."""
    g = torch.Generator().manual_seed(seed)
    xs, us = [], []
    with torch.no_grad():
        for T in lengths:
            u = (torch.rand(T, system.n_u, generator=g, dtype=F64) * 2 - 1) * 5
            x = [(torch.rand(1, system.n_x, generator=g, dtype=F64) * 2 - 1) * 10]
            for t in range(T):
                x.append(system.step(x[-1], u[t : t + 1]))
            xs.append(torch.cat(x))
            us.append(u)
    return Trajectories(xs, us)


@pytest.fixture(scope="module")
def truth() -> LCS:
    return random_lcs(2, 1, 2, seed=4)


@pytest.fixture(scope="module")
def trajs(truth) -> Trajectories:
    return _simulate(truth, [12, 3, 25, 7])


# -- the container -----------------------------------------------------------------------------


def test_shapes_and_transitions():
    g = np.random.default_rng(0)
    xs = [g.standard_normal((4, 3)), torch.randn(3, 3, generator=torch.Generator().manual_seed(0))]
    us = [g.standard_normal((3, 2)), g.standard_normal((2, 2))]
    t = Trajectories(xs, us)
    assert (len(t), t.n_x, t.n_u, t.lengths) == (2, 3, 2, (3, 2))
    assert repr(t) == "Trajectories(K=2, transitions=5, n_x=3, n_u=2)"
    d = t.to_transitions()
    assert isinstance(d, lcs_cvx.Dataset) and len(d) == 5 and d.x.dtype == F64 and d.lam is None
    np.testing.assert_array_equal(d.x[:3].numpy(), xs[0][:3])
    np.testing.assert_array_equal(d.x_next[:3].numpy(), xs[0][1:])
    np.testing.assert_array_equal(d.x[3:].numpy(), xs[1][:2].numpy())
    np.testing.assert_array_equal(d.x_next[3:].numpy(), xs[1][1:].numpy())
    np.testing.assert_array_equal(d.u.numpy(), np.concatenate(us))
    xs[0][0, 0] = 99.0  # copied
    assert t.xs[0][0, 0] != 99.0


def _arrays(lengths=(5, 18, 4, 18), n_x=2, n_u=1):
    g = np.random.default_rng(1)
    return [g.standard_normal((T + 1, n_x)) for T in lengths], [g.standard_normal((T, n_u)) for T in lengths]


def test_mismatched_rows_message():
    xs, us = _arrays(lengths=(5, 18, 4, 17))
    us[3] = us[3][:16]
    with pytest.raises(LCSInputError) as e:
        Trajectories(xs, us)
    assert str(e.value) == "us[3]: expected 17 rows (one fewer than xs[3]'s 18), received 16"


@pytest.mark.parametrize(
    "case, says",
    [
        ("empty", "xs: expected at least one trajectory, received an empty list"),
        ("count", "us: expected 4 input arrays (one per trajectory of xs), received 3"),
        ("n_x", "xs[2]: expected 2 columns (n_x of xs[0]), received 3"),
        ("n_u", "us[1]: expected 1 columns (n_u of us[0]), received 2"),
        ("nan", "xs[1]: expected finite values, received 2 NaN/inf entries, the first in row 3, column 0 (nan)"),
        ("inf", "us[3]: expected finite values, received 1 NaN/inf entries, the first in row 0, column 0 (-inf)"),
        ("ndim", "xs[0]: expected a 2-D array, received shape (6,)"),
        ("short", "xs[2]: expected at least 2 rows (a state and the next), received 1"),
        ("not a list", "xs: expected a list of 2-D arrays (one per trajectory), received str"),
    ],
)
def test_bad_input_is_refused_by_name(case, says):
    xs, us = _arrays()
    if case == "empty":
        xs, us = [], []
    elif case == "count":
        us = us[:3]
    elif case == "n_x":
        xs[2] = np.zeros((5, 3))
    elif case == "n_u":
        us[1] = np.zeros((18, 2))
    elif case == "nan":
        xs[1][3] = np.nan
    elif case == "inf":
        us[3][0, 0] = -np.inf
    elif case == "ndim":
        xs[0] = xs[0][:, 0]
    elif case == "short":
        xs[2], us[2] = xs[2][:1], us[2][:0]
    elif case == "not a list":
        xs = "abc"
    with pytest.raises(LCSInputError) as e:
        Trajectories(xs, us)
    assert str(e.value) == says


def test_split_by_whole_trajectories(trajs):
    a, b = trajs.split(0.5, seed=3)
    assert len(a) == 2 and len(b) == 2
    assert sorted(a.lengths + b.lengths) == sorted(trajs.lengths)
    again = trajs.split(0.5, seed=3)[0]
    assert all(torch.equal(x, y) for x, y in zip(a.xs, again.xs, strict=True))
    for frac in (0.1, 0.95, 1.0, 0.0):
        with pytest.raises(LCSInputError, match="^frac: "):
            trajs.split(frac)


# -- files -------------------------------------------------------------------------------------


def test_npz_round_trip(trajs, tmp_path):
    path = tmp_path / "t.npz"
    trajs.save(path)
    with np.load(path, allow_pickle=False) as f:
        assert sorted(f.files) == ["offsets", "u", "x"]
        assert f["offsets"].tolist() == [0, 13, 17, 43, 51]
    back = Trajectories.load(path)
    assert back.lengths == trajs.lengths
    for a, b in zip(back.xs + back.us, trajs.xs + trajs.us, strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize(
    "arrays, says",
    [
        ({"x": np.zeros((5, 2)), "u": np.zeros((3, 1))}, "missing ['offsets']"),
        ({"x": np.zeros((5, 2)), "u": np.zeros((3, 1)), "offsets": np.array([0, 1, 5])}, "steps of at least 2"),
        ({"x": np.zeros((5, 2)), "u": np.zeros((3, 1)), "offsets": np.array([0, 2, 4])}, "from 0 to 5"),
        ({"x": np.zeros((5, 2)), "u": np.zeros((4, 1)), "offsets": np.array([0, 2, 5])}, "expected 3 rows"),
        ({"x": np.full((5, 2), np.nan), "u": np.zeros((3, 1)), "offsets": np.array([0, 2, 5])}, "xs[0]: expected finite"),
    ],
)
def test_bad_npz_is_refused(tmp_path, arrays, says):
    path = tmp_path / "bad.npz"
    np.savez(path, **arrays)
    with pytest.raises(LCSInputError) as e:
        Trajectories.load(path)
    assert str(e.value).startswith("path: ") and says in str(e.value) and str(path) in str(e.value)


def test_csv_default_columns_and_the_last_row(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text(
        "time,trajectory,x_0,x_1,u_0\n"
        "0,a,1,2,0.5\n"
        "1,a,3,4,0.25\n"
        "2,a,5,6,\n"          # the last row of 'a': its input left empty
        "# a comment\n"
        "0,b,7,8,1.5\n"
        "1,b,9,10,123\n"      # the last row of 'b': its input is not read
    )
    t = Trajectories.load(path)
    assert t.lengths == (2, 1)
    np.testing.assert_array_equal(t.xs[0].numpy(), [[1, 2], [3, 4], [5, 6]])
    np.testing.assert_array_equal(t.us[0].numpy(), [[0.5], [0.25]])
    np.testing.assert_array_equal(t.xs[1].numpy(), [[7, 8], [9, 10]])
    np.testing.assert_array_equal(t.us[1].numpy(), [[1.5]])


def test_csv_named_columns_and_interleaved_ids(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text("run,p,v,f\n1,0,1,9\n2,5,5,9\n1,1,2,8\n2,6,6,\n1,2,3,\n")
    t = Trajectories.load(path, columns={"x": ["p", "v"], "u": ["f"]}, trajectory="run")
    assert t.lengths == (2, 1)
    np.testing.assert_array_equal(t.xs[0].numpy(), [[0, 1], [1, 2], [2, 3]])
    np.testing.assert_array_equal(t.us[0].numpy(), [[9], [8]])
    np.testing.assert_array_equal(t.xs[1].numpy(), [[5, 5], [6, 6]])


@pytest.mark.parametrize(
    "text, says",
    [
        ("x_0,u_0\n1,2\n2,\n", "trajectory: expected a column 'trajectory'"),
        ("trajectory,x_0,u_0\na,1,2\nb,2,3\nb,3,\n", "trajectory 'a' of"),
        ("trajectory,x_0,u_0\na,1,\na,2,\n", "line 2 of"),  # an inner row's input is read
        ("trajectory,x_0,u_0\na,1,2\na,nan,\n", "column 'x_0': expected a finite number, received 'nan'"),
        ("trajectory,x_0,x_2,u_0\na,1,1,2\na,2,2,\n", "missing ['x_1']"),
        ("trajectory,x_0\na,1\na,2\n", "missing ['u_0..']"),
        ("trajectory,x_0,u_0\n,1,2\n", "expected a trajectory id"),
    ],
)
def test_bad_csv_is_refused(tmp_path, text, says):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(LCSInputError) as e:
        Trajectories.load(path)
    assert says in str(e.value)


def test_csv_and_npz_agree(trajs, tmp_path):
    rows = ["trajectory,x_0,x_1,u_0"]
    for i, (x, u) in enumerate(zip(trajs.xs, trajs.us, strict=True)):
        for t in range(x.shape[0]):
            u_text = repr(float(u[t, 0])) if t < u.shape[0] else ""
            rows.append(f"{i},{float(x[t, 0])!r},{float(x[t, 1])!r},{u_text}")
    (tmp_path / "t.csv").write_text("\n".join(rows) + "\n")
    back = Trajectories.load(tmp_path / "t.csv")
    assert back.lengths == trajs.lengths
    assert all(torch.equal(a, b) for a, b in zip(back.xs + back.us, trajs.xs + trajs.us, strict=True))


# -- rollout_error -----------------------------------------------------------------------------


def test_h1_is_e_test_and_other_models_are_not_zero(trajs):
    model = LCS(2, 1, 3, stiffness=1.0, seed=9, init_scale=1.0, dtype=F64)
    errs = rollout_error(model, trajs, horizons=(1, 5, 20))
    assert list(errs) == [1, 5, 20]
    assert errs[1] == pytest.approx(relative_error(model, trajs.to_transitions()), rel=1e-12)
    assert errs[1] > 1e-3 and errs[5] > 1e-3 and errs[20] > 1e-3


def test_the_true_system_has_zero_rollout_error(truth, trajs):
    errs = rollout_error(truth, trajs, horizons=[1, 3, 12, 25])
    assert all(e < 1e-24 for e in errs.values()), errs


def test_hand_computed_linear_case():
    # x' = 2 x + u (no contact: C = 0); two trajectories, lengths 2 and 1.
    model = LCS.from_matrices(A=[[2.0]], B=[[1.0]], C=[[0.0]], d=[0.0], D=[[0.0]], E=[[0.0]], F=[[1.0]], c=[1.0])
    xs = [np.array([[1.0], [2.0], [5.0]]), np.array([[1.0], [3.0]])]
    us = [np.array([[1.0], [1.0]]), np.array([[0.0]])]
    errs = rollout_error(model, Trajectories(xs, us), horizons=(1, 2))
    # H=1 windows: 1 -> 3 (recorded 2), 2 -> 5 (5), 1 -> 2 (3): errors 1, 0, 1; targets 4, 25, 9
    # H=2 window: 1 -> 3 -> 7 (recorded 5): error 4, target 25
    assert errs == {1: pytest.approx(2 / 38, rel=1e-14), 2: pytest.approx(4 / 25, rel=1e-14)}


def test_one_step_call_per_horizon_step(trajs, truth, monkeypatch):
    calls = []
    step = LCS.step

    def counting(self, x, u, *a, **k):
        calls.append(x.shape[0])
        return step(self, x, u, *a, **k)

    monkeypatch.setattr(LCS, "step", counting)
    rollout_error(truth, trajs, horizons=(5, 2))
    # every window of every trajectory at once: all starts, then those with 2, 3, ... steps left
    assert calls == [sum(max(0, T - h + 1) for T in trajs.lengths) for h in range(1, 6)]


@pytest.mark.parametrize(
    "horizons, says",
    [
        ((1, 26), "horizons: expected at most 25 steps (the longest trajectory's), received [26]"),
        ((0,), "horizons: expected integers >= 1"),
        ((), "horizons: expected integers >= 1"),
        ((2.0,), "horizons: expected integers >= 1"),
    ],
)
def test_bad_horizons(truth, trajs, horizons, says):
    with pytest.raises(LCSInputError) as e:
        rollout_error(truth, trajs, horizons=horizons)
    assert str(e.value).startswith(says)


def test_dimension_mismatch(trajs):
    with pytest.raises(LCSInputError, match=r"^trajectories: expected n_x=3, n_u=1"):
        rollout_error(LCS(3, 1, 2, seed=0), trajs)
