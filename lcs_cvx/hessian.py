r"""Hessian of the violation-based loss, Lemma 4, and its products with vectors.

Per sample ``t`` the violation problem (V), eq. (9b), is

    l_t(theta) = min_{z >= 0} J_t(theta, z),      z = (lam, phi) in R^{2 n_lam},
    J_t = 1/2 ||C lam + r_t||^2 + (1/eps) (lam^T phi + ||F lam + q_t - phi||^2 / (2 gamma)),

with ``r_t = A x_t + B u_t + d - x'_t`` and ``q_t = D x_t + E u_t + c``
(:meth:`lcs_cvx.problems.ViolationProblem.objective`, ``phi`` kept as a variable). The package's
``L_eps`` is the batch *mean* of ``l_t`` (:func:`lcs_cvx.violation_loss`; the paper sums).

Lemma 4. With ``z_t`` the solution, the envelope theorem gives ``grad L = mean_t J_theta``
(Lemma 3) and, differentiating once more,

    hess L = mean_t [ J_thth - J_thz (diag(J_z) + diag(z_t) J_zz)^{-1} diag(z_t) J_zth ].

Reduction used here. Under strict complementarity every component of ``z_t`` is either free
(``z_i > 0``, ``(J_z)_i = 0``) or bound-active (``z_i = 0``, ``(J_z)_i > 0``). A bound-active
row of ``diag(J_z) + diag(z) J_zz`` is ``(J_z)_i e_i^T`` and the matching row of the right-hand
side ``diag(z) J_zth`` is zero, so ``dz_i/dtheta = 0``: that row drops out. A free row is
``z_i (J_zz)_{i,:}`` with right-hand side ``z_i (J_zth)_i``; dividing by ``z_i > 0`` leaves
``(J_zz)_{FF} dz_F/dtheta = -(J_zth)_F``. Hence, with ``F_t`` the free set of sample ``t``,

    hess L = mean_t [ J_thth - (J_thz)_{:,F_t} (J_zz)_{F_t F_t}^{-1} (J_zth)_{F_t,:} ].

``J_zz`` does not depend on the sample (:func:`objective_hessian_zz`); ``(J_zz)_{FF}`` is a
principal submatrix of a positive definite matrix (Lemma 3(a), ``gamma < sigma_min(F + F^T)``),
so the correction is positive semidefinite. Each sample's masked system is solved batched as
``M_t = (m m^T) o J_zz + diag(1 - m)`` with ``m`` the 0/1 free mask, a Cholesky factor per
sample. ``J_zth`` and ``J_thth`` (z fixed) are written out in closed form
(:func:`objective_jacobians`, :func:`objective_linearisation`): with the residuals
``rho = [e; w / sqrt(eps gamma)]`` of ``J = 1/2 ||rho||^2 + lam^T phi / eps``, which are linear in
every parameter but ``G``, ``J_thth = rho_theta^T rho_theta`` plus the curvature of
``F = G G^T + H - H^T + s I``: ``d^2 J / dG_ab dG_cd = S_ac delta_bd`` with
``S = (w lam^T + lam w^T) / (eps gamma)``. The tests check them against ``torch.func`` and the
Hessian against finite differences of the gradient. At an index where strict complementarity fails (``z_i = 0 = (J_z)_i``) the solver's
classification is held, i.e. the one-sided Hessian in which that bound stays active.

Parameter ordering: ``theta`` is the concatenation, in the order of
:data:`lcs_cvx.system.PARAMETER_NAMES` = ``(A, B, C, d, D, E, G, H, c)``, of each parameter
flattened row-major (``.reshape(-1)``, so ``A[i, j]`` sits at ``i * n_x + j`` of A's slice).
:func:`parameter_slices` maps names to slices; every parameter is included, whatever its
``requires_grad``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import torch

from ._checks import LCSInputError, SolverError, as_matrix, as_transitions, check_positive
from .losses import violation_fast
from .parameters import F_adjoint
from .problems import ViolationProblem
from .system import LCS, PARAMETER_NAMES

__all__ = [
    "violation_hessian",
    "violation_hvp",
    "hvp_operator",
    "parameter_slices",
    "flatten_parameters",
    "unflatten",
    "objective_hessian_zz",
    "objective_jacobians",
    "objective_linearisation",
    "Setup",
    "setup",
]


def parameter_slices(model: LCS) -> dict[str, slice]:
    """``{name: slice}`` of each parameter in the flat ``theta`` (order of ``PARAMETER_NAMES``)."""
    out, start = {}, 0
    for name in PARAMETER_NAMES:
        k = getattr(model, name).numel()
        out[name] = slice(start, start + k)
        start += k
    return out


def flatten_parameters(model: LCS) -> torch.Tensor:
    """The model's parameters as one detached ``(P,)`` vector (see :func:`parameter_slices`)."""
    return torch.cat([getattr(model, k).detach().reshape(-1) for k in PARAMETER_NAMES])


