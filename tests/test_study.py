"""The study runner (lcs_cvx.study, `lcs-cvx study`): every smoke config of Fig. 1 runs on a
process pool, finished cells are skipped, an interrupted run resumes without duplicates, a Dask
LocalCluster and a real `dask scheduler` + `dask worker` on loopback give the same numbers, the
store keeps a module study's job results exactly, the report writes figures and tables with the
authors' numbers (and a best-recipe panel's beside its paper-recipe panel's: `compare`), and
config errors name the file and the key."""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

import lcs_cvx
from lcs_cvx.cli import main
from lcs_cvx.study import Store, cell_seeds, config_hash, expand, load_config, report, run_config
from lcs_cvx.study.cells import REFERENCE, run_cell, setup_cell
from lcs_cvx.study.report import load_anchors

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "studies" / "configs"
SMOKE = sorted(p.stem for p in CONFIGS.glob("fig1*_smoke.toml")
               if not p.stem.endswith("_best_smoke"))
#: The best-recipe panels, each reported beside its paper-recipe study (``compare``).
BEST = {"fig1a_n_lam_best": "fig1a_n_lam", "fig1b_n_x_best": "fig1b_n_x",
        "fig1c_stiffness_best": "fig1c_stiffness"}
PANELS = {"fig1a_n_lam_smoke": "a", "fig1b_n_x_smoke": "b", "fig1c_stiffness_smoke": "c",
          "fig1d_gamma_smoke": "d", "fig1e_eps_smoke": "e"}


def _rows(out: Path, study: str | None = None) -> list[sqlite3.Row]:
    conn = sqlite3.connect(out / "studies.sqlite")
    conn.row_factory = sqlite3.Row
    q = "SELECT * FROM cells" + (" WHERE study = ?" if study else "") + " ORDER BY key"
    rows = conn.execute(q, (study,) if study else ()).fetchall()
    conn.close()
    return rows


@pytest.fixture(scope="module")
def pool_out(tmp_path_factory) -> Path:
    """Every smoke config run once on a 2-worker process pool, into one database."""
    out = tmp_path_factory.mktemp("pool")
    for name in SMOKE:
        summary = run_config(CONFIGS / f"{name}.toml", out=out, workers=2, progress=False)
        assert (summary.executed, summary.skipped, summary.failed) == (summary.total, 0, 0)
    return out


def test_there_is_a_smoke_config_per_panel():
    assert SMOKE == sorted(PANELS)
    for name in SMOKE:
        full = load_config(CONFIGS / f"{name.removesuffix('_smoke')}.toml")
        smoke = load_config(CONFIGS / f"{name}.toml")
        assert smoke["panel"] == full["panel"] == PANELS[name]
        assert smoke["sweep"]["param"] == full["sweep"]["param"]
        assert len(smoke["sweep"]["values"]) == 2 and smoke["trials"] == 1


@pytest.mark.parametrize("name", SMOKE)
def test_smoke_config_runs_on_the_process_pool(pool_out, name):
    config = load_config(CONFIGS / f"{name}.toml")
    rows = _rows(pool_out, name)
    assert len(rows) == len(expand(config))
    for r in rows:
        assert math.isfinite(r["e_test"]) and r["e_test"] > 0
        assert r["modes"] >= 1 and r["sigma_min"] > 0 and r["wall_time"] > 0
    # both methods of a (value, trial) -- and reference cells -- share truth, data and init
    groups: dict[tuple, set] = {}
    for r in rows:
        slot = 0 if config["sweep"]["shared_truth"] else r["value_index"]
        seeds = (r["seed_truth"], r["seed_train"], r["seed_test"], r["seed_init"], r["seed_fit"])
        groups.setdefault((slot, r["trial"]), set()).add((seeds, r["sigma_min"], r["modes"]))
    assert all(len(g) == 1 for g in groups.values())
    if name.startswith("fig1c"):  # G = 0: sigma_min(F + F^T) = 2 s exactly
        for r in rows:
            assert r["sigma_min"] == pytest.approx(2 * r["value"], rel=1e-9)
    if config["reference_methods"]:
        assert {r["method"] for r in rows if r["value_index"] == REFERENCE} == {"prediction"}
    conn = sqlite3.connect(pool_out / "studies.sqlite")
    ids = [i for (i,) in conn.execute("SELECT id FROM cells WHERE study = ?", (name,))]
    conn.close()
    with Store(pool_out) as store:
        curves = [store.curve(i) for i in ids]
    assert [[r["iteration"] for r in c] for c in curves] == [[10, 20]] * len(rows)  # eval_every 10
    assert all(math.isfinite(r["loss"]) and r["phase"] == "adam" for c in curves for r in c)


