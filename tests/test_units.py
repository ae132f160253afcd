"""Adding and removing complementarity units (lcs_cvx.units)."""

import pytest
import torch

import lcs_cvx
from lcs_cvx import LCSInputError
from lcs_cvx.units import grow, prune, submodel


def test_submodel_of_all_units_is_the_model():
    sys = lcs_cvx.random_lcs(4, 2, 3, seed=0)
    data = lcs_cvx.make_dataset(sys, 200, seed=1)
    same = submodel(sys, [0, 1, 2])
    assert torch.allclose(same.F, sys.F, atol=1e-12)
    assert torch.allclose(same.step(data.x, data.u), sys.step(data.x, data.u), atol=1e-9)


def test_submodel_permutes_units():
    sys = lcs_cvx.random_lcs(4, 2, 3, seed=0)
    data = lcs_cvx.make_dataset(sys, 200, seed=1)
    perm = submodel(sys, [2, 0, 1])
    assert torch.allclose(perm.F, sys.F[[2, 0, 1]][:, [2, 0, 1]], atol=1e-12)
    assert torch.allclose(perm.step(data.x, data.u), sys.step(data.x, data.u), atol=1e-9)


def test_grow_keeps_the_old_block_and_submodel_recovers_it():
    sys = lcs_cvx.random_lcs(4, 2, 3, seed=0)
    big = grow(sys, 2, torch.Generator().manual_seed(0))
    assert big.n_lam == 5 and big.sigma_min >= 2 * float(sys.stiffness) - 1e-12
    assert torch.allclose(big.F[:3, :3], sys.F, atol=1e-12)
    back = submodel(big, [0, 1, 2])
    assert torch.allclose(back.F, sys.F, atol=1e-12)
    for name in ("A", "B", "C", "d", "D", "E", "c"):
        assert torch.equal(getattr(back, name), getattr(sys, name)), name


def test_prune_removes_the_useless_unit():
    """Unit 3 is decoupled (F block diagonal) and has C[:, 3] = 0: it never changes x', so
    pruning to 3 units removes it and keeps the system's predictions exactly."""
    sys = lcs_cvx.random_lcs(4, 2, 3, seed=0)
    F = torch.zeros(4, 4, dtype=torch.float64)
    F[:3, :3] = sys.F
    F[3, 3] = 2.0
    m = sys.to_matrices()
    big = lcs_cvx.LCS.from_matrices(
        A=m["A"], B=m["B"], d=m["d"], F=F,
        C=torch.cat([sys.C, torch.zeros(4, 1, dtype=torch.float64)], 1),
        D=torch.cat([sys.D, torch.ones(1, 4, dtype=torch.float64)], 0),
        E=torch.cat([sys.E, torch.ones(1, 2, dtype=torch.float64)], 0),
        c=torch.cat([sys.c, -torch.ones(1, dtype=torch.float64)]),
    )
    data = lcs_cvx.make_dataset(sys, 300, seed=1)
    assert bool((big.solve_lcp(data.x, data.u)[:, 3] > 0).any())  # the unit is active somewhere
    small = prune(big, 3, data.x, data.u, data.x_next)
    assert small.n_lam == 3
    assert torch.allclose(small.step(data.x, data.u), data.x_next, atol=1e-8)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda s: submodel(s, []), r"keep: expected distinct unit indices in \[0, 3\)"),
        (lambda s: submodel(s, [0, 0]), r"keep: expected distinct"),
        (lambda s: submodel(s, [3]), r"keep: expected distinct"),
        (lambda s: grow(s, -1, torch.Generator()), r"extra: expected an integer >= 0"),
    ],
)
def test_invalid_units(call, match):
    with pytest.raises(LCSInputError, match=match):
        call(lcs_cvx.random_lcs(4, 2, 3, seed=0))
