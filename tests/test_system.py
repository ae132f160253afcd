"""The LCS model (:mod:`lcs_cvx.system`), eq. (1):

    x' = A x + B u + C lam + d,    0 <= lam _|_ D x + E u + F lam + c >= 0,
    F = G G^T + H - H^T + s I.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import random_p_matrix
from zoo import K_WALL, SPRING_POINTS, spring_wall, spring_wall_by_hand

import lcs_cvx
from lcs_cvx import LCS, LCPSolution, random_lcs
from lcs_cvx.lcp import solve_lcp_brute
from lcs_cvx.problems import sym_min_eig
from lcs_cvx.system import ACTIVE_TOL, DEFAULT_STIFFNESS, MATRIX_NAMES, PARAMETER_NAMES

F64 = torch.float64


def uniform(shape, scale, seed):
    g = np.random.default_rng(seed)
    return torch.tensor(scale * (2 * g.random(shape) - 1), dtype=F64)


# -- construction and the parameterisation of F -------------------------------------------


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("stiffness", [1e-3, 0.5, 2.0])
def test_random_lcs_f_is_a_p_matrix(seed, stiffness):
    n_lam = 5
    sys = random_lcs(3, 2, n_lam, stiffness=stiffness, seed=seed)
    I = torch.eye(n_lam, dtype=F64)
    expected = sys.G @ sys.G.mT + sys.H - sys.H.mT + stiffness * I
    assert torch.allclose(sys.F, expected, rtol=0, atol=1e-15)
    eig = torch.linalg.eigvalsh(sys.F + sys.F.mT)
    assert float(eig[0]) >= 2 * stiffness * (1 - 1e-12)
    assert sys.sigma_min == pytest.approx(float(eig[0]), rel=1e-14)
    assert sys.sigma_min == pytest.approx(float(sym_min_eig(sys.F)), rel=1e-14)


def test_random_lcs_entries_seed_and_shapes():
    sys = random_lcs(4, 2, 3, seed=11)
    shapes = {"A": (4, 4), "B": (4, 2), "C": (4, 3), "d": (4,), "D": (3, 4), "E": (3, 2),
              "G": (3, 3), "H": (3, 3), "c": (3,)}
    for name in PARAMETER_NAMES:
        p = getattr(sys, name)
        assert tuple(p.shape) == shapes[name]
        assert p.dtype == F64
        assert not p.requires_grad
        assert float(p.abs().max()) <= 1.0  # U[-1, 1]
    allvals = torch.cat([getattr(sys, k).flatten() for k in PARAMETER_NAMES])
    assert float(allvals.min()) < -0.5 and float(allvals.max()) > 0.5
    again = random_lcs(4, 2, 3, seed=11)
    other = random_lcs(4, 2, 3, seed=12)
    for name in PARAMETER_NAMES:
        assert torch.equal(getattr(sys, name), getattr(again, name))
    assert not torch.equal(sys.A, other.A)
    assert float(sys.stiffness) == 0.5
    assert "n_lam=3" in repr(sys)


def test_lcs_init_parameters():
    m = LCS(3, 2, 4, stiffness=0.7, init_scale=0.1, seed=0)
    assert [n for n, _ in m.named_parameters()] == list(PARAMETER_NAMES)
    assert all(p.requires_grad for p in m.parameters())
    assert float(m.A.detach().std()) == pytest.approx(0.1, rel=0.5)
    assert m.sigma_min >= 1.4 * (1 - 1e-12)
    m2 = LCS(3, 2, 4, stiffness=0.7, init_scale=0.1, seed=0)
    assert all(torch.equal(a, b) for a, b in zip(m.parameters(), m2.parameters(), strict=True))
    zero = LCS(3, 2, 4, stiffness=1.0, init_scale=0.0)
    assert float(zero.A.detach().abs().max()) == 0.0
    assert torch.equal(zero.F.detach(), torch.eye(4, dtype=F64))


def test_lcs_and_random_lcs_share_their_defaults():
    """Seed 0 and one stiffness for both: the defaults are reproducible, and a default model's
    F + F^T >= 2 s I contains every default ground truth's F."""
    m, t = LCS(3, 2, 4), random_lcs(3, 2, 4)
    assert float(m.stiffness) == float(t.stiffness) == DEFAULT_STIFFNESS
    again = LCS(3, 2, 4)
    assert all(torch.equal(a, b) for a, b in zip(m.parameters(), again.parameters(), strict=True))
    assert all(torch.equal(a, b) for a, b in zip(t.parameters(), random_lcs(3, 2, 4, seed=0).parameters(),
                                                  strict=True))
    assert t.sigma_min >= 2 * float(m.stiffness) * (1 - 1e-12)