def test_schema_1_database_is_converted_on_open(tmp_path):
    """A database of schema 1 (one row per curve record) opens as schema 2, curves intact."""
    conn = sqlite3.connect(tmp_path / "studies.sqlite")
    conn.executescript("""
        CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
        INSERT INTO meta VALUES ('schema_version', '1');
        CREATE TABLE cells (id INTEGER PRIMARY KEY, key TEXT NOT NULL UNIQUE);
        INSERT INTO cells VALUES (1, 'a'), (2, 'b');
        CREATE TABLE curves (cell_id INTEGER NOT NULL, iteration INTEGER, phase TEXT, loss REAL,
            e_test REAL, eps REAL, lr REAL, wall_time REAL, restart INTEGER);
        INSERT INTO curves VALUES (1, 100, 'adam', 0.5, NULL, 1e-4, 1e-3, 1.5, 0),
            (2, 100, 'adam', 0.25, 1e-3, 1e-4, 1e-3, 2.0, 0), (1, 200, 'adam', 0.125, 2e-4, 1e-4, 1e-3, 3.0, 0);
    """)
    conn.commit()
    conn.close()
    with Store(tmp_path) as store:
        assert store.curve(1) == [
            {"iteration": 100, "phase": "adam", "loss": 0.5, "e_test": None, "eps": 1e-4,
             "lr": 1e-3, "wall_time": 1.5, "restart": 0},
            {"iteration": 200, "phase": "adam", "loss": 0.125, "e_test": 2e-4, "eps": 1e-4,
             "lr": 1e-3, "wall_time": 3.0, "restart": 0},
        ]
        assert [r["loss"] for r in store.curve(2)] == [0.25]
        version = store.conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
        assert version == ("2",)


def test_running_again_skips_every_finished_cell(pool_out):
    before = _rows(pool_out)
    summary = run_config(CONFIGS / "fig1a_n_lam_smoke.toml", out=pool_out, workers=2, progress=False)
    assert (summary.executed, summary.skipped) == (0, summary.total)
    assert [tuple(r) for r in _rows(pool_out)] == [tuple(r) for r in before]


def test_a_new_description_of_the_same_config_replaces_the_old(tmp_path):
    config = {"name": "s", "panel": "a", "description": "old", "path": "a.toml"}
    with Store(str(tmp_path)) as store:
        store.add_study("h", config)
        store.add_study("h", {**config, "description": "new", "path": "b.toml"})
        (study,) = store.studies()
    assert study["config"]["description"] == "new" and study["path"] == "b.toml"


def test_an_interrupted_run_resumes_without_duplicates(pool_out, tmp_path):
    path = CONFIGS / "fig1e_eps_smoke.toml"
    first = run_config(path, out=tmp_path, workers=2, max_cells=1, progress=False)
    assert (first.executed, len(_rows(tmp_path))) == (1, 1)
    second = run_config(path, out=tmp_path, workers=2, progress=False)
    assert (second.skipped, second.executed) == (1, second.total - 1)
    rows = _rows(tmp_path)
    assert len(rows) == len({r["key"] for r in rows}) == second.total
    reference = {r["key"]: r["e_test"] for r in _rows(pool_out, "fig1e_eps_smoke")}
    assert {r["key"]: r["e_test"] for r in rows} == reference  # same as an uninterrupted run


def test_ctrl_c_in_the_client_keeps_every_finished_cell(tmp_path, monkeypatch):
    real = Store.add_cell

    def add_then_interrupt(self, *args, **kwargs):
        real(self, *args, **kwargs)
        raise KeyboardInterrupt

    path = CONFIGS / "fig1d_gamma_smoke.toml"
    monkeypatch.setattr(Store, "add_cell", add_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        run_config(path, out=tmp_path, workers=2, progress=False)
    assert len(_rows(tmp_path)) == 1
    monkeypatch.setattr(Store, "add_cell", real)
    summary = run_config(path, out=tmp_path, workers=2, progress=False)
    assert (summary.skipped, summary.executed) == (1, summary.total - 1)
    conn = sqlite3.connect(tmp_path / "studies.sqlite")
    assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    conn.close()


def test_dask_local_cluster_gives_the_process_pool_results(pool_out, tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  host="127.0.0.1", dashboard_address=None) as cluster:
        summary = run_config(CONFIGS / "fig1a_n_lam_smoke.toml", out=tmp_path,
                             scheduler=cluster.scheduler_address, progress=False)
    assert (summary.executed, summary.failed) == (summary.total, 0)
    dask_rows = {r["key"]: r for r in _rows(tmp_path)}
    pool_rows = {r["key"]: r for r in _rows(pool_out, "fig1a_n_lam_smoke")}
    assert dask_rows.keys() == pool_rows.keys()
    for key, r in dask_rows.items():
        assert abs(r["e_test"] - pool_rows[key]["e_test"]) <= 1e-12
        assert r["final_loss"] == pytest.approx(pool_rows[key]["final_loss"], rel=1e-12)


#: The grace of the real-Dask test's processes between SIGTERM and SIGKILL (s). No other bound:
#: a start or a run that hangs is ended by pytest-timeout.
DASK_STOP_S = 10.0


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _stop(procs: list[subprocess.Popen]) -> None:
    """End the processes this test started (each leads its own process group: the worker's
    nanny and its child go with it): SIGTERM, then SIGKILL after DASK_STOP_S."""
    for p in procs:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGTERM)
    deadline = time.monotonic() + DASK_STOP_S
    for p in procs:
        try:
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=DASK_STOP_S)


