"""Bad input is stopped at the boundary with :class:`lcs_cvx.LCSInputError` (a ValueError) whose
message names the argument and says what was expected and what was received."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from lcs_cvx import LCS, Dataset, LCSInputError, make_dataset, random_lcs, solve_lcp

F64 = torch.float64


@pytest.fixture(scope="module")
def sys():
    return random_lcs(3, 2, 2, seed=0)


def zeros(*shape, dtype=F64):
    return torch.zeros(*shape, dtype=dtype)


def test_error_type():
    assert issubclass(LCSInputError, ValueError)


# -- x and u -------------------------------------------------------------------------------

STEP_LIKE = ["step", "solve_lcp", "lcp_offset", "active_set", "forward"]


@pytest.mark.parametrize("method", STEP_LIKE)
@pytest.mark.parametrize(
    "x, received",
    [
        (zeros(5, 4), r"\(5, 4\)"),
        (zeros(4), r"\(4,\)"),
        (zeros(5, 3, 1), r"\(5, 3, 1\)"),
        (np.zeros((2, 2)), r"\(2, 2\)"),
    ],
)
def test_wrong_shape_of_x(sys, method, x, received):
    with pytest.raises(LCSInputError, match=rf"^x: expected shape \(N, 3\) or \(3,\), received shape {received}$"):
        getattr(sys, method)(x, zeros(5, 2))


@pytest.mark.parametrize("method", STEP_LIKE)
@pytest.mark.parametrize("u, received", [(zeros(5, 3), r"\(5, 3\)"), (zeros(5, 2, 2), r"\(5, 2, 2\)")])
def test_wrong_shape_of_u(sys, method, u, received):
    with pytest.raises(LCSInputError, match=rf"^u: expected shape \(N, 2\) or \(2,\), received shape {received}$"):
        getattr(sys, method)(zeros(5, 3), u)


@pytest.mark.parametrize("method", ["step", "solve_lcp"])
@pytest.mark.parametrize("bad, count", [(float("nan"), 1), (float("inf"), 1), (-float("inf"), 1)])
def test_non_finite_x(sys, method, bad, count):
    x = zeros(4, 3)
    x[2, 1] = bad
    with pytest.raises(LCSInputError, match=rf"^x: expected finite values, received {count} NaN/inf entries$"):
        getattr(sys, method)(x, zeros(4, 2))
    u = np.zeros((4, 2))
    u[:, 0] = bad
    with pytest.raises(LCSInputError, match=r"^u: expected finite values, received 4 NaN/inf entries$"):
        getattr(sys, method)(zeros(4, 3), u)


@pytest.mark.parametrize("method", ["step", "solve_lcp"])
def test_dtype_mismatch(sys, method):
    with pytest.raises(LCSInputError, match=r"^x: expected dtype torch\.float64 \(the model's\), received torch\.float32"):
        getattr(sys, method)(zeros(4, 3, dtype=torch.float32), zeros(4, 2))
    with pytest.raises(LCSInputError, match=r"^u: expected dtype torch\.float64 \(the model's\), received torch\.float32"):
        getattr(sys, method)(zeros(4, 3), zeros(4, 2, dtype=torch.float32))
    sys32 = random_lcs(3, 2, 2, seed=0, dtype=torch.float32)
    with pytest.raises(LCSInputError, match=r"^x: expected dtype torch\.float32 \(the model's\), received torch\.float64"):
        getattr(sys32, method)(zeros(4, 3), zeros(4, 2, dtype=torch.float32))


def test_complex_and_non_numeric_x(sys):
    with pytest.raises(LCSInputError, match=r"^x: expected a real floating array, received tensor of shape \(4, 3\) and dtype torch\.complex128"):
        sys.step(torch.zeros(4, 3, dtype=torch.complex128), zeros(4, 2))
    with pytest.raises(LCSInputError, match=r"^x: expected a real array, received str 'abc'"):
        sys.step("abc", zeros(1, 2))


@pytest.mark.parametrize("method", ["step", "solve_lcp", "lcp_offset"])
def test_batch_size_mismatch(sys, method):
    with pytest.raises(LCSInputError, match=r"^u: expected 5 rows to match the other inputs, received 3$"):
        getattr(sys, method)(zeros(5, 3), zeros(3, 2))
    with pytest.raises(LCSInputError, match=r"^u: expected 1 rows to match the other inputs, received 3$"):
        getattr(sys, method)(zeros(3), zeros(3, 2))


def test_rollout_bad_inputs(sys):
    with pytest.raises(LCSInputError, match=r"^us: expected shape \(2, T, 2\) or \(T, 2\), received shape \(3, 4, 2\)$"):
        sys.rollout(zeros(2, 3), zeros(3, 4, 2))
    with pytest.raises(LCSInputError, match=r"^us: expected shape \(1, T, 2\) or \(T, 2\), received shape \(4, 3\)$"):
        sys.rollout(zeros(3), zeros(4, 3))
    with pytest.raises(LCSInputError, match=r"^x0: expected shape \(N, 3\) or \(3,\), received shape \(2,\)$"):
        sys.rollout(zeros(2), zeros(4, 2))


# -- dimensions and scalars ----------------------------------------------------------------


@pytest.mark.parametrize("n_lam", [0, -1, 2.0, 2.5, "2", None, True])
def test_n_lam_must_be_a_positive_int(n_lam):
    with pytest.raises(LCSInputError, match=rf"^n_lam: expected an integer >= 1, received {re.escape(repr(n_lam))}$"):
        LCS(3, 2, n_lam)
    with pytest.raises(LCSInputError, match=r"^n_lam: expected an integer >= 1"):
        random_lcs(3, 2, n_lam)


def test_n_x_and_n_u(sys):
    with pytest.raises(LCSInputError, match=r"^n_x: expected an integer >= 1, received 0$"):
        LCS(0, 2, 2)
    with pytest.raises(LCSInputError, match=r"^n_u: expected an integer >= 0, received -1$"):
        LCS(3, -1, 2)
    with pytest.raises(LCSInputError, match=r"^n_u: expected an integer >= 0, received 1\.5$"):
        LCS(3, 1.5, 2)
    with pytest.raises(LCSInputError, match=r"^dtype: expected torch\.float32 or torch\.float64, received torch\.float16$"):
        LCS(3, 2, 2, dtype=torch.float16)
    with pytest.raises(LCSInputError, match=r"^init_scale: expected a number >= 0, received -0\.1$"):
        LCS(3, 2, 2, init_scale=-0.1)


@pytest.mark.parametrize("stiffness, msg", [
    (0.0, r"expected a finite number > 0, received 0\.0"),
    (-1.0, r"expected a finite number > 0, received -1\.0"),
    (float("nan"), r"expected a finite number > 0, received nan"),
    (float("inf"), r"expected a finite number > 0, received inf"),
    ("1", r"expected a positive number, received '1'"),
])
def test_stiffness_must_be_positive(stiffness, msg):
    with pytest.raises(LCSInputError, match=rf"^stiffness: {msg}$"):
        LCS(3, 2, 2, stiffness=stiffness)
    with pytest.raises(LCSInputError, match=rf"^stiffness: {msg}$"):
        random_lcs(3, 2, 2, stiffness=stiffness)


@pytest.mark.parametrize("noise, shown", [(-0.1, r"-0\.1"), (-1e-9, r"-1e-09"), (float("nan"), "nan"), (float("inf"), "inf"), ("0.1", "'0.1'")])
def test_noise_must_be_nonnegative(sys, noise, shown):
    with pytest.raises(LCSInputError, match=rf"^noise: expected a finite standard deviation >= 0, received {shown}$"):
        make_dataset(sys, 10, noise=noise)


def test_make_dataset_other_arguments(sys):
    with pytest.raises(LCSInputError, match=r"^n: expected an integer >= 1, received 0$"):
        make_dataset(sys, 0)
    with pytest.raises(LCSInputError, match=r"^x_scale: expected a finite number > 0, received -1"):
        make_dataset(sys, 10, x_scale=-1.0)
    with pytest.raises(LCSInputError, match=r"^u_scale: expected a finite number > 0, received 0"):
        make_dataset(sys, 10, u_scale=0.0)


# -- files ---------------------------------------------------------------------------------


def test_load_missing_file(tmp_path):
    path = tmp_path / "nope.npz"
    with pytest.raises(LCSInputError, match=r"^path: expected an existing \.npz file, received '.*nope\.npz' \(not found\)$"):
        Dataset.load(path)


def test_load_file_lacking_arrays(tmp_path):
    path = tmp_path / "partial.npz"
    np.savez(path, x=np.zeros((3, 2)), u=np.zeros((3, 1)))
    with pytest.raises(LCSInputError, match=r"^path: expected arrays 'x', 'u', 'x_next' in '.*partial\.npz', missing \['x_next'\] \(found \['u', 'x'\]\)$"):
        Dataset.load(path)


def test_load_file_that_is_not_npz(tmp_path):
    path = tmp_path / "junk.npz"
    path.write_text("not an npz")
    with pytest.raises(LCSInputError, match=r"^path: expected an \.npz data file .*, received '.*junk\.npz' \(could not read it"):
        Dataset.load(path)


def test_load_truncated_npz(tmp_path):
    """A truncated file is refused by name (not a BadZipFile traceback), and its handle is
    closed (warnings are errors in the tests: an unclosed file would fail this test)."""
    full, path = tmp_path / "full.npz", tmp_path / "truncated.npz"
    Dataset.from_arrays(np.zeros((50, 2)), np.zeros((50, 1)), np.zeros((50, 2))).save(full)
    path.write_bytes(full.read_bytes()[:200])
    with pytest.raises(LCSInputError, match=r"^path: expected an \.npz data file .*truncated\.npz' \(could not read it"):
        Dataset.load(path)


def test_load_refuses_pickled_arrays(tmp_path):
    path = tmp_path / "pickled.npz"
    obj = np.empty(3, dtype=object)
    np.savez(path, x=obj, u=np.zeros((3, 1)), x_next=np.zeros((3, 2)))
    with pytest.raises(LCSInputError, match=r"^path: expected an \.npz data file .*could not read it.*allow_pickle"):
        Dataset.load(path)


def test_load_file_with_inconsistent_arrays(tmp_path):
    path = tmp_path / "bad.npz"
    np.savez(path, x=np.zeros((3, 2)), u=np.zeros((3, 1)), x_next=np.zeros((4, 2)))
    with pytest.raises(LCSInputError, match=r"^x_next: expected 3 rows to match the other inputs, received 4$"):
        Dataset.load(path)


# -- solver selection ----------------------------------------------------------------------


@pytest.mark.parametrize("method", ["Fast", "clarabel", "", None])
def test_unknown_method(sys, method):
    F = torch.eye(2, dtype=F64)
    with pytest.raises(LCSInputError, match=rf"^method: expected one of 'fast', 'cvxpy', 'brute', received {method!r}$"):
        solve_lcp(F, zeros(3, 2), method=method)
    with pytest.raises(LCSInputError, match=r"^method: expected one of 'fast', 'cvxpy', 'brute'"):
        sys.solve_lcp(zeros(3, 3), zeros(3, 2), method=method)
    with pytest.raises(LCSInputError, match=r"^method: expected one of"):
        sys.step(zeros(3, 3), zeros(3, 2), method=method)


def test_brute_force_dimension_limit():
    with pytest.raises(LCSInputError, match=r"^n_lam: brute force enumerates 2\^n sets, expected n <= 12, received 13$"):
        solve_lcp(torch.eye(13, dtype=F64), zeros(1, 13), method="brute")