@pytest.mark.parametrize("seed", range(4))
def test_from_matrices_round_trip(seed):
    sys = random_lcs(4, 2, 3, seed=seed)
    mats = sys.to_matrices()
    assert list(mats) == list(MATRIX_NAMES)
    assert all(isinstance(v, np.ndarray) and v.dtype == np.float64 for v in mats.values())
    back = LCS.from_matrices(**mats)
    mats2 = back.to_matrices()
    for k in MATRIX_NAMES:
        if k == "F":
            assert np.abs(mats2["F"] - mats["F"]).max() <= 1e-12
        else:
            assert np.array_equal(mats2[k], mats[k])
    assert back.sigma_min == pytest.approx(sys.sigma_min, rel=1e-10)
    x, u = uniform((50, 4), 10, seed), uniform((50, 2), 5, seed + 1)
    assert torch.allclose(back.step(x, u), sys.step(x, u), rtol=1e-10, atol=1e-10)
    # to_matrices returns copies
    mats["A"][0, 0] = 123.0
    assert float(sys.A[0, 0]) != 123.0


def test_from_matrices_arbitrary_p_matrix():
    """Any F with F + F^T > 0 (not built from G, H) is reproduced, including a non-symmetric one."""
    F = random_p_matrix(4, smin=0.05, seed=3)
    g = np.random.default_rng(0)
    sys = LCS.from_matrices(
        A=g.standard_normal((2, 2)), B=g.standard_normal((2, 1)), C=g.standard_normal((2, 4)),
        d=g.standard_normal(2), D=g.standard_normal((4, 2)), E=g.standard_normal((4, 1)),
        F=F.numpy(), c=g.standard_normal(4),
    )
    assert torch.allclose(sys.F, F, rtol=0, atol=1e-12)
    assert sys.sigma_min == pytest.approx(0.05, rel=1e-8)


@pytest.mark.parametrize(
    "F, smin",
    [
        (np.array([[1.0, 0.0], [0.0, -0.5]]), "-1"),
        (np.array([[0.0, 1.0], [-1.0, 0.0]]), "0"),  # skew: F + F^T = 0
        (np.array([[1.0, 3.0], [0.0, 1.0]]), "-1"),  # P-matrix (positive minors) but F + F^T indefinite
    ],
)
def test_from_matrices_rejects_non_p_matrix(F, smin):
    kw = dict(A=np.eye(2), B=np.zeros((2, 1)), C=np.zeros((2, 2)), d=np.zeros(2),
              D=np.zeros((2, 2)), E=np.zeros((2, 1)), c=np.zeros(2))
    with pytest.raises(lcs_cvx.LCSInputError, match=rf"F: expected F \+ F\^T positive definite.*sigma_min\(F \+ F\^T\) = {smin}"):
        LCS.from_matrices(F=F, **kw)


# -- a hand-solvable system: a point mass against a spring wall ----------------------------


