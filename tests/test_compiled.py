"""The compiled loss kernels (lcs_cvx/_kernels/compiled.py) against the array kernels.

The fast losses run compiled for one model's float64 CPU tensors and in the array kernels
otherwise (``arrays="numpy"`` forces them on CPU): the two implementations of the same
algorithm must give the same solutions, active sets, sweep counts and loss values, and the same
gradients to round-off -- and, where they differ by design (a sample that does not converge,
non-finite data), the compiled path must hand over to the array path or raise its error.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from helpers import lemma3_gradients, make_problem, rel_err

import lcs_cvx
from lcs_cvx import FallbackWarning, LCSInputError
from lcs_cvx import losses as losses_module
from lcs_cvx.losses import prediction_fast, violation_fast
from lcs_cvx.system import PARAMETER_NAMES
from lcs_cvx.value_and_grad import violation_value_and_grad

GAMMA, EPS = 1e-2, 1e-3
SIZES = [(4, 2, 1), (5, 2, 4), (6, 3, 12), (40, 4, 6)]


def _run(fn, model, data, arrays, **kw):
    model.zero_grad()
    info = fn(model, data.x, data.u, data.x_next, arrays=arrays, **kw)
    info.loss.backward()
    return info, {k: getattr(model, k).grad.clone() for k in PARAMETER_NAMES}


@pytest.mark.parametrize("n_x, n_u, n_lam", SIZES)
def test_compiled_violation_is_the_array_kernel(n_x, n_u, n_lam):
    """Same lam (to round-off of an n x n solve), active sets, sweeps and value; the gradients
    to the round-off of Lemma 3's expressions (their terms' magnitude, :func:`lemma3_gradients`)."""
    model, data = make_problem(n_lam=n_lam, n=60, model="perturbed", seed=n_lam, n_x=n_x, n_u=n_u)
    c, gc = _run(violation_fast, model, data, "compiled", gamma=GAMMA, eps=EPS)
    a, ga = _run(violation_fast, model, data, "numpy", gamma=GAMMA, eps=EPS)
    assert float((c.lam - a.lam).abs().max()) <= 1e-12 * (1.0 + float(a.lam.abs().max()))
    assert torch.equal(c.active, a.active) and c.iterations == a.iterations
    assert c.n_fallback == 0 and c.phi.shape == a.phi.shape
    assert float(c.loss.detach()) == pytest.approx(float(a.loss.detach()), rel=1e-12)
    scale = lemma3_gradients(model, data, a.lam, a.phi, GAMMA, EPS, magnitude=True)
    for name in PARAMETER_NAMES:
        assert float(((gc[name] - ga[name]).abs() / scale[name].clamp(min=1e-300)).max()) <= 1e-12, name


@pytest.mark.parametrize("n_x, n_u, n_lam", SIZES)
def test_compiled_prediction_is_the_array_kernel(n_x, n_u, n_lam):
    """Same lam, free sets, w, sweeps, degenerate count and value; gradients to 1e-12."""
    model, data = make_problem(n_lam=n_lam, n=60, model="perturbed", seed=n_lam, n_x=n_x, n_u=n_u)
    c, gc = _run(prediction_fast, model, data, "compiled")
    a, ga = _run(prediction_fast, model, data, "numpy")
    assert float((c.lam - a.lam).abs().max()) <= 1e-12 * (1.0 + float(a.lam.abs().max()))
    assert float((c.w - a.w).abs().max()) <= 1e-12 * (1.0 + float(a.w.abs().max()))
    assert torch.equal(c.active, a.active) and c.iterations == a.iterations
    assert c.n_degenerate == a.n_degenerate
    assert float(c.loss.detach()) == pytest.approx(float(a.loss.detach()), rel=1e-12)
    for name in PARAMETER_NAMES:
        assert rel_err(gc[name], ga[name]) <= 1e-12, name


def test_compiled_counts_degenerate_samples_as_the_array_kernel():
    """Samples with lam_i = w_i = 0 (q_i = 0 at a zero of lam): counted alike, the same
    one-sided gradient (the index held at zero)."""
    model, data = make_problem(n_lam=3, n=30, model="perturbed", seed=5)
    with torch.no_grad():  # x = u = 0 on the first 10 samples and c >= 0, c_0 = 0: q = c there,
        x, u = data.x.clone(), data.u.clone()  # whose LCP has lam = 0 and w_0 = q_0 = 0
        x[:10] = 0.0
        u[:10] = 0.0
        model.c.abs_()
        model.c[0] = 0.0
    data = SimpleNamespace(x=x, u=u, x_next=data.x_next)
    c, gc = _run(prediction_fast, model, data, "compiled")
    a, ga = _run(prediction_fast, model, data, "numpy")
    assert c.n_degenerate == a.n_degenerate >= 1
    for name in PARAMETER_NAMES:
        assert rel_err(gc[name], ga[name]) <= 1e-12, name


@pytest.mark.parametrize("fn, kw", [(violation_fast, {"gamma": GAMMA, "eps": EPS}), (prediction_fast, {})])
def test_compiled_warm_start_ends_where_it_starts(fn, kw):
    """Warm-started with its own final active sets, a solve makes no sweep and gives the same
    numbers; a warm start of the wrong shape is named."""
    model, data = make_problem(n_lam=6, n=50, model="perturbed", seed=2)
    cold, g_cold = _run(fn, model, data, "compiled", **kw)
    warm, g_warm = _run(fn, model, data, "compiled", warm_start=cold.active, **kw)
    assert warm.iterations == 0 and torch.equal(warm.active, cold.active)
    assert float((warm.lam - cold.lam).abs().max()) <= 1e-13
    for name in PARAMETER_NAMES:
        assert rel_err(g_warm[name], g_cold[name]) <= 1e-10, name
    with pytest.raises(LCSInputError, match="warm_start"):
        fn(model, data.x, data.u, data.x_next, arrays="compiled", warm_start=cold.active[:, :2], **kw)


@pytest.mark.parametrize("fn, kw", [(violation_fast, {"gamma": GAMMA, "eps": EPS}), (prediction_fast, {})])
def test_unconverged_samples_go_to_the_array_kernels_and_their_reference(fn, kw, monkeypatch):
    """With no sweep allowed, samples are left unconverged: the compiled path hands the batch
    to the array kernels, which say so (FallbackWarning) and solve them with the reference."""
    model, data = make_problem(n_lam=4, n=40, model="perturbed", seed=1)
    monkeypatch.setattr(losses_module, "MAX_ITER", 0)
    with pytest.warns(FallbackWarning):
        c = fn(model, data.x, data.u, data.x_next, arrays="compiled", **kw)
    with pytest.warns(FallbackWarning):
        a = fn(model, data.x, data.u, data.x_next, arrays="numpy", **kw)
    assert c.n_fallback == a.n_fallback > 0
    # two code paths (compiled products, then the array kernels' own): equal to a few ulps
    assert float(c.loss.detach()) == pytest.approx(float(a.loss.detach()), rel=1e-12, abs=0)


@pytest.mark.parametrize("loss", [lcs_cvx.violation_loss, lcs_cvx.prediction_loss,
                                  lcs_cvx.violation_value_and_grad, lcs_cvx.prediction_value_and_grad])
@pytest.mark.parametrize("name", ["x", "u", "x_next"])
def test_non_finite_data_are_named(loss, name):
    """The public losses leave the finiteness of ready tensors to the compiled kernel, which
    reports it: the error names the input, as for any other input."""
    model, data = make_problem(n_lam=3, n=20, seed=4)
    values = {"x": data.x.clone(), "u": data.u.clone(), "x_next": data.x_next.clone()}
    values[name][3, 0] = float("nan")
    with pytest.raises(LCSInputError, match=f"^{name}: expected finite values"):
        loss(model, values["x"], values["u"], values["x_next"])


@pytest.mark.parametrize("which", ["violation", "prediction"])
def test_value_and_grad_is_loss_and_backward(which):
    """``*_value_and_grad`` gives the numbers of ``*_loss(...).backward()`` bit for bit on the
    compiled path, and to round-off through autograd (float32, NumPy inputs)."""
    model, data = make_problem(n_lam=5, n=50, model="perturbed", seed=3)
    kw = {"gamma": GAMMA, "eps": EPS} if which == "violation" else {}
    loss_fn = getattr(lcs_cvx, f"{which}_loss")
    vg_fn = getattr(lcs_cvx, f"{which}_value_and_grad")
    model.zero_grad()
    value = loss_fn(model, data.x, data.u, data.x_next, **kw)
    value.backward()
    v, g = vg_fn(model, data.x, data.u, data.x_next, **kw)
    assert v.shape == () and not v.requires_grad and float(v) == float(value.detach())
    assert set(g) == set(PARAMETER_NAMES)
    for name in PARAMETER_NAMES:
        assert torch.equal(g[name], getattr(model, name).grad), name
    v_np, g_np = vg_fn(model, data.x.numpy(), data.u.numpy(), data.x_next.numpy(), **kw)
    assert float(v_np) == float(v)
    for name in PARAMETER_NAMES:
        assert torch.equal(g_np[name], g[name]), name
    m32 = model.to(torch.float32)
    v32, g32 = vg_fn(m32, data.x.float(), data.u.float(), data.x_next.float(), **kw)
    assert v32.dtype == torch.float32 and float(v32) == pytest.approx(float(v), rel=1e-3)
    assert g32["A"].dtype == torch.float32 and g32["A"].shape == g["A"].shape


def test_compiled_arrays_name_what_stands_in_the_way():
    model, data = make_problem(n_lam=3, n=10, seed=0)
    m32 = model.to(torch.float32)
    with pytest.raises(LCSInputError, match="arrays: 'compiled' runs one model's float64 CPU"):
        violation_fast(m32, data.x.float(), data.u.float(), data.x_next.float(), gamma=GAMMA,
                       eps=EPS, arrays="compiled")


def test_parameter_arrays_follow_the_parameters():
    """The compiled path keeps arrays on the parameters' memory between calls: an optimiser's
    in-place step, a ``.data`` replacement and a new parameter are all seen."""
    model, data = make_problem(n_lam=4, n=30, model="perturbed", seed=6)
    fresh = lambda m: float(violation_fast(m, data.x, data.u, data.x_next, gamma=GAMMA, eps=EPS,  # noqa: E731
                                           arrays="numpy").loss.detach())
    compiled = lambda m: float(violation_fast(m, data.x, data.u, data.x_next, gamma=GAMMA,  # noqa: E731
                                              eps=EPS, arrays="compiled").loss.detach())
    first = compiled(model)
    opt = torch.optim.SGD(model.parameters(), lr=1e-3)
    violation_fast(model, data.x, data.u, data.x_next, gamma=GAMMA, eps=EPS).loss.backward()
    opt.step()
    assert compiled(model) != first
    assert compiled(model) == pytest.approx(fresh(model), rel=1e-12)
    model.A.data = model.A.data + 0.1
    assert compiled(model) == pytest.approx(fresh(model), rel=1e-12)
    model.C = torch.nn.Parameter(model.C.detach() * 2.0)
    assert compiled(model) == pytest.approx(fresh(model), rel=1e-12)
    before = compiled(model)
    model.stiffness.fill_(2.0 * float(model.stiffness))  # the stiffness buffer, in place ...
    assert compiled(model) != before and compiled(model) == pytest.approx(fresh(model), rel=1e-12)
    model.stiffness = torch.tensor(0.3, dtype=torch.float64)  # ... and replaced
    assert compiled(model) == pytest.approx(fresh(model), rel=1e-12)


def test_value_and_grad_checks_gamma_against_the_model():
    """Lemma 2's bound, checked by the one-call API from 2 s on as by the loss (named error)."""
    model, data = make_problem(n_lam=3, n=20, model="perturbed", seed=2)
    s = float(model.stiffness)
    with pytest.raises(LCSInputError, match="gamma"):
        violation_value_and_grad(model, data.x, data.u, data.x_next, gamma=1e6 * s)
    value, grads = violation_value_and_grad(model, data.x, data.u, data.x_next, gamma=s)  # < 2 s
    assert math.isfinite(float(value)) and set(grads) == set(PARAMETER_NAMES)


