"""The PWA regression comparison: the baselines (affine, MLP, PARC) fit and are measured like an
LCS, the grid runner trains them as methods of a cell (and a loss under its own recipe,
``"violation@best"``), a per-cell time limit kills a slow cell and records it as timed out
(kept on resume, run again under a larger limit), a baseline whose own fit fails is recorded as
failed (once, never retried, shown in both reports), and the smoke study of
``studies/configs/pwa_compare_smoke.toml`` runs every method for real and is reported."""

from __future__ import annotations

import importlib.util
import re
import sqlite3
import sys
import time
from pathlib import Path

import pytest
import torch

from lcs_cvx import Dataset, LCSInputError, count_modes, make_dataset, random_lcs, relative_error
from lcs_cvx.study import Store, config_hash, expand, load_config, run_config
from lcs_cvx.study.baselines import OPTIONS, BaselineFailed, baseline_options, fit_baseline
from lcs_cvx.study.cells import setup_cell, work
from lcs_cvx.study.limits import ChildError, run_limited

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "studies" / "configs"
SMOKE = CONFIGS / "pwa_compare_smoke.toml"
METHODS = ["violation", "violation@best", "prediction", "parc", "mlp", "affine"]
needs_parc = pytest.mark.skipif(
    importlib.util.find_spec("pyparc") is None,
    reason="pyparc is not installed (the baselines extra: pip install 'lcs_cvx[baselines]')")


def _rows(out: Path) -> list[sqlite3.Row]:
    conn = sqlite3.connect(out / "studies.sqlite")
    conn.row_factory = sqlite3.Row
    rows = conn.execute("SELECT * FROM cells ORDER BY id").fetchall()
    conn.close()
    return rows


def _write(tmp_path: Path, text: str, name: str = "c.toml") -> Path:
    path = tmp_path / name
    path.write_text(f'extends = "{SMOKE.as_posix()}"\n' + text)
    return path


# -- the baselines ---------------------------------------------------------------------------
def test_affine_baseline_recovers_an_affine_map_exactly():
    g = torch.Generator().manual_seed(0)
    x, u = torch.randn(200, 3, generator=g, dtype=torch.float64), torch.randn(200, 2, generator=g, dtype=torch.float64)
    A, B, d = (torch.randn(s, generator=g, dtype=torch.float64) for s in ((3, 3), (3, 2), (3,)))
    data = Dataset(x, u, x @ A.T + u @ B.T + d)
    model, info = fit_baseline("affine", baseline_options("affine", None), data, seed=0, modes=1)
    assert info == {}
    assert relative_error(model, data) < 1e-20


@needs_parc
def test_parc_fits_two_pieces_better_than_one():
    """PARC (pyparc, called for real) on a one-unit LCS: two affine pieces; with K = its two
    modes it beats the best single affine map by far."""
    truth = random_lcs(2, 1, 1, stiffness=1.0, seed=3)
    train, test = make_dataset(truth, 300, noise=0.0, seed=1), make_dataset(truth, 100, seed=2)
    modes = count_modes(truth, train)
    assert modes == 2
    parc, info = fit_baseline("parc", baseline_options("parc", None), train, seed=0, modes=modes)
    affine, _ = fit_baseline("affine", {}, train, seed=0, modes=modes)
    assert info["K"] == 2 and info["K_final"] == 2 and 1 <= info["iterations"] <= 15
    assert relative_error(parc, test) < relative_error(affine, test) / 5
    # a batch of as many rows as PARC has features (n_x + n_u = 3) is a batch, not one sample
    assert torch.equal(parc.step(test.x[:3], test.u[:3]), parc.step(test.x, test.u)[:3])


@needs_parc
def test_parc_is_seeded_and_leaves_numpys_global_generator_alone():
    import numpy as np

    truth = random_lcs(2, 1, 2, stiffness=1.0, seed=4)
    train, test = make_dataset(truth, 200, seed=1), make_dataset(truth, 50, seed=2)
    opts = baseline_options("parc", {"K": 3, "maxiter": 3})
    np.random.seed(123)
    before = np.random.get_state()[1].copy()
    a, _ = fit_baseline("parc", opts, train, seed=7, modes=0)
    assert (np.random.get_state()[1] == before).all()
    b, _ = fit_baseline("parc", opts, train, seed=7, modes=0)
    assert torch.equal(a.step(test.x, test.u), b.step(test.x, test.u))


