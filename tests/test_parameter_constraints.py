"""Known structure (lcs_cvx.parameter_constraints, LCS.fix / LCS.mask): fixed parameters come back
bit-identical and masked entries exactly 0 after every optimiser, pruning and re-initialisation;
the restricted second-order step is the reduced problem's; the constrained least squares is
the per-row least squares on the free columns."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
import torch

import lcs_cvx
from lcs_cvx import LCS, LCSInputError
from lcs_cvx.hessian import flatten_parameters, parameter_slices, violation_hessian
from lcs_cvx.losses import regularizer, violation_loss
from lcs_cvx.parameter_constraints import (
    allowed_extra_units,
    free_entries,
    free_vector,
    growth_blocker,
    has_constraints,
    keeps_structure,
    mask_gradients_,
    project_,
    row_lstsq,
)
from lcs_cvx.resizing import add_units, eliminate_unit, keep_units, prune_units, refit_dynamics
from lcs_cvx.second_order import gauss_newton_matrix, gauss_newton_step, newton_step
from lcs_cvx.system import PARAMETER_NAMES

F64 = torch.float64
GAMMA, EPS = 0.5, 1e-2

# a (3, 1, 2) system; C's row 1 and D's column 1 held at 0 (the same pattern for both units),
# d[2] held at 0
C_MASK = [[1, 1], [0, 0], [1, 1]]
D_MASK = [[1, 0, 1], [1, 0, 1]]
D_VEC_MASK = [1, 1, 0]


@pytest.fixture(scope="module")
def system():
    truth = lcs_cvx.random_lcs(3, 1, 2, seed=0)
    with torch.no_grad():
        truth.C[1] = 0.0
        truth.D[:, 1] = 0.0
        truth.d[2] = 0.0
    train = lcs_cvx.make_dataset(truth, 300, noise=0.01, seed=1)
    test = lcs_cvx.make_dataset(truth, 100, seed=2)
    return truth, train, test


def structured(truth: LCS, seed: int = 3) -> LCS:
    """A learner that knows A and B and the zeros of C, D and d."""
    return LCS(3, 1, 2, stiffness=1.0, seed=seed).fix(A=truth.A, B=truth.B).mask(
        C=C_MASK, D=D_MASK, d=D_VEC_MASK)


def assert_structure_kept(model: LCS, truth: LCS) -> None:
    for name in ("A", "B"):
        assert torch.equal(getattr(model, name).detach(), getattr(truth, name)), name
        assert not getattr(model, name).requires_grad
    assert set(model.masks) == {"C", "D", "d"}
    assert bool((model.C[1] == 0).all()) and bool((model.D[:, 1] == 0).all())
    assert model.d[2].item() == 0.0
    assert all(getattr(model, k).requires_grad for k in ("C", "d", "D", "E", "G", "H", "c"))


# -- the API: fix, mask, masks ---------------------------------------------------------------
def test_fix_sets_copies_and_fixes():
    A = np.arange(16, dtype=np.float64).reshape(4, 4)
    m = LCS(4, 2, 3)
    assert m.fix(A=A) is m
    A[0, 0] = 99.0  # copied
    assert m.A[0, 0].item() == 0.0 and not m.A.requires_grad and m.B.requires_grad
    assert not bool(free_entries(m, "A").any()) and bool(free_entries(m, "B").all())
    assert has_constraints(m) and not has_constraints(LCS(4, 2, 3))
    # the torch convention fixes too
    m.B.requires_grad_(False)
    assert not bool(free_entries(m, "B").any())


def test_fix_F_sets_G_and_H():
    F = torch.tensor([[2.0, 0.5], [-0.3, 1.5]], dtype=F64)
    m = LCS(3, 1, 2, stiffness=0.5).fix(F=F)
    assert torch.allclose(m.F, F, atol=1e-12)
    assert not m.G.requires_grad and not m.H.requires_grad and m.C.requires_grad
    with pytest.raises(LCSInputError, match=r"^F: expected a symmetric part \(F \+ F\^T\) / 2 >= s I "
                                            r"with s = 0.5 .*received smallest eigenvalue 0.2"):
        LCS(3, 1, 2, stiffness=0.5).fix(F=0.2 * torch.eye(2, dtype=F64))


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda m: m.fix(A=np.zeros((3, 4))), r"^A: expected shape \(4, 4\), received \(3, 4\)$"),
        (lambda m: m.fix(c=np.zeros(4)), r"^c: expected shape \(3,\), received \(4,\)$"),
        (lambda m: m.fix(Q=np.zeros(3)), r"^Q: expected a parameter name among \('A', .*'F'\), "
                                          r"received 'Q'$"),
        (lambda m: m.fix(F=np.eye(3), G=np.eye(3)), r"^F: expected F alone or G and H, received F "
                                                     r"together with G$"),
        (lambda m: m.fix(A=np.full((4, 4), np.nan)), r"^A: expected finite values"),
        (lambda m: m.mask(A=np.ones((3, 4))), r"^A: expected a mask of shape \(4, 4\), received "
                                               r"shape \(3, 4\)$"),
        (lambda m: m.mask(d=[1, 0.5, 2, 1]), r"^d: expected a mask of bool or 0/1 values, received 2 "
                                              r"other values \(e.g. \[0.5, 2.0\]\)$"),
        (lambda m: m.mask(G=np.ones((3, 3))), r"^G: expected a maskable parameter name among \('A', "
                                               r"'B', 'C', 'd', 'D', 'E', 'c'\), received 'G' \(G and H"),
        (lambda m: m.mask(X=1), r"^X: expected a maskable parameter name"),
        (lambda m: m.mask(A="ones"), r"^A: expected a bool or 0/1 array of shape \(4, 4\), received "
                                      r"str 'ones'$"),
        (lambda m: m.mask(c=[1, 0, 1]).fix(c=[1.0, 1.0, 1.0]),
         r"^c: expected the held values at the entries its mask holds \(0 for mask, the given ones for hold\), received 1 other values there$"),
        (lambda m: LCS(4, 2, 3, mask=[("A", 1)]), r"^mask: expected a dict"),
    ],
)
def test_named_errors(call, match):
    m = LCS(4, 2, 3)
    before = {k: v.clone() for k, v in m.state_dict().items()}
    with pytest.raises(LCSInputError, match=match):
        call(m)
    # nothing half-applied by a refused call (the mask of the c case was a separate, valid call)
    assert all(getattr(m, k).requires_grad for k in PARAMETER_NAMES)
    if "c" not in m.masks:
        assert all(torch.equal(v, m.state_dict()[k]) for k, v in before.items())


def test_mask_sets_zeros_and_is_a_plain_attribute():
    m = LCS(4, 2, 3, init_scale=1.0, mask={"A": np.eye(4, dtype=bool)})
    assert bool((m.A[~torch.eye(4, dtype=torch.bool)] == 0).all()) and bool((m.A.diagonal() != 0).all())
    m.mask(E=torch.tensor([[1, 0], [0, 1], [1, 1]]), c=np.array([1.0, 0.0, 1.0]))
    masks = m.masks
    assert set(masks) == {"A", "E", "c"} and masks["E"].dtype == torch.bool
    masks["A"][:] = True  # a copy
    assert not bool(m.masks["A"].all())
    assert m.E[0, 1].item() == 0.0 and m.c[1].item() == 0.0
    assert free_vector(m).sum() == sum(p.numel() for p in m.parameters()) - 12 - 2 - 1
    # not in the state dict: models with and without masks exchange parameters
    plain = LCS(4, 2, 3, seed=5)
    assert set(m.state_dict()) == set(plain.state_dict())
    plain.load_state_dict(m.state_dict())
    m.load_state_dict(LCS(4, 2, 3, seed=6).state_dict())
    assert set(m.masks) == {"A", "E", "c"} and plain.masks == {}
    twin = copy.deepcopy(m)
    assert all(torch.equal(twin.masks[k], m.masks[k]) for k in m.masks)
    m.mask(A=None)
    assert set(m.masks) == {"E", "c"} and set(twin.masks) == {"A", "E", "c"}


def test_project_and_mask_gradients():
    m = LCS(2, 1, 2, init_scale=1.0).mask(A=[[1, 0], [1, 1]])
    (m.A.sum() * 3.0).backward()
    mask_gradients_(m)
    assert m.A.grad.tolist() == [[3.0, 0.0], [3.0, 3.0]]
    with torch.no_grad():
        m.A[0, 1] = 5.0
    project_(m)
    assert m.A[0, 1].item() == 0.0


def test_nothing_to_learn_is_an_error(system):
    truth, train, _ = system
    with pytest.raises(LCSInputError, match=r"^model: expected at least one learnable entry.*"
                                            r"random_lcs returns such a model"):
        lcs_cvx.fit(lcs_cvx.random_lcs(3, 1, 2), train, recipe="plain", iterations=1, progress=False)
    with pytest.raises(LCSInputError, match=r"^model: expected at least one learnable entry"):
        gauss_newton_step(lcs_cvx.random_lcs(3, 1, 2), train.x, train.u, train.x_next,
                          gamma=GAMMA, eps=EPS, reg=0.0, damping=1.0)


# -- extra units --------------------------------------------------------------------------
def test_extra_units_with_structure(system):
    truth, train, _ = system
    same = structured(truth)  # every unit has the same pattern: grown units copy it
    assert growth_blocker(same) is None and allowed_extra_units(same, "auto", 2) == 2
    big = add_units(same, 2, torch.Generator().manual_seed(0))
    assert big.masks["C"].tolist() == [[True] * 4, [False] * 4, [True] * 4]
    assert big.masks["D"].tolist() == [[True, False, True]] * 4
    assert bool((big.C[1] == 0).all()) and torch.equal(big.A, same.A) and not big.A.requires_grad

    uneven = LCS(3, 1, 2).mask(D=[[1, 1, 1], [1, 0, 1]])
    fixed_D = LCS(3, 1, 2).fix(D=np.ones((2, 3)))
    assert growth_blocker(uneven) == "the mask of D differs between units"
    assert growth_blocker(fixed_D) == "D is fixed"
    assert allowed_extra_units(fixed_D, "auto", 1) == 0
    with pytest.raises(LCSInputError, match=r"^extra_units: expected 0 or 'auto' for a model on "
                                            r"which D is fixed .*received 2$"):
        allowed_extra_units(fixed_D, 2, 2)
    with pytest.raises(LCSInputError, match=r"^extra: expected 0 for a model on which the mask of D "
                                            r"differs between units"):
        add_units(uneven, 1, torch.Generator())
    with pytest.raises(LCSInputError, match=r"^extra_units: expected 0 or 'auto'"):
        lcs_cvx.fit(fixed_D, train, recipe="best", extra_units=2, iterations=2, progress=False)
    # "auto" resolves to 0: the best recipe runs without growing
    lcs_cvx.fit(fixed_D, train, recipe="best", iterations=2, refine_iterations=1, progress=False)
    assert torch.equal(fixed_D.D, torch.ones(2, 3, dtype=F64))


# -- every optimiser path ------------------------------------------------------------------
FIT_PATHS = {
    "paper": {"recipe": "paper", "iterations": 60},
    "best": {"recipe": "best", "iterations": 120, "reinit_every": 20, "refine_iterations": 2,
             "refine_batch": 300, "prune_batch": 300},
    "gauss-newton": {"optimizer": "gauss-newton", "iterations": 3},
    "newton": {"optimizer": "newton", "iterations": 3},
    "prediction+polish": {"recipe": "plain", "loss": "prediction", "iterations": 40, "polish_iterations": 20},
    "restarts+keep_best": {"recipe": "plain", "iterations": 30, "restarts": 2, "keep_best": True, "eval_every": 10},
}


@pytest.mark.parametrize("path", FIT_PATHS)
def test_fit_keeps_fixed_and_masked(system, path):
    truth, train, test = system
    model = structured(truth)
    seen = []

    def check(record, current):  # at every record of every restart, too
        assert_structure_kept(current, truth)
        seen.append(record["restart"])

    result = lcs_cvx.fit(model, train, test=test, progress=False, callbacks=[check], **FIT_PATHS[path])
    assert result.model is model
    assert_structure_kept(model, truth)
    assert seen and seen[-1] == result.settings.run.restarts - 1  # the best recipe: 2 runs
    assert np.isfinite(result.history[-1]["e_test"])


def held_structured(truth: LCS, seed: int = 3) -> LCS:
    """A learner that holds the first row of A and d's last two entries at the truth's values
    (d[1] nonzero: a held value, not a zero), and the zeros of C and D."""
    nan = float("nan")
    A = torch.full((3, 3), nan, dtype=torch.float64)
    A[0] = truth.A[0]
    return LCS(3, 1, 2, stiffness=1.0, seed=seed).mask(C=C_MASK, D=D_MASK).hold(
        A=A, d=[nan, float(truth.d[1]), 0.0])


@pytest.mark.parametrize("path", FIT_PATHS)
def test_fit_keeps_held_values(system, path):
    """Entries held at nonzero values (LCS.hold) come back bit-identical from every training
    path (their gradients zeroed, every step restoring them; through the normalised coordinates
    and back), the rest is learned."""
    truth, train, test = system
    assert float(truth.d[1]) != 0.0
    model = held_structured(truth)
    start = model.A.detach().clone()

    def kept(current: LCS) -> None:
        assert torch.equal(current.A[0].detach(), truth.A[0]), "A[0]"
        assert current.d[1].item() == truth.d[1].item() and current.d[2].item() == 0.0
        assert bool((current.C[1] == 0).all()) and bool((current.D[:, 1] == 0).all())

    result = lcs_cvx.fit(model, train, test=test, progress=False,
                         callbacks=[lambda record, current: kept(current)], **FIT_PATHS[path])
    kept(model)
    assert not torch.equal(model.A[1:].detach(), start[1:])  # the free rows were learned
    assert np.isfinite(result.history[-1]["e_test"])


def test_hold_sets_values_and_is_checked(system, tmp_path):
    truth, _, _ = system
    model = held_structured(truth)
    assert model.masks["d"].tolist() == [True, False, False]
    assert model.held["d"][1].item() == truth.d[1].item() and math.isnan(model.held["d"][0].item())
    lcs_cvx.save_model(model, tmp_path / "held.npz")
    loaded = lcs_cvx.load_model(tmp_path / "held.npz")
    assert lcs_cvx.load_metadata(tmp_path / "held.npz")["format_version"] == lcs_cvx.io.FORMAT_VERSION
    assert all(torch.equal(getattr(loaded, k), getattr(model, k)) for k in PARAMETER_NAMES)
    assert {k: v.tolist() for k, v in loaded.masks.items()} == {k: v.tolist() for k, v in model.masks.items()}
    assert torch.equal(torch.nan_to_num(loaded.held["d"]), torch.nan_to_num(model.held["d"]))
    # units cannot be added where a unit-indexed parameter holds a value other than 0
    grown = LCS(3, 1, 2, stiffness=1.0, seed=0).hold(c=[0.5, 0.5])
    assert growth_blocker(grown) == "entries of c are held at values other than 0"
    assert growth_blocker(LCS(3, 1, 2, seed=0).hold(c=[0.0, 0.0])) is None
    assert growth_blocker(model) is None  # A and d are not indexed by the units
    # a later mask of another parameter leaves the held values as they are
    again = held_structured(truth).mask(E=[[1], [0]])
    assert again.d[1].item() == truth.d[1].item() and torch.equal(again.A[0].detach(), truth.A[0])
    assert again.E[1, 0].item() == 0.0
    with pytest.raises(LCSInputError, match=r"^G: expected a name among"):
        LCS(3, 1, 2).hold(G=np.zeros((2, 2)))
    with pytest.raises(LCSInputError, match=r"^d: expected an array of shape \(3,\) \(NaN where learned\), received shape \(2,\)"):
        LCS(3, 1, 2).hold(d=[0.0, 1.0])
    with pytest.raises(LCSInputError, match=r"^d: expected an array of shape \(3,\) \(NaN where learned\), received str"):
        LCS(3, 1, 2).hold(d="gravity")
    with pytest.raises(LCSInputError, match=r"^d: expected finite values to hold"):
        LCS(3, 1, 2).hold(d=[0.0, float("inf"), float("nan")])


def test_best_recipe_grows_units_with_structure(system):
    """The "best" path above really trains extra units, reinitialises and prunes them."""
    from lcs_cvx.train.state import TrainState

    truth, train, _ = system
    opts = lcs_cvx.RECIPES["best"]
    state = TrainState(structured(truth), train, opts, 0)
    assert state.n_extra == 1 and state.work.n_lam == 3
    assert set(state.work.masks) == {"C", "D", "d"} and not state.work.A.requires_grad


def test_fix_F_through_gauss_newton(system):
    truth, train, _ = system
    model = LCS(3, 1, 2, stiffness=0.25, seed=3).fix(F=truth.F, c=truth.c)
    G, H, c = model.G.detach().clone(), model.H.detach().clone(), model.c.detach().clone()
    lcs_cvx.fit(model, train, recipe="plain", optimizer="gauss-newton", iterations=2, progress=False)
    assert torch.equal(model.G, G) and torch.equal(model.H, H) and torch.equal(model.c, c)


def test_checkpoint_resume_keeps_structure(system, tmp_path):
    truth, train, test = system
    options = {**FIT_PATHS["best"], "eval_every": 20, "checkpoint_every": 20}
    ckpt = tmp_path / "run.ckpt"
    first = structured(truth)
    lcs_cvx.fit(first, train, test=test, progress=False, checkpoint=ckpt,
                callbacks=[lambda rec, m: rec["iteration"] >= 40], **options)
    assert_structure_kept(first, truth)
    resumed = structured(truth, seed=4)  # the checkpoint's values replace the free ones
    lcs_cvx.fit(resumed, train, test=test, progress=False, checkpoint=ckpt, resume=True, **options)
    clean = structured(truth)
    lcs_cvx.fit(clean, train, test=test, progress=False, **options)
    assert_structure_kept(resumed, truth)
    assert all(torch.equal(getattr(resumed, k), getattr(clean, k)) for k in PARAMETER_NAMES)


def test_reinit_saturated_redraws_free_entries_only():
    from lcs_cvx.train.phases import reinit_saturated
    from lcs_cvx.train.state import TrainState

    truth = lcs_cvx.random_lcs(3, 1, 2, seed=1)
    data = lcs_cvx.make_dataset(truth, 200, seed=1)
    model = LCS(3, 1, 2, init_scale=0.5, seed=2).fix(D=np.ones((2, 3))).mask(E=[[0], [1]],
                                                                            C=[[1, 1], [0, 0], [1, 1]])
    with torch.no_grad():
        model.c[0] = -1e3  # unit 0 active on every sample: saturated
        model.c[1] = 1e5  # unit 1 never active
    before = {k: getattr(model, k).detach().clone() for k in PARAMETER_NAMES}
    reinit_saturated(TrainState(model, data, lcs_cvx.RECIPES["best"].replace(extra_units=0), 0))
    assert torch.equal(model.D, before["D"]) and model.E[0, 0].item() == 0.0
    assert model.c[0].item() != -1e3 and model.C[0, 0].item() != float(before["C"][0, 0])
    assert bool((model.C[1] == 0).all())
    assert torch.equal(model.c[1], before["c"][1])  # unit 1 is not saturated


# -- second order: the restricted step is the reduced problem's -----------------------------
def _full_copy(model: LCS) -> LCS:
    """The same values, every parameter learnable and unmasked."""
    full = LCS(model.n_x, model.n_u, model.n_lam, stiffness=float(model.stiffness))
    full.load_state_dict(model.state_dict())
    return full


def _penalty_step(model: LCS, data, mu: float, reg: float, matrix) -> torch.Tensor:
    """The full problem's step with the non-free coordinates held by a huge diagonal penalty:
    ``(M + mu I + K diag(1 - f)) d = -g``, which tends to the reduced step as ``K -> inf``."""
    full = _full_copy(model)
    loss = violation_loss(full, data.x, data.u, data.x_next, gamma=GAMMA, eps=EPS) + regularizer(full, reg)
    g = torch.cat([t.reshape(-1) for t in torch.autograd.grad(loss, list(full.parameters()))])
    M = matrix(full)
    reg_diag = torch.zeros_like(g)
    reg_diag[parameter_slices(full)["C"]] = 2.0 * reg
    M = 0.5 * (M + M.mT) + torch.diag(reg_diag + mu)
    held = (~free_vector(model)).to(F64)
    return -torch.linalg.solve(M + torch.diag(1e12 * held), g)


@pytest.mark.parametrize("method", ["gauss-newton", "newton"])
def test_restricted_step_is_the_reduced_problems(system, method):
    truth, train, _ = system
    data = lcs_cvx.Dataset(train.x[:100], train.u[:100], train.x_next[:100])
    model = structured(truth)
    with torch.no_grad():  # near the truth: the step is accepted at once
        for k in ("C", "d", "D", "E", "c"):
            getattr(model, k).copy_(getattr(truth, k) + 0.05)
        project_(model)
    mu, reg = (1e-2 if method == "gauss-newton" else 1.0), 1e-3  # Newton: M + mu I definite
    before = copy.deepcopy(model)
    theta0 = flatten_parameters(model)
    if method == "gauss-newton":
        res = gauss_newton_step(model, data.x, data.u, data.x_next, gamma=GAMMA, eps=EPS, reg=reg,
                                damping=mu, max_tries=1)
        matrix = lambda m: gauss_newton_matrix(m, data.x, data.u, data.x_next, GAMMA, EPS)  # noqa: E731
    else:
        res = newton_step(model, data.x, data.u, data.x_next, gamma=GAMMA, eps=EPS, reg=reg,
                          damping=mu, max_tries=1)
        matrix = lambda m: violation_hessian(m, data.x, data.u, data.x_next, GAMMA, EPS)  # noqa: E731
    assert res.accepted
    d = flatten_parameters(model) - theta0
    assert bool((d[~free_vector(model)] == 0).all())
    expected = _penalty_step(before, data, mu, reg, matrix)
    t = float(d @ expected / (expected @ expected))  # Newton's line search may halve the step
    assert t in (1.0, 0.5, 0.25) or min(abs(t - 2.0 ** -k) for k in range(12)) < 1e-6
    assert float((d - t * expected).norm() / expected.norm()) < 1e-6
    assert_structure_kept(model, truth)


@pytest.mark.parametrize("step", [gauss_newton_step, newton_step])
def test_operator_path_projects(system, step):
    """Conjugate gradients on the projected operator (dense_max=0): the fixed coordinates come
    back bit-identical, masked entries 0, and the loss decreases."""
    truth, train, _ = system
    model = structured(truth)
    res = step(model, train.x, train.u, train.x_next, gamma=GAMMA, eps=EPS, reg=1e-3, damping=1e-2,
               dense_max=0)
    assert res.accepted
    assert_structure_kept(model, truth)


# -- least squares with known entries -------------------------------------------------------
def test_row_lstsq_is_the_per_row_least_squares():
    g = torch.Generator().manual_seed(0)
    N, K, R = 50, 6, 4
    phi, target = torch.randn(N, K, generator=g, dtype=F64), torch.randn(N, R, generator=g, dtype=F64)
    free = torch.rand(R, K, generator=g) > 0.4
    free[0] = False  # a row without free entries
    free[1] = free[2]  # two rows with one pattern
    fixed = torch.randn(R, K, generator=g, dtype=F64)
    ridge = torch.rand(K, generator=g, dtype=F64) * 0.1
    W = row_lstsq(phi, target, free, fixed, ridge)
    assert torch.equal(W[~free], fixed[~free])  # copied exactly
    for i in range(R):
        S = free[i]
        if not bool(S.any()):
            continue
        b = target[:, i] - phi[:, ~S] @ fixed[i, ~S]
        # 1/(2N) ||b - phi_S w||^2 + 1/2 sum ridge w^2 as one stacked least-squares problem
        stacked = torch.cat([phi[:, S] / N ** 0.5, torch.diag(ridge[S].sqrt())])
        rhs = torch.cat([b / N ** 0.5, torch.zeros(int(S.sum()), dtype=F64)])
        w = torch.linalg.lstsq(stacked, rhs[:, None]).solution[:, 0]
        assert torch.allclose(W[i, S], w, rtol=1e-10, atol=1e-12)
    every = row_lstsq(phi, target, torch.ones(R, K, dtype=torch.bool), fixed, ridge)
    expected = torch.linalg.solve(phi.mT @ phi / N + torch.diag(ridge), phi.mT @ target / N).mT
    assert torch.equal(every, expected)
    with pytest.raises(LCSInputError, match=r"^row_lstsq: expected phi \(N, K\)"):
        row_lstsq(phi, target, free[:, :3], fixed, ridge)


def test_refit_dynamics_fits_free_entries_only(system):
    truth, train, _ = system
    model = structured(truth)
    refit_dynamics(model, train.x, train.u, train.x_next)
    assert_structure_kept(model, truth)
    lam = model.solve_lcp(train.x, train.u).lam.detach()
    phi = torch.cat([train.x, train.u, lam, torch.ones(len(train), 1, dtype=F64)], 1)
    W = torch.cat([model.A, model.B, model.C, model.d[:, None]], 1).detach()
    free = torch.cat([torch.zeros(3, 4, dtype=torch.bool), torch.tensor(C_MASK, dtype=torch.bool),
                      torch.tensor(D_VEC_MASK, dtype=torch.bool)[:, None]], 1)
    for i in range(3):
        S = free[i]
        b = train.x_next[:, i] - phi[:, ~S] @ W[i, ~S]
        w = torch.linalg.lstsq(phi[:, S], b[:, None]).solution[:, 0]
        assert torch.allclose(W[i, S], w, rtol=1e-8, atol=1e-10), i


# -- pruning ---------------------------------------------------------------------------------
def test_pruning_respects_fixed_and_masked():
    """Unit 3 is active on every sample: eliminating it is exact but moves C_3 D_3 / F_33 into A.
    With A fixed (or masked where that product lands) the elimination is not a candidate."""
    sys = lcs_cvx.random_lcs(4, 2, 4, seed=5)
    with torch.no_grad():
        sys.c[3] = -1e3
    data = lcs_cvx.make_dataset(sys, 300, seed=1)
    sys.requires_grad_(True)
    assert keeps_structure(eliminate_unit(sys, 3), sys, [0, 1, 2])
    free_pruned = prune_units(sys, 3, data.x, data.u, data.x_next)
    assert not torch.equal(free_pruned.A, sys.A)  # the elimination, chosen when allowed

    fixed = copy.deepcopy(sys).fix(A=sys.A)
    assert not keeps_structure(eliminate_unit(fixed, 3), fixed, [0, 1, 2])
    assert keeps_structure(keep_units(fixed, [0, 1, 2]), fixed, [0, 1, 2])
    pruned = prune_units(fixed, 3, data.x, data.u, data.x_next)
    assert torch.equal(pruned.A, sys.A) and not pruned.A.requires_grad

    pattern = torch.ones(4, 4, dtype=torch.bool)
    pattern[0, 1] = False
    masked = copy.deepcopy(sys).mask(A=pattern, C=torch.ones(4, 4))
    assert not keeps_structure(eliminate_unit(masked, 3), masked, [0, 1, 2])
    pruned = prune_units(masked, 3, data.x, data.u, data.x_next)
    assert pruned.A[0, 1].item() == 0.0 and pruned.masks["A"].tolist() == pattern.tolist()
    assert pruned.masks["C"].shape == (4, 3)


# -- model files -----------------------------------------------------------------------------
def test_save_load_round_trip(system, tmp_path):
    truth, _, _ = system
    model = structured(truth)
    lcs_cvx.save_model(model, tmp_path / "m.npz")
    loaded = lcs_cvx.load_model(tmp_path / "m.npz")
    assert all(torch.equal(getattr(loaded, k), getattr(model, k)) for k in PARAMETER_NAMES)
    assert [k for k in PARAMETER_NAMES if not getattr(loaded, k).requires_grad] == ["A", "B"]
    assert {k: v.tolist() for k, v in loaded.masks.items()} == {
        k: v.tolist() for k, v in model.masks.items()}
    meta = lcs_cvx.load_metadata(tmp_path / "m.npz")
    assert meta["fixed"] == ["A", "B"] and meta["masks"] == ["C", "d", "D"]

    # a version-1 file (no structure) loads learnable
    arrays = dict(np.load(tmp_path / "m.npz"))
    old = json.loads(str(arrays["meta"]))
    old["format_version"] = 1
    del old["fixed"], old["masks"]
    plain = {k: v for k, v in arrays.items() if not k.startswith("mask_")}
    np.savez(tmp_path / "v1.npz", **{**plain, "meta": np.array(json.dumps(old))})
    v1 = lcs_cvx.load_model(tmp_path / "v1.npz")
    assert all(p.requires_grad for p in v1.parameters()) and v1.masks == {}

    bad = {**arrays, "mask_C": arrays["mask_C"].astype(np.float64)}
    np.savez(tmp_path / "bad.npz", **bad)
    with pytest.raises(LCSInputError, match=r"array 'mask_C' in .*expected a bool array of shape "
                                            r"\(3, 2\), received shape \(3, 2\) and dtype float64"):
        lcs_cvx.load_model(tmp_path / "bad.npz")
    # version 3: a masked entry holds its stored value; version 2 held masked entries at 0 only
    filled = {**arrays, "C": np.ones((3, 2))}
    np.savez(tmp_path / "filled.npz", **filled)
    held = lcs_cvx.load_model(tmp_path / "filled.npz")
    assert torch.equal(held.C.detach(), torch.ones(3, 2, dtype=torch.float64))
    assert torch.equal(held.held["C"][~held.masks["C"]], torch.ones(3, 2, dtype=torch.float64)[~held.masks["C"]])
    v2 = json.loads(str(arrays["meta"]))
    v2["format_version"] = 2
    np.savez(tmp_path / "filled_v2.npz", **{**filled, "meta": np.array(json.dumps(v2))})
    with pytest.raises(LCSInputError, match=r"expected C to be 0 where the mask is False \(format version 2\)"):
        lcs_cvx.load_model(tmp_path / "filled_v2.npz")
    lcs_cvx.load_model(tmp_path / "m.npz")  # a version-2 reader's file with zeros loads either way
