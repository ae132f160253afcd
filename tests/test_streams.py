"""lcs_cvx.streams: streams at two rates on one clock against closed forms (no files)."""

from __future__ import annotations

import numpy as np
import pytest

from lcs_cvx import LCSInputError
from lcs_cvx.streams import SNAP, Stream, align


def sine(t):
    return np.sin(3.0 * t)


def test_states_interpolate_and_inputs_hold_on_the_grid():
    t_x, t_u = np.arange(0, 2.0, 0.01), np.arange(0, 2.0, 0.03)
    x = Stream("x", t_x, sine(t_x), "state", ("x",))
    u = Stream("u", t_u, np.arange(len(t_u), dtype=float), "input", ("u",))
    [(xs, us)], desc = align([x, u], dt=0.025)
    grid = 0.025 * np.arange(len(xs))
    bound = 9.0 * 0.01**2 / 8  # |x''| h^2 / 8 of linear interpolation
    assert np.abs(xs[:, 0] - sine(grid)).max() <= bound
    assert np.array_equal(us[:, 0], np.floor(grid[:-1] / 0.03 + SNAP))  # the last command at or before
    assert desc.dt == 0.025 and desc.splits == 0 and desc.transitions == len(us)


def test_a_grid_point_at_a_sample_takes_it_as_it_is():
    t = np.arange(100) * 0.1 + 1e-9  # time stamps a nanosecond late
    [(xs, _)], _ = align([Stream("x", t, sine(t), "state", ("x",))], dt=0.1)
    assert np.array_equal(xs[:, 0], sine(t))


def test_gaps_split_and_short_pieces_are_counted():
    t = np.concatenate([np.arange(0, 1, 0.01), np.arange(1.5, 1.505, 0.01), np.arange(2.0, 3.0, 0.01)])
    runs, desc = align([Stream("x", t, sine(t), "state", ("x",))], dt=0.01)
    assert len(runs) == 2 and desc.splits == 2 and desc.dropped_pieces == 1
    # a gap of one stream past the others' end cuts nothing
    t_u = np.concatenate([np.arange(0, 2.0, 0.05), [5.0]])
    runs, desc = align([Stream("x", t[t < 1], sine(t[t < 1]), "state", ("x",)),
                        Stream("u", t_u, np.zeros(len(t_u)), "input", ("u",))], dt=0.05)
    assert len(runs) == 1 and desc.splits == 0 and len(runs[0][1]) == 19
    with pytest.raises(LCSInputError, match=r"max_gap: expected a number > 0"):
        align([Stream("x", t, sine(t), "state", ("x",))], max_gap=0)


def test_bad_streams_are_named():
    t = np.arange(10) * 0.1
    with pytest.raises(LCSInputError, match=r"stream 'x': expected one time stamp per sample, received 10 time "
                                            r"stamps and 9 samples"):
        Stream("x", t, np.zeros(9), "state", ("x",))
    with pytest.raises(LCSInputError, match=r"kind: expected 'state' or 'input', received 'output'"):
        Stream("x", t, np.zeros(10), "output", ("x",))
    with pytest.raises(LCSInputError, match=r"state: expected at least one state stream"):
        align([Stream("u", t, np.zeros(10), "input", ("u",))])
    with pytest.raises(LCSInputError, match=r"stream 'x': expected at least two samples, received 1"):
        align([Stream("x", t[:1], np.zeros(1), "state", ("x",))])
