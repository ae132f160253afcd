"""lcs_cvx.per_sample: the LCP, the violation loss and the prediction loss of a model whose
matrices differ per sample (a rigid body's), each checked three ways -- the fast kernels, the
cvxpylayers reference over the declared problems, and central finite differences (float64)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import lcs_cvx
from lcs_cvx.per_sample import prediction_loss_info, solve_sample_lcp, violation_loss_info
from lcs_cvx.problems import convex_lcp_problem

F64 = torch.float64
GAMMA, EPS = 0.01, 1.0


def body(**kw) -> lcs_cvx.RigidBodyContact:
    args = {"half_sizes": [0.05, 0.045, 0.055], "mass": 0.4, "dt": 0.01, "mu": 0.3, "ground": 0.0,
            "com": (0.002, -0.001, 0.001), "inertia": [0.0008, 0.0009, 0.001], "friction_directions": 3}
    args.update(kw)
    return lcs_cvx.RigidBodyContact(**args)


def contact_samples(n: int = 6, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """States near the floor (tilted, moving) and next states of a slightly different body plus
    noise: every sample has corners in contact and a nonzero residual."""
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g, dtype=F64) * torch.tensor([0.1, 0.3, 0.3, 0.3], dtype=F64)
    q[:, 0] += 1.0
    q = q / q.norm(dim=1, keepdim=True)
    p = torch.cat([0.1 * torch.randn(n, 2, generator=g, dtype=F64), 0.045 + 0.005 * torch.rand(n, 1, generator=g, dtype=F64)], 1)
    w = torch.randn(n, 3, generator=g, dtype=F64)
    v = 0.3 * torch.randn(n, 3, generator=g, dtype=F64) - torch.tensor([0, 0, 0.3], dtype=F64)
    x = torch.cat([q, p, w, v], 1)
    u = torch.zeros(n, 0, dtype=F64)
    with torch.no_grad():
        other = body(mu=0.5, half_sizes=[0.052, 0.05, 0.05])
        x_next = other.step(x, u) + 0.01 * torch.randn(n, 13, generator=g, dtype=F64)
        x_next[:, :4] /= x_next[:, :4].norm(dim=1, keepdim=True)
    return x, u, x_next


def grads(loss: torch.Tensor, model: torch.nn.Module) -> dict[str, torch.Tensor]:
    params = dict(model.named_parameters())
    gs = torch.autograd.grad(loss, list(params.values()))
    return dict(zip(params, gs, strict=True))


def finite_difference(f, model: torch.nn.Module, h: float = 1e-6) -> dict[str, torch.Tensor]:
    """Central differences of ``f()`` in every parameter entry (step ``h`` in the parameter's own
    units, which are the body's: log sizes, lengths over its size)."""
    out = {}
    for name, p in model.named_parameters():
        g = torch.zeros_like(p)
        flat = p.data.view(-1)
        for i in range(flat.numel()):
            old = float(flat[i])
            flat[i] = old + h
            up = float(f())
            flat[i] = old - h
            down = float(f())
            flat[i] = old
            g.view(-1)[i] = (up - down) / (2 * h)
        out[name] = g
    return out


def test_the_samples_are_in_contact():
    m = body()
    x, u, _ = contact_samples()
    with torch.no_grad():
        lam = m.solve_lcp(x, u)
    assert bool((lam.sum(1) > 0).all())


def test_the_lcp_of_each_sample_is_the_declared_problems():
    m = body()
    x, u, _ = contact_samples()
    with torch.no_grad():
        lcs = m.sample_lcs(x, u)
        lam = solve_sample_lcp(lcs)
        ref = torch.stack([convex_lcp_problem(lcs.q.shape[1]).solve(lcs.F[i], lcs.q[i:i + 1])[0] for i in range(len(x))])
    assert torch.allclose(lam, ref.clamp(min=0), atol=1e-7)
    w = (lcs.F @ lam[..., None])[..., 0] + lcs.q
    assert float(lam.min()) >= 0 and float(w.min()) > -1e-12 and float((lam * w).abs().max()) < 1e-15


@pytest.mark.parametrize("kind", ["violation", "prediction"])
def test_loss_and_gradient_three_ways(kind):
    m = body(residual=True, corner_radius=0.004)  # every learnable quantity: the residual map (nonzero), the radius
    with torch.no_grad():
        m.residual_map.copy_(0.01 * torch.randn(6, 14, generator=torch.Generator().manual_seed(5), dtype=F64))
    x, u, x_next = contact_samples()

    def loss(solver: str) -> torch.Tensor:
        lcs = m.sample_lcs(x, u)
        if kind == "violation":
            return violation_loss_info(lcs, x_next, GAMMA, EPS, solver=solver).loss
        return prediction_loss_info(lcs, x_next, solver=solver).loss

    fast = loss("fast")
    layer = loss("cvxpylayers")
    # the interior point's answer is accurate to its tolerances (a relative KKT residual of
    # ~1e-6 against the pivoting's 1e-16, amplified by 1 / (gamma eps) in (V)'s value)
    assert abs(float(fast.detach()) - float(layer.detach())) <= 1e-3 * abs(float(fast.detach()))
    g_fast, g_layer = grads(fast, m), grads(layer, m)
    with torch.no_grad():
        g_fd = finite_difference(lambda: loss("fast"), m)
    largest = max(float(g.abs().max()) for g in g_fast.values())
    for name in g_fast:
        scale = float(g_fast[name].abs().max())
        # the layer's contacts out of touch keep lam ~ 1e-8 (an interior point): absolute slack
        assert float((g_fast[name] - g_layer[name]).abs().max()) <= 1e-2 * scale + 1e-4 * largest, name
        assert float((g_fast[name] - g_fd[name]).abs().max()) <= 1e-6 * scale + 1e-9 * largest, name
    assert any(float(g.abs().max()) > 0 for g in g_fast.values())


def test_the_lemma_4_hessian_three_ways():
    m = body(corner_radius=0.004)
    x, u, x_next = contact_samples()
    H = lcs_cvx.violation_hessian(m, x, u, x_next, gamma=GAMMA, eps=EPS)
    params = [p for p in m.parameters() if p.requires_grad]
    assert H.shape == (sum(p.numel() for p in params),) * 2
    assert torch.allclose(H, H.mT, atol=1e-9 * float(H.abs().max()))

    def gradient(solver: str) -> torch.Tensor:
        loss = m.loss_info("violation", x, u, x_next, gamma=GAMMA, eps=EPS, solver=solver).loss
        return torch.cat([g.reshape(-1) for g in torch.autograd.grad(loss, params)])

    def differences(solver: str, h: float) -> torch.Tensor:
        cols = []
        for p in params:
            flat = p.data.view(-1)
            for i in range(flat.numel()):
                old = float(flat[i])
                flat[i] = old + h
                up = gradient(solver)
                flat[i] = old - h
                down = gradient(solver)
                flat[i] = old
                cols.append((up - down) / (2 * h))
        return torch.stack(cols, dim=1)

    scale = float(H.abs().max())
    # the envelope gradient of the fast kernel, differenced: Lemma 4 to the differences' accuracy
    assert float((differences("fast", 1e-5) - H).abs().max()) <= 1e-6 * scale
    # the cvxpylayers layer's gradient, differenced with a step long enough for the interior
    # point's tolerances (its gradient's noise / h); the step's own truncation is ~0.9 % here
    assert float((differences("cvxpylayers", 2e-2) - H).abs().max()) <= 2e-2 * scale


def test_the_public_losses_take_a_rigid_body():
    m = body()
    x, u, x_next = contact_samples()
    info = lcs_cvx.violation_loss_info(m, x, u, x_next, gamma=GAMMA, eps=EPS)
    lcs = m.sample_lcs(x, u)
    # the same numbers but for the quaternions' normalisation at the boundary (round-off)
    assert torch.allclose(info.loss.detach(), violation_loss_info(lcs, x_next, GAMMA, EPS).loss.detach(), rtol=1e-13)
    assert info.lam.shape == (len(x), m.n_lam) and info.n_fallback == 0
    pred = lcs_cvx.prediction_loss(m, x, u, x_next)
    assert torch.allclose(pred.detach(), prediction_loss_info(lcs, x_next).loss.detach(), rtol=1e-13)


def test_the_violation_loss_is_below_the_prediction_loss_and_approaches_it():
    """(V)'s value at the LCP's lam (phi = w) is the prediction loss: the minimum is at most it,
    and tends to it as eps -> 0 (eq. (9) and its limit)."""
    m = body()
    x, u, x_next = contact_samples()
    with torch.no_grad():
        lcs = m.sample_lcs(x, u)
        pred = float(prediction_loss_info(lcs, x_next).loss)
        values = [float(violation_loss_info(lcs, x_next, GAMMA, eps).loss) for eps in (1.0, 1e-2, 1e-4, 1e-6)]
    assert all(v <= pred * (1 + 1e-9) for v in values)
    assert values == sorted(values) and abs(values[-1] - pred) < 1e-3 * pred


def test_gamma_above_the_compliance_bound_is_refused():
    m = body(compliance=0.004)
    x, u, x_next = contact_samples()
    with pytest.raises(lcs_cvx.LCSInputError, match="gamma: expected 0 < gamma < 0.004"):
        lcs_cvx.violation_loss(m, x, u, x_next, gamma=0.005, eps=EPS)


def test_fit_learns_friction_back_from_slides():
    """Slides of a body with mu = 0.5 (its own simulation): fit, started at mu = 0.2 with only
    mu learnable, recovers it (violation loss, Adam)."""
    truth = body(mu=0.5, friction_directions=4)
    g = torch.Generator().manual_seed(1)
    n = 300
    q = torch.tensor([[1.0, 0, 0, 0]], dtype=F64).expand(n, 4)
    p = torch.cat([torch.zeros(n, 2, dtype=F64), torch.full((n, 1), 0.055 - 0.002, dtype=F64)], 1)
    vxy = torch.randn(n, 2, generator=g, dtype=F64)
    x = torch.cat([q, p, torch.zeros(n, 3, dtype=F64), vxy, torch.zeros(n, 1, dtype=F64)], 1)
    u = torch.zeros(n, 0, dtype=F64)
    with torch.no_grad():
        data = lcs_cvx.Dataset(x, u, truth.step(x, u))
    model = body(mu=0.2, friction_directions=4, learn=("mu",))
    res = lcs_cvx.fit(model, data, loss="violation", gamma=GAMMA, eps=1e-4, iterations=300, lr=0.05,
                      batch_size=100, progress=False)
    assert abs(float(model.mu.detach()) - 0.5) < 0.01
    assert res.history[-1]["loss"] < res.history[0]["loss"]


def test_fit_refuses_what_a_rigid_body_has_no_use_for():
    x, u, x_next = contact_samples()
    data = lcs_cvx.Dataset(x, u, x_next)
    with pytest.raises(lcs_cvx.LCSInputError, match="optimizer: expected 'adam'"):
        lcs_cvx.fit(body(), data, optimizer="gauss-newton", progress=False)
    fixed = body(learn=())
    with pytest.raises(lcs_cvx.LCSInputError, match="model: expected at least one learnable quantity"):
        lcs_cvx.fit(fixed, data, progress=False)


def test_fit_on_trajectories_runs_the_simulation_error_phase_and_judges_the_body():
    truth = body(mu=0.4)
    g = torch.Generator().manual_seed(2)
    xs = []
    with torch.no_grad():
        for _ in range(6):
            x0 = torch.tensor([[1.0, 0, 0, 0, 0, 0, 0.2, 0, 0, 0, 0, 0, 0]], dtype=F64)
            x0[0, 7:10] = 3 * torch.randn(3, generator=g, dtype=F64)
            x0[0, 10:12] = torch.randn(2, generator=g, dtype=F64)
            xs.append(truth.rollout(x0, torch.zeros(1, 40, 0, dtype=F64))[0])
    runs = lcs_cvx.Trajectories(xs, [np.zeros((40, 0))] * 6)
    model = body(mu=0.2)
    res = lcs_cvx.fit(model, runs, loss="violation", gamma=GAMMA, eps=EPS, iterations=20, lr=3e-3,
                      rollout_horizon=5, rollout_iterations=5, rollout_batch=8, eval_every=10, progress=False)
    phases = {h["phase"] for h in res.history}
    assert phases == {"adam", "rollout"}
    assert np.isfinite(res.heldout_error) and res.verdict
    assert all(bool(torch.isfinite(p).all()) for p in model.parameters())