def unflatten(model: LCS, theta: torch.Tensor) -> dict[str, torch.Tensor]:
    """Inverse of :func:`flatten_parameters`: ``{name: tensor of the parameter's shape}``."""
    return {
        k: theta[s].reshape(getattr(model, k).shape) for k, s in parameter_slices(model).items()
    }


def objective_hessian_zz(
    C: torch.Tensor, F: torch.Tensor, gamma: float, eps: float
) -> torch.Tensor:
    """``J_zz`` ``(2 n, 2 n)`` of (V) in ``z = (lam, phi)``; the same for every sample::

        [[C^T C + F^T F / (eps gamma),  (I - F^T / gamma) / eps],
         [(I - F / gamma) / eps,        I / (eps gamma)        ]]

    Args: C ``(n_x, n)``, F ``(n, n)``; or one per sample, ``(B, n_x, n)``, ``(B, n, n)`` (then
    ``(B, 2 n, 2 n)``, :func:`lcs_cvx.per_sample.violation_hessian`). Positive definite iff
    ``C^T C + (F + F^T - gamma I)/eps`` is (its Schur complement), which
    ``0 < gamma < sigma_min(F + F^T)`` guarantees. (:meth:`lcs_cvx.problems.ViolationProblem.hessian_zz`.)
    """
    return ViolationProblem.hessian_zz(C, F, gamma, eps)


class Setup(NamedTuple):
    """What every entry point needs (:func:`setup`): the validated ``x``, ``u``, ``x_next``, the
    solution ``z = (lam, phi)`` ``(B, 2n)`` of (V), its free mask ``m`` ``(B, 2n)`` (0/1) and the
    per-sample Cholesky factors ``chol`` ``(B, 2n, 2n)`` of
    ``M_t = (m m^T) o J_zz + diag(1 - m)``."""

    x: torch.Tensor
    u: torch.Tensor
    x_next: torch.Tensor
    z: torch.Tensor
    m: torch.Tensor
    chol: torch.Tensor


def setup(model: Any, x: Any, u: Any, x_next: Any, gamma: float, eps: float) -> Setup:
    """Validate, solve (V) once (no grad) and factor the masked ``J_zz`` of every sample
    (:class:`Setup`). Package-internal: :mod:`lcs_cvx.second_order` builds on it."""
    if not isinstance(model, LCS):
        raise LCSInputError(f"model: expected an lcs_cvx.LCS, received {type(model).__name__}")
    x, u, x_next = as_transitions(model, x, u, x_next)
    check_positive("eps", eps)
    with torch.no_grad():  # checks gamma; z is exactly the loss's (lam, phi)
        info = violation_fast(model, x, u, x_next, gamma=gamma, eps=eps)
    kw = {"dtype": model.dtype, "device": model.device}
    z = torch.cat([info.lam, info.phi], dim=1)
    m = (z > 0).to(z.dtype)
    with torch.no_grad():
        Jzz = objective_hessian_zz(model.C, model.F, gamma, eps)
        eye = torch.eye(z.shape[1], **kw)
        M = Jzz * (m[:, :, None] * m[:, None, :]) + eye * (1.0 - m)[:, None, :]
        chol, bad = torch.linalg.cholesky_ex(M)
    if bool((bad != 0).any()):  # not expected: (J_zz)_FF is positive definite (Lemma 3(a))
        raise SolverError(
            f"(J_zz)_FF not positive definite on {int((bad != 0).sum())} samples; "
            f"check gamma < sigma_min(F + F^T) = {model.sigma_min:.6g}"
        )
    return Setup(x, u, x_next, z, m, chol)


