r"""A check with known answers for :class:`lcs_cvx.RigidBodyContact`: tosses of a MuJoCo box whose
size, friction and inertia are chosen here (not a cube), learned back from at most 64 tosses.

1. :data:`TRUTH`: a box of half sizes 60 x 45 x 35 mm, 0.5 kg, friction 0.4, the inertia of a solid
   box of that size, on a plane at height 0; MuJoCo steps it at 10 steps per recorded period of
   :data:`lcs_cvx.datasets.CUBE_DT` (contact time constant 5 ms).
2. Tosses (:func:`tosses`): from a random orientation at 0.1-0.3 m, random horizontal and
   vertical velocity and spin, :data:`STEPS` recorded steps each; 64 training, 16 validation and 32
   test tosses (seeded).
3. Learned (:func:`fit`): the study's rigid body (:mod:`studies.cube.rigid`) started from a 100 mm
   cube guess (half sizes 50 mm), ``mu = 0.2`` and its solid-box inertia, the floor at 0, with the
   study's budget; beside it the study's affine map and MLP (:mod:`studies.cube.models`).
4. ``OUT/simulated_box_<cone>.md`` and ``.json``: the learned half sizes, friction and inertia
   against the truth, and every model's whole-toss errors on the test tosses (dair_pll's metric).

    python -m studies.cube.simulated_box --out studies/results/cube [--cone elliptic|pyramidal]

MuJoCo's elliptic cone is Coulomb's (friction ``mu`` in every tangent direction), the default; its
pyramidal cone has 4 edges in each contact's tangent frame (friction ``mu`` along them, ``mu /
sqrt 2`` between), a different friction law than the rigid body's world-aligned 8-edge cone, so
its ``mu`` is not the same quantity.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from dataclasses import replace

import numpy as np
import torch

import lcs_cvx
from lcs_cvx.datasets import CUBE_DT

from . import models as M
from . import rigid
from .metrics import dair_pll_errors
from .tosses import MACHINE

__all__ = ["TRUTH", "STEPS", "tosses", "fit", "main"]

#: The simulated box: half sizes (m), mass (kg), friction, inertia (kg m², diagonal).
TRUTH = {"half_sizes": (0.06, 0.045, 0.035), "mass": 0.5, "mu": 0.4}
TRUTH["inertia"] = tuple(TRUTH["mass"] / 3 * (b * b + c * c) for b, c in
                         ((0.045, 0.035), (0.06, 0.035), (0.06, 0.045)))
#: Recorded steps per toss.
STEPS = 140
#: When the committed results were computed.
DATE = "2026-11-28"

_XML = """<mujoco><option timestep="{ts}" integrator="implicitfast" cone="{cone}"/>
<worldbody><geom type="plane" size="5 5 .1" friction="{mu} 0.005 0.0001" solref="0.005 1"/>
<body name="box"><freejoint/><inertial pos="0 0 0" mass="{mass}" diaginertia="{I}"/>
<geom type="box" size="{hs}" friction="{mu} 0.005 0.0001" solref="0.005 1"/></body></worldbody></mujoco>"""


def tosses(n: int, seed: int, substeps: int = 10, cone: str = "elliptic") -> lcs_cvx.Trajectories:
    """``n`` tosses of :data:`TRUTH` (states as :data:`lcs_cvx.datasets.CUBE_COLUMNS`); ``cone``:
    MuJoCo's friction cone, ``"elliptic"`` (Coulomb's: friction ``mu`` in every direction) or
    ``"pyramidal"`` (4 edges in each contact's own tangent frame: ``mu`` along them, ``mu /
    sqrt 2`` between)."""
    import mujoco

    t = TRUTH
    model = mujoco.MjModel.from_xml_string(_XML.format(
        ts=CUBE_DT / substeps, cone=cone, mu=t["mu"], mass=t["mass"], I=" ".join(map(str, t["inertia"])),
        hs=" ".join(map(str, t["half_sizes"]))))
    data = mujoco.MjData(model)
    rng = np.random.default_rng(seed)
    xs = []
    for _ in range(n):
        mujoco.mj_resetData(model, data)
        q = rng.normal(size=4)
        data.qpos[:3] = [0.0, 0.0, rng.uniform(0.1, 0.3)]
        data.qpos[3:7] = q / np.linalg.norm(q)
        data.qvel[:3] = [*rng.uniform(-1.0, 1.0, 2), rng.uniform(-1.0, 0.5)]
        data.qvel[3:6] = rng.normal(0.0, 5.0, 3)
        traj = []
        for step in range(STEPS + 1):
            if step:
                for _ in range(substeps):
                    mujoco.mj_step(model, data)
            traj.append(np.concatenate([data.qpos[3:7], data.qpos[:3], data.qvel[3:6], data.qvel[:3]]))
        xs.append(np.array(traj))
    return lcs_cvx.Trajectories(xs, [np.zeros((STEPS, 0))] * n)


def _guess(train: lcs_cvx.Trajectories, seed: int = 0) -> lcs_cvx.RigidBodyContact:
    """A user's guess: a 100 mm cube of the known mass, mu = 0.2, on a floor at 0."""
    del train, seed
    return lcs_cvx.RigidBodyContact(half_sizes=[0.05] * 3, mass=TRUTH["mass"], dt=CUBE_DT, mu=0.2, ground=0.0,
                                    friction_directions=rigid.FRICTION_DIRECTIONS)


