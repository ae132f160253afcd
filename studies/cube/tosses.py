"""The cube study's tosses (:func:`lcs_cvx.datasets.cube_tosses`) split by toss, and the note its
outputs carry: what :mod:`studies.cube.study` fits on and :mod:`studies.cube.report` and
:mod:`studies.cube.split_effect` evaluate on.

Split 50 / 25 / 25 % (dair_pll's proportions for real data) by a fixed permutation of the 550
tosses (NumPy ``default_rng(SPLIT_SEED)``): 275 training, 138 validation and 137 test tosses.
"""

from __future__ import annotations

import numpy as np

import lcs_cvx

__all__ = ["SPLIT_SEED", "SMOKE_TOSSES", "MACHINE", "DATE", "split", "subset", "study_parts"]

SPLIT_SEED = 0
#: The validation and test tosses of a smoke run (a check of the plumbing, not a measurement).
SMOKE_TOSSES = 8
#: The machine and date of the committed results (the reports' "measured on" note).
MACHINE = "2-core x86-64 VM, 1 torch thread"
DATE = "2026-11-26 (the kinematic LCSs, the LCS in the cube's symmetry frames, the rigid body and the comparison with dair_pll: 2026-11-28)"


def split(n_tosses: int, seed: int = SPLIT_SEED) -> dict[str, list[int]]:
    """Toss indices ``{"train": 50 %, "validation": 25 %, "test": the rest}`` of a seeded
    permutation (disjoint, together every toss)."""
    perm = np.random.default_rng(seed).permutation(n_tosses).tolist()
    a, b = n_tosses // 2, n_tosses // 2 + (n_tosses - n_tosses // 2 + 1) // 2
    return {"train": perm[:a], "validation": perm[a:b], "test": perm[b:]}


def subset(data: lcs_cvx.Trajectories, idx: list[int]) -> lcs_cvx.Trajectories:
    """The tosses ``idx`` of ``data``, in that order."""
    return lcs_cvx.Trajectories([data.xs[i] for i in idx], [data.us[i] for i in idx])


def study_parts(n_tosses: int, smoke: bool = False) -> dict[str, list[int]]:
    """:func:`split`, with :data:`SMOKE_TOSSES` validation and test tosses for a smoke run."""
    parts = split(n_tosses)
    if smoke:
        parts = {"train": parts["train"], "validation": parts["validation"][:SMOKE_TOSSES],
                 "test": parts["test"][:SMOKE_TOSSES]}
    return parts