def test_spring_wall_by_hand():
    """The zoo's spring wall (``tests/zoo.py``) as a system: lam and the next state by hand."""
    sys = spring_wall()
    k = K_WALL
    pts = SPRING_POINTS  # (p, v, u)
    x = torch.tensor([[p, v] for p, v, _ in pts], dtype=F64)
    u = torch.tensor([[uu] for _, _, uu in pts], dtype=F64)
    lam_hand, xn_hand = spring_wall_by_hand(pts)
    assert [bool(v) for v in lam_hand[:, 0] > 0] == [False, True, True, False, True]
    for method in ("fast", "brute", "cvxpy"):
        sol = sys.solve_lcp(x, u, method=method)
        assert isinstance(sol, LCPSolution)
        assert torch.allclose(sol.lam, lam_hand, rtol=1e-8, atol=1e-9)
        assert torch.allclose(sys.step(x, u, method=method), xn_hand, rtol=1e-8, atol=1e-9)
    # physics: in contact the wall is a spring, p' = -lam / k
    xn = sys.step(x, u)
    sol = sys.solve_lcp(x, u)
    lam = sol.lam
    # a learnable model: lam (and w = F lam + q) through the differentiable active-set map
    assert lam.requires_grad and sol.w.requires_grad
    assert torch.allclose(sol.w, lam @ sys.F.mT + sys.lcp_offset(x, u), rtol=0, atol=1e-14)
    contact = lam[:, 0] > 0
    assert torch.allclose(xn[contact, 0], -lam[contact, 0] / k, rtol=1e-12, atol=1e-14)
    # out of contact w = p' >= 0: the mass never ends a step inside the wall without a force
    assert bool((xn[~contact, 0] >= 0).all())
    assert bool((xn[:, 0] + lam[:, 0] / k >= -1e-14).all())
    assert torch.equal(sys.active_set(x, u), lam_hand > 0)
    assert torch.allclose(sys(x, u), xn, rtol=0, atol=0)
    # from_matrices gives a learnable model: the values above went through the differentiable
    # active-set map; without autograd the pivoting's own answer is returned -- the same
    assert xn.requires_grad
    with torch.no_grad():
        assert torch.allclose(sys.step(x, u), xn_hand, rtol=1e-12, atol=1e-14)


def test_spring_wall_rollout_bounces():
    """Falling onto the wall under gravity the mass comes to rest at the spring's equilibrium
    p = -g/k (lam = g), with the wall force never negative."""
    sys = spring_wall().requires_grad_(False)
    g = 9.81
    T = 400
    xs = sys.rollout(torch.tensor([0.5, 0.0], dtype=F64), torch.full((T, 1), -g, dtype=F64))
    assert xs.shape == (T + 1, 2)
    assert float(xs[:, 0].min()) < 0  # it reached the wall
    # a stiff wall time-stepped implicitly dissipates: the mass settles where lam = g
    assert float(xs[-1, 0]) == pytest.approx(-g / K_WALL, rel=1e-3)
    assert abs(float(xs[-1, 1])) < 1e-3


# -- rollout -------------------------------------------------------------------------------


def test_rollout_shapes_and_equality_with_step(small_system):
    sys = small_system
    N, T = 6, 5
    x0 = uniform((N, 4), 10, 0)
    us = uniform((N, T, 2), 5, 1)
    xs = sys.rollout(x0, us)
    assert xs.shape == (N, T + 1, 4)
    assert torch.equal(xs[:, 0], x0)
    x = x0
    for t in range(T):
        x = sys.step(x, us[:, t])
        assert torch.allclose(xs[:, t + 1], x, rtol=0, atol=0)
    # a single trajectory, as 1-D x0 and 2-D us (tensor and numpy)
    one = sys.rollout(x0[2], us[2])
    assert one.shape == (T + 1, 4)
    assert torch.allclose(one, xs[2], rtol=1e-12, atol=1e-12)
    one_np = sys.rollout(x0[2].numpy(), us[2].numpy())
    assert one_np.shape == (T + 1, 4)
    assert torch.allclose(one_np, one, rtol=0, atol=0)
    # a batch of one stays batched
    assert sys.rollout(x0[2:3], us[2:3]).shape == (1, T + 1, 4)
    # T = 0: just the initial state
    assert torch.equal(sys.rollout(x0, us[:, :0]), x0[:, None])


