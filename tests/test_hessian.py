"""Lemma 4: the Hessian of the violation loss (:mod:`lcs_cvx.hessian`) and its vector products.

Checked (float64) against central finite differences of Lemma 3's analytic gradient (autograd of
``violation_loss(..., solver="fast")``), for symmetry, hvp against ``H @ v``, ``J_zz`` against
autograd, and on a contact-free system against the closed-form least-squares Hessian.
The finite-difference models are small perturbations of a random ground truth; ``eps`` is
mostly moderate (0.1, 1) so differences are well conditioned. At the paper's ``eps = 1e-4`` the
Hessian is a difference of terms ~1/(eps gamma) ~ 1e6 larger than itself, so the agreements
there are looser (documented per test).
"""

from __future__ import annotations

import copy

import pytest
import torch

import lcs_cvx
from lcs_cvx.hessian import (
    flatten_parameters,
    objective_hessian_zz,
    objective_jacobians,
    objective_linearisation,
    parameter_slices,
    unflatten,
    violation_hessian,
    violation_hvp,
)
from lcs_cvx.problems import ViolationProblem
from lcs_cvx.second_order import gauss_newton_matrix, gauss_newton_operator
from lcs_cvx.system import PARAMETER_NAMES

F64 = torch.float64
GAMMA = 1e-2
#: (eps, central-difference step on theta, tolerance relative to max |H|). The error is the
#: gradient's round-off over 2 * step (observed 3e-9 .. 1.2e-7 at eps >= 0.1, step 1e-6); at the
#: paper's eps = 1e-4 the gradient is ~1/(eps gamma) larger, so the step is 1e-4 (observed 1e-6;
#: it scales as 1/step down to 1e-7, i.e. truncation error is negligible).
FD_CASES = [(1e-1, 1e-6, 1e-6), (1.0, 1e-6, 1e-6), (1e-4, 1e-4, 1e-5)]

DIMS = [(3, 2, 2), (4, 1, 3)]

# torch's forward-mode AD (used by jacfwd / jvp) scripts its decompositions on first use and
# emits this from inside torch; it is not ours to fix.
pytestmark = pytest.mark.filterwarnings(
    "ignore:`torch.jit.script` is deprecated:DeprecationWarning"
)


def perturbed_model(n_x, n_u, n_lam, n=30, seed=0, scale=0.1):
    """A model ``theta* + scale N(0, 1)`` around a random ground truth, and the truth's data."""
    truth = lcs_cvx.random_lcs(n_x, n_u, n_lam, stiffness=0.5, seed=seed)
    data = lcs_cvx.make_dataset(truth, n, seed=seed)
    model = copy.deepcopy(truth)
    gen = torch.Generator().manual_seed(seed + 100)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(scale * torch.randn(p.shape, generator=gen, dtype=F64))
    return model.requires_grad_(True), data


def gradient_and_mask(model, theta, data, eps):
    """Lemma 3's gradient of ``L_eps`` at ``theta`` (flat), and the free mask of ``(lam, phi)``."""
    with torch.no_grad():
        for k, v in unflatten(model, theta).items():
            getattr(model, k).copy_(v)
    info = lcs_cvx.violation_loss_info(model, data.x, data.u, data.x_next, GAMMA, eps, solver="fast")
    grads = torch.autograd.grad(info.loss, [getattr(model, k) for k in PARAMETER_NAMES])
    return torch.cat([g.reshape(-1) for g in grads]), torch.cat([info.lam > 0, info.phi > 0], 1)


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / b.abs().max())


# -- the Hessian against finite differences of the analytic gradient ----------------------


@pytest.mark.parametrize(("eps", "step", "rtol"), FD_CASES)
@pytest.mark.parametrize("dims", DIMS)
def test_hessian_matches_finite_differences(dims, eps, step, rtol):
    model, data = perturbed_model(*dims)
    H = violation_hessian(model, data.x, data.u, data.x_next, GAMMA, eps)
    theta0 = flatten_parameters(model)
    P = theta0.numel()
    assert H.shape == (P, P) and H.dtype == F64
    _, mask0 = gradient_and_mask(model, theta0, data, eps)
    n_lam = dims[2]
    # the batch exercises both branches of lam (otherwise the correction term is untested)
    assert 0 < int(mask0[:, :n_lam].sum()) < mask0[:, :n_lam].numel()
    H_fd = torch.empty(P, P, dtype=F64)
    for i in range(P):
        e_i = torch.zeros(P, dtype=F64)
        e_i[i] = step
        g_plus, mask_plus = gradient_and_mask(model, theta0 + e_i, data, eps)
        g_minus, mask_minus = gradient_and_mask(model, theta0 - e_i, data, eps)
        # no sample crosses a kink of L_eps inside the stencil: the difference is a derivative
        assert torch.equal(mask_plus, mask0) and torch.equal(mask_minus, mask0), (
            f"active set changed along theta[{i}]"
        )
        H_fd[:, i] = (g_plus - g_minus) / (2 * step)
    assert rel(H, H_fd) <= rtol


