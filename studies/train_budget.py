"""Time the "paper" and "best" recipes on the same training-comparison cell, one after the other
in one process (one torch thread, ``time.process_time``), as in studies/README.md's table.

    python studies/train_budget.py N_LAM TRIAL [TRIAL ...]

Prints one JSON line per trial: CPU and wall seconds and e_test of each recipe.
"""

import json
import sys
import time
import warnings
from pathlib import Path

import torch

from lcs_cvx import LCS, fit, make_dataset, random_lcs, relative_error
from lcs_cvx.study.cells import expand
from lcs_cvx.study.config import load_config

CONFIGS = Path(__file__).resolve().parent / "configs"


def run(value: float, trial: int) -> dict:
    out: dict = {"n_lam": value, "trial": trial}
    for recipe in ("paper", "best"):
        cell = next(c for c in expand(load_config(str(CONFIGS / f"train_{recipe}.toml")))
                    if c["value"] == value and c["trial"] == trial)
        s, d, ln, seeds = cell["system"], cell["data"], cell["learner"], cell["seeds"]
        truth = random_lcs(s["n_x"], s["n_u"], s["n_lam"], stiffness=s["stiffness"],
                           seed=seeds["truth"], g_scale=s["g_scale"])
        scales = {"x_scale": d["x_scale"], "u_scale": d["u_scale"]}
        train = make_dataset(truth, d["n_train"], noise=d["noise"], seed=seeds["train"], **scales)
        test = make_dataset(truth, d["n_test"], noise=0.0, seed=seeds["test"], **scales)
        options = {k: tuple(v) if isinstance(v, list) else v for k, v in cell["fit"].items()}
        learner = LCS(s["n_x"], s["n_u"], s["n_lam"], stiffness=ln["stiffness"],
                      init_scale=ln["init_scale"], seed=seeds["init"])
        t0, w0 = time.process_time(), time.perf_counter()
        result = fit(learner, train, test=test, recipe=recipe, progress=False, seed=seeds["fit"],
                     **options)
        out[recipe] = {"cpu": round(time.process_time() - t0, 1),
                       "wall": round(time.perf_counter() - w0, 1),
                       "e_test": relative_error(result.model, test)}
    return out


if __name__ == "__main__":
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")
    for t in sys.argv[2:]:
        print(json.dumps(run(float(sys.argv[1]), int(t))), flush=True)