@needs_parc
def test_a_parc_fit_that_fails_in_pyparc_raises_baseline_failed():
    """K = 30 pieces on 30 samples (min_number 10): every cluster is too small, pyparc merges
    them all away and its own fit raises (as at n_lambda = 20 of the comparison, ~17,000 modes on
    5,000 samples); our wrapper names the method and keeps the original as the cause."""
    import numpy as np

    train = make_dataset(random_lcs(2, 1, 2, stiffness=1.0, seed=4), 30, seed=1)
    state = np.random.get_state()[1].copy()
    with pytest.raises(BaselineFailed, match=re.escape(
            "PARC failed: ValueError: attempt to get argmax of an empty sequence")) as info:
        fit_baseline("parc", baseline_options("parc", {"K": 30}), train, seed=0, modes=0)
    assert isinstance(info.value, RuntimeError) and isinstance(info.value.__cause__, ValueError)
    assert (np.random.get_state()[1] == state).all()  # numpy's generator restored all the same


def test_mlp_baseline_picks_the_grid_point_with_the_lowest_held_out_error():
    truth = random_lcs(2, 1, 2, stiffness=1.0, seed=5)
    train, test = make_dataset(truth, 400, seed=1), make_dataset(truth, 100, seed=2)
    opts = baseline_options("mlp", {"hidden": [[8], [16]], "lr": [1e-3, 1e-2], "iterations": 200,
                                    "eval_every": 50})
    model, info = fit_baseline("mlp", opts, train, seed=0, modes=0)
    assert len(info["grid"]) == 4
    assert info["val_mse"] == min(g["val_mse"] for g in info["grid"])
    assert (info["hidden"], info["lr"]) in [(g["hidden"], g["lr"]) for g in info["grid"]
                                            if g["val_mse"] == info["val_mse"]]
    affine, _ = fit_baseline("affine", {}, train, seed=0, modes=0)
    assert relative_error(model, test) < 1.0  # it learned something (untrained: ~1)
    assert relative_error(affine, test) < 1.0


@pytest.mark.parametrize("table, named", [
    ({"hiden": [[8]]}, "baselines.mlp.hiden: unknown key"),
    ({"hidden": [8]}, "baselines.mlp.hidden: expected a non-empty list of layer-size lists"),
    ({"lr": []}, "baselines.mlp.lr: expected a non-empty list"),
    ({"val_fraction": 1.0}, "baselines.mlp.val_fraction: expected a number in (0, 1)"),
])
def test_baseline_options_name_the_key(table, named):
    with pytest.raises(LCSInputError, match=re.escape(named)):
        baseline_options("mlp", table)


def test_parc_defaults_are_the_authors_settings():
    opts = baseline_options("parc", None)
    assert opts == {"K": "modes", "separation": "Voronoi", "sigma": 1.0, "alpha": 1e-3,
                    "beta": 1e-3, "maxiter": 15, "cost_tol": 1e-4, "min_number": 10,
                    "fit_on_partition": True, "softmax_maxiter": 100_000, "kmeans_init": 10}
    assert set(OPTIONS) == {"affine", "mlp", "parc"}


def test_parc_without_pyparc_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyparc.parc", None)  # as if not installed
    with pytest.raises(ModuleNotFoundError, match=re.escape("the PARC baseline")) as info:
        fit_baseline("parc", baseline_options("parc", None), None, seed=0, modes=2)
    assert "pip install 'lcs_cvx[baselines]'" in str(info.value)


# -- configs -----------------------------------------------------------------------------------
def test_a_loss_with_its_own_recipe_and_the_baselines_are_methods_of_a_cell():
    config = load_config(CONFIGS / "pwa_compare.toml")
    cells = {(c["value_index"], c["trial"], c["method"]): c for c in expand(config)}
    paper, best = cells[(0, 0, "violation")], cells[(0, 0, "violation@best")]
    assert (paper["recipe"], best["recipe"]) == ("paper", "best")
    # [fit.paper] / [fit.best], in the authors' scaling (eps x 2, gamma / 2, reg / 2)
    assert (paper["fit"]["iterations"], paper["fit"]["eps"], paper["fit"]["batch_size"]) == (2500, 2e-2, 100)
    assert "iterations" not in best["fit"] and (best["fit"]["eps"], best["fit"]["batch_size"]) == (2e-4, 200)
    assert paper["fit"]["loss"] == best["fit"]["loss"] == "violation"
    parc = cells[(0, 0, "parc")]
    assert parc["fit"] is None and parc["recipe"] is None and parc["baseline"]["K"] == "modes"
    # same truth, data and start for every method of a (value, trial)
    assert paper["seeds"] == best["seeds"] == parc["seeds"]
    # PARC in the first 3 trials only; every other method in all 10
    trials = {m: sorted({t for (_, t, mm) in cells if mm == m}) for m in METHODS}
    assert trials["parc"] == [0, 1, 2] and all(trials[m] == list(range(10)) for m in METHODS if m != "parc")
    assert paper["time_limit"] == 3600