@pytest.mark.parametrize("dims", DIMS)
def test_hessian_symmetric_and_hvp_agrees(dims):
    model, data = perturbed_model(*dims, n=50, seed=1)
    H = violation_hessian(model, data.x, data.u, data.x_next, GAMMA, 1e-1)
    assert rel(H, H.mT) <= 1e-10
    gen = torch.Generator().manual_seed(3)
    for _ in range(3):
        v = torch.randn(H.shape[0], generator=gen, dtype=F64)
        hv = violation_hvp(model, data.x, data.u, data.x_next, v, GAMMA, 1e-1)
        assert hv.shape == v.shape
        assert float((hv - H @ v).norm() / (H @ v).norm()) <= 1e-9


def test_paper_eps_hvp_agrees():
    """At the paper's eps = 1e-4 the two paths still agree (cancellation costs ~6 digits)."""
    model, data = perturbed_model(4, 1, 3, n=40, seed=2)
    H = violation_hessian(model, data.x, data.u, data.x_next)
    v = torch.randn(H.shape[0], generator=torch.Generator().manual_seed(0), dtype=F64)
    hv = violation_hvp(model, data.x, data.u, data.x_next, v)
    assert float((hv - H @ v).norm() / (H @ v).norm()) <= 1e-8
    assert rel(H, H.mT) <= 1e-9


def test_parameters_not_requiring_grad_and_model_untouched():
    """All parameters are differentiated whatever their requires_grad; the model is unchanged."""
    model, data = perturbed_model(3, 2, 2)
    before = flatten_parameters(model)
    H1 = violation_hessian(model, data.x, data.u, data.x_next, GAMMA, 1.0)
    model.requires_grad_(False)
    H2 = violation_hessian(model, data.x, data.u, data.x_next, GAMMA, 1.0)
    assert torch.equal(H1, H2)
    assert torch.equal(before, flatten_parameters(model))


# -- pieces ---------------------------------------------------------------------------------


def test_objective_hessian_zz_closed_form():
    """The sample-independent J_zz equals autograd's Hessian of the (lam, phi) objective."""
    model, data = perturbed_model(4, 1, 3)
    n, eps = model.n_lam, 1e-3
    with torch.no_grad():
        F, C = model.F.detach(), model.C.detach()
        q = model.lcp_offset(data.x[:1], data.u[:1])
        r = data.x[:1] @ model.A.mT + data.u[:1] @ model.B.mT + model.d - data.x_next[:1]

    def J(z):
        return ViolationProblem.objective(z[:n][None], z[n:][None], C, F, q, r, GAMMA, eps)[0]

    auto = torch.func.hessian(J)(torch.rand(2 * n, dtype=F64))
    closed = objective_hessian_zz(C, F, GAMMA, eps)
    assert rel(closed, auto) <= 1e-13
    assert float(torch.linalg.eigvalsh(closed)[0]) > 0  # Lemma 3(a)


def test_parameter_slices_roundtrip():
    model = lcs_cvx.LCS(3, 2, 4, stiffness=1.0, seed=0)
    slices = parameter_slices(model)
    assert list(slices) == list(PARAMETER_NAMES)
    theta = flatten_parameters(model)
    assert slices["c"].stop == theta.numel() == sum(p.numel() for p in model.parameters())
    assert torch.equal(theta[slices["A"]].reshape(3, 3), model.A.detach())  # row-major
    assert theta[slices["B"]][1 * 2 + 0] == model.B[1, 0]
    for k, v in unflatten(model, theta).items():
        assert torch.equal(v, getattr(model, k).detach())


# -- closed form: a contact-free system -----------------------------------------------------


