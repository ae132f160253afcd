r"""The cube study's models beside dair_pll's recorded results on the same tosses, in dair_pll's
whole-toss metric (:func:`studies.cube.metrics.dair_pll_errors`).

dair_pll's numbers are the means over its recorded runs at 512 training tosses
(``helpers/results_cluster.json`` of DAIRLab/dair_pll; hyperparameter variants included), with
whole-toss rollouts on its test tosses: ``pos_int_traj`` (the mean over the rollout's steps of
the Euclidean position error) and ``angle_int_traj`` (the mean rotation angle). Ours: the models
the study fitted on its 275 training tosses (:mod:`studies.cube.study`), rolled out over the
study's 137 test tosses from each toss's first state; beside them the physics references of
:mod:`studies.cube.physics` (MuJoCo's and Drake's cube with dair_pll's nominal parameters, and with
friction, contact stiffness and inertia chosen on the validation tosses) on the same test tosses.

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
from lcs_cvx.datasets import CUBE_SIDE, cube_tosses

from . import kinematic, physics, rigid, symmetry
from . import models as M
from .metrics import dair_pll_errors
from .tosses import MACHINE, study_parts, subset

__all__ = ["DAIR_PLL", "DAIR_PLL_CURVE", "RIGID_KEYS", "compare", "rigid_body_curve", "nearest_dair_pll_size", "main"]

#: dair_pll's recorded means at 512 training tosses: method -> (position m, rotation rad).
DAIR_PLL = {
    "ContactNets": (0.036, math.radians(24)),
    "ContactNets + residual": (0.026, math.radians(25)),
    "Drake, nominal parameters": (0.048, math.radians(18)),
    "differentiable simulation": (0.069, math.radians(35)),
    "end-to-end MLP": (0.288, math.radians(49)),
}
#: dair_pll's recorded means by training tosses (its runs of 2^k tosses, half for training; its
#: metric, mm and degrees): the learning curves of its methods.
DAIR_PLL_CURVE = {
    "ContactNets (as plotted)": {4: (30.6, 22.0), 8: (28.9, 32.1), 16: (19.4, 20.9), 32: (20.2, 25.7),
                                 64: (22.8, 30.7), 128: (23.1, 30.7), 256: (22.3, 28.2)},
    "ContactNets + residual": {4: (32.8, 30.9), 8: (27.4, 34.1), 16: (18.0, 22.2), 32: (19.5, 25.8),
                               64: (22.7, 29.3), 128: (22.4, 29.8), 256: (21.2, 26.8)},
    "structured differentiable simulation": {4: (72.6, 43.0), 8: (35.9, 26.7), 16: (25.1, 21.7), 32: (32.2, 31.8),
                                             64: (22.1, 22.1), 128: (22.1, 20.6), 256: (17.2, 18.5)},
    "Drake, nominal cube": {4: (45.5, 16.8), 8: (45.1, 19.6), 16: (47.4, 16.1), 32: (48.5, 18.4),
                            64: (49.7, 19.6), 128: (49.1, 19.3), 256: (48.6, 18.9)},
    "end-to-end MLP": {4: (262.8, 52.5), 8: (286.6, 43.1), 16: (269.7, 46.7), 32: (278.2, 47.6),
                       64: (287.4, 52.7), 128: (284.4, 50.2), 256: (288.2, 49.6)},
}
#: When the committed comparison was computed.
DATE = "2026-11-28"
#: The targets: better than every method above, at 256 or more training tosses.
TARGET = (0.026, math.radians(18))
#: The rigid body's targets at 256 or more training tosses (position m, rotation rad): ahead of
#: ContactNets with and without residual and of the tuned physics reference; and the aim, ahead of
#: every run group in dair_pll's records.
RIGID_TARGET = (0.021, math.radians(22))
RIGID_AIM = (0.017, math.radians(18.5))


def nearest_dair_pll_size(size: int) -> int:
    """The training size of dair_pll's curve nearest ``size`` (in ratio)."""
    return min(DAIR_PLL_CURVE["ContactNets (as plotted)"], key=lambda n: abs(math.log(n / size)))


#: The rigid bodies of the study (spec keys): sharp corners, rounded corners.
RIGID_KEYS = ("rigid_body", "rigid_body_rounded")


