"""Choosing n_lam (:mod:`lcs_cvx.selection`): the parsimony rule on hand-made tables, one real
selection on a small system (its table recomputed), the plumbing to ``fit`` with a stand-in
trainer, and bad input named."""

from __future__ import annotations

import math
import sys

import pytest
import torch

import lcs_cvx
from lcs_cvx import (
    LCS,
    Dataset,
    LCSInputError,
    make_dataset,
    random_lcs,
    relative_error,
    select_n_lam,
)
from lcs_cvx.selection import Selection, choose

# -- the rule -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("errors", "tolerance", "chosen"),
    [
        ({1: 0.30, 2: 0.0104, 4: 0.0100, 8: 0.0101}, 0.1, 2),  # 2 is within 10 % of 4's
        ({1: 0.30, 2: 0.0104, 4: 0.0100, 8: 0.0101}, 0.0, 4),  # tolerance 0: the arg-min
        ({1: 0.30, 2: 0.0104, 4: 0.0100, 8: 0.0101}, 0.03, 4),  # 0.0104 > 1.03 * 0.0100
        ({1: 0.30, 2: 0.0104, 4: 0.0100, 8: 0.0101}, 0.04, 2),  # the bound itself counts
        ({8: 0.5, 4: 0.5, 2: 0.5}, 0.0, 2),  # a tie goes to the smaller n_lam, in any order
        ({3: 0.2, 1: 0.2}, 0.0, 1),
        ({1: 0.0, 2: 0.0}, 0.1, 1),  # exact fits (noiseless data): the smallest
        ({1: 2e-11, 2: 8e-11, 3: 7e-13}, 0.1, 1),  # exact but for round-off (EXACT_ERROR): the smallest
        ({1: 2e-11, 2: 8e-11, 3: 7e-13}, 0.0, 1),
        ({1: 2e-9, 2: 1e-9, 3: 1e-12}, 0.1, 2),  # above EXACT_ERROR the ratio decides
        ({1: 0.9, 2: 0.01}, 100.0, 1),  # a huge tolerance: always the smallest
        ({5: 0.1}, 0.1, 5),
        ({1: math.nan, 2: 0.5, 4: math.inf}, 0.1, 2),  # diverged runs are never chosen
    ],
)
def test_choose(errors, tolerance, chosen):
    assert choose(errors, tolerance) == chosen


@pytest.mark.parametrize(
    ("errors", "tolerance", "says"),
    [
        ({}, 0.1, r"errors: expected a non-empty mapping"),
        ([0.1, 0.2], 0.1, r"errors: expected a non-empty mapping"),
        ({0: 0.1}, 0.1, r"errors: expected integers >= 1 as n_lam, received \[0\]"),
        ({1.5: 0.1}, 0.1, r"errors: expected integers >= 1 as n_lam, received \[1.5\]"),
        ({1: -0.1}, 0.1, r"errors: expected errors >= 0, received -0.1 for n_lam=1"),
        ({1: "a"}, 0.1, r"errors: expected numbers as errors"),
        ({1: math.nan}, 0.1, r"errors: expected at least one finite error"),
        ({1: 0.1}, -0.01, r"tolerance: expected a finite number >= 0, received -0.01"),
        ({1: 0.1}, math.inf, r"tolerance: expected a finite number >= 0, received inf"),
        ({1: 0.1}, True, r"tolerance: expected a finite number >= 0, received True"),
    ],
)
def test_choose_refuses(errors, tolerance, says):
    with pytest.raises(LCSInputError, match=says):
        choose(errors, tolerance)


# -- a real selection ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def data() -> Dataset:
    return make_dataset(random_lcs(2, 1, 2, seed=0), 1000, noise=1e-2, seed=1)


@pytest.fixture(scope="module")
def selection(data) -> Selection:
    return select_n_lam(data, [3, 1, 2], optimizer="gauss-newton", iterations=30, progress=False)