def test_contact_free_equals_least_squares_hessian():
    """``c`` large: q > 0 on every sample, so lam = 0 (bound-active, strictly), phi = q (free)
    and ``L_eps = mean 1/2 ||A x + B u + d - x'||^2`` near theta. The Hessian is then the
    least-squares one in (A, B, d), zero in C (lam = 0) and in the LCP block (phi absorbs q).

    With w = (x, u, 1), S = mean w w^T and row-major vec: H_AA = I (x) S_xx, H_AB = I (x) S_xu,
    H_Ad = I (x) S_x1 (an (n_x^2, n_x) block), H_BB = I (x) S_uu, H_Bd = I (x) S_u1, H_dd = I.
    """
    model, data = perturbed_model(3, 2, 2, n=40)
    with torch.no_grad():
        model.c.fill_(1e3)
    eps = 1e-1
    info = lcs_cvx.violation_loss_info(model, data.x, data.u, data.x_next, GAMMA, eps)
    assert bool((info.lam == 0).all()) and bool((info.phi > 100).all())
    H = violation_hessian(model, data.x, data.u, data.x_next, GAMMA, eps)

    n_x = model.n_x
    w = torch.cat([data.x, data.u, torch.ones(len(data), 1, dtype=F64)], 1)
    S = w.mT @ w / len(data)
    ix, iu, i1 = slice(0, n_x), slice(n_x, n_x + model.n_u), slice(n_x + model.n_u, None)
    eye = torch.eye(n_x, dtype=F64)
    blocks = {
        ("A", "A"): torch.kron(eye, S[ix, ix]),
        ("A", "B"): torch.kron(eye, S[ix, iu]),
        ("A", "d"): torch.kron(eye, S[ix, i1]),
        ("B", "B"): torch.kron(eye, S[iu, iu]),
        ("B", "d"): torch.kron(eye, S[iu, i1]),
        ("d", "d"): eye,
    }
    sl = parameter_slices(model)
    expected = torch.zeros_like(H)
    for (a, b), blk in blocks.items():
        expected[sl[a], sl[b]] = blk
        expected[sl[b], sl[a]] = blk.mT
    assert rel(H, expected) <= 1e-10


# -- input validation -----------------------------------------------------------------------


def test_invalid_input_raises():
    model, data = perturbed_model(3, 2, 2, n=10)
    x, u, xn = data.x, data.u, data.x_next
    P = flatten_parameters(model).numel()
    with pytest.raises(lcs_cvx.LCSInputError, match=r"x: expected shape \(N, 3\)"):
        violation_hessian(model, x[:, :2], u, xn)
    with pytest.raises(lcs_cvx.LCSInputError, match="x_next: expected 10 rows"):
        violation_hessian(model, x, u, xn[:5])
    with pytest.raises(lcs_cvx.LCSInputError, match="NaN"):
        violation_hessian(model, x, u, torch.full_like(xn, float("nan")))
    with pytest.raises(lcs_cvx.LCSInputError, match="gamma: expected 0 < gamma < sigma_min"):
        violation_hessian(model, x, u, xn, gamma=1e3)
    with pytest.raises(lcs_cvx.LCSInputError, match="eps"):
        violation_hvp(model, x, u, xn, torch.zeros(P, dtype=F64), eps=-1.0)
    with pytest.raises(lcs_cvx.LCSInputError, match=rf"v: expected shape \({P},\)"):
        violation_hvp(model, x, u, xn, torch.zeros(P + 1, dtype=F64))
    with pytest.raises(lcs_cvx.LCSInputError, match="v: expected dtype"):
        violation_hvp(model, x, u, xn, torch.zeros(P, dtype=torch.float32))
    with pytest.raises(lcs_cvx.LCSInputError, match="model: expected an lcs_cvx.LCS"):
        violation_hessian(object(), x, u, xn)


# -- closed-form Jacobians of (V) and the Gauss--Newton matrix ------------------------------


def _autodiff_jacobians(model, data, z, eps):
    """rho_theta and J_ztheta by torch.func.jacfwd through the model (the oracle)."""
    n, x, u, xn = model.n_lam, data.x, data.u, data.x_next
    root = (1.0 / (eps * GAMMA)) ** 0.5
    theta0 = flatten_parameters(model)

    def with_theta(theta, fn):
        params = unflatten(model, theta)
        saved = {k: getattr(model, k) for k in PARAMETER_NAMES}
        try:
            for k, v in params.items():  # functional: plain tensors in place of the Parameters
                delattr(model, k)
                setattr(model, k, v)
            return fn()
        finally:
            for k, v in saved.items():
                delattr(model, k)
                model.register_parameter(k, v)

    def rho(theta):
        def fn():
            lam, phi = z[:, :n], z[:, n:]
            e = x @ model.A.mT + u @ model.B.mT + lam @ model.C.mT + model.d - xn
            w = x @ model.D.mT + u @ model.E.mT + lam @ model.F.mT + model.c - phi
            return torch.cat([e, root * w], 1)
        return with_theta(theta, fn)

    def grad_z(theta):
        def fn():
            q = x @ model.D.mT + u @ model.E.mT + model.c
            r = x @ model.A.mT + u @ model.B.mT + model.d - xn
            C, F = model.C, model.F
            return torch.func.grad(
                lambda zz: ViolationProblem.objective(zz[:, :n], zz[:, n:], C, F, q, r, GAMMA, eps).sum()
            )(z)
        return with_theta(theta, fn)

    return torch.func.jacfwd(rho)(theta0), torch.func.jacfwd(grad_z)(theta0)