def test_compiled_kernel_reports_non_finite_data_without_work():
    """The kernel's own contract: status -1 and no sample solved when the data are not finite."""
    from lcs_cvx._kernels import compiled

    model, data = make_problem(n_lam=3, n=8, seed=0)
    P = {k: np.ascontiguousarray(getattr(model, k).detach().numpy()) for k in PARAMETER_NAMES}
    x = data.x.numpy().copy()
    x[2, 1] = np.inf
    out = compiled.prediction(P["A"], P["B"], P["C"], P["d"], P["D"], P["E"], P["c"], P["G"],
                              P["H"], 1.0, x, data.u.numpy(), data.x_next.numpy(), 1e-11, 100, 3,
                              1e-9, np.zeros((0, 0), dtype=np.bool_))
    assert out[5] == -1 and out[6] == 0


@pytest.mark.parametrize("n", [1, 4, 12])
def test_compiled_lcp_is_the_array_kernel(n):
    """``solve_lcp_fast`` compiled (one float64 CPU ``F``, the default there) and in NumPy
    arrays: the same solutions, slacks, free sets and sweeps; a warm start from its own free sets
    makes no sweep; unconverged samples reach the same reference (FallbackWarning)."""
    from lcs_cvx.lcp import solve_lcp_fast

    truth = lcs_cvx.random_lcs(6, 2, n, stiffness=0.5, seed=n)
    data = lcs_cvx.make_dataset(truth, 300, seed=1)
    with torch.no_grad():
        F, q = truth.F, truth.lcp_offset(data.x, data.u)
    c, a = solve_lcp_fast(F, q, arrays="compiled"), solve_lcp_fast(F, q, arrays="numpy")
    assert float((c.lam - a.lam).abs().max()) <= 1e-12 * (1.0 + float(a.lam.abs().max()))
    assert float((c.w - a.w).abs().max()) <= 1e-12 * (1.0 + float(a.w.abs().max()))
    assert torch.equal(c.free, a.free) and c.iterations == a.iterations and c.n_fallback == 0
    assert float(c.residual.max()) <= 1e-13
    warm = solve_lcp_fast(F, q, warm_start=c.free)
    assert warm.iterations == 0 and torch.equal(warm.lam, c.lam)
    if n > 1:
        with pytest.warns(FallbackWarning):
            c0 = solve_lcp_fast(F, q, max_iter=0, arrays="compiled")
        with pytest.warns(FallbackWarning):
            a0 = solve_lcp_fast(F, q, max_iter=0, arrays="numpy")
        assert c0.n_fallback == a0.n_fallback > 0
        assert float((c0.lam - a0.lam).abs().max()) <= 1e-12 * (1.0 + float(a0.lam.abs().max()))