def test_the_time_limit_is_not_part_of_a_cells_key(tmp_path):
    a = expand(load_config(SMOKE))
    b = expand(load_config(_write(tmp_path, "time_limit = 7\n")))
    assert [c["key"] for c in a] == [c["key"] for c in b]
    assert {c["time_limit"] for c in b} == {7}


def test_committed_fig1_results_keep_their_config_hashes():
    """Configs without the comparison's keys hash as before: the committed databases of the
    Fig. 1 studies still match their configs (read-only). ``train_best`` was trained with version
    1 of the best recipe: its keys are the current cells' without the recipe version."""
    from lcs_cvx.study.cells import cell_key

    def version_1(cells):
        return {cell_key({k: v for k, v in c.items() if k not in ("key", "recipe_version")})
                for c in cells}

    for directory, name in (("fig1", "fig1a_n_lam"), ("fig1b", "fig1b_n_x"), ("train_best", "train_best")):
        db = ROOT / "studies" / "results" / directory / "studies.sqlite"
        conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
        hashes = {h for (h,) in conn.execute("SELECT config_hash FROM studies WHERE name = ?", (name,))}
        keys = {k for (k,) in conn.execute("SELECT key FROM cells WHERE study = ?", (name,))}
        conn.close()
        config = load_config(CONFIGS / f"{name}.toml")
        assert config_hash(config) in hashes
        cells = expand(config)
        expected = version_1(cells) if name == "train_best" else {c["key"] for c in cells}
        assert keys <= expected and keys
        if name == "train_best":  # and the current version trains them anew
            assert not keys & {c["key"] for c in cells}


@pytest.mark.parametrize("text, named", [
    ('methods = ["violation@fast"]\n', "methods: expected a list of distinct methods"),
    ('methods = ["parc", "parc"]\n', "methods: expected a list of distinct methods"),
    ("time_limit = 0\n", "time_limit: expected a number of seconds > 0"),
    ("method_trials = { parc = 2 }\n", "method_trials.parc: expected an integer in [1, trials = 1]"),
    ("method_trials = { parcc = 1 }\n", "method_trials.parcc: unknown method"),
    ("[baselines.parc]\nK = 0\n", "baselines.parc.K: expected \"modes\""),
    ("[baselines.lasso]\n", "baselines.lasso: unknown key"),
])
def test_config_errors_name_the_key(tmp_path, text, named):
    with pytest.raises(LCSInputError, match=re.escape(named)):
        load_config(_write(tmp_path, text))


# -- time limit --------------------------------------------------------------------------------
def test_a_cell_raising_in_its_process_is_reported_with_its_traceback():
    with pytest.raises(ChildError, match="KeyError: 'system'"):
        run_limited(work, {"method": "violation"}, 60)


def test_the_time_limit_kills_a_slow_cell_and_records_it(tmp_path):
    """A violation cell of 10^8 iterations (hours) under a 3 s limit: killed, stored with status
    'timeout', its modes and the seconds it ran; running again keeps it, a larger limit would
    run it again."""
    path = _write(tmp_path, 'methods = ["violation"]\ntime_limit = 3\n[sweep]\nvalues = [4]\n'
                            "[fit.paper]\niterations = 100_000_000\n")
    t0 = time.perf_counter()
    summary = run_config(path, out=tmp_path / "out", workers=1, progress=False)
    assert time.perf_counter() - t0 < 90
    assert (summary.total, summary.executed, summary.failed, summary.timed_out) == (1, 1, 0, 1)
    [row] = _rows(tmp_path / "out")
    assert row["status"] == "timeout" and row["e_test"] is None and row["time_limit"] == 3
    [cell] = expand(load_config(path))
    truth, train, *_ = setup_cell(cell)
    assert row["modes"] == count_modes(truth, train)  # reported by the cell before its fit
    assert 3 <= row["wall_time"] < 30 and 0 < row["fit_wall_time"] <= row["wall_time"]
    again = run_config(path, out=tmp_path / "out", workers=1, progress=False)
    assert (again.skipped, again.executed) == (1, 0)
    from lcs_cvx.study import report

    [table] = [w for w in report(tmp_path / "out", anchors_path=None) if w.endswith(".md")]
    assert "Timed out (killed at the config's time limit; no e_test" in Path(table).read_text()
    assert "violation 1 cells" in Path(table).read_text()
    with Store(tmp_path / "out") as store:
        assert store.finished_keys(3) == {row["key"]} == store.finished_keys(2)
        assert store.finished_keys(5) == set() == store.finished_keys(None)