def test_a_dask_scheduler_and_worker_processes_give_the_local_results(pool_out, tmp_path):
    """`dask scheduler` and `dask worker` (the console scripts beside this Python) as separate
    processes on 127.0.0.1; the fig1a smoke study through `lcs-cvx study run --scheduler`."""
    distributed = pytest.importorskip("dask.distributed")
    dask_bin = Path(sys.executable).parent / "dask"
    if not dask_bin.is_file():
        pytest.skip(f"no dask console script beside {sys.executable}")
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    # the workers import this checkout's lcs_cvx; no thread oversubscription
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
           "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    common = {"cwd": tmp_path, "env": env, "start_new_session": True,
              "stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    procs: list[subprocess.Popen] = []
    try:
        procs.append(subprocess.Popen(
            [str(dask_bin), "scheduler", "--host", "127.0.0.1", "--port", str(port),
             "--no-dashboard", "--idle-timeout", "300s"], **common))
        procs.append(subprocess.Popen(
            [str(dask_bin), "worker", address, "--host", "127.0.0.1", "--nworkers", "1",
             "--nthreads", "1", "--no-dashboard", "--death-timeout", "30",
             "--local-directory", str(tmp_path / "worker")], **common))
        while True:  # the scheduler takes a few seconds to listen
            try:
                client = distributed.Client(address, timeout=5)
                break
            except (OSError, TimeoutError):
                assert procs[0].poll() is None, f"dask scheduler exited ({procs[0].returncode})"
                time.sleep(0.5)
        try:
            client.wait_for_workers(1)
            [worker_pid] = client.run(os.getpid).values()
        finally:
            client.close()

        out = tmp_path / "out"
        argv = ["study", "run", str(CONFIGS / "fig1a_n_lam_smoke.toml"), "--out", str(out),
                "--scheduler", address]
        outcome: dict[str, int | BaseException] = {}

        def run() -> None:
            try:
                outcome["rc"] = main(argv)
            except BaseException as exc:  # reported below, in the test's thread
                outcome["error"] = exc

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        thread.join()
    finally:
        _stop(procs)
    assert "error" not in outcome, outcome.get("error")
    assert outcome["rc"] == 0
    dask_rows = {r["key"]: r for r in _rows(out)}
    pool_rows = {r["key"]: r for r in _rows(pool_out, "fig1a_n_lam_smoke")}
    assert len(dask_rows) == len(expand(load_config(CONFIGS / "fig1a_n_lam_smoke.toml")))
    assert dask_rows.keys() == pool_rows.keys()  # complete: every cell, none failed
    with Store(out) as store:
        assert store.failures(next(iter(dask_rows.values()))["config_hash"]) == []
    for key, r in dask_rows.items():
        assert r["host"].endswith(f":{worker_pid}")  # ran in the dask worker process
        assert abs(r["e_test"] - pool_rows[key]["e_test"]) <= 1e-12
        assert r["final_loss"] == pytest.approx(pool_rows[key]["final_loss"], rel=1e-12)
        assert r["settings_json"] == pool_rows[key]["settings_json"]


def test_report_writes_figures_and_tables_with_the_anchors(pool_out, capsys):
    assert main(["study", "report", str(pool_out)]) == 0
    written = capsys.readouterr().out
    for name in SMOKE:
        png, pdf, md = (pool_out / f"{name}.{ext}" for ext in ("png", "pdf", "md"))
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and pdf.read_bytes()[:5] == b"%PDF-"
        assert str(md) in written
    table = (pool_out / "fig1a_n_lam_smoke.md").read_text()
    assert "| n_λ | cells | modes (mean) |" in table
    assert "authors 1: prediction mean" in table and "authors 2: violation mean" in table
    row4 = next(line for line in table.splitlines() if line.startswith("| 4 |"))
    assert "0.00119" in row4 and "0.000186" in row4 and "| 16 |" in row4 and "0.00019" in row4
    stiff = (pool_out / "fig1c_stiffness_smoke.md").read_text()
    assert "0.00955" in stiff and "1.86e-05" in stiff  # s = 1e-3
    gamma = (pool_out / "fig1d_gamma_smoke.md").read_text()
    assert "Reference `prediction`" in gamma and "0.000749" in gamma