# -- active set ---------------------------------------------------------------------------


def test_active_set_matches_brute_force(small_system):
    sys = small_system
    x, u = uniform((500, 4), 10, 2), uniform((500, 2), 5, 3)
    act = sys.active_set(x, u)
    assert act.dtype == torch.bool and act.shape == (500, 3)
    brute = solve_lcp_brute(sys.F, sys.lcp_offset(x, u))
    assert torch.equal(act, brute.lam > ACTIVE_TOL)  # the default tolerance
    assert torch.unique(act, dim=0).shape[0] >= 4  # several modes are visited
    assert torch.equal(sys.active_set(x, u, tol=1e9), torch.zeros_like(act))


def test_lcp_offset_and_step_formula(small_system):
    sys = small_system
    x, u = uniform((20, 4), 10, 4), uniform((20, 2), 5, 5)
    q = sys.lcp_offset(x, u)
    assert torch.allclose(q, x @ sys.D.T + u @ sys.E.T + sys.c, rtol=0, atol=1e-14)
    lam = sys.solve_lcp(x, u).lam
    w = lam @ sys.F.T + q
    assert bool((lam >= 0).all()) and bool((w >= -1e-10).all())
    assert float((lam * w).abs().max()) <= 1e-10
    xn = sys.step(x, u)
    assert torch.allclose(xn, x @ sys.A.T + u @ sys.B.T + lam @ sys.C.T + sys.d, rtol=0, atol=1e-13)
    for method in ("brute", "cvxpy"):
        assert torch.allclose(sys.solve_lcp(x, u, method=method).lam, lam, rtol=1e-7, atol=1e-7)


# -- batched vs single ---------------------------------------------------------------------


def test_batched_equals_single_samples(small_system):
    sys = small_system
    x, u = uniform((30, 4), 10, 6), uniform((30, 2), 5, 7)
    batched = sys.step(x, u)
    lam_b = sys.solve_lcp(x, u).lam
    for i in range(30):
        single = sys.step(x[i], u[i])  # one state in, one state out
        assert single.shape == (4,)
        assert torch.allclose(single, batched[i], rtol=1e-12, atol=1e-12)
        assert torch.allclose(sys.solve_lcp(x[i], u[i]).lam[0], lam_b[i], rtol=1e-12, atol=1e-12)
    # numpy and nested lists are accepted as well: the same 30 rows are the same operations in
    # the same order (bit-identical); 2 rows against 30 are another BLAS blocking (a few ulps)
    assert torch.equal(sys.step(x.numpy(), u.numpy()), batched)
    assert sys.step(x[0].tolist(), u[0].numpy()).shape == (4,)
    assert torch.allclose(sys.step(x[:2].tolist(), u[:2].tolist()), batched[:2], rtol=1e-12, atol=1e-12)


def test_no_input_system():
    sys = random_lcs(3, 0, 2, seed=1)
    x = uniform((10, 3), 10, 0)
    xn = sys.step(x, torch.zeros(10, 0, dtype=F64))
    lam = sys.solve_lcp(x, np.zeros((10, 0))).lam
    assert torch.allclose(xn, x @ sys.A.T + lam @ sys.C.T + sys.d, rtol=0, atol=1e-13)


# -- gradients -----------------------------------------------------------------------------


def _strictly_complementary_samples(sys, n, seed, margin=1e-2):
    x, u = uniform((4 * n, sys.n_x), 10, seed), uniform((4 * n, sys.n_u), 5, seed + 1)
    with torch.no_grad():
        lam = sys.solve_lcp(x, u).lam
        w = lam @ sys.F.mT + sys.lcp_offset(x, u)
    ok = torch.maximum(lam, w).amin(-1) >= margin
    idx = ok.nonzero().squeeze(1)[:n]
    assert idx.numel() == n
    return x[idx], u[idx], lam[idx]