def _residuals(model: LCS, x, u, x_next, z) -> tuple[torch.Tensor, torch.Tensor]:
    """``e = C lam + A x + B u + d - x'`` ``(B, n_x)`` and ``w = F lam + D x + E u + c - phi``."""
    n = model.n_lam
    lam, phi = z[:, :n], z[:, n:]
    with torch.no_grad():
        e = x @ model.A.mT + u @ model.B.mT + lam @ model.C.mT + model.d - x_next
        w = x @ model.D.mT + u @ model.E.mT + lam @ model.F.mT + model.c - phi
    return e, w


def _delta_rows(f: torch.Tensor, R: int) -> torch.Tensor:
    """``(B, R, R, K)``: ``d (M f)_i / d M_jk = delta_ij f_k`` for a row-major ``(R, K)`` ``M``."""
    B, K = f.shape
    out = f.new_zeros(B, R, R, K)
    out.diagonal(dim1=1, dim2=2).copy_(f.unsqueeze(-1).expand(B, K, R))
    return out


def _flat_GH(T_F: torch.Tensor, G: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`lcs_cvx.parameters.F_adjoint` of ``T_F`` ``(..., n, n)``, each block flattened
    row-major to ``(..., n * n)`` (the Jacobians' column layout)."""
    dG, dH = F_adjoint(T_F, G)
    return dG.flatten(-2), dH.flatten(-2)


def objective_jacobians(
    model: LCS,
    x: torch.Tensor,
    u: torch.Tensor,
    x_next: torch.Tensor,
    z: torch.Tensor,
    gamma: float,
    eps: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    r"""Closed-form first-order pieces of (V) at a fixed ``z = (lam, phi)``, per sample.

    With ``e = C lam + A x + B u + d - x'``, ``w = F lam + D x + E u + c - phi`` and
    ``kappa = 1 / (eps gamma)``:

    - ``rho_theta`` ``(B, n_x + n, P)``: the Jacobian of the residuals
      ``rho = [e; sqrt(kappa) w]`` (Gauss--Newton; ``J = 1/2 ||rho||^2 + lam^T phi / eps``);
    - ``J_ztheta`` ``(B, 2 n, P)``: the Jacobian of ``J_z = [C^T e + phi / eps + kappa F^T w;
      lam / eps - kappa w]`` (Lemma 4's mixed block).

    Both are Kronecker-structured (``d e_i / d A_jk = delta_ij x_k``, ...), written out block by
    block in ``(A, B, C, d, D, E, F, c)`` and taken to ``(G, H)`` by the chain rule of
    ``F = G G^T + H - H^T + s I``; columns in the order of :func:`parameter_slices`. The same
    numbers as ``torch.func.jacfwd`` through the objective (tested), several times faster.
    """
    m = model
    n, n_x = m.n_lam, m.n_x
    lam = z[:, :n]
    B = x.shape[0]
    kappa = 1.0 / (eps * gamma)
    e, w = _residuals(m, x, u, x_next, z)
    with torch.no_grad():
        C, F, G = m.C.detach(), m.F.detach(), m.G.detach()
        ones = torch.ones(B, 1, dtype=x.dtype, device=x.device)
        eye_n = torch.eye(n, dtype=x.dtype, device=x.device)
        feats = {"A": x, "B": u, "d": ones}

        # rho rows: e depends on (A, B, C, d), w on (D, E, F, c)
        e_blocks = {k: _delta_rows(f, n_x).reshape(B, n_x, -1) for k, f in feats.items()}
        e_blocks["C"] = _delta_rows(lam, n_x).reshape(B, n_x, -1)
        w_blocks = {k2: _delta_rows(f, n).reshape(B, n, -1)
                    for k2, f in (("D", x), ("E", u), ("c", ones))}
        wF = _delta_rows(lam, n)  # (B, n, n, n): d w_i / d F_jm
        w_blocks["G"], w_blocks["H"] = _flat_GH(wF, G)

        # J_z rows for lam: C^T (de/dtheta) + kappa F^T (dw/dtheta) + the explicit C and F terms
        lam_blocks = {k: torch.einsum("jl,bk->bljk", C, f).reshape(B, n, -1) for k, f in feats.items()}
        lam_blocks["C"] = (torch.einsum("jl,bm->bljm", C, lam)
                           + torch.einsum("lm,bj->bljm", eye_n, e)).reshape(B, n, -1)
        for k2, f in (("D", x), ("E", u), ("c", ones)):
            lam_blocks[k2] = kappa * torch.einsum("jl,bk->bljk", F, f).reshape(B, n, -1)
        lamF = kappa * (torch.einsum("jl,bm->bljm", F, lam) + torch.einsum("lm,bj->bljm", eye_n, w))
        lam_blocks["G"], lam_blocks["H"] = _flat_GH(lamF, G)

        sl = parameter_slices(m)
        P = sl[PARAMETER_NAMES[-1]].stop
        rho_theta = x.new_zeros(B, n_x + n, P)
        J_ztheta = x.new_zeros(B, 2 * n, P)
        root = kappa**0.5
        for k, block in e_blocks.items():
            rho_theta[:, :n_x, sl[k]] = block
        for k, block in w_blocks.items():
            rho_theta[:, n_x:, sl[k]] = block * root
            J_ztheta[:, n:, sl[k]] = block * -kappa
        for k, block in lam_blocks.items():
            J_ztheta[:, :n, sl[k]] = block
    return rho_theta, J_ztheta


def objective_linearisation(
    model: LCS,
    x: torch.Tensor,
    u: torch.Tensor,
    x_next: torch.Tensor,
    z: torch.Tensor,
    gamma: float,
    eps: float,
) -> tuple[Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
           Callable[[torch.Tensor, torch.Tensor], torch.Tensor]]:
    r"""Products with the two Jacobians of :func:`objective_jacobians`, without forming them.

    Returns ``jvp(v) -> (rho_theta v (B, r), J_ztheta v (B, 2 n))`` for ``v`` ``(P,)``, and
    ``vjp(a, b) -> sum_t rho_theta_t^T a_t + J_ztheta_t^T b_t`` ``(P,)`` for ``a`` ``(B, r)``,
    ``b`` ``(B, 2 n)``: with ``dF = dG G^T + G dG^T + dH - dH^T``,
    ``de = dA x + dB u + dC lam + dd``, ``dw = dF lam + dD x + dE u + dc``,
    ``rho_theta v = [de; sqrt(kappa) dw]`` and
    ``J_ztheta v = [C^T de + dC^T e + kappa (F^T dw + dF^T w); -kappa dw]``; ``vjp`` is its
    transpose, written out. A few ``(B, n) x (n, n)`` products each: the Gauss--Newton and
    Newton operators for large models.
    """
    m = model
    n, n_x = m.n_lam, m.n_x
    lam = z[:, :n]
    kappa = 1.0 / (eps * gamma)
    root = kappa**0.5
    e, w = _residuals(m, x, u, x_next, z)
    C, F, G = m.C.detach(), m.F.detach(), m.G.detach()
    sl = parameter_slices(m)
    shapes = {k: getattr(m, k).shape for k in PARAMETER_NAMES}

    def jvp(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        d = {k: v[sl[k]].reshape(shapes[k]) for k in PARAMETER_NAMES}
        dG = d["G"] @ G.mT
        dF = dG + dG.mT + d["H"] - d["H"].mT
        de = x @ d["A"].mT + u @ d["B"].mT + lam @ d["C"].mT + d["d"]
        dw = x @ d["D"].mT + u @ d["E"].mT + lam @ dF.mT + d["c"]
        dg = de @ C + e @ d["C"] + kappa * (dw @ F + w @ dF)
        return torch.cat([de, root * dw], 1), torch.cat([dg, -kappa * dw], 1)

    def vjp(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        b_lam, b_phi = b[:, :n], b[:, n:]
        ce = a[:, :n_x] + b_lam @ C.mT
        cw = root * a[:, n_x:] + kappa * (b_lam @ F.mT - b_phi)
        gF = cw.mT @ lam + kappa * (w.mT @ b_lam)
        g = {
            "A": ce.mT @ x, "B": ce.mT @ u, "C": ce.mT @ lam + e.mT @ b_lam, "d": ce.sum(0),
            "D": cw.mT @ x, "E": cw.mT @ u, "G": (gF + gF.mT) @ G, "H": gF - gF.mT,
            "c": cw.sum(0),
        }
        return torch.cat([g[k].reshape(-1) for k in PARAMETER_NAMES])

    return jvp, vjp


def _gg_curvature(model: LCS, x, u, x_next, z, gamma: float, eps: float) -> torch.Tensor:
    """``S`` ``(n, n)`` with ``d^2 J / dG_ab dG_cd = S_ac delta_bd`` (batch mean, z fixed): the only
    second derivative of ``J`` beyond ``rho_theta^T rho_theta``, from ``w``'s ``F lam`` term with
    ``F = G G^T + ...``: ``S = kappa mean_t (w_t lam_t^T + lam_t w_t^T)``."""
    _, w = _residuals(model, x, u, x_next, z)
    lam = z[:, : model.n_lam]
    W = w.mT @ lam
    return (W + W.mT) / (eps * gamma * z.shape[0])


def violation_hessian(
    model: LCS, x: Any, u: Any, x_next: Any, gamma: float = 1e-2, eps: float = 1e-4
) -> torch.Tensor:
    r"""Hessian of ``L_eps`` (batch mean, as :func:`lcs_cvx.violation_loss`), Lemma 4.

    ``mean_t [J_thth - (J_thz)_F (J_zz)_FF^{-1} (J_zth)_F]`` -- see the module docstring for the
    reduction of Lemma 4's formula under strict complementarity and for the ordering of ``theta``
    (:data:`lcs_cvx.system.PARAMETER_NAMES`, row-major; :func:`parameter_slices`).

    Args:
        model: an :class:`lcs_cvx.LCS`; or a model with per-sample matrices
            (:class:`lcs_cvx.RigidBodyContact`: :func:`lcs_cvx.per_sample.violation_hessian`,
            ``theta`` its learnable parameters).
        x: ``(N, n_x)``; u: ``(N, n_u)``; x_next: ``(N, n_x)``.
        gamma: ``0 < gamma < sigma_min(F + F^T)`` (Lemma 2; checked). eps: ``> 0``.

    Returns:
        ``(P, P)`` tensor of the model's dtype, no autograd graph. Defined where strict
        complementarity holds on every sample (Lemma 3(b)).

    Example:
        >>> import lcs_cvx
        >>> sys = lcs_cvx.random_lcs(3, 2, 2, seed=0)
        >>> data = lcs_cvx.make_dataset(sys, 20)
        >>> violation_hessian(sys, data.x, data.u, data.x_next, eps=0.1).shape
        torch.Size([44, 44])
    """
    if not isinstance(model, LCS) and hasattr(model, "sample_lcs"):
        from .per_sample import violation_hessian as per_sample_hessian

        return per_sample_hessian(model, x, u, x_next, gamma, eps)
    x, u, x_next, z, m, chol = setup(model, x, u, x_next, gamma, eps)
    rho_theta, Jzt = objective_jacobians(model, x, u, x_next, z, gamma, eps)  # (B, r | 2n, P)
    B = z.shape[0]
    with torch.no_grad():
        R = rho_theta.reshape(-1, rho_theta.shape[-1])
        H = R.mT @ R / B  # J_thth (z fixed): rho_theta^T rho_theta + the curvature of F = G G^T
        sl = parameter_slices(model)["G"]
        H[sl, sl] += torch.kron(_gg_curvature(model, x, u, x_next, z, gamma, eps),
                                torch.eye(model.n_lam, dtype=z.dtype, device=z.device))
        # Y_t = chol_t^{-1} (m o J_zth): the correction mean_t Y_t^T Y_t is symmetric PSD by form
        Y = torch.linalg.solve_triangular(chol, m[:, :, None] * Jzt, upper=False).reshape(-1, R.shape[-1])
        return H - Y.mT @ Y / B


def hvp_operator(
    model: LCS, x: Any, u: Any, x_next: Any, gamma: float = 1e-2, eps: float = 1e-4
) -> Callable[[torch.Tensor], torch.Tensor]:
    """``v -> hess L_eps @ v`` (Lemma 4) with the solve and factorisations done once, for
    iterative methods that need many products at the same ``theta`` (see :func:`violation_hvp`)."""
    x, u, x_next, z, m, chol = setup(model, x, u, x_next, gamma, eps)
    jvp, vjp = objective_linearisation(model, x, u, x_next, z, gamma, eps)
    S = _gg_curvature(model, x, u, x_next, z, gamma, eps)
    sl, n, B = parameter_slices(model)["G"], model.n_lam, z.shape[0]

    def matvec(v: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            rho_v, Jzt_v = jvp(v)  # (B, r), (B, 2n)
            s = torch.cholesky_solve((m * Jzt_v).unsqueeze(-1), chol).squeeze(-1) * m
            out = vjp(rho_v, -s) / B  # (rho_theta^T rho_theta - J_thz (.)^{-1} J_zth) v
            out[sl] += (S @ v[sl].reshape(n, n)).reshape(-1)  # (S kron I) v_G
            return out

    return matvec


def violation_hvp(
    model: LCS,
    x: Any,
    u: Any,
    x_next: Any,
    v: Any,
    gamma: float = 1e-2,
    eps: float = 1e-4,
) -> torch.Tensor:
    r"""Hessian-vector product ``hess L_eps @ v`` (Lemma 4) without forming the ``(P, P)`` matrix.

    ``J_thth v`` by forward-over-reverse at fixed ``z``; the correction
    ``-mean_t (J_thz)_F (J_zz)_FF^{-1} (J_zth v)_F`` by one batched jvp of ``J_z``, one batched
    Cholesky solve with the masked ``M_t`` and one vjp. Cost: a few evaluations of ``J``.

    Args:
        model, x, u, x_next, gamma, eps: as :func:`violation_hessian`.
        v: ``(P,)`` direction, ordered as :func:`parameter_slices`.

    Returns:
        ``(P,)`` tensor, no autograd graph.
    """
    P = sum(getattr(model, k).numel() for k in PARAMETER_NAMES) if isinstance(model, LCS) else 0
    op = hvp_operator(model, x, u, x_next, gamma, eps)
    v = as_matrix("v", v, (P,), dtype=model.dtype, device=model.device)
    return op(v)