def test_a_finished_result_replaces_a_timed_out_one(tmp_path):
    cell = expand(load_config(SMOKE))[0]
    ok = {"status": "ok", "e_test": 0.5, "final_loss": 1.0, "modes": 4, "sigma_min": 1.0,
          "fit_wall_time": 1.0, "wall_time": 1.5, "settings": {}, "warnings": [], "host": "h",
          "curve": [{"iteration": 1, "phase": "adam", "loss": 1.0, "e_test": 0.5, "eps": 0.1,
                     "lr": 0.1, "wall_time": 0.1, "restart": 0}]}
    timeout = {**ok, "status": "timeout", "e_test": None, "final_loss": None, "curve": []}
    with Store(tmp_path) as store:
        assert store.add_cell({**cell, "time_limit": 2}, 0, timeout)
        assert store.add_cell({**cell, "time_limit": 10}, 0, ok)
        assert not store.add_cell(cell, 0, ok)  # a finished cell is never replaced
        [row] = store.cells([cell["key"]]).values()
        assert (row["status"], row["e_test"], row["time_limit"]) == ("ok", 0.5, 10)
        assert len(store.curve(row["id"])) == 1


def test_a_database_from_before_time_limits_gains_the_columns(tmp_path):
    conn = sqlite3.connect(tmp_path / "studies.sqlite")
    conn.execute("CREATE TABLE cells (id INTEGER PRIMARY KEY, key TEXT NOT NULL UNIQUE, "
                 "config_hash TEXT NOT NULL, study TEXT NOT NULL, value_index INTEGER NOT NULL, "
                 "value REAL, trial INTEGER NOT NULL, method TEXT NOT NULL, seed INTEGER NOT NULL, "
                 "seed_truth INTEGER NOT NULL, seed_train INTEGER NOT NULL, seed_test INTEGER NOT NULL, "
                 "seed_init INTEGER NOT NULL, seed_fit INTEGER NOT NULL, e_test REAL, final_loss REAL, "
                 "modes INTEGER, sigma_min REAL, fit_wall_time REAL, wall_time REAL, "
                 "settings_json TEXT NOT NULL, cell_json TEXT NOT NULL, warnings_json TEXT, "
                 "host TEXT, finished TEXT NOT NULL)")
    conn.execute("INSERT INTO cells VALUES (1, 'k', 'h', 's', 0, 1.0, 0, 'violation', 0, 1, 2, 3, "
                 "4, 5, 0.1, 0.2, 4, 1.0, 1.0, 2.0, '{}', '{}', '[]', 'host', 'now')")
    conn.commit()
    conn.close()
    with Store(tmp_path) as store:
        [row] = store.cells(["k"]).values()
        assert (row["status"], row["time_limit"], row["e_test"]) == ("ok", None, 0.1)
        assert store.finished_keys() == {"k"}


# -- failed baselines --------------------------------------------------------------------------
def _failed_result(error: str) -> dict:
    return {"status": "failed", "e_test": None, "final_loss": None, "modes": 4, "sigma_min": 1.0,
            "fit_wall_time": 2.0, "wall_time": 2.5, "settings": {"K": "modes", "error": error},
            "warnings": [], "host": "h", "curve": []}


def test_a_failed_cell_is_finished_under_any_time_limit_and_clears_its_failures(tmp_path):
    cell = {**expand(load_config(SMOKE))[0], "time_limit": 2}
    with Store(tmp_path) as store:
        store.add_failure(cell, "Traceback: an earlier run's error")
        assert [f["key"] for f in store.failures(cell["config_hash"])] == [cell["key"]]
        assert store.add_cell(cell, 0, _failed_result("PARC failed: ValueError: x"))
        assert store.failures(cell["config_hash"]) == []
        [row] = store.cells([cell["key"]]).values()
        assert (row["status"], row["e_test"], row["fit_wall_time"]) == ("failed", None, 2.0)
        # unlike a timed-out cell, no limit makes it run again
        for limit in (None, 1, 2, 1e9):
            assert store.finished_keys(limit) == {cell["key"]}