def test_select_on_a_small_system(data, selection):
    sel = selection
    assert [row["n_lam"] for row in sel.table] == [1, 2, 3]  # by increasing n_lam
    assert all(set(row) == {"n_lam", "validation_error", "train_error", "wall_time", "grows_more"} for row in sel.table)
    assert sorted(sel.results) == [1, 2, 3]
    assert all(sel.results[n].model.n_lam == n for n in (1, 2, 3))
    assert all(sel.results[n].settings.run.seed == 0 and sel.results[n].settings.flat()["iterations"] == 30
               for n in (1, 2, 3))

    # the split select_n_lam documents; every error recomputed from the candidates' models
    part, held = data.split(0.8, seed=0)
    for row in sel.table:
        model = sel.results[row["n_lam"]].model
        assert row["validation_error"] == relative_error(model, held)
        assert row["train_error"] == relative_error(model, part)
        assert 0 < row["wall_time"] < 60
    errors = {row["n_lam"]: row["validation_error"] for row in sel.table}
    assert sel.n_lam == choose(errors, 0.1)
    assert sel.model is sel.results[sel.n_lam].model
    assert relative_error(sel.model, held) == errors[sel.n_lam]  # measured, not assumed
    assert sel.refit is None
    # one unit cannot hold the two of the truth; two fit to the noise floor, three no better
    assert errors[1] > 10 * min(errors.values())
    assert errors[2] < 1e-5 and sel.n_lam == 2


def test_summary_prints_the_table(selection):
    text = str(selection)
    assert text == selection.summary()
    lines = text.splitlines()
    assert lines[0].split() == ["n_lam", "validation", "error", "train", "error", "wall", "time"]
    for line, row in zip(lines[1:4], selection.table, strict=True):
        fields = line.replace("*", " ").split()
        assert int(fields[0]) == row["n_lam"]
        assert float(fields[1]) == pytest.approx(row["validation_error"], rel=1e-4)
        assert float(fields[2]) == pytest.approx(row["train_error"], rel=1e-4)
        assert ("*" in line) == (row["n_lam"] == selection.n_lam)
    assert lines[4].startswith(f"chosen n_lam={selection.n_lam}: the smallest within 10% ")
    assert lines[4].endswith("held-out 20% of train)")


# -- the plumbing, with a stand-in trainer ---------------------------------------------------


class _FakeFit:
    """Records its calls; "learns" nothing. Returns a result holding the model."""

    def __init__(self):
        self.calls = []

    def __call__(self, model, train, **kwargs):
        self.calls.append((model, train, kwargs))

        class Result:
            pass

        r = Result()
        r.model = model
        return r


@pytest.fixture
def fake_fit(monkeypatch):
    fake = _FakeFit()
    monkeypatch.setattr(lcs_cvx.selection, "fit", fake)
    return fake


def test_validation_set_make_model_and_options_are_passed(data, fake_fit):
    valid = make_dataset(random_lcs(2, 1, 2, seed=0), 50, seed=7)
    made = []

    def make_model(n):
        made.append(n)
        model = LCS(2, 1, n, stiffness=0.25, seed=10 + n)
        model.d.requires_grad_(False)  # a fixed parameter (known structure)
        return model

    options = lcs_cvx.RECIPES["best"]
    sel = select_n_lam(data, (4, 2), valid, make_model=make_model, seed=3, progress=False,
                       options=options, iterations=9, test=valid)
    assert made == [2, 4]
    assert [c[0].n_lam for c in fake_fit.calls] == [2, 4]
    for model, train, kwargs in fake_fit.calls:
        assert train is data  # the whole training set: the validation set is separate
        assert kwargs == {"progress": False, "seed": 3, "options": options, "iterations": 9, "test": valid}
        assert float(model.stiffness) == 0.25 and not model.d.requires_grad
    for row in sel.table:
        assert row["validation_error"] == relative_error(sel.results[row["n_lam"]].model, valid)
    assert sel.validation == "validation set"