def fit(out: str, n_train: int = 64, cone: str = "elliptic") -> dict:
    """Fit the rigid body, the affine map and the MLP on ``n_train`` simulated tosses; their test
    errors and the learned quantities."""
    torch.set_num_threads(1)
    train, val, test = (tosses(n, seed=s, cone=cone) for n, s in ((n_train, 1), (16, 2), (32, 3)))
    os.makedirs(os.path.join(out, "models"), exist_ok=True)
    budget = M.Budget(mlp_steps=3000)
    rows = {}
    for name, fitter in (("rigid body", lambda p: rigid.fit(train, val, budget, p, start_model=_guess)),
                         ("affine LS", lambda p: M.specs()[0].fit(train, val, budget, p)),
                         ("MLP", lambda p: M.specs()[2].fit(train, val, replace(budget, mlp_grid=M.MLP_GRID[:2]), p))):
        t0 = time.perf_counter()
        ext = "pt" if name == "MLP" else "npz"
        step, info = fitter(os.path.join(out, "models", f"simulated_box_{cone}_{name.split()[0].lower()}.{ext}"))
        rows[name] = {"test": dair_pll_errors(step, test.xs), "wall": time.perf_counter() - t0,
                      **({"physical": info["physical"]} if "physical" in info else {})}
        print(name, rows[name]["test"], flush=True)
    return {"truth": TRUTH, "n_train": n_train, "cone": cone, "rows": rows}


def write(out: str, result: dict) -> str:
    """``OUT/simulated_box_<cone>.md`` (and ``.json``)."""
    t, learned = result["truth"], result["rows"]["rigid body"]["physical"]
    hs = np.asarray(learned["half_sizes"])
    rel = hs / np.asarray(t["half_sizes"]) - 1
    I = np.diag(np.asarray(learned["inertia"]))
    L = ["# A simulated box learned back: known answers for the rigid body", "",
         f"Written by `python -m studies.cube.simulated_box --out {out} --cone {result['cone']}` on {DATE} "
         f"({MACHINE}).", "",
         f"MuJoCo tosses of a box (not a cube), {result['n_train']} for training, 16 for validation, 32 for test "
         f"(`studies/cube/simulated_box.py`), MuJoCo's {result['cone']} friction cone; the rigid body (an 8-edge "
         "cone, its edges at mu) started from a 100 mm cube, mu 0.2.", "",
         "| quantity | truth | learned | error |", "|---|---:|---:|---:|"]
    for k, axis in enumerate("xyz"):
        L.append(f"| half size {axis} | {1e3 * t['half_sizes'][k]:.1f} mm | {1e3 * hs[k]:.1f} mm | {100 * rel[k]:+.1f} % |")
    L.append(f"| friction mu | {t['mu']:.2f} | {learned['mu']:.3f} | {100 * (learned['mu'] / t['mu'] - 1):+.1f} % |")
    for k, axis in enumerate("xyz"):
        L.append(f"| inertia {axis}{axis} | {t['inertia'][k]:.3g} kg m² | {I[k]:.3g} kg m² | "
                 f"{100 * (I[k] / t['inertia'][k] - 1):+.1f} % |")
    L += ["", "Whole-toss rollouts of the 32 test tosses (dair_pll's metric: mean position error, mean rotation "
          "angle):", "", "| model | position | rotation | diverged |", "|---|---:|---:|---:|"]
    for name, r in result["rows"].items():
        e = r["test"]
        L.append(f"| {name} | {1e3 * e['pos']:.1f} mm | {math.degrees(e['rot']):.1f}° | {e['diverged']} / 32 |")
    ok_size = bool(np.all(np.abs(rel) <= 0.05))
    ok_mu = abs(learned["mu"] / t["mu"] - 1) <= 0.2
    rb = result["rows"]["rigid body"]["test"]
    ahead = all(rb["pos"] < r["test"]["pos"] and rb["rot"] < r["test"]["rot"]
                for name, r in result["rows"].items() if name != "rigid body")
    L += ["", f"Half sizes within 5 %: {'yes' if ok_size else 'no'}; mu within 20 %: {'yes' if ok_mu else 'no'}; "
          f"whole tosses better than the affine map and the MLP in both: {'yes' if ahead else 'no'}.", ""]
    text = "\n".join(L)
    with open(os.path.join(out, f"simulated_box_{result['cone']}.md"), "w") as f:
        f.write(text)
    with open(os.path.join(out, f"simulated_box_{result['cone']}.json"), "w") as f:
        json.dump(result, f, indent=1)
    return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="A simulated box learned back by the rigid body.")
    ap.add_argument("--out", default=os.path.join("studies", "results", "cube"))
    ap.add_argument("--train", type=int, default=64)
    ap.add_argument("--cone", choices=("elliptic", "pyramidal"), default="elliptic",
                    help="MuJoCo's friction cone of the simulated tosses")
    args = ap.parse_args(argv)
    print(write(args.out, fit(args.out, args.train, args.cone)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
