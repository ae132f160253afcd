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

from lcs_cvx import fit, relative_error
from lcs_cvx.study.cells import expand, setup_cell
from lcs_cvx.study.config import load_config

CONFIGS = Path(__file__).resolve().parent / "configs"


def run(value: float, trial: int) -> dict:
    out: dict = {"n_lam": value, "trial": trial}
    for recipe in ("paper", "best"):
        cell = next(c for c in expand(load_config(str(CONFIGS / f"train_{recipe}.toml")))
                    if c["value"] == value and c["trial"] == trial)
        _, train, test, learner, options = setup_cell(cell)
        t0, w0 = time.process_time(), time.perf_counter()
        result = fit(learner, train, test=test, recipe=cell["recipe"], progress=False,
                     seed=cell["seeds"]["fit"], **options)
        out[recipe] = {"cpu": round(time.process_time() - t0, 1),
                       "wall": round(time.perf_counter() - w0, 1),
                       "e_test": relative_error(result.model, test)}
    return out


if __name__ == "__main__":
    torch.set_num_threads(1)
    warnings.simplefilter("ignore")
    for t in sys.argv[2:]:
        print(json.dumps(run(float(sys.argv[1]), int(t))), flush=True)