@pytest.mark.parametrize("dims", [(3, 2, 2), (5, 2, 4)])
@pytest.mark.parametrize("eps", [1e-1, 1e-4])
def test_closed_form_jacobians_match_autodiff(dims, eps):
    """objective_jacobians (Kronecker blocks, chain rule to G and H) and the matrix-free
    objective_linearisation against jacfwd; measured agreement ~1e-16 relative."""
    model, data = perturbed_model(*dims)
    info = lcs_cvx.violation_loss_info(model, data.x, data.u, data.x_next, GAMMA, eps)
    z = torch.cat([info.lam, info.phi], 1)
    R, Z = objective_jacobians(model, data.x, data.u, data.x_next, z, GAMMA, eps)
    R_ad, Z_ad = _autodiff_jacobians(model, data, z, eps)
    assert R.shape == R_ad.shape and Z.shape == Z_ad.shape
    assert rel(R, R_ad) <= 1e-13 and rel(Z, Z_ad) <= 1e-13
    jvp, vjp = objective_linearisation(model, data.x, data.u, data.x_next, z, GAMMA, eps)
    gen = torch.Generator().manual_seed(1)
    v = torch.randn(R.shape[-1], generator=gen, dtype=F64)
    a = torch.randn(R.shape[:2], generator=gen, dtype=F64)
    b = torch.randn(Z.shape[:2], generator=gen, dtype=F64)
    Rv, Zv = jvp(v)
    assert rel(Rv, R @ v) <= 1e-13 and rel(Zv, Z @ v) <= 1e-13
    assert rel(vjp(a, b), torch.einsum("brp,br->p", R, a) + torch.einsum("bkp,bk->p", Z, b)) <= 1e-13


@pytest.mark.parametrize("dims", [(3, 2, 2), (5, 2, 4)])
def test_gauss_newton_matrix_and_operator_are_the_definition(dims):
    """mean_t J_t^T J_t with J_t = rho_theta + rho_z dz/dtheta, dz_F = -(J_zz)_FF^{-1} (J_ztheta)_F,
    built here from the autodiff Jacobians; the dense matrix and the operator agree with it."""
    model, data = perturbed_model(*dims)
    eps, n = 1e-2, model.n_lam
    info = lcs_cvx.violation_loss_info(model, data.x, data.u, data.x_next, GAMMA, eps)
    z = torch.cat([info.lam, info.phi], 1)
    R, Z = _autodiff_jacobians(model, data, z, eps)
    with torch.no_grad():
        m = (z > 0).to(F64)
        Jzz = objective_hessian_zz(model.C, model.F, GAMMA, eps)
        root = (1.0 / (eps * GAMMA)) ** 0.5
        rho_z = torch.cat([
            torch.cat([model.C, torch.zeros(model.n_x, n, dtype=F64)], 1),
            torch.cat([root * model.F, -root * torch.eye(n, dtype=F64)], 1),
        ])
    J = []
    for t in range(z.shape[0]):
        free = m[t].bool()
        dz = torch.zeros(2 * n, R.shape[-1], dtype=F64)
        dz[free] = -torch.linalg.solve(Jzz[free][:, free], Z[t][free])
        J.append(R[t] + rho_z @ dz)
    J = torch.stack(J)
    expected = torch.einsum("brp,brq->pq", J, J) / z.shape[0]
    dense = gauss_newton_matrix(model, data.x, data.u, data.x_next, GAMMA, eps)
    assert rel(dense, expected) <= 1e-10
    op = gauss_newton_operator(model, data.x, data.u, data.x_next, GAMMA, eps)
    v = torch.randn(expected.shape[0], generator=torch.Generator().manual_seed(2), dtype=F64)
    assert rel(op(v), expected @ v) <= 1e-10
