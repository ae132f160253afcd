"""A study reported beside another study of the same database (config key ``compare = NAME``).

A study whose config has ``compare = NAME`` is reported beside the study of that name in the same
database (the latest one, if several have it): per swept value its table adds the compared
study's mean and median e_test for each of this study's losses (its methods of the same loss:
``"violation"`` under its own recipe), the ratios "compared mean / this study's mean" and, where
the anchors have the loss's means, "authors' mean / this study's mean", and the mean fit wall
time per cell (``fit_wall_time``) of both and its ratio; its notes say whether the paired cells
(same value and trial) drew the same truth, data and start; its figure draws the compared boxes
beside this study's. A compared study missing from the database is said in one line of the notes.
"""

from __future__ import annotations

import math
import statistics
from typing import Any

from ._stats import anchor, e_tests, fmt, stat
from .cells import expand
from .config import method_parts

__all__ = ["comparison", "compare_columns", "described", "value_index"]


def value_index(values: list[Any], value: Any) -> int | None:
    for j, v in enumerate(values):
        if math.isclose(float(v), float(value), rel_tol=1e-9):
            return j
    return None


def _same_draws(this: dict[str, Any], other: dict[str, Any],
                pairs: list[tuple[str, str]]) -> str:
    """Whether each cell of ``this`` config and the cell of ``other`` with the same swept value,
    trial and paired method draw the same truth, data and start (seeds, system, data, learner)."""
    partners: dict[str, list[str]] = {}
    for m, m2 in pairs:
        partners.setdefault(m, []).append(m2)
    theirs = {(float(c["value"]), c["trial"], c["method"]): c
              for c in expand(other) if c["value"] is not None}
    n, differ = 0, []
    for c in expand(this):
        for m2 in partners.get(c["method"], []) if c["value"] is not None else []:
            o = theirs.get((float(c["value"]), c["trial"], m2))
            if o is None:
                continue
            n += 1
            if any(c[k] != o[k] for k in ("seeds", "system", "data", "learner")):
                differ.append(c)
    if not n:
        return "no paired cells (no common swept value and trial)"
    if not differ:
        return f"yes, in all {n} paired cells (same seeds, system, data and learner)"
    c = differ[0]
    return (f"no: {len(differ)} of {n} paired cells differ (e.g. {c['value']:g}, trial "
            f"{c['trial']}: seeds, system, data or learner)")