def test_default_models_and_refit(data, fake_fit):
    sel = select_n_lam(data, [1, 2], holdout=0.25, tolerance=1e9, stiffness=0.75, seed=5,
                       refit=True, progress=False)
    (m1, p1, _), (m2, p2, _), (m3, p3, kw) = fake_fit.calls
    part, _ = data.split(0.75, seed=5)
    assert torch.equal(p1.x, part.x) and p2 is p1 and len(p1) == 750
    for m in (m1, m2):
        fresh = LCS(2, 1, m.n_lam, stiffness=0.75, seed=5)
        assert all(torch.equal(v, fresh.state_dict()[k]) for k, v in m.state_dict().items())
    assert sel.n_lam == 1  # the huge tolerance: the smallest
    assert p3 is data and m3.n_lam == 1 and m3 is not m1 and kw["seed"] == 5  # the refit
    assert sel.model is m3 and sel.results[1].model is m1 and sel.refit.model is m3
    assert sel.summary().endswith("; refit on all of train")


def test_progress_lines_on_a_terminal(data, fake_fit, monkeypatch, capsys):
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    select_n_lam(data, [1, 2], progress=True)
    err = capsys.readouterr().err.splitlines()
    assert [line.split(":")[0] for line in err] == ["select_n_lam", "select_n_lam"]
    assert err[0].startswith("select_n_lam: n_lam=1 (1/2): validation error ")
    select_n_lam(data, [1, 2], progress=False)
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize(
    ("kwargs", "says"),
    [
        ({"candidates": []}, r"candidates: expected at least one n_lam, received none"),
        ({"candidates": [0, 2]}, r"candidates: expected integers >= 1 as n_lam, received \[0\]"),
        ({"candidates": [1, 2.0]}, r"candidates: expected integers >= 1 as n_lam, received \[2.0\]"),
        ({"candidates": [True]}, r"candidates: expected integers >= 1 as n_lam, received \[True\]"),
        ({"candidates": "124"}, r"candidates: expected a list of integers >= 1"),
        ({"candidates": 4}, r"candidates: expected a list of integers >= 1"),
        ({"candidates": [2, 1, 2]}, r"candidates: expected distinct n_lam, received \[2\] more than once"),
        ({"validation": "v"}, r"validation: expected an lcs_cvx.Dataset \(as train, or None\), received str"),
        ({"validation": "n_u"}, r"validation: expected n_x=2, n_u=1 \(train's\), received n_x=2, n_u=2"),
        ({"validation": "empty"}, r"validation: expected at least one sample"),
        ({"holdout": 0.0}, r"holdout: expected a fraction in \(0, 1\), received 0.0"),
        ({"holdout": 1}, r"holdout: expected a fraction in \(0, 1\), received 1"),
        ({"tolerance": -0.5}, r"tolerance: expected a finite number >= 0, received -0.5"),
        ({"make_model": lambda n: LCS(2, 1, n + 1)}, r"make_model: expected an lcs_cvx.LCS with n_x=2, n_u=1, n_lam=1 for n_lam=1, received n_x=2, n_u=1, n_lam=2"),
        ({"make_model": lambda n: None}, r"make_model: expected an lcs_cvx.LCS .* received NoneType"),
        ({"checkpoint": "run.ckpt"}, r"checkpoint: expected none in select_n_lam"),
        ({"refit": True, "validation": "ok"}, r"refit: expected False with a validation set"),
        ({"train": "tiny"}, r"train: expected enough samples to hold 0.2 of them out, received 2"),
        ({"train": [1]}, r"train: expected an lcs_cvx.Dataset or lcs_cvx.Trajectories, received list"),
    ],
)
def test_bad_input_is_named(data, fake_fit, kwargs, says):
    args = {"train": data, "candidates": [1, 2]}
    args.update(kwargs)
    other = {"v": "v", "n_u": make_dataset(random_lcs(2, 2, 1), 10), "empty": data[:0], "ok": data[:10]}
    if isinstance(args.get("validation"), str):
        args["validation"] = other[args["validation"]]
    if isinstance(args["train"], str):
        args["train"] = data[:2]
    with pytest.raises(LCSInputError, match=says):
        select_n_lam(args.pop("train"), args.pop("candidates"), progress=False, **args)
    assert fake_fit.calls == []  # refused before any training