def test_the_pwa_report_tells_failed_from_timed_out(tmp_path):
    """The PWA table (no pyparc needed: the points are written by hand): a point where PARC's
    fit failed says "failed", one where it timed out "timed out", with the failure's message in
    the notes and the figure's marks for both."""
    from studies.pwa.report import BEST, PARC, markdown, plot

    def method(e=(), t=(), out=(), failed=(), errors=()):
        return {"expected": 2, "e_test": list(e), "time": list(t), "timeouts": list(out),
                "limit": 60.0 if out else None, "failed": list(failed), "errors": list(errors)}

    msg = "PARC failed: ValueError: attempt to get argmax of an empty sequence"
    points = [
        {"value": 4, "modes": 16.0, "methods": {BEST: method([1e-3, 2e-3], [1.0, 1.0]),
                                                 PARC: method([0.1, 0.2], [20.0, 30.0])}},
        {"value": 16, "modes": 2000.0, "methods": {BEST: method([1e-3, 2e-3], [2.0, 2.0]),
                                                    PARC: method(out=[60.5, 61.0])}},
        {"value": 20, "modes": 17000.0, "methods": {BEST: method([1e-3, 2e-3], [3.0, 3.0]),
                                                     PARC: method(failed=[40.0, 50.0], errors=[msg])}},
    ]
    config = {"name": "pwa_hand", "trials": 2, "methods": [BEST, PARC], "time_limit": 60.0,
              "system": {"n_x": 4, "n_u": 2}, "data": {"n_train": 5000, "n_test": 1000}}
    r = {"study": {"path": "hand.toml", "config_hash": "h"}, "config": config, "points": points,
         "n_cells": 12, "n_done": 12, "cell_time": 1.0, "failures": []}
    table = markdown(r)
    rows = {line.split(" | ")[0]: line for line in table.splitlines() if line.startswith("| ")}
    assert "| 20 | 17,000 | 0.0015 | 3 | failed | – (2 failed after 45 s) |" in table
    assert "| 16 | 2,000 | 0.0015 | 2 | – | – (2 timed out ≥ 60 s) |" in table
    assert "| 20 | 17,000 | – (PARC failed) | – (PARC failed) | PARC failed | PARC failed | yes |" in table
    assert "| 16 | 2,000 | – (PARC timed out) | ≥ 30 (timed out) | PARC timed out | yes | n/a |" in table
    assert f"- Failed (the method's own fit raised; no e_test, left out of the medians; " \
           f"recorded once, not retried): PARC at n_λ = 20: 2 cells ({msg})." in table
    # the authors' 2,021 modes: our n_λ = 16 point (2,000 modes), where PARC timed out
    assert rows["| 2,021"].count("timed out") == 1 and "| failed |" in rows["| 2,021"]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    saved = {}
    real_savefig = plt.Figure.savefig

    def keep_labels(fig, *args, **kwargs):
        saved["labels"] = fig.axes[1].get_legend_handles_labels()[1]
        return real_savefig(fig, *args, **kwargs)

    plt.Figure.savefig = keep_labels
    try:
        written = plot(r, str(tmp_path / "hand"))
    finally:
        plt.Figure.savefig = real_savefig
    assert all(Path(w).stat().st_size > 1000 for w in written)
    assert "PARC: timed out (at the limit)" in saved["labels"]
    assert "PARC: fit failed (at the seconds until it failed)" in saved["labels"]


