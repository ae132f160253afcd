"""fit(..., log=...): a callback of every history record, or TensorBoard event files read back
with TensorBoard's own event reader."""

from __future__ import annotations

import pytest
import torch

import lcs_cvx
from lcs_cvx import LCSInputError

accumulator = pytest.importorskip("tensorboard.backend.event_processing.event_accumulator")


def runs():
    truth = lcs_cvx.random_lcs(2, 1, 2, seed=0)
    g = torch.Generator().manual_seed(1)
    us = [torch.randn(25, 1, generator=g, dtype=torch.float64) for _ in range(6)]
    return lcs_cvx.Trajectories([truth.rollout(torch.randn(2, generator=g, dtype=torch.float64), u) for u in us], us)


def test_tensorboard_events_hold_one_scalar_per_record(tmp_path):
    result = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), runs(), recipe="plain", iterations=100, eval_every=20,
                         rollout_iterations=20, restarts=2, log=tmp_path / "tb", progress=False)
    events = accumulator.EventAccumulator(str(tmp_path / "tb"))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    assert {"restart_0/loss", "restart_0/heldout", "restart_0/lr", "restart_0/phase", "restart_1/loss"} <= tags
    for r in (0, 1):
        mine = [h for h in result.history if h["restart"] == r]
        for name in ("loss", "heldout"):
            got = [(e.step, e.value) for e in events.Scalars(f"restart_{r}/{name}")]
            want = [(h["iteration"], h[name]) for h in mine]
            assert [s for s, _ in got] == [s for s, _ in want]
            # TensorBoard stores float32
            assert all(abs(v - w) <= 1e-6 * abs(w) for (_, v), (_, w) in zip(got, want, strict=True))
    phases = [e.value for e in events.Scalars("restart_0/phase")]
    assert phases[0] == 0.0 and phases[-1] == 5.0  # adam, then the simulation-error phase ("rollout")


def test_a_callback_gets_every_record_and_cannot_stop_the_run(tmp_path):
    seen = []
    result = lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), runs(), recipe="plain", iterations=60, eval_every=20,
                         rollout_horizon=None, log=lambda rec: seen.append(rec) or True, progress=False)
    assert seen == result.history and len(seen) == 3
    with pytest.raises(LCSInputError, match=r"log: expected None, a callable of a history record or a directory"):
        lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), runs(), recipe="plain", iterations=5, log=3, progress=False)
    with pytest.raises(LCSInputError, match=r"log: expected None with ensemble=True"):
        lcs_cvx.fit(lcs_cvx.LCS(2, 1, 2, seed=3), runs().to_transitions(), recipe="plain", iterations=5, restarts=2,
                    ensemble=True, log=tmp_path, progress=False)