def test_factor_table_keeps_each_state_once_until_three_quarters_full():
    """:func:`lookup` gives a new state an empty slot and a state seen before its own slot; once
    three quarters are kept, new states get the scratch slot and are never found. Up to the
    table's bits a state's key is its slot; above ``TABLE_N`` there is only the scratch slot."""
    from lcs_cvx._kernels import dense

    k = 12  # more flags than the table's 2**9 slots: hashed
    meta = dense.factor_table(6, k, k)[0]
    S = int(meta[-1, 3])
    keys = np.random.default_rng(0).permutation(2**k)[:S]
    states = [np.array([(key >> (k - 1 - i)) & 1 for i in range(k)], dtype=bool) for key in keys]
    kept = 3 * S // 4
    slots = []
    for state in states[:kept]:
        at, found = dense.lookup(meta, state, k)
        assert not found and 0 <= at < S
        slots.append(at)
    assert len(set(slots)) == kept
    for state, at in zip(states[:kept], slots, strict=True):
        assert dense.lookup(meta, state, k) == (at, True)
    for state in states[kept:kept + 5]:
        assert dense.lookup(meta, state, k) == (S, False)
        assert dense.lookup(meta, state, k) == (S, False)
    state = np.array([True, False, True, True])
    meta = dense.factor_table(2, 4, 4)[0]
    assert dense.lookup(meta, state, 4) == (0b1011, False)
    assert dense.lookup(meta, state, 4) == (0b1011, True)
    meta = dense.factor_table(dense.TABLE_N + 1, 4, 4)[0]
    assert dense.lookup(meta, state, 4) == (0, False)
    assert dense.lookup(meta, state, 4) == (0, False)


