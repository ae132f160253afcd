"""Adding and removing complementarity units (lcs_cvx.resizing)."""

import pytest
import torch

import lcs_cvx
from lcs_cvx import LCSInputError
from lcs_cvx.resizing import add_units, eliminate_unit, keep_units, prune_units, refit_dynamics


def test_submodel_of_all_units_is_the_model():
    sys = lcs_cvx.random_lcs(4, 2, 3, seed=0)
    data = lcs_cvx.make_dataset(sys, 200, seed=1)
    same = keep_units(sys, [0, 1, 2])
    assert torch.allclose(same.F, sys.F, atol=1e-12)
    assert torch.allclose(same.step(data.x, data.u), sys.step(data.x, data.u), atol=1e-9)


def test_submodel_permutes_units():
    sys = lcs_cvx.random_lcs(4, 2, 3, seed=0)
    data = lcs_cvx.make_dataset(sys, 200, seed=1)
    perm = keep_units(sys, [2, 0, 1])
    assert torch.allclose(perm.F, sys.F[[2, 0, 1]][:, [2, 0, 1]], atol=1e-12)
    assert torch.allclose(perm.step(data.x, data.u), sys.step(data.x, data.u), atol=1e-9)


def test_grow_keeps_the_old_block_and_submodel_recovers_it():
    sys = lcs_cvx.random_lcs(4, 2, 3, seed=0).requires_grad_(True)  # learnable: no fixed units
    big = add_units(sys, 2, torch.Generator().manual_seed(0))
    assert big.n_lam == 5 and big.sigma_min >= 2 * float(sys.stiffness) - 1e-12
    assert torch.allclose(big.F[:3, :3], sys.F, atol=1e-12)
    back = keep_units(big, [0, 1, 2])
    assert torch.allclose(back.F, sys.F, atol=1e-12)
    for name in ("A", "B", "C", "d", "D", "E", "c"):
        assert torch.equal(getattr(back, name), getattr(sys, name)), name


def _useless_unit() -> tuple[lcs_cvx.LCS, lcs_cvx.LCS]:
    """A (4, 2, 3) system and the same with a 4th unit that is decoupled (F block diagonal), active
    on some samples and has C[:, 3] = 0."""
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
    return sys, big


def test_prune_removes_the_useless_unit():
    """The useless unit never changes x', so pruning to 3 units removes it and keeps the
    system's predictions exactly."""
    sys, big = _useless_unit()
    data = lcs_cvx.make_dataset(sys, 300, seed=1)
    assert bool((big.solve_lcp(data.x, data.u).lam[:, 3] > 0).any())  # the unit is active somewhere
    small = prune_units(big, 3, data.x, data.u, data.x_next)
    assert small.n_lam == 3
    assert torch.allclose(small.step(data.x, data.u), data.x_next, atol=1e-8)


@pytest.mark.parametrize("lookahead", [1, 2, 3])
def test_prune_lookahead_keeps_the_best_repaired_candidate(lookahead):
    """The repair below spoils the first candidate it is given (the lowest loss before repair)
    beyond what a refit of (A, B, C, d) undoes. With lookahead 1 that candidate is kept; with
    k > 1 the k best are repaired and the best after repair (a lossless one) is kept."""
    sys, big = _useless_unit()
    data = lcs_cvx.make_dataset(sys, 300, seed=1)
    seen: list[lcs_cvx.LCS] = []

    def repair(model: lcs_cvx.LCS) -> None:
        seen.append(model)
        if len(seen) == 1:
            with torch.no_grad():
                model.c.add_(1e3)  # every unit inactive: no refit of the output brings it back

    small = prune_units(big, 3, data.x, data.u, data.x_next, repair=repair, lookahead=lookahead)
    assert len(seen) == lookahead  # one removal, the k best candidates repaired
    with torch.no_grad():
        err = float((small.step(data.x, data.u) - data.x_next).abs().max())
    if lookahead == 1:
        assert small is seen[0] and err > 1e-3
    else:
        assert small is not seen[0] and err < 1e-6


def _always_active(seed: int = 0) -> lcs_cvx.LCS:
    """A (4, 2, 4) system whose unit 3 is active on every sample of make_dataset's box."""
    sys = lcs_cvx.random_lcs(4, 2, 4, seed=seed)
    with torch.no_grad():
        sys.c[3] = -1e3
    return sys


