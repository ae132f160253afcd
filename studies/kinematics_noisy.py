"""Known kinematics on noisy runs of positional systems: the held-out score of an LCS whose
positions are integrated (``lcs_cvx.Kinematics``) against the same LCS learning them, the
kinematic model in uncentred coordinates (the scaling's rule before it centred models whose
held rows are whole), and the affine map.

Systems ``random_lcs(4, 1, 2, seed=s)`` with damped velocity rows and ``x[0:2]`` integrated from
``x[2:4]`` (dt = 0.05); 12 runs of 40 steps from ``default_rng(s)``, states with N(0, 0.01^2)
noise; ``fit(LCS(4, 1, 2, seed=1), runs, iterations=1000)`` (two runs held out, the 10-step
rollout score relative to the recorded change).

    python -m studies.kinematics_noisy [--seeds 0,1,2]
"""

from __future__ import annotations

import argparse
from unittest import mock

import numpy as np
import torch

import lcs_cvx
import lcs_cvx.scaling

KINEMATICS = lcs_cvx.Kinematics(0.05, positions={0: 2, 1: 3})


def runs(seed: int) -> lcs_cvx.Trajectories:
    truth = lcs_cvx.random_lcs(4, 1, 2, seed=seed)
    with torch.no_grad():
        truth.A[2:] *= 0.5  # damped velocities: bounded runs
    truth.with_kinematics(KINEMATICS)
    rng = np.random.default_rng(seed)
    xs, us = [], []
    for _ in range(12):
        u = rng.uniform(-1, 1, (40, 1))
        x = truth.rollout(rng.uniform(-2, 2, 4), u).detach().numpy()
        xs.append(x + 0.01 * rng.standard_normal(x.shape))
        us.append(u)
    return lcs_cvx.Trajectories(xs, us)


def scores(seed: int) -> dict[str, float]:
    data = runs(seed)
    out = {}
    for name, kin in (("learned", None), ("known", KINEMATICS)):
        result = lcs_cvx.fit(lcs_cvx.LCS(4, 1, 2, seed=1, kinematics=kin), data, recipe="plain", iterations=1000, progress=False)
        out[name] = result.heldout_error
    out["affine"] = result.affine_heldout_error
    old_rule = lambda model, name, others: bool(lcs_cvx.scaling._constrained_entries(model, name).any())  # noqa: E731
    with mock.patch.object(lcs_cvx.scaling, "_held_rows_vary", old_rule):
        result = lcs_cvx.fit(lcs_cvx.LCS(4, 1, 2, seed=1, kinematics=KINEMATICS), data, recipe="plain", iterations=1000,
                             progress=False)
    out["known, uncentred"] = result.heldout_error
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    print("| seed | kinematics learned | known | known, uncentred | affine map |\n|---:|---:|---:|---:|---:|")
    for seed in (int(s) for s in args.seeds.split(",")):
        r = scores(seed)
        print(f"| {seed} | {r['learned']:.4f} | {r['known']:.4f} | {r['known, uncentred']:.4f} | {r['affine']:.4f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