def test_a_factor_from_the_table_is_a_new_factorisation():
    """One candidate solve of (V) and of the LCP on a sample whose state another sample put in
    the call's table gives, bit for bit, what it gives with a fresh table (which builds and
    factors the matrix)."""
    from lcs_cvx._kernels import compiled as kernels
    from lcs_cvx._kernels import dense

    rng = np.random.default_rng(1)
    n = 5
    R = rng.normal(size=(n, n))
    LtL, K, F = R @ R.T + n * np.eye(n), rng.normal(size=(n, n)), R @ R.T + np.eye(n) + np.triu(R) - np.triu(R).T
    data, state = rng.normal(size=(2, n)), rng.random(2 * n) < 0.5

    def violation_candidate(s, table):
        lam, t, g, bad, tol = np.empty(n), np.empty(n), np.empty(n), np.zeros(2 * n, bool), np.full(3, 1e-11)
        count = kernels._violation_solve(state, LtL, K, np.ascontiguousarray(K.T), data, -data, s, tol, lam, t,
                                         g, bad, table[0], table[1], table[3], np.empty((n, n)))
        return lam, t, g, bad, count

    def lcp_candidate(s, table):
        lam, w, bad = np.empty(n), np.empty(n), np.zeros(n, bool)
        count = kernels._lcp_solve(F, data, s, -1e-11, lam, w, bad, state[:n], *table)
        return lam, w, bad, count

    for candidate, k in ((violation_candidate, 2 * n), (lcp_candidate, n)):
        shared = dense.factor_table(n, k, k)
        candidate(0, shared)  # sample 0 builds the state's factor
        assert dense.lookup(shared[0], state, k)[1]
        for reused, fresh in zip(candidate(1, shared), candidate(1, dense.factor_table(n, k, k)), strict=True):
            assert np.array_equal(reused, fresh)