def rigid_body_curve(out: str) -> list[dict]:
    """The rigid bodies (:data:`RIGID_KEYS`) fitted at each study size (their records in
    ``OUT/cube.jsonl``), in dair_pll's metric on the test tosses, with their learned quantities."""
    data = cube_tosses()
    test = subset(data, study_parts(len(data))["test"])
    specs = {s.key: s for s in M.specs()}
    rows = []
    with open(os.path.join(out, "cube.jsonl")) as f:
        records = [r for r in map(json.loads, filter(str.strip, f)) if r["key"] in RIGID_KEYS]
    for rec in sorted(records, key=lambda r: (RIGID_KEYS.index(r["key"]), r["size"])):
        spec = specs[rec["key"]]
        err = dair_pll_errors(spec.load(os.path.join(out, rec["model_file"])), test.xs)
        rows.append({"model": spec.name, "size": rec["size"], **err, "physical": rec["fit"]["physical"],
                     "wall": rec["fit"]["wall"]})
    return rows


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
    """The physics references (:mod:`studies.cube.physics`, MuJoCo and Drake) on the test tosses:
    nominal, and tuned on the validation tosses; the floor from the first ``size`` training tosses."""
    parts = study_parts(len(data))
    train, val, test = (subset(data, parts[k]) for k in ("train", "validation", "test"))
    floor = physics.floor_height(train.xs[:size])
    rows = []
    for engine, label, nominal in (("mujoco", "MuJoCo", physics.NOMINAL), ("drake", "Drake", physics.NOMINAL_DRAKE)):
        t0 = time.perf_counter()
        tuned, grid = physics.tune(val.xs, floor, engine)
        tune_wall = time.perf_counter() - t0
        for name, p in ((f"{label}, nominal parameters", replace(nominal, floor=floor)),
                        (f"{label}, tuned on the validation tosses", tuned)):
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
        "Rotation: the shorter angle between the predicted and the recorded orientation; *rotation, "
        "atan2*: dair_pll's own, `2 atan2(|v|, w)` of `q^-1 q_hat` with no choice between `q_hat` and "
        "`-q_hat` (larger where a prediction's quaternion crosses to the other hemisphere).", "",
        "| method | training tosses | position | rotation | rotation, atan2 | position, RMS | final tilt | diverged |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, (pos, rot) in DAIR_PLL.items():
        lines.append(f"| dair_pll: {name} | 512 | {_mm(pos)} | | {_deg(rot)} | | | |")
    for name, curve in DAIR_PLL_CURVE.items():
        pos, rot = curve[256]
        lines.append(f"| dair_pll: {name} | 256 | {pos:.1f} mm | | {rot:.1f}° | | | |")
    for r in rows:
        source, n = ("physics reference", "0") if "physics" in r else ("lcs_cvx study", str(args.size))
        lines.append(f"| {source}: {r['model']} | {n} | {_mm(r['pos'])} | {_deg(r['rot'])} | "
                     f"{_deg(r.get('rot_atan2', math.nan))} | "
                     f"{_mm(r['pos_rms'])} | {_deg(r['end_tilt'])} | {r['diverged']} / 137 |")
    for r in rows:
        a = r.get("activity")
        if a is not None:
            lines += ["", f"*{r['model']}*: a unit is active in {100 * a['at_contact']:.0f} % of the test states "
                      f"whose lowest corner is within 5 mm of the floor ({a['states_at_contact']} states) and in "
                      f"{100 * a['in_flight']:.0f} % of those above 20 mm, in flight ({a['states_in_flight']}); one "
                      f"of the 8 units started at the corners in {100 * a['corner_units_in_flight']:.0f} % of "
                      "those in flight."]
    phys = {r["model"]: r for r in rows if "physics" in r}
    mj_nominal, mj_tuned = (phys[f"MuJoCo, {k}"]["physics"] for k in ("nominal parameters", "tuned on the validation tosses"))
    dr_nominal, dr_tuned = (phys[f"Drake, {k}"]["physics"] for k in ("nominal parameters", "tuned on the validation tosses"))

    def grid_size(label: str) -> int:
        return len(phys[f"{label}, tuned on the validation tosses"]["grid"])
    lines += ["", "*Physics references* (`studies/cube/physics.py`): the box of the tosses' size and mass on a plane "
              f"at the training tosses' resting height ({1000 * mj_nominal['floor']:.1f} mm) with dair_pll's URDF's "
              f"{mj_nominal['friction']:g} Coulomb friction and {mj_nominal['inertia']:.3g} kg m² inertia. *MuJoCo*: "
              f"contact time constant {mj_nominal['time_constant']:g} s, 10 steps per recorded period; tuned: "
              f"friction {mj_tuned['friction']:g}, time constant {mj_tuned['time_constant']:g} s, inertia "
              f"{mj_tuned['inertia']:.3g} kg m² ({grid_size('MuJoCo')}-point grid). *Drake* (dair_pll's own "
              "simulator): a discrete MultibodyPlant at the recorded period, point contact, TAMSI; nominal as dair_pll "
              f"runs it (the ground's friction {dr_nominal['ground_friction']:g}, combined by Drake with the cube's to "
              f"{2 * dr_nominal['friction'] * dr_nominal['ground_friction'] / (dr_nominal['friction'] + dr_nominal['ground_friction']):.2f}; "
              f"Drake's default stiffness and dissipation); tuned: friction {dr_tuned['friction']:g} on both surfaces, "
              f"point stiffness {dr_tuned['stiffness']:g} N/m, Hunt–Crossley dissipation {dr_tuned['dissipation']:g} s/m, "
              f"inertia {dr_tuned['inertia']:.3g} kg m² ({grid_size('Drake')}-point grid). Each tuned point has the lowest "
              "whole-toss rotation error on the validation tosses. Nothing is learned from the training tosses but the "
              "floor's height: the geometry and the rigid-body equations are exact, a reference for what the tosses allow."]
    curve = rigid_body_curve(args.out)
    if curve:
        lines += ["", "## The rigid body along the learning curve", "",
                  "`rigid body` (`studies/cube/rigid.py`): `lcs_cvx.RigidBodyContact`, the time-stepping LCS of the "
                  "cube's state, started from the data sheet's cube and fitted by `lcs_cvx.fit` (violation loss per "
                  "sample, then the simulation-error phase); `rigid body, rounded corners`: the same with its corners "
                  f"rounded (start radius {1000 * rigid.CORNER_RADIUS:g} mm, learned). Beside them dair_pll's ContactNets "
                  "row as plotted at the nearest of its sizes (its test sets: 16-128 tosses; ours: the 137 test tosses).",
                  "", "| model | training tosses | position | rotation | rotation, atan2 | ContactNets (dair_pll size) | "
                  "at or below it in both | learned side | corner radius | mu | inertia (diagonal mean) | fit |",
                  "|---|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|"]
        for r in curve:
            n = nearest_dair_pll_size(r["size"])
            cn = DAIR_PLL_CURVE["ContactNets (as plotted)"][n]
            ok = 1000 * r["pos"] <= cn[0] and math.degrees(r["rot"]) <= cn[1]
            p = r["physical"]
            inertia = sum(p["inertia"][k][k] for k in range(3)) / 3
            lines.append(f"| {r['model']} | {r['size']} | {_mm(r['pos'])} | {_deg(r['rot'])} | {_deg(r['rot_atan2'])} | "
                         f"{cn[0]:.1f} mm / {cn[1]:.1f}° ({n}) | {'yes' if ok else 'no'} | "
                         f"{1000 * p['side']:.1f} mm | {1000 * p.get('corner_radius', 0.0):.1f} mm | {p['mu']:.3f} | "
                         f"{inertia:.3g} kg m² | {r['wall']:.0f} s |")
        lines += ["", f"The cube's side is {1000 * CUBE_SIDE:.1f} mm (within 5 %: {0.95 * 1000 * CUBE_SIDE:.1f}-"
                  f"{1.05 * 1000 * CUBE_SIDE:.1f} mm); its data sheet's inertia 0.00081 kg m², mu 0.15. Targets at "
                  f"256 or more tosses: position ≤ {_mm(RIGID_TARGET[0])} and rotation ≤ {_deg(RIGID_TARGET[1])} (ahead "
                  "of ContactNets with and without residual and of the tuned physics reference); the aim: "
                  f"≤ {_mm(RIGID_AIM[0])} and ≤ {_deg(RIGID_AIM[1])}."]
        def within(r: dict, t: tuple[float, float]) -> str:
            return "yes" if r["pos"] <= t[0] and r["rot"] <= t[1] else "no"
        for r in (r for r in curve if r["size"] >= 256):
            lines += ["", f"{r['model']}, at {r['size']} tosses (this seed; `seeds.md` has seeds 0-3): the target met: "
                      f"{within(r, RIGID_TARGET)}; the aim met: {within(r, RIGID_AIM)}."]
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
