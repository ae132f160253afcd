r"""The cube study's models beside dair_pll's recorded results on the same tosses, in dair_pll's
whole-toss metric (:func:`studies.cube.metrics.dair_pll_errors`).

dair_pll's numbers are the means over its recorded runs at 512 training tosses
(``helpers/results_cluster.json`` of DAIRLab/dair_pll; hyperparameter variants included), with
whole-toss rollouts on its test tosses: ``pos_int_traj`` (the mean over the rollout's steps of
the Euclidean position error) and ``angle_int_traj`` (the mean rotation angle). Ours: the models
the study fitted on its 275 training tosses (:mod:`studies.cube.study`), rolled out over the
study's 137 test tosses from each toss's first state; beside them the physics reference of
:mod:`studies.cube.physics` (MuJoCo's cube with dair_pll's nominal parameters, and with friction,
contact stiffness and inertia chosen on the validation tosses) on the same test tosses.

    python -m studies.cube.contactnets --out studies/results/cube [--size 275]

writes ``OUT/contactnets.md`` (and ``contactnets.json``).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import time
from dataclasses import asdict, replace

import torch

import lcs_cvx
from lcs_cvx.datasets import cube_tosses

from . import kinematic, physics, symmetry
from . import models as M
from .metrics import dair_pll_errors
from .tosses import MACHINE, study_parts, subset

__all__ = ["DAIR_PLL", "compare", "main"]

#: dair_pll's recorded means at 512 training tosses: method -> (position m, rotation rad).
DAIR_PLL = {
    "ContactNets": (0.036, math.radians(24)),
    "ContactNets + residual": (0.026, math.radians(25)),
    "Drake, nominal parameters": (0.048, math.radians(18)),
    "differentiable simulation": (0.069, math.radians(35)),
    "end-to-end MLP": (0.288, math.radians(49)),
}
#: When the committed comparison was computed.
DATE = "2026-11-28"
#: The targets: better than every method above, at 256 or more training tosses.
TARGET = (0.026, math.radians(18))


def compare(out: str, size: int) -> list[dict]:
    """dair_pll's metric of every spec's model fitted at ``size`` tosses (those in ``out``)."""
    torch.set_num_threads(1)
    data = cube_tosses()
    test = subset(data, study_parts(len(data))["test"])
    rows = []
    for spec in M.specs():
        path = M.model_path(out, size, spec)
        if not os.path.exists(path):
            continue
        t0 = time.perf_counter()
        err = dair_pll_errors(spec.load(path), test.xs)
        row = {"model": spec.name, **err, "wall": time.perf_counter() - t0}
        model = lcs_cvx.load_model(path) if spec.ext == "npz" and spec.key.startswith("lcs") else None
        if model is not None and model.n_x == 16:  # the symmetric model's units act on the states in its frames
            xs = [symmetry.to_frame(x, symmetry.frame_of(x)) for x in test.xs] if spec.key == "lcs_symmetry" \
                else list(test.xs)
            row["activity"] = contact_activity(model, xs)
        rows.append(row)
    return rows + physics_rows(data, size)


def physics_rows(data: lcs_cvx.Trajectories, size: int) -> list[dict]:
    """The physics reference (:mod:`studies.cube.physics`) on the test tosses: nominal, and tuned
    on the validation tosses; the floor from the first ``size`` training tosses."""
    parts = study_parts(len(data))
    train, val, test = (subset(data, parts[k]) for k in ("train", "validation", "test"))
    floor = physics.floor_height(train.xs[:size])
    rows = []
    t0 = time.perf_counter()
    tuned, grid = physics.tune(val.xs, floor)
    tune_wall = time.perf_counter() - t0
    for name, p in (("MuJoCo, nominal parameters", replace(physics.NOMINAL, floor=floor)),
                    ("MuJoCo, tuned on the validation tosses", tuned)):
        t0 = time.perf_counter()
        rows.append({"model": name, "physics": asdict(p), **physics.errors(p, test.xs),
                     "wall": time.perf_counter() - t0 + (tune_wall if p is tuned else 0.0)})
    rows[-1]["grid"] = grid
    return rows


def contact_activity(model: lcs_cvx.LCS, xs: list[torch.Tensor], near: float = 0.005, far: float = 0.02
                     ) -> dict[str, float]:
    """Of the test states of a model on the state with the up coordinates, the fraction with a
    unit active (``lam_i > ACTIVE_TOL``) where the lowest corner is within ``near`` of the floor
    (at contact) and where it is above ``far`` (in flight), and the fraction in flight with one of
    the units started at the corners (the first 8) active."""
    x = kinematic.augment(lcs_cvx.Trajectories(xs, [t[:-1, :0] for t in xs])).xs
    x = torch.cat(x)
    corners = torch.tensor(list(itertools.product((-kinematic.HALF_SIDE, kinematic.HALF_SIDE), repeat=3)),
                           dtype=torch.float64)
    low = (x[:, 6:7] + x[:, 13:16] @ corners.T).min(1).values
    units = model.active_set(x, x[:, :0])
    active, corners_active = units.any(1), units[:, :8].any(1)
    at, fly = low < near, low > far
    return {"at_contact": float(active[at].double().mean()), "in_flight": float(active[fly].double().mean()),
            "corner_units_in_flight": float(corners_active[fly].double().mean()),
            "states_at_contact": int(at.sum()), "states_in_flight": int(fly.sum())}


def _deg(rad: float) -> str:
    return "inf" if not math.isfinite(rad) else f"{math.degrees(rad):.1f}°"


def _mm(m: float) -> str:
    return "inf" if not math.isfinite(m) else f"{1000 * m:.1f} mm"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="The cube study's models in dair_pll's whole-toss metric.")
    ap.add_argument("--out", default=os.path.join("studies", "results", "cube"))
    ap.add_argument("--size", type=int, default=275)
    args = ap.parse_args(argv)
    rows = compare(args.out, args.size)
    with open(os.path.join(args.out, "contactnets.json"), "w") as f:
        json.dump({"size": args.size, "rows": rows}, f, indent=1)
    lines = [
        "# The cube beside dair_pll: whole-toss rollouts in dair_pll's metric", "",
        f"Written by `python -m studies.cube.contactnets --out {args.out} --size {args.size}` on {DATE} "
        f"({MACHINE}).", "",
        "Metric (dair_pll's `pos_int_traj`, `angle_int_traj`): one open-loop rollout per test toss from its "
        "first state to its end; per toss the mean over the rollout's steps of the Euclidean position error "
        "and of the rotation angle, then the mean over the tosses. dair_pll: the means over its recorded runs "
        "at 512 training tosses (`helpers/results_cluster.json` of DAIRLab/dair_pll). lcs_cvx study: the "
        f"models fitted on {args.size} training tosses, on the study's 137 test tosses; the study's own "
        "position metric (RMS over the rollout, `studies/results/cube/report.md`) beside it, and the final "
        "tilt: the mean over the test tosses of the last predicted orientation's angle from resting on a face "
        "(`acos max_k |g_k|`, g the up direction in the body frame; the recorded tosses end within about 1°).", "",
        "| method | training tosses | position | rotation | position, RMS | final tilt | diverged |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, (pos, rot) in DAIR_PLL.items():
        lines.append(f"| dair_pll: {name} | 512 | {_mm(pos)} | {_deg(rot)} | | | |")
    for r in rows:
        source, n = ("physics reference", "0") if "physics" in r else ("lcs_cvx study", str(args.size))
        lines.append(f"| {source}: {r['model']} | {n} | {_mm(r['pos'])} | {_deg(r['rot'])} | "
                     f"{_mm(r['pos_rms'])} | {_deg(r['end_tilt'])} | {r['diverged']} / 137 |")
    for r in rows:
        a = r.get("activity")
        if a is not None:
            lines += ["", f"*{r['model']}*: a unit is active in {100 * a['at_contact']:.0f} % of the test states "
                      f"whose lowest corner is within 5 mm of the floor ({a['states_at_contact']} states) and in "
                      f"{100 * a['in_flight']:.0f} % of those above 20 mm, in flight ({a['states_in_flight']}); one "
                      f"of the 8 units started at the corners in {100 * a['corner_units_in_flight']:.0f} % of "
                      "those in flight."]
    nominal, tuned = (r["physics"] for r in rows if "physics" in r)
    lines += ["", "*Physics reference* (`studies/cube/physics.py`): MuJoCo's box of the tosses' size and mass on a "
              f"plane at the training tosses' resting height ({1000 * nominal['floor']:.1f} mm), {nominal['friction']:g} "
              f"Coulomb friction and {nominal['inertia']:.3g} kg m² inertia (dair_pll's URDF), contact time constant "
              f"{nominal['time_constant']:g} s, 10 steps per recorded period; tuned: friction {tuned['friction']:g}, "
              f"time constant {tuned['time_constant']:g} s, inertia {tuned['inertia']:.3g} kg m², the point of a "
              f"{len(next(r for r in rows if 'grid' in r)['grid'])}-point grid with the lowest whole-toss rotation error "
              "on the validation tosses. Nothing is learned from the training tosses but the floor's height: the "
              "geometry and the rigid-body equations are exact, a reference for what the tosses allow."]
    met = [r["model"] for r in rows if r["pos"] <= TARGET[0] and r["rot"] <= TARGET[1] and "physics" not in r]
    lines += ["", f"Target (better than every dair_pll method): position ≤ {_mm(TARGET[0])} and rotation ≤ "
              f"{_deg(TARGET[1])}. Met by: {', '.join(met) if met else 'none'}."]
    best_physics = min(r["rot"] for r in rows if "physics" in r)
    if best_physics > TARGET[1]:
        lines += ["", f"The rotation target is below the physics reference on these test tosses "
                  f"({_deg(best_physics)} at best): a simulator with the cube's exact geometry and parameters "
                  "chosen on the validation tosses does not reach it here either (dair_pll's Drake number is on "
                  "its own test tosses, with its own contact model)."]
    lines += [""]
    with open(os.path.join(args.out, "contactnets.md"), "w") as f:
        f.write("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