@needs_parc
def test_a_parc_fit_that_fails_is_recorded_once_and_reported(tmp_path, monkeypatch, capsys):
    """PARC failing for real in its child process (min_number 1,000 on 500 samples: every
    cluster merged away): the cell is stored as 'failed' with the error in its settings, the
    failure an earlier run logged is cleared, a second run hands nothing to the executor, and
    both reports show it."""
    from lcs_cvx.study import report, runner
    from studies.pwa.report import write_report

    path = _write(tmp_path, 'methods = ["parc"]\n[sweep]\nvalues = [2]\n'
                            "[baselines.parc]\nmin_number = 1000\n")
    [cell] = expand(load_config(path))
    out = tmp_path / "out"
    with Store(out) as store:  # as if an earlier run had logged it (before BaselineFailed)
        store.add_failure(cell, "Traceback ...\nValueError: attempt to get argmax of an empty sequence")
    handed: list[int] = []
    real_pool = runner.process_pool

    def counting_pool(cells, *args, **kwargs):
        handed.append(len(cells))
        return real_pool(cells, *args, **kwargs)

    monkeypatch.setattr(runner, "process_pool", counting_pool)
    summary = run_config(path, out=out, workers=1, progress=False)
    assert (summary.executed, summary.failed, summary.timed_out, summary.baseline_failed) == (1, 0, 0, 1)
    msg = "PARC failed: ValueError: attempt to get argmax of an empty sequence"
    assert f"the method's own fit failed (value 2, trial 0, parc): {msg}; recorded as 'failed'" \
        in capsys.readouterr().err
    [row] = _rows(out)
    import json

    settings = json.loads(row["settings_json"])
    assert (row["status"], row["e_test"], row["final_loss"], row["modes"]) == ("failed", None, None, 4)
    assert settings["error"] == msg and settings["min_number"] == 1000 and settings["K"] == "modes"
    assert 0 < row["fit_wall_time"] <= row["wall_time"]
    with Store(out) as store:
        assert store.failures(cell["config_hash"]) == []
        assert store.curve(row["id"]) == []
    again = run_config(path, out=out, workers=1, progress=False)
    assert (again.skipped, again.executed, again.baseline_failed) == (1, 0, 0)
    assert handed == [1]  # the second run handed no cell to the executor
    [table] = [w for w in report(out, anchors_path=None) if w.endswith(".md")]
    text = Path(table).read_text()
    assert ("- Failed (the method's own fit raised; no e_test, left out of the statistics): "
            f"parc 1 cells ({msg}).") in text
    assert "Failures logged" not in text
    [pwa] = [w for w in write_report(out) if w.endswith(".md")]
    assert "| 2 | 4 | failed | – (1 failed after" in Path(pwa).read_text()


# -- the smoke study ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def smoke_out(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("pwa")
    summary = run_config(SMOKE, out=out, workers=1, progress=False)
    assert (summary.total, summary.executed, summary.failed, summary.timed_out) == (12, 12, 0, 0)
    return out


@needs_parc
def test_smoke_study_runs_every_method_for_real(smoke_out):
    rows = _rows(smoke_out)
    assert sorted({r["method"] for r in rows}) == sorted(METHODS)
    assert all(r["status"] == "ok" and 0 < r["e_test"] < 10 for r in rows)
    assert {r["value"]: r["modes"] for r in rows} == {2.0: 4, 4.0: 16}  # 2^n_lam on 500 samples
    parc = [r for r in rows if r["method"] == "parc"]
    import json

    assert [json.loads(r["settings_json"])["K"] for r in parc] == [4, 16]
    # each cell ran in its own child process (the time limit's)
    assert len({r["host"] for r in rows}) == len(rows)


@needs_parc
def test_resume_keeps_every_finished_cell(smoke_out):
    before = {r["key"]: r["e_test"] for r in _rows(smoke_out)}
    again = run_config(SMOKE, out=smoke_out, workers=1, progress=False)
    assert (again.skipped, again.executed) == (12, 0)
    assert {r["key"]: r["e_test"] for r in _rows(smoke_out)} == before


@needs_parc
def test_report_writes_the_figure_and_the_table_beside_the_authors(smoke_out, capsys):
    from studies.pwa.report import main as report_main

    assert report_main([str(smoke_out)]) == 0
    stem = smoke_out / "pwa_compare_smoke_vs_modes"
    assert all((stem.with_suffix(s)).stat().st_size > 1000 for s in (".png", ".pdf"))
    table = stem.with_suffix(".md").read_text()
    assert "authors (published)" not in table  # that is the figure's legend
    assert "the authors' published numbers" in table
    assert "| 16 | 4 (16) | 9 |" in table  # authors' 16 modes beside our n_λ = 4 (16 modes)
    assert "| 2,021 |" in table and "failed" in table
    assert "## Targets" in table and "| 4 | 16 |" in table
    assert "wrote" in capsys.readouterr().out


@needs_parc
def test_generic_report_handles_baselines(smoke_out):
    from lcs_cvx.study import report

    written = report(smoke_out, anchors_path=None)
    table = Path([w for w in written if w.endswith(".md")][0]).read_text()
    assert "parc mean" in table and "violation@best mean" in table