def test_report_of_a_directory_without_a_database_exits_2(tmp_path, capsys):
    assert main(["study", "report", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "no study database" in err and str(tmp_path) in err


def test_seeds_are_derived_from_seed_value_and_trial():
    config = load_config(CONFIGS / "fig1a_n_lam.toml")
    cells = expand(config)
    assert [c["key"] for c in cells] == [c["key"] for c in expand(config)]
    assert len({c["key"] for c in cells}) == len(cells) == 6 * 30 * 2
    c = next(c for c in cells if c["value_index"] == 2 and c["trial"] == 7)
    assert c["seeds"] == cell_seeds(config["seed"], 2, 7)
    assert len(set(c["seeds"].values())) == 5
    assert cell_seeds(1, 2, 7) != cell_seeds(1, 2, 8) != cell_seeds(1, 3, 7)
    d = expand(load_config(CONFIGS / "fig1d_gamma.toml"))  # shared truth across gamma
    assert len({str(x["seeds"]) for x in d if x["trial"] == 3}) == 1


def test_g_scale_zero_gives_the_stiff_generator_of_fig1c():
    s = 1e-3
    base = lcs_cvx.random_lcs(8, 2, 10, stiffness=s, seed=4)
    stiff = lcs_cvx.random_lcs(8, 2, 10, stiffness=s, seed=4, g_scale=0.0)
    assert torch.count_nonzero(stiff.G) == 0
    assert torch.equal(stiff.H, base.H) and torch.equal(stiff.D, base.D)
    assert stiff.sigma_min == pytest.approx(2 * s, rel=1e-9)
    with pytest.raises(lcs_cvx.LCSInputError, match="g_scale"):
        lcs_cvx.random_lcs(2, 1, 2, g_scale=-1.0)


def _write(tmp_path: Path, text: str, name: str = "bad.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


GOOD = f'extends = "{(CONFIGS / "fig1a_n_lam_smoke.toml").as_posix()}"\nname = "t"\n'


@pytest.mark.parametrize(
    ("text", "named"),
    [
        (GOOD + "trails = 3\n", "trails"),
        (GOOD + "[fit]\nlrr = 1e-3\n", "fit.lrr"),
        (GOOD + "[system]\nn_y = 3\n", "system.n_y"),
        (GOOD + "[fit.paper.lr]\nadam = 1e-3\n", "fit.paper.lr.adam"),
        (GOOD + "trials = 0\n", "trials"),
        (GOOD + "methods = ['prediction', 'newton']\n", "methods"),
        (GOOD + "recipe = 'fast'\n", "recipe"),
        (GOOD + "[sweep]\nvalues = []\n", "sweep.values"),
        (GOOD + "[sweep]\nvalues = [1, 0]\n", "sweep.values"),
        (GOOD + "[sweep]\nparam = 'system.n_z'\n", "sweep.param"),
        (GOOD + "[system]\nn_lam = 3\n", "system.n_lam"),
        (GOOD + "[data]\nnoise = -1.0\n", "data.noise"),
        (GOOD + "[fit.paper]\nlr = { prediction = -1.0, violation = 5e-3 }\n", "fit.lr"),
        (GOOD + "[fit]\ngamma = 5.0\n", "fit.gamma"),  # authors' 5.0 is 2.5 here, >= 2 s = 2
        (GOOD + "[fit]\nbatch_size = 'big'\n", "fit.batch_size"),
        (GOOD + "reference_methods = ['prediction']\n", "reference_methods"),
        (GOOD + "compare = 3\n", "compare"),
        (GOOD + "compare = ['fig1a_n_lam']\n", "compare"),
        (GOOD + "compare = 't'\n", "compare"),  # the study itself
        ('extends = "missing.toml"\nname = "t"\n', "missing.toml"),
        ("name = 't'\ntrials = [\n", "not valid TOML"),
    ],
)
def test_config_errors_name_the_file_and_the_key(tmp_path, capsys, text, named):
    path = _write(tmp_path, text)
    with pytest.raises(lcs_cvx.LCSInputError, match="bad.toml|missing.toml") as info:
        load_config(path)
    assert named in str(info.value)
    assert main(["study", "run", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("lcs-cvx study: error: ") and named in err
    assert not (tmp_path / "out").exists()


def test_cli_errors_exit_2(tmp_path, capsys):
    assert main(["study", "run", str(tmp_path / "nope.toml")]) == 2
    assert "nope.toml: config file not found" in capsys.readouterr().err
    assert main(["study"]) == 2
    assert "expected a subcommand" in capsys.readouterr().err
    assert main(["study", "run", str(CONFIGS / "fig1a_n_lam_smoke.toml"), "--only", "seed=1"]) == 2
    assert "--only" in capsys.readouterr().err


def test_cli_run_with_only_runs_the_matching_cells(tmp_path, capsys):
    argv = ["study", "run", str(CONFIGS / "fig1b_n_x_smoke.toml"), "--workers", "1",
            "--out", str(tmp_path), "--only", "value=8,method=violation"]
    assert main(argv) == 0
    assert "4 cells, 0 already finished, 1 run now, 0 failed" in capsys.readouterr().out
    [row] = _rows(tmp_path)
    assert (row["value"], row["method"]) == (8.0, "violation")


@pytest.mark.parametrize("name", [*BEST, *(f"{n}_smoke" for n in BEST)])
def test_best_panels_train_the_paper_panels_violation_cells(name):
    """Each best-recipe config trains the violation cells of its paper config: same seeds,
    truths, data and starts (cell by cell), only the recipe differs; compare names it."""
    paper_name = BEST[name.removesuffix("_smoke")] + ("_smoke" if name.endswith("_smoke") else "")
    best, paper = load_config(CONFIGS / f"{name}.toml"), load_config(CONFIGS / f"{paper_name}.toml")
    assert best["name"] == name and best["compare"] == paper_name
    assert (best["recipe"], best["methods"], paper["recipe"]) == ("best", ["violation"], "paper")
    for key in ("seed", "trials", "sweep", "system", "data", "learner", "convention", "panel"):
        assert best[key] == paper[key], key
    assert config_hash(best) == config_hash({k: v for k, v in best.items() if k != "compare"})
    theirs = {(c["value_index"], c["trial"]): c for c in expand(paper) if c["method"] == "violation"}
    ours = expand(best)
    assert len(ours) == len(theirs) == len(paper["sweep"]["values"]) * paper["trials"]
    for c in ours:
        o = theirs[(c["value_index"], c["trial"])]
        assert c["seeds"] == o["seeds"] == cell_seeds(best["seed"], c["value_index"], c["trial"])
        assert all(c[k] == o[k] for k in ("system", "data", "learner"))
        assert c["recipe"] == "best" and o["recipe"] == "paper" and c["key"] != o["key"]


def _table(md: str) -> list[dict[str, str]]:
    """The rows of the report's table, as {column: cell}."""
    lines = [line for line in md.splitlines() if line.startswith("| ")]
    head = [h.strip() for h in lines[0].strip("|").split("|")]
    return [dict(zip(head, (c.strip() for c in line.strip("|").split("|")), strict=True))
            for line in lines[1:]]


@pytest.mark.parametrize("name", [f"{n}_smoke" for n in BEST])
def test_report_shows_the_compared_study_beside_the_best_one(tmp_path, name):
    """A best smoke study and the violation cells of its paper smoke study in one database: the
    best study's table has the paper study's e_test and fit time per value (recomputed from the
    store here), the ratios, and the authors' ratio; without the paper study, one line says so."""
    paper_name = load_config(CONFIGS / f"{name}.toml")["compare"]
    out = tmp_path / "out"
    paper = run_config(CONFIGS / f"{paper_name}.toml", out=out, workers=1,
                       only={"method": "violation"}, progress=False)
    best = run_config(CONFIGS / f"{name}.toml", out=out, workers=1, progress=False)
    assert (paper.executed, best.executed, paper.failed + best.failed) == (2, 2, 0)
    written = report(out)
    assert str(out / f"{name}.png") in written
    md = (out / f"{name}.md").read_text()
    rows = _table(md)
    with Store(out) as store:
        [hash_paper] = [s["config_hash"] for s in store.studies() if s["name"] == paper_name]
    assert "yes, in all 2 paired cells" in md and f"hash `{hash_paper}`" in md
    conn = sqlite3.connect(out / "studies.sqlite")
    stored = {(s, v): (e, t) for s, v, e, t in conn.execute(
        "SELECT study, value, e_test, fit_wall_time FROM cells WHERE method = 'violation'")}
    conn.close()
    config = load_config(CONFIGS / f"{name}.toml")
    label = config["sweep"]["label"]
    assert [float(r[label]) for r in rows] == config["sweep"]["values"]
    sets = load_anchors(str(ROOT / "studies" / "anchors.toml")).get(config["panel"], {})
    sets = sets.get("sets", []) if sets.get("param") == config["sweep"]["param"] else []
    fmt = "{:.3g}".format
    paired = f"violation (paper recipe, {paper_name})"
    for row in rows:
        v = float(row[label])
        (e_paper, t_paper), (e_best, t_best) = stored[(paper_name, v)], stored[(name, v)]
        assert row["violation (best recipe) mean"] == fmt(e_best)
        assert row[f"{paired} mean"] == row[f"{paired} median"] == fmt(e_paper)
        assert row[f"violation mean: {paper_name} / this study"] == fmt(e_paper / e_best)
        assert row["fit s / cell"] == fmt(t_best)
        assert row[f"fit s / cell ({paper_name})"] == fmt(t_paper)
        assert row[f"fit s / cell: this study / {paper_name}"] == fmt(t_best / t_paper)
        for k, aset in enumerate(sets):
            authors = [r["violation_mean"] for r in aset["rows"]
                       if math.isclose(r["value"], v) and "violation_mean" in r]
            col = f"authors{f' {k + 1}' if len(sets) > 1 else ''} / this study: violation mean"
            assert row[col] == (fmt(authors[0] / e_best) if authors else "–")
    assert bool(sets) == ("| authors" in md)  # (a), (c) have the authors' means, (b) none
    assert "fit s / cell" not in (out / f"{paper_name}.md").read_text()  # no compare key
    # the compared study gone from the database: one line, no comparison columns
    alone = tmp_path / "alone"
    alone.mkdir()
    src, dst = sqlite3.connect(out / "studies.sqlite"), sqlite3.connect(alone / "studies.sqlite")
    src.backup(dst)
    src.close()
    dst.execute("DELETE FROM studies WHERE name = ?", (paper_name,))
    dst.commit()
    dst.close()
    report(alone)
    md = (alone / f"{name}.md").read_text()
    assert "paper recipe" not in md and "fit s / cell" not in md
    [line] = [line for line in md.splitlines() if f"`{paper_name}`" in line]
    assert line == (f"- Compared study `{paper_name}` (`compare`): not in this database; run "
                    "its config with the same `--out` to show it here.")


def test_recipe_best_runs_both_methods(tmp_path):
    path = _write(tmp_path, GOOD.replace('name = "t"', 'name = "best"') + 'recipe = "best"\n'
                  "[fit.best]\niterations = 20\nrefine_iterations = 1\nrefine_batch = 100\n")
    summary = run_config(path, out=tmp_path / "out", workers=2, progress=False)
    assert (summary.executed, summary.failed) == (summary.total, 0)
    conn = sqlite3.connect(tmp_path / "out" / "studies.sqlite")
    settings = {m: json.loads(s) for m, s in conn.execute("SELECT method, settings_json FROM cells")}
    conn.close()
    assert settings["violation"]["recipe"] == settings["prediction"]["recipe"] == "best"
    assert settings["violation"]["refine"] == "gauss-newton" and settings["prediction"]["refine"] is None
    assert settings["violation"]["lr_schedule"] == settings["prediction"]["lr_schedule"] == "cosine"


def test_ensembles_give_every_cell_its_own_result(tmp_path):
    """``ensemble=True`` trains a swept value's trials of one method together; every cell's
    e_test, curve (wall times aside) and settings are those of the cell run on its own, and a
    second run finds every cell finished."""
    path = tmp_path / "three_trials.toml"
    path.write_text(f'extends = "{CONFIGS / "fig1a_n_lam_smoke.toml"}"\nname = "three"\ntrials = 3\n')
    alone = run_config(path, out=tmp_path / "alone", workers=2, progress=False)
    together = run_config(path, out=tmp_path / "together", workers=2, progress=False, ensemble=True)
    assert (together.total, together.executed, together.failed) == (12, 12, 0)
    rows_alone, rows_together = _rows(tmp_path / "alone"), _rows(tmp_path / "together")
    assert [r["key"] for r in rows_alone] == [r["key"] for r in rows_together] and alone.failed == 0
    same = ("e_test", "final_loss", "modes", "sigma_min", "settings_json", "cell_json", "seed_fit")
    curves = []
    for out in ("alone", "together"):
        with Store(tmp_path / out) as store:
            curves.append([[{k: v for k, v in rec.items() if k != "wall_time"} for rec in store.curve(r["id"])]
                           for r in _rows(tmp_path / out)])
    for a, b, ca, cb in zip(rows_alone, rows_together, *curves, strict=True):
        assert all(a[f] == b[f] for f in same), a["key"]
        assert ca == cb and len(ca) == 2
    again = run_config(path, out=tmp_path / "together", workers=2, progress=False, ensemble=True)
    assert (again.skipped, again.executed) == (12, 0)


def test_ensembles_group_the_cells_that_differ_in_their_seeds_only():
    from lcs_cvx.study.batched_cells import ensembles

    config = load_config(CONFIGS / "fig1a_n_lam_smoke.toml")
    config["trials"] = 5
    cells = expand(config)
    jobs = ensembles(cells)
    assert len(jobs) == 4  # 2 values x 2 methods
    for job in jobs:
        assert len(job["cells"]) == 5 and {c["trial"] for c in job["cells"]} == set(range(5))
        assert len({(c["value"], c["method"]) for c in job["cells"]}) == 1
    # largest first: the larger n_lam's two ensembles, then the smaller's, each pair in config order
    values = sorted({c["value"] for c in cells}, reverse=True)
    methods = list(dict.fromkeys(c["method"] for c in cells))
    assert [(j["value"], j["method"]) for j in jobs] == [(v, m) for v in values for m in methods]
    assert sorted(len(j["cells"]) for j in ensembles(cells, size=2)) == [1] * 4 + [2] * 8
    assert [len(j["cells"]) for j in ensembles(cells, size=2)][:4] == [2, 2, 2, 2]
    assert sorted(c["key"] for j in jobs for c in j["cells"]) == sorted(c["key"] for c in cells)


def test_ensemble_work_orders_by_problem_size():
    from lcs_cvx.study.batched_cells import work

    cell = {"fit": {"iterations": 10, "batch_size": 20}, "system": {"n_x": 2, "n_u": 1, "n_lam": 3}}
    assert work([cell]) == 10 * 20 * 36 and work([cell, cell]) == 2 * work([cell])
    assert work([{"fit": None, "system": {}}]) == 1  # a baseline: every missing field counts 1


def test_ensemble_size_without_ensemble_is_refused(tmp_path):
    with pytest.raises(lcs_cvx.LCSInputError, match="ensemble_size.*ensemble=False"):
        run_config(CONFIGS / "fig1a_n_lam_smoke.toml", out=tmp_path, ensemble_size=2, progress=False)


def test_ensembles_leave_baselines_and_unsupported_options_to_run_alone():
    """A baseline cell, or a cell whose fit options the ensemble loop does not run (the best
    recipe's extra units and refinement), is a job of its own, run by ``run_cell``."""
    from lcs_cvx.study.batched_cells import alone, ensembles

    cells = expand(load_config(CONFIGS / "pwa_compare_smoke.toml"))
    jobs = ensembles(cells)
    for job in jobs:
        assert job["alone"] == (job["method"] not in ("violation", "prediction"))
        assert len(job["cells"]) == 1 or not job["alone"]
    assert {c["method"] for c in cells if alone(c)} == {m for m in {c["method"] for c in cells}
                                                         if m not in ("violation", "prediction")}
    assert sorted(c["key"] for j in jobs for c in j["cells"]) == sorted(c["key"] for c in cells)


def test_a_best_recipe_study_with_ensemble_gives_the_per_cell_results(tmp_path):
    one = run_config(CONFIGS / "fig1a_n_lam_best_smoke.toml", out=tmp_path / "one", workers=1,
                     progress=False)
    together = run_config(CONFIGS / "fig1a_n_lam_best_smoke.toml", out=tmp_path / "two", workers=1,
                          progress=False, ensemble=True)
    assert together.failed == one.failed == 0 and together.executed == one.executed > 0
    a, b = _rows(tmp_path / "one"), _rows(tmp_path / "two")
    assert [(r["key"], r["e_test"]) for r in a] == [(r["key"], r["e_test"]) for r in b]


#: Calls of :func:`run_study` below (a ``kind = "module"`` study runs in this process).
MODULE_CALLS: list[tuple] = []


def run_study(config: dict, out_dir: str, workers: int) -> None:
    MODULE_CALLS.append((config, out_dir, workers))


def test_module_kind_calls_the_modules_run_study(tmp_path, capsys):
    path = _write(tmp_path, 'name = "physics"\nkind = "module"\nmodule = "test_study"\n'
                  "n_steps = 7\n", "physics.toml")
    out = tmp_path / "out"
    assert main(["study", "run", str(path), "--workers", "3", "--out", str(out)]) == 0
    [(config, out_dir, workers)] = MODULE_CALLS
    assert (config["name"], config["n_steps"], out_dir, workers) == ("physics", 7, str(out), 3)
    bad = _write(tmp_path, 'name = "p"\nkind = "module"\nmodule = "no_such_module_x"\n', "m.toml")
    assert main(["study", "run", str(bad)]) == 2
    assert "module: cannot import 'no_such_module_x'" in capsys.readouterr().err



def test_module_kind_gets_the_scheduler_if_its_run_study_takes_one(tmp_path, capsys, monkeypatch):
    (tmp_path / "mod_with_scheduler.py").write_text(
        "CALLS = []\n"
        "def run_study(config, out_dir, workers, scheduler=None):\n"
        "    CALLS.append((config['name'], workers, scheduler))\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    path = _write(tmp_path, 'name = "m"\nkind = "module"\nmodule = "mod_with_scheduler"\n', "m.toml")
    argv = ["study", "run", str(path), "--workers", "2", "--out", str(tmp_path / "out")]
    assert main([*argv, "--scheduler", "tcp://127.0.0.1:1"]) == 0
    assert main(argv) == 0
    import mod_with_scheduler

    assert mod_with_scheduler.CALLS == [("m", 2, "tcp://127.0.0.1:1"), ("m", 2, None)]
    # a run_study without the keyword: refused, not silently run on local processes
    old = _write(tmp_path, 'name = "p"\nkind = "module"\nmodule = "test_study"\n', "p.toml")
    MODULE_CALLS.clear()
    assert main(["study", "run", str(old), "--scheduler", "local", "--out", str(tmp_path / "o2")]) == 2
    assert "takes no scheduler argument" in capsys.readouterr().err and MODULE_CALLS == []


def test_job_results_round_trip_exactly_through_the_store(tmp_path):
    g = np.random.default_rng(0)
    result = {"matrices": {"A": g.normal(size=(3, 3)), "F": np.eye(2, dtype=np.float32)},
              "mask": g.random(5) > 0.5, "ints": np.arange(4, dtype=np.int64).reshape(2, 2),
              "val_error": math.inf, "nan": math.nan, "third": 1 / 3, "scalar": np.float64(0.1),
              "settings": {"z": 1, "a": (0.9, 0.9), "recipe": None}, "history": [{"loss": 1e-300}]}
    with Store(tmp_path) as store:
        assert store.add_job("k1", "s", "fit_lcs", result) is True
        assert store.add_job("k1", "s", "fit_lcs", {"other": 1}) is False  # never written twice
        assert store.jobs(["k2"]) == {}
        with pytest.raises(TypeError, match=r"result: cannot store a value of type set"):
            store.add_job("k3", "s", "fit_lcs", {"bad": {1, 2}})
        assert store.jobs(["k3"]) == {}
    with Store(tmp_path) as store:  # reopened: what was committed
        back = store.jobs(["k1", "k2"])["k1"]
    for name, a in result["matrices"].items():
        assert back["matrices"][name].dtype == a.dtype and np.array_equal(back["matrices"][name], a)
    assert back["mask"].dtype == bool and np.array_equal(back["mask"], result["mask"])
    assert back["ints"].shape == (2, 2) and np.array_equal(back["ints"], result["ints"])
    assert back["val_error"] == math.inf and math.isnan(back["nan"]) and back["third"] == 1 / 3
    assert back["scalar"] == 0.1 and type(back["scalar"]) is float
    assert list(back["settings"]) == ["z", "a", "recipe"] and back["settings"]["a"] == [0.9, 0.9]
    assert back["history"] == [{"loss": 1e-300}]


def test_a_database_without_the_jobs_table_gains_it(tmp_path):
    with Store(tmp_path) as store:
        store.conn.execute("DROP TABLE jobs")
    with Store(tmp_path) as store:
        assert store.add_job("k", "s", "fit_mlp", {"x": 1}) and store.jobs(["k"]) == {"k": {"x": 1}}


def test_setup_cell_is_the_work_run_cell_measures():
    """setup_cell (what studies/train_budget.py times) draws the cell's truth, data and learner
    from its seeds: fitting them as run_cell does gives run_cell's e_test exactly."""
    cell = expand(load_config(CONFIGS / "fig1a_n_lam_smoke.toml"))[1]
    truth, train, test, learner, options = setup_cell(cell)
    s = cell["system"]
    assert (learner.n_x, learner.n_u, learner.n_lam) == (s["n_x"], s["n_u"], s["n_lam"])
    assert (len(train), len(test)) == (cell["data"]["n_train"], cell["data"]["n_test"])
    assert float(test.x.abs().max()) <= cell["data"]["x_scale"]
    result = lcs_cvx.fit(learner, train, test=test, recipe=cell["recipe"], progress=False,
                         seed=cell["seeds"]["fit"], **options)
    ran = run_cell(cell)
    assert lcs_cvx.relative_error(result.model, test) == ran["e_test"]
    assert truth.sigma_min == ran["sigma_min"]


def test_a_recipe_past_version_1_is_in_its_cells_keys_and_checked_when_run():
    """A cell trained under an earlier version of its recipe is never taken for a current one:
    the version is part of the key of a recipe past version 1 (paper-recipe keys unchanged), and
    a cell made for another version is refused by name."""
    from lcs_cvx.train.recipes import RECIPE_VERSIONS

    config = load_config(CONFIGS / "fig1a_n_lam_best_smoke.toml")
    cells = expand(config)
    assert {c["recipe"] for c in cells} == {"best"}
    assert all(c["recipe_version"] == RECIPE_VERSIONS["best"] > 1 for c in cells)
    paper = expand(load_config(CONFIGS / "fig1a_n_lam_smoke.toml"))
    assert not any("recipe_version" in c for c in paper)
    old = {k: v for k, v in cells[0].items() if k not in ("recipe_version", "key")}
    from lcs_cvx.study.cells import cell_key

    assert cell_key(old) != cells[0]["key"]
    stale = {**cells[0], "recipe_version": 1}
    with pytest.raises(lcs_cvx.LCSInputError, match="recipe_version: .*version 1 of recipe 'best'"):
        run_cell(stale)
