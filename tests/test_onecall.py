"""lcs_cvx.train.onecall: Adam's steps on the one-call path against ``loss.backward();
adam.step()`` (the autograd step the trainer took before, and still takes where the one-call
path does not apply), and the compiled Adam update against torch's.

Two code paths, so numbers agree to round-off (torch may fuse a multiply and an add where the
compiled update does not), never with ``==``.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from helpers import make_problem

import lcs_cvx
import lcs_cvx.train.phases as phases
from lcs_cvx._kernels.adam import adam_update
from lcs_cvx.losses import prediction_fast, regularizer, violation_fast
from lcs_cvx.parameter_constraints import mask_gradients_, project_
from lcs_cvx.system import PARAMETER_NAMES
from lcs_cvx.train.onecall import adam_step, data_arrays

F64 = torch.float64
GAMMA, EPS, REG = 1e-2, 1e-3, 1e-4


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / b.abs().max().clamp_min(1e-300))


@pytest.mark.parametrize("beta1", [0.9, 0.3])
def test_the_compiled_update_is_torchs_adam(beta1):
    """One update of the compiled kernel against ``torch.optim.Adam.step`` on the same state,
    five steps in a row (both branches of torch's ``lerp``: weight below and above 1/2)."""
    rng = np.random.default_rng(0)
    p_ref = [torch.tensor(rng.standard_normal(s), requires_grad=True) for s in [(3, 4), (5,)]]
    p_new = [p.detach().clone() for p in p_ref]
    adam = torch.optim.Adam(p_ref, lr=3e-2, betas=(beta1, 0.95), eps=1e-7)
    m = [torch.zeros_like(p) for p in p_new]
    v = [torch.zeros_like(p) for p in p_new]
    steps = [torch.zeros(1, dtype=torch.float32) for _ in p_new]
    for t in range(1, 6):
        grads = [torch.tensor(rng.standard_normal(tuple(p.shape))) for p in p_ref]
        for p, g in zip(p_ref, grads, strict=True):
            p.grad = g.clone()
        adam.step()
        assert adam_update(tuple(p.view(-1).numpy() for p in p_new), tuple(g.view(-1).numpy() for g in grads),
                           tuple(a.view(-1).numpy() for a in m), tuple(a.view(-1).numpy() for a in v),
                           tuple(s.numpy() for s in steps), beta1, 0.95, 1e-7, 3e-2 / (1 - beta1**t),
                           (1 - 0.95**t) ** 0.5, float(t))
        for p, q, mk, vk, s in zip(p_ref, p_new, m, v, steps, strict=True):
            st = adam.state[p]
            assert _rel(q, p.detach()) <= 1e-14 and _rel(mk, st["exp_avg"]) <= 1e-14
            # the step counts are small integers in float32: exact
            assert _rel(vk, st["exp_avg_sq"]) <= 1e-14 and float(s[0]) == float(st["step"]) == t
    # a parameter whose count is not one behind the step: nothing changes, False
    before = p_new[0].clone()
    assert not adam_update((p_new[0].view(-1).numpy(),), (grads[0].view(-1).numpy(),), (m[0].view(-1).numpy(),),
                           (v[0].view(-1).numpy(),), (steps[0].numpy(),), beta1, 0.95, 1e-7, 1e-2, 1.0, 9.0)
    assert torch.equal(p_new[0], before) and float(steps[0][0]) == 5


def _autograd_step(adam, model, loss, x, u, x_next):
    """The trainer's autograd step: fast loss, regulariser, backward, Adam."""
    info = (violation_fast(model, x, u, x_next, gamma=GAMMA, eps=EPS) if loss == "violation"
            else prediction_fast(model, x, u, x_next))
    value = info.loss + regularizer(model, REG)
    adam.zero_grad()
    value.backward()
    mask_gradients_(model)
    adam.step()
    project_(model)
    return float(value.detach()), info.active


@pytest.mark.parametrize("loss", ["violation", "prediction"])
@pytest.mark.parametrize("constrained", [False, True])
def test_steps_are_the_autograd_steps(loss, constrained):
    """Ten steps of the one-call path and of the autograd path from the same model and Adam
    state: the same losses, active sets, parameters and Adam moments (to round-off); with a
    fixed parameter and a mask, the fixed one unchanged and the masked entries held at 0."""
    model, data = make_problem(n_lam=4, n=120, model="perturbed", seed=5)
    if constrained:
        model.fix(B=model.B.detach().clone())
        model.mask(C=torch.rand(model.C.shape, generator=torch.Generator().manual_seed(1)) > 0.3)
    ref = copy.deepcopy(model)
    a_ref = torch.optim.Adam(ref.parameters(), lr=1e-2, betas=(0.9, 0.9), eps=1e-6)
    a_new = torch.optim.Adam(model.parameters(), lr=1e-2, betas=(0.9, 0.9), eps=1e-6)
    x, u, x_next = data_arrays(data)
    # the first step creates Adam's state: the one-call path leaves it to torch
    assert adam_step(a_new, model, loss, x, u, x_next, None, gamma=GAMMA, eps=EPS, reg=REG) is None
    _autograd_step(a_ref, ref, loss, data.x, data.u, data.x_next)
    _autograd_step(a_new, model, loss, data.x, data.u, data.x_next)
    fixed_B = model.B.detach().clone()
    for k in range(10):
        rows = torch.arange(k * 10, k * 10 + 40) % len(data)
        value, active = _autograd_step(a_ref, ref, loss, data.x[rows], data.u[rows], data.x_next[rows])
        got, finite_F, got_active = adam_step(a_new, model, loss, x[rows], u[rows], x_next[rows], None,
                                              gamma=GAMMA, eps=EPS, reg=REG)
        # the first step from equal states: equal to a few ulps; later ones from parameters a
        # few ulps apart, which the loss's conditioning (eps = 1e-3) and Adam's normalised
        # steps amplify by up to ~1e5 over ten steps
        tol = 1e-14 if k == 0 else 1e-9
        assert finite_F and got == pytest.approx(value, rel=tol, abs=0)
        assert np.array_equal(got_active, active.numpy())
        if k == 0:
            for name in PARAMETER_NAMES:
                assert _rel(getattr(model, name).detach(), getattr(ref, name).detach()) <= 1e-14, name
    for name in PARAMETER_NAMES:
        assert _rel(getattr(model, name).detach(), getattr(ref, name).detach()) <= 1e-9, name
    for p, q in zip(model.parameters(), ref.parameters(), strict=True):
        if q.requires_grad:
            assert _rel(a_new.state[p]["exp_avg"], a_ref.state[q]["exp_avg"]) <= 1e-9
            assert float(a_new.state[p]["step"]) == float(a_ref.state[q]["step"]) == 11  # integer counts
    if constrained:
        assert torch.equal(model.B.detach(), fixed_B) and not model.B.requires_grad
        assert bool((model.C.detach()[~model.masks["C"]] == 0).all())


def test_where_it_does_not_apply_nothing_changes():
    """float32 models, a stack's optimiser options, a non-converging batch: None, the model
    and the optimiser untouched (the trainer then takes the autograd step)."""
    model, data = make_problem(n_lam=3, n=60, seed=2)
    x, u, x_next = data_arrays(data)
    adam = torch.optim.Adam(model.parameters(), lr=1e-2)
    _autograd_step(adam, model, "violation", data.x, data.u, data.x_next)
    before = {k: v.detach().clone() for k, v in model.state_dict().items()}
    f32 = copy.deepcopy(model).to(torch.float32)
    assert adam_step(torch.optim.Adam(f32.parameters()), f32, "violation", x, u, x_next, None,
                     gamma=GAMMA, eps=EPS, reg=REG) is None
    amsgrad = torch.optim.Adam(model.parameters(), amsgrad=True)
    assert adam_step(amsgrad, model, "violation", x, u, x_next, None, gamma=GAMMA, eps=EPS, reg=REG) is None
    assert data_arrays(lcs_cvx.Dataset(data.x.float(), data.u.float(), data.x_next.float())) is None
    assert all(torch.equal(v, before[k]) for k, v in model.state_dict().items())


def test_unconverged_batches_take_the_autograd_step(monkeypatch):
    """With no pivoting sweep allowed, the compiled kernel leaves samples unconverged: the
    one-call step declines and the trainer's autograd step ends them with the reference
    solvers (FallbackWarning), as before."""
    model, data = make_problem(n_lam=4, n=80, model="perturbed", seed=1)
    x, u, x_next = data_arrays(data)
    adam = torch.optim.Adam(model.parameters(), lr=1e-2)
    _autograd_step(adam, model, "violation", data.x, data.u, data.x_next)
    monkeypatch.setattr(lcs_cvx.losses, "MAX_ITER", 0)
    assert adam_step(adam, model, "violation", x, u, x_next, None, gamma=GAMMA, eps=EPS, reg=REG) is None


@pytest.mark.parametrize("off", [("adam_steps",), ("adam_steps", "adam_step")],
                         ids=["one-call-steps", "autograd-steps"])
@pytest.mark.parametrize("recipe", ["paper", "polish", "masked"])
def test_fit_in_stretches_is_the_fit_step_by_step(recipe, off, monkeypatch):
    """A whole ``fit`` (Adam with warm starts and the learning-rate and eps schedules; with
    ``"polish"``, the prediction-loss polish too; with ``"masked"``, a fixed parameter and a mask)
    as it runs, many compiled steps to a call (``adam_steps``), against the same fit with its
    steps one call each (``adam_step``) and with autograd steps. All make the same operations
    in the same order: the kernel's gradient (times 1.0 through autograd) plus ``reg (2 C)``,
    masked entries zeroed, the same compiled Adam update (``adam_update_from_grads`` for the
    autograd steps). So the parameters are equal bit for bit; the recorded losses add the
    regulariser's value through NumPy, numba or torch (a few ulps)."""
    truth = lcs_cvx.random_lcs(4, 2, 3, seed=0)
    train = lcs_cvx.make_dataset(truth, 1000, noise=0.01, seed=1)
    kw = ({"recipe": "paper", "iterations": 150} if recipe != "polish" else
          {"recipe": "plain", "iterations": 100, "polish_iterations": 40, "lr_schedule": "cosine", "eps_start": 1e-1})

    def model() -> lcs_cvx.LCS:
        m = lcs_cvx.LCS(4, 2, 3, seed=2)
        if recipe == "masked":
            m.fix(B=torch.zeros(4, 2, dtype=F64))
            m.mask(D=torch.tensor([[True, False, True, True]] * 3))
        return m

    made = []  # the steps each compiled call made: the stretches do run
    real = phases.adam_steps
    monkeypatch.setattr(phases, "adam_steps", lambda *a, **k: made.append(real(*a, **k)) or made[-1])
    fast = model()
    r_fast = lcs_cvx.fit(fast, train, progress=False, eval_every=10, **kw)
    assert made and all(m is not None for m in made) and sum(m[0] for m in made) >= 90
    for name in off:
        monkeypatch.setattr(phases, name, lambda *a, **k: None)
    slow = model()
    r_slow = lcs_cvx.fit(slow, train, progress=False, eval_every=10, **kw)
    assert [h["phase"] for h in r_fast.history] == [h["phase"] for h in r_slow.history]
    for a, b in zip(r_fast.history, r_slow.history, strict=True):
        assert a["loss"] == pytest.approx(b["loss"], rel=1e-13)
    for name in PARAMETER_NAMES:
        assert torch.equal(getattr(fast, name), getattr(slow, name)), name
    if recipe == "masked":
        assert not bool(fast.B.detach().any()) and not bool(fast.D.detach()[:, 1].any())


def test_autograd_steps_update_as_the_one_call_steps():
    """``adam_update_from_grads``: on float64 CPU parameters with a state, the compiled update
    (what the one-call steps run, so the two kinds of step mix in one run with one arithmetic);
    torch's ``step`` on the first step and on float32 parameters."""
    from lcs_cvx.train.onecall import adam_update_from_grads

    for dtype in (torch.float64, torch.float32):
        p = torch.tensor([1.0, -2.0, 3.0], dtype=dtype, requires_grad=True)
        q = p.detach().clone().requires_grad_(True)
        a_p, a_q = torch.optim.Adam([p], lr=0.1), torch.optim.Adam([q], lr=0.1)
        for t in range(3):
            for v in (p, q):
                v.grad = torch.tensor([0.5, -0.25, 1e-3 * (t + 1)], dtype=dtype)
            a_p.step()
            adam_update_from_grads(a_q)
            assert float(a_q.state[q]["step"]) == t + 1
        assert _rel(q.detach().double(), p.detach().double()) <= (1e-15 if dtype == torch.float64 else 0.0)