def test_step_gradients_match_finite_differences():
    sys = random_lcs(3, 2, 3, seed=4)
    x, u, lam = _strictly_complementary_samples(sys, 4, seed=8)
    assert bool((lam > 0).any()) and bool((lam == 0).any())  # both kinds of index
    names = list(PARAMETER_NAMES)
    params = [getattr(sys, k).detach().clone().requires_grad_(True) for k in names]

    def f(*ps):
        return torch.func.functional_call(sys, dict(zip(names, ps, strict=True)), (x, u))

    assert torch.autograd.gradcheck(f, tuple(params), eps=1e-6, atol=1e-6, rtol=1e-6)


def test_step_gradients_wrt_inputs_and_through_module_backward():
    sys = LCS.from_matrices(**random_lcs(3, 2, 3, seed=5).to_matrices())
    x, u, _ = _strictly_complementary_samples(sys, 3, seed=1)
    xg = x.clone().requires_grad_(True)
    ug = u.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: sys.step(a, b), (xg, ug), eps=1e-6, atol=1e-6)
    # .backward() on the module's own parameters agrees with a central difference
    loss = (sys.step(x, u) ** 2).sum()
    loss.backward()
    h = 1e-6
    for name in ("A", "C", "D", "G", "H", "c"):
        p = getattr(sys, name)
        idx = (0,) * p.dim()
        with torch.no_grad():
            p[idx] += h
            up = float((sys.step(x, u) ** 2).sum())
            p[idx] -= 2 * h
            down = float((sys.step(x, u) ** 2).sum())
            p[idx] += h
        fd = (up - down) / (2 * h)
        assert float(p.grad[idx]) == pytest.approx(fd, rel=1e-5, abs=1e-6), name
    assert float(sys.G.grad.abs().max()) > 0  # the LCP part really carries gradient


def test_no_graph_without_grad(small_system):
    x, u = uniform((5, 4), 10, 0), uniform((5, 2), 5, 1)
    assert not small_system.step(x, u).requires_grad
    m = LCS(4, 2, 3, stiffness=1.0, seed=0)
    assert m.step(x, u).requires_grad
    with torch.no_grad():
        assert not m.step(x, u).requires_grad


# -- float32 -------------------------------------------------------------------------------


def test_float32_model():
    sys64 = random_lcs(4, 2, 3, seed=9)
    sys32 = random_lcs(4, 2, 3, seed=9, dtype=torch.float32)
    assert sys32.dtype == torch.float32 and sys32.F.dtype == torch.float32
    x, u = uniform((200, 4), 10, 0), uniform((200, 2), 5, 1)
    xn32 = sys32.step(x.float(), u.float())
    assert xn32.dtype == torch.float32
    xn64 = sys64.step(x, u)
    rel = (xn32.double() - xn64).norm() / xn64.norm()
    assert float(rel) <= 1e-5
    # numpy float64 input is converted to the model's dtype
    assert sys32.step(x.numpy(), u.numpy()).dtype == torch.float32
    # the learnable float32 model trains: gradients are float32 and finite
    m = LCS(4, 2, 3, stiffness=1.0, seed=0, dtype=torch.float32)
    loss = ((m.step(x.float(), u.float()) - xn32) ** 2).mean()
    loss.backward()
    assert m.G.grad.dtype == torch.float32 and bool(torch.isfinite(m.G.grad).all())
    assert float(m.A.grad.abs().max()) > 0
    # from_matrices into float32
    back32 = LCS.from_matrices(**sys64.to_matrices(), dtype=torch.float32)
    assert torch.allclose(back32.step(x.float(), u.float()), xn32, rtol=1e-4, atol=1e-4)
