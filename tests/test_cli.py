"""The command-line interface: `lcs-cvx demo` prints checked facts, bad arguments exit 2."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch

import lcs_cvx
from lcs_cvx.cli import COMMANDS, build_parser, main


def _facts(out: str) -> dict[str, str]:
    """``"key: value"`` lines of the demo's output as a dict."""
    return dict(line.split(": ", 1) for line in out.strip().splitlines())


def _leading_float(text: str) -> float:
    return float(text.split()[0].rstrip("x"))


def test_demo_prints_checked_facts(capsys):
    threads = torch.get_num_threads()
    learn = ["--learn-n", "1000", "--learn-iterations", "300"]
    assert main(["demo", "--n", "2000", "--n-lam", "4", *learn]) == 0
    assert torch.get_num_threads() == threads  # restored after the run
    facts = _facts(capsys.readouterr().out)

    assert facts["LCS"].startswith("n_x=10, n_u=4, n_lam=4 ")
    system = lcs_cvx.random_lcs(10, 4, 4, stiffness=0.5, seed=0)
    assert _leading_float(facts["sigma_min(F+F^T)"]) == pytest.approx(system.sigma_min, rel=1e-5)
    assert facts["data"].startswith("2000 samples, noise 0.01 ")

    data = lcs_cvx.make_dataset(system, 2000, noise=0.01, seed=0)
    modes = int(facts["hybrid modes"].split()[0])
    assert modes == lcs_cvx.count_modes(system, data)
    assert 1 <= modes <= 2**4

    assert _leading_float(facts["fast LCP"]) > 0
    assert "1 thread," in facts["fast LCP"]
    assert _leading_float(facts["max LCP residual"]) < 1e-12
    assert facts["fallbacks"] == "0"
    assert _leading_float(facts["Clarabel"]) > 0
    assert "over 20 random samples" in facts["max |lam_fast - lam_clarabel|"]
    assert _leading_float(facts["max |lam_fast - lam_clarabel|"]) < 1e-8
    assert _leading_float(facts["speed-up"]) > 0

    # the learning part: both losses from the same start, e_test well below the start's
    assert facts["learning"].startswith("a random LCS n_x=10, n_u=4, n_lam=4 (")
    start = lcs_cvx.LCS(10, 4, 4, stiffness=1.0, seed=4)
    test = lcs_cvx.make_dataset(lcs_cvx.random_lcs(10, 4, 4, stiffness=0.5, seed=1), 1000, seed=3)
    e_start = lcs_cvx.relative_error(start, test)
    for loss in ("violation", "prediction"):
        e = float(facts[f"  {loss:<10s} loss"].split()[1])
        assert 0 < e < 0.1 * e_start, (loss, e, e_start)


def test_demo_threads_option(capsys):
    assert main(["demo", "--n", "50", "--n-lam", "2", "--threads", "2", "--learn-n-lam", "0"]) == 0
    assert "2 threads," in _facts(capsys.readouterr().out)["fast LCP"]


@pytest.mark.parametrize(
    ("argv", "named"),
    [
        (["demo", "--n-lam", "0"], "--n-lam"),
        (["demo", "--n-x", "0"], "--n-x"),
        (["demo", "--n-lam", "2", "--n", "0"], "--n"),
        (["demo", "--stiffness", "-1"], "--stiffness"),
        (["demo", "--threads", "0"], "--threads"),
        (["demo", "--seed", "-1"], "--seed"),
        (["demo", "--n-lam", "four"], "--n-lam"),
    ],
)
def test_bad_argument_exits_2_naming_it(capsys, argv, named):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    message = err.strip().splitlines()[-1]
    assert message.startswith("lcs-cvx demo: error: ")
    assert named in message


def test_demo_fails_when_the_check_fails(capsys, monkeypatch):
    monkeypatch.setattr("lcs_cvx.cli.demo.CHECK_TOL", -1.0)  # no difference can pass
    assert main(["demo", "--n", "50", "--n-lam", "2", "--learn-n-lam", "0"]) == 1
    assert "check failed" in capsys.readouterr().err


def test_no_command_exits_2(capsys):
    assert main([]) == 2
    assert "required" in capsys.readouterr().err


def test_every_command_is_registered():
    parser = build_parser()
    for cmd in COMMANDS:
        args = parser.parse_args([cmd.name])
        assert args.run is cmd.run


def _entry_point() -> list[str]:
    script = Path(sys.executable).with_name("lcs-cvx")
    return [str(script)] if script.exists() else [sys.executable, "-m", "lcs_cvx.cli"]


@pytest.mark.parametrize("entry", ["script", "module"])
def test_installed_entry_points(entry):
    cmd = _entry_point() if entry == "script" else [sys.executable, "-m", "lcs_cvx.cli"]
    small = ["demo", "--n", "300", "--n-x", "3", "--n-u", "2", "--n-lam", "3", "--learn-n-lam", "0"]
    # no timeout of its own: a hung command is ended by pytest-timeout
    ok = subprocess.run(cmd + small, capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    assert _facts(ok.stdout)["LCS"].startswith("n_x=3, n_u=2, n_lam=3 ")

    bad = subprocess.run(cmd + ["demo", "--n-lam", "0"], capture_output=True, text=True)
    assert bad.returncode == 2
    assert bad.stdout == ""
    assert (
        bad.stderr.strip() == "lcs-cvx demo: error: --n-lam: expected an integer >= 1, received 0"
    )
