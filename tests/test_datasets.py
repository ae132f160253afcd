"""The shipped data sets (lcs_cvx.datasets): the ContactNets cube tosses as trajectories."""

from __future__ import annotations

import numpy as np
import torch

import lcs_cvx
from lcs_cvx.datasets import CUBE_COLUMNS, CUBE_DT, CUBE_SIDE, cube_tosses


def test_cube_tosses_are_550_tosses_of_13_states_without_input():
    tosses = cube_tosses()
    assert isinstance(tosses, lcs_cvx.Trajectories)
    assert len(tosses) == 550 and tosses.n_x == 13 and tosses.n_u == 0
    assert len(CUBE_COLUMNS) == 13
    lengths = np.array([len(x) for x in tosses.xs])
    assert lengths.min() == 85 and lengths.max() == 139 and lengths.sum() == 58_362
    x = torch.cat(tosses.xs)
    q = x[:, :4]
    assert torch.allclose(q.norm(dim=1), torch.ones(len(q), dtype=q.dtype), atol=1e-6)  # unit quaternions
    # the cube rests on the table at the end of a toss: its centre about half a side up
    heights = torch.stack([t[-1, 6] for t in tosses.xs])
    assert abs(float(heights.median()) - CUBE_SIDE / 2) < 0.01
    # positions and velocities agree: the finite difference of the position is the velocity
    t = tosses.xs[0]
    fd = (t[2:, 4:7] - t[:-2, 4:7]) / (2 * CUBE_DT)
    assert float((fd - t[1:-1, 10:13]).abs().median()) < 0.1


def test_cube_tosses_split_by_toss():
    train, rest = cube_tosses().split(0.5, seed=0)
    assert len(train) == 275 and len(rest) == 275
    first = {tuple(x[0].tolist()) for x in train.xs}
    assert not first & {tuple(x[0].tolist()) for x in rest.xs}