def comparison(summary: dict[str, Any], summaries: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The study named by ``summary``'s ``compare`` among ``summaries`` (the latest of that name)
    and the pairs (this study's method, its method of the same loss); None without ``compare``.
    ``{"name", "summary": None}`` when no study of that name is there."""
    config = summary["study"]["config"]
    name = config.get("compare")
    if name is None:
        return None
    found = [s for s in summaries if s["study"]["name"] == name]
    if not found:
        return {"name": name, "summary": None}
    other = found[-1]
    oconfig = other["study"]["config"]
    pairs, unpaired = [], []
    for m in config["methods"]:
        loss = method_parts(m, config["recipe"])[0]
        same = [m2 for m2 in oconfig["methods"] if method_parts(m2, oconfig["recipe"])[0] == loss]
        pairs += [(m, m2) for m2 in same]
        if not same:
            unpaired.append(m)
    return {"name": name, "summary": other, "n_same_name": len(found), "pairs": pairs,
            "unpaired": unpaired, "draws": _same_draws(config, oconfig, pairs)}


def described(method: str, recipe: str, study: str | None = None) -> str:
    """``"violation (paper recipe, fig1a_n_lam)"``; a baseline keeps its name."""
    loss, own = method_parts(method, recipe)
    inside = ", ".join(x for x in ((f"{own} recipe" if own else None), study) if x)
    return f"{loss} ({inside})" if inside else loss


def _fit_time(rows: list[dict[str, Any]]) -> float | None:
    return stat([r["fit_wall_time"] for r in rows if r.get("fit_wall_time") is not None],
                 statistics.fmean)


def _ratio(a: Any, b: Any) -> float | None:
    return a / b if a is not None and b is not None and b > 0 else None


def compare_columns(summary: dict[str, Any], compared: dict[str, Any],
                     sets: list[dict[str, Any]]) -> tuple[list[str], list[list[str]], list[str]]:
    """The comparison's header, its cells per swept value and its notes."""
    config = summary["study"]["config"]
    other = compared["summary"]
    oconfig, oname = other["study"]["config"], compared["name"]
    pairs = compared["pairs"]
    ours_m = list(dict.fromkeys(m for m, _ in pairs))
    theirs_m = list(dict.fromkeys(m2 for _, m2 in pairs))
    loss = {m: method_parts(m, config["recipe"])[0] for m in config["methods"]}
    # a method is named by its loss, unless two of this study's methods share it
    tag = {m: (loss[m] if list(loss.values()).count(loss[m]) == 1 else m) for m in loss}
    named = {m2: described(m2, oconfig["recipe"], oname) for m2 in theirs_m}
    anchored = [(k, s, m) for m in config["methods"] for k, s in enumerate(sets)
                if any(f"{loss[m]}_mean" in r for r in s["rows"])]
    head = [f"{named[m2]} {name}" for m2 in theirs_m for name in ("mean", "median")]
    head += [f"{tag[m]} mean: {oname}{'' if len(theirs_m) == 1 else ' ' + m2} / this study"
             for m, m2 in pairs]
    head += [f"authors{' ' + str(k + 1) if len(sets) > 1 else ''} / this study: {tag[m]} mean"
             for k, _, m in anchored]
    head += ["fit s / cell", f"fit s / cell ({oname})", f"fit s / cell: this study / {oname}"]
    rows = []
    for i, v in enumerate(summary["values"]):
        j = value_index(other["values"], v)
        theirs = {m2: e_tests(other["per"][(j, m2)]) if j is not None else [] for m2 in theirs_m}
        mean = {m: stat(e_tests(summary["per"][(i, m)]), statistics.fmean) for m in config["methods"]}
        cells = [fmt(stat(theirs[m2], f)) for m2 in theirs_m
                 for f in (statistics.fmean, statistics.median)]
        cells += [fmt(_ratio(stat(theirs[m2], statistics.fmean), mean[m])) for m, m2 in pairs]
        cells += [fmt(_ratio(anchor(s, v, f"{loss[m]}_mean"), mean[m])) for _, s, m in anchored]
        mine = _fit_time([r for m in ours_m for r in summary["per"][(i, m)]])
        fits = (_fit_time([r for m2 in theirs_m for r in other["per"][(j, m2)]])
                if j is not None else None)
        cells += [fmt(mine), fmt(fits), fmt(_ratio(mine, fits))]
        rows.append(cells)
    study = other["study"]
    methods = ", ".join(f"`{m2}`" for m2 in theirs_m) or "no"
    done = sum(len(other["per"][(j, m2)]) for m2 in theirs_m for j in range(len(other["values"])))
    several = (f" (the latest of {compared['n_same_name']} studies of that name)"
               if compared["n_same_name"] > 1 else "")
    notes = [f"- Compared with `{oname}`{several}: config `{study['path']}` (hash "
             f"`{study['config_hash']}`), recipe `{oconfig['recipe']}`; its {methods} cells, "
             f"{done} finished. Same truth, data and start per swept value and trial: "
             f"{compared['draws']}.",
             "- `fit s / cell`: mean `fit_wall_time` (seconds in the fit) of each study's compared "
             "cells; wall times are comparable only when both studies ran under the same load. "
             "The ratios divide means: an e_test ratio `… / this study` above 1 means this "
             "study's mean e_test is lower, a fit time ratio `this study / …` below 1 that its "
             "fits are faster."]
    notes += [f"- `{oname}` has no method with the loss of `{m}`: no comparison columns for it."
              for m in compared["unpaired"]]
    return head, rows, notes