def test_pivot_is_exact_for_an_always_active_unit():
    sys = _always_active()
    data = lcs_cvx.make_dataset(sys, 300, seed=1)
    assert bool((data.lam[:, 3] > 0).all())
    small = eliminate_unit(sys, 3)
    assert small.n_lam == 3 and small.sigma_min >= 2 * float(sys.stiffness) - 1e-9  # Assumption 1 kept
    assert torch.allclose(small.step(data.x, data.u), data.x_next, atol=1e-8)
    # the kept units' lam is unchanged; deleting the unit instead is wrong
    assert torch.allclose(small.solve_lcp(data.x, data.u).lam, data.lam[:, :3], atol=1e-8)
    deleted = keep_units(sys, [0, 1, 2])
    with torch.no_grad():
        assert float((deleted.step(data.x, data.u) - data.x_next).abs().max()) > 1.0


def test_pivot_matches_the_schur_complement_formula():
    sys = lcs_cvx.random_lcs(3, 1, 3, seed=4)
    small = eliminate_unit(sys, 1)
    F, r = sys.F.detach(), [0, 2]
    schur = F[r][:, r] - F[r][:, [1]] @ F[[1]][:, r] / F[1, 1]
    assert torch.allclose(small.F, schur, atol=1e-12)
    assert torch.allclose(small.A, sys.A - torch.outer(sys.C[:, 1], sys.D[1]) / F[1, 1], atol=1e-12)


def test_refit_dynamics_recovers_the_output_matrices():
    sys = lcs_cvx.random_lcs(4, 2, 3, seed=2)
    data = lcs_cvx.make_dataset(sys, 400, seed=3)
    m = lcs_cvx.LCS.from_matrices(**sys.to_matrices())
    with torch.no_grad():
        for name in ("A", "B", "C", "d"):
            getattr(m, name).add_(0.3 * torch.randn_like(getattr(m, name)))
    loss = refit_dynamics(m, data.x, data.u, data.x_next)
    assert loss < 1e-20
    for name in ("A", "B", "C", "d"):
        assert torch.allclose(getattr(m, name), getattr(sys, name), atol=1e-9), name
    # with reg, the exact minimiser of L_pred + reg ||C||^2: its gradient in (A, B, C, d) vanishes
    refit_dynamics(m, data.x, data.u, data.x_next, reg=0.1)
    m.zero_grad()
    lam = m.solve_lcp(data.x, data.u).lam.detach()
    pred = data.x @ m.A.mT + data.u @ m.B.mT + lam @ m.C.mT + m.d
    (0.5 * ((pred - data.x_next) ** 2).sum(-1).mean() + 0.1 * (m.C ** 2).sum()).backward()
    for name in ("A", "B", "C", "d"):
        assert float(getattr(m, name).grad.abs().max()) < 1e-9, name


def test_prune_eliminates_an_always_active_unit():
    """Deleting any unit of this system loses its predictions; eliminating unit 3 keeps them."""
    sys = _always_active(seed=5)
    data = lcs_cvx.make_dataset(sys, 300, seed=1)
    sys.requires_grad_(True)  # random_lcs fixes every parameter; an elimination changes A, B, d
    calls = []
    small = prune_units(sys, 3, data.x, data.u, data.x_next, repair=lambda m: calls.append(m.n_lam))
    assert small.n_lam == 3 and calls == [3]
    assert torch.allclose(small.step(data.x, data.u), data.x_next, atol=1e-7)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda s: keep_units(s, []), r"keep: expected distinct unit indices in \[0, 3\)"),
        (lambda s: keep_units(s, [0, 0]), r"keep: expected distinct"),
        (lambda s: keep_units(s, [3]), r"keep: expected distinct"),
        (lambda s: add_units(s, -1, torch.Generator()), r"extra: expected an integer >= 0"),
        (lambda s: eliminate_unit(s, 3), r"j: expected a unit index in \[0, 3\)"),
        (lambda s: eliminate_unit(s, True), r"j: expected a unit index"),
        (lambda s: eliminate_unit(keep_units(s, [0]), 0), r"n_lam >= 2, received 0 \(n_lam = 1\)"),
        (lambda s: prune_units(s, 0, *([torch.zeros(1, 4)] * 3)), r"n_lam: expected an integer in \[1, 3\]"),
        (lambda s: prune_units(s, 2, *([torch.zeros(1, 4)] * 3), lookahead=0), r"lookahead: expected an integer >= 1"),
    ],
)
def test_invalid_units(call, match):
    with pytest.raises(LCSInputError, match=match):
        call(lcs_cvx.random_lcs(4, 2, 3, seed=0))
