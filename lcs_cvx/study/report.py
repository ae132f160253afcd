"""``lcs-cvx study report DIR``: the paper-style figure and table of every study in a database.

For each study (each config hash) in ``DIR/studies.sqlite`` it writes ``DIR/<name>.png``,
``DIR/<name>.pdf`` -- e_test per swept value as box plots (prediction vs violation, log e_test
axis, log x axis where the values span decades; means as white markers; a reference method as a
horizontal line at its median; the authors' published means as crosses), the layout of Fig. 1 --
and ``DIR/<name>.md``: per swept value the hybrid modes of the data (mean), sigma_min(F + F^T) of
the truth (mean), mean and median e_test of each method and, where ``studies/anchors.toml`` has
them for the study's panel and swept parameter, the authors' numbers beside ours. Cells killed at
the config's time limit, and baseline cells whose own fit failed (``status = "failed"``, e.g.
PARC at thousands of modes), have no e_test: they are left out of the statistics and counted in
a line of the table's notes each (the failed ones with their distinct error messages).

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

import json
import math
import os
import statistics
from pathlib import Path
from typing import Any

from .._checks import LCSInputError
from .cells import REFERENCE, expand
from .config import method_parts, read_toml
from .store import Store

__all__ = ["report", "load_anchors", "summarize", "comparison", "default_anchors_path",
           "failed_cells", "short_error"]

#: The swept values span "decades" (log x axis) when max / min reaches this.
LOG_X_RATIO = 30.0
_COLORS = {"prediction": "tab:blue", "violation": "tab:orange", "violation@best": "tab:red",
           "prediction@best": "tab:cyan", "parc": "tab:green", "mlp": "tab:purple",
           "affine": "tab:gray"}
#: Colours of a compared study's boxes whose method colour this study already uses.
_SPARE_COLORS = ("tab:brown", "tab:olive", "tab:pink", "tab:cyan")


def default_anchors_path() -> str | None:
    """``studies/anchors.toml`` of the working directory, else of this source checkout."""
    for base in (Path.cwd(), Path(__file__).resolve().parents[2]):
        p = base / "studies" / "anchors.toml"
        if p.is_file():
            return str(p)
    return None


def load_anchors(path: str | None) -> dict[str, Any]:
    """``{panel: {"param": ..., "sets": [{"label", "note", "rows": [{value, ...}]}]}}``."""
    if path is None:
        return {}
    data = read_toml(path, "anchors file not found")
    for panel, entry in data.items():
        if not isinstance(entry, dict) or "param" not in entry or not isinstance(entry.get("sets"), list):
            raise LCSInputError(f"{path}: {panel}: expected a table with 'param' and [[{panel}.sets]]")
        for s in entry["sets"]:
            if "label" not in s or not isinstance(s.get("rows"), list):
                raise LCSInputError(f"{path}: {panel}.sets: expected 'label' and 'rows' in each set")
    return data


def _anchor_sets(study: dict[str, Any], anchors: dict[str, Any]) -> list[dict[str, Any]]:
    entry = anchors.get(study["config"].get("panel") or "", {})
    return entry.get("sets", []) if entry.get("param") == study["config"]["sweep"]["param"] else []


def _anchor(aset: dict[str, Any], value: float, metric: str) -> Any:
    for row in aset["rows"]:
        if math.isclose(float(row["value"]), float(value), rel_tol=1e-9) and metric in row:
            return row[metric]
    return None


def summarize(store: Store, study: dict[str, Any]) -> dict[str, Any]:
    """Finished cells of ``study`` grouped by swept value and method (report's input); its
    ``failures`` are the logged failures of cells not stored since (still to retry)."""
    config = study["config"]
    cells = expand(config)
    found = store.cells([c["key"] for c in cells])
    values = config["sweep"]["values"]
    per = {(i, m): [] for i in [REFERENCE, *range(len(values))]
           for m in config["methods"] + config["reference_methods"]}
    for c in cells:
        row = found.get(c["key"])
        if row is not None:
            per[(c["value_index"], c["method"])].append(row)
    return {"study": study, "values": values, "per": per, "n_cells": len(cells),
            "n_done": len(found),
            "failures": [f for f in store.failures(study["config_hash"]) if f["key"] not in found],
            "cell_time": sum(r["wall_time"] for r in found.values())}


def _e(rows: list[dict[str, Any]]) -> list[float]:
    return [r["e_test"] for r in rows if r["e_test"] is not None]


def _fmt(v: Any) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    return f"{v:.3g}" if isinstance(v, float) else str(v)


def _stat(xs: list[float], f) -> float | None:
    return f(xs) if xs else None


def short_error(text: str, width: int = 100) -> str:
    """A failure's message on one line, cut to ``width`` characters (``…`` marks a cut)."""
    line = " ".join(str(text).split())
    return line if len(line) <= width else line[: width - 1].rstrip() + "…"


def failed_cells(rows: list[dict[str, Any]]) -> tuple[int, list[str]]:
    """How many of ``rows`` (stored cells) have ``status = "failed"``, and their distinct
    shortened error messages (``settings_json["error"]``), in order of appearance."""
    failed = [r for r in rows if r.get("status") == "failed"]
    errors = [short_error(json.loads(r.get("settings_json") or "{}").get("error", "no message"))
              for r in failed]
    return len(failed), list(dict.fromkeys(errors))


def _colour_key(method: str, recipe: str) -> str:
    """The key of :data:`_COLORS` of a method under ``recipe``: ``"violation"`` under "best" is
    drawn as ``"violation@best"``."""
    loss, own = method_parts(method, recipe)
    return method if own in (None, "paper") or method != loss else f"{loss}@{own}"


def _value_index(values: list[Any], value: Any) -> int | None:
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


def _described(method: str, recipe: str, study: str | None = None) -> str:
    """``"violation (paper recipe, fig1a_n_lam)"``; a baseline keeps its name."""
    loss, own = method_parts(method, recipe)
    inside = ", ".join(x for x in ((f"{own} recipe" if own else None), study) if x)
    return f"{loss} ({inside})" if inside else loss


def _fit_time(rows: list[dict[str, Any]]) -> float | None:
    return _stat([r["fit_wall_time"] for r in rows if r.get("fit_wall_time") is not None],
                 statistics.fmean)


def _ratio(a: Any, b: Any) -> float | None:
    return a / b if a is not None and b is not None and b > 0 else None


def _compare_columns(summary: dict[str, Any], compared: dict[str, Any],
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
    described = {m2: _described(m2, oconfig["recipe"], oname) for m2 in theirs_m}
    anchored = [(k, s, m) for m in config["methods"] for k, s in enumerate(sets)
                if any(f"{loss[m]}_mean" in r for r in s["rows"])]
    head = [f"{described[m2]} {stat}" for m2 in theirs_m for stat in ("mean", "median")]
    head += [f"{tag[m]} mean: {oname}{'' if len(theirs_m) == 1 else ' ' + m2} / this study"
             for m, m2 in pairs]
    head += [f"authors{' ' + str(k + 1) if len(sets) > 1 else ''} / this study: {tag[m]} mean"
             for k, _, m in anchored]
    head += ["fit s / cell", f"fit s / cell ({oname})", f"fit s / cell: this study / {oname}"]
    rows = []
    for i, v in enumerate(summary["values"]):
        j = _value_index(other["values"], v)
        theirs = {m2: _e(other["per"][(j, m2)]) if j is not None else [] for m2 in theirs_m}
        mean = {m: _stat(_e(summary["per"][(i, m)]), statistics.fmean) for m in config["methods"]}
        cells = [_fmt(_stat(theirs[m2], f)) for m2 in theirs_m
                 for f in (statistics.fmean, statistics.median)]
        cells += [_fmt(_ratio(_stat(theirs[m2], statistics.fmean), mean[m])) for m, m2 in pairs]
        cells += [_fmt(_ratio(_anchor(s, v, f"{loss[m]}_mean"), mean[m])) for _, s, m in anchored]
        mine = _fit_time([r for m in ours_m for r in summary["per"][(i, m)]])
        fits = (_fit_time([r for m2 in theirs_m for r in other["per"][(j, m2)]])
                if j is not None else None)
        cells += [_fmt(mine), _fmt(fits), _fmt(_ratio(mine, fits))]
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


def markdown(summary: dict[str, Any], anchors: dict[str, Any],
             compared: dict[str, Any] | None = None) -> str:
    """The study's markdown table and notes; ``compared``: :func:`comparison`'s result."""
    study = summary["study"]
    config = study["config"]
    label = config["sweep"]["label"]
    methods, refs = config["methods"], config["reference_methods"]
    sets = _anchor_sets(study, anchors)
    head = [label, "cells", "modes (mean)", "σ_min(F+Fᵀ) (mean)"]
    for m in methods:
        d = _described(m, config["recipe"]) if compared is not None else m
        head += [f"{d} mean", f"{d} median"]
    anchor_cols = [(k, s, metric) for k, s in enumerate(sets)
                   for metric in ("prediction_mean", "violation_mean", "modes")
                   if any(metric in r for r in s["rows"])]
    head += [f"authors{' ' + str(k + 1) if len(sets) > 1 else ''}: {metric.replace('_', ' ')}"
             for k, _, metric in anchor_cols]
    extra_rows: list[list[str]] = [[] for _ in summary["values"]]
    compare_notes = []
    if compared is not None and compared["summary"] is None:
        compare_notes.append(f"- Compared study `{compared['name']}` (`compare`): not in this "
                             "database; run its config with the same `--out` to show it here.")
    elif compared is not None:
        extra_head, extra_rows, compare_notes = _compare_columns(summary, compared, sets)
        head += extra_head
    lines = [f"# {config['name']}" + (f" — Fig. 1({config['panel']})" if config.get("panel") else ""),
             "",
             f"config `{study['path']}` (hash `{study['config_hash']}`), recipe `{config['recipe']}`, "
             f"convention `{config['convention']}`, trials: {config['trials']}; "
             f"{summary['n_done']}/{summary['n_cells']} cells finished, "
             f"{summary['cell_time']:.1f} s of cell wall time.",
             ""]
    if config.get("description"):
        lines += [config["description"].strip(), ""]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, v in enumerate(summary["values"]):
        rows = [r for m in methods for r in summary["per"][(i, m)]]
        expected = config["trials"] * len(methods)
        cells = [_fmt(v), f"{len(rows)}/{expected}",
                 _fmt(_stat([float(r["modes"]) for r in rows], statistics.fmean)),
                 _fmt(_stat([r["sigma_min"] for r in rows], statistics.fmean))]
        for m in methods:
            xs = _e(summary["per"][(i, m)])
            cells += [_fmt(_stat(xs, statistics.fmean)), _fmt(_stat(xs, statistics.median))]
        cells += [_fmt(_anchor(s, v, metric)) for _, s, metric in anchor_cols]
        cells += extra_rows[i]
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    for m in refs:
        xs = _e(summary["per"][(REFERENCE, m)])
        lines.append(f"- Reference `{m}` (trained once per trial, independent of {label}): "
                     f"{len(xs)}/{config['trials']} cells, mean {_fmt(_stat(xs, statistics.fmean))}, "
                     f"median {_fmt(_stat(xs, statistics.median))}.")
    for k, s in enumerate(sets):
        note = " " + " ".join(s["note"].split()) if s.get("note") else ""
        lines.append(f"- Authors{' ' + str(k + 1) if len(sets) > 1 else ''}: {s['label']}.{note}")
    lines += compare_notes
    timed_out: dict[str, int] = {}
    for (_, m), rows in summary["per"].items():
        for r in rows:
            if r.get("status") == "timeout":
                timed_out[m] = timed_out.get(m, 0) + 1
    if timed_out:
        lines.append("- Timed out (killed at the config's time limit; no e_test, left out of the "
                     "statistics): " + ", ".join(f"{m} {n}" for m, n in sorted(timed_out.items()))
                     + " cells.")
    failed_by: dict[str, list[dict[str, Any]]] = {}
    for (_, m), rows in summary["per"].items():
        failed_by.setdefault(m, []).extend(rows)
    parts = []
    for m in sorted(failed_by):
        n, errors = failed_cells(failed_by[m])
        if n:
            parts.append(f"{m} {n} cells ({'; '.join(errors)})")
    if parts:
        lines.append("- Failed (the method's own fit raised; no e_test, left out of the "
                     "statistics): " + ", ".join(parts) + ".")
    failed = {f["key"] for f in summary["failures"]}
    if failed:
        lines.append(f"- Failures logged: {len(failed)} cells (see the `failures` table); "
                     "they are retried by the next `lcs-cvx study run`.")
    return "\n".join(lines).rstrip() + "\n"


def _positions(values: list[float]) -> tuple[list[float], bool]:
    vs = [float(v) for v in values]
    log = min(vs) > 0 and max(vs) / min(vs) >= LOG_X_RATIO
    return ([math.log10(v) for v in vs] if log else vs), log


def _series(summary: dict[str, Any], compared: dict[str, Any] | None) -> list[dict[str, Any]]:
    """The box groups of the figure: ``{"key", "label", "color", "data": [e_test list per
    swept value]}``, this study's methods and, with a comparison, each compared method just
    before the method it is paired with."""
    config = summary["study"]["config"]
    n = len(summary["values"])
    if compared is None or compared["summary"] is None:
        return [{"key": m, "label": m, "color": _COLORS.get(m, "grey"),
                 "data": [_e(summary["per"][(i, m)]) for i in range(n)]}
                for m in config["methods"]]
    other = compared["summary"]
    oconfig = other["study"]["config"]
    used = {_COLORS.get(_colour_key(m, config["recipe"]), "grey") for m in config["methods"]}
    spare = iter(_SPARE_COLORS)
    out = []
    for m in config["methods"]:
        for m0, m2 in compared["pairs"]:
            if m0 != m:
                continue
            color = _COLORS.get(_colour_key(m2, oconfig["recipe"]), "grey")
            if color in used:
                color = next(spare, "grey")
            used.add(color)
            idx = [_value_index(other["values"], v) for v in summary["values"]]
            out.append({"key": ("compared", m2), "color": color,
                        "label": _described(m2, oconfig["recipe"], compared["name"]),
                        "data": [_e(other["per"][(j, m2)]) if j is not None else [] for j in idx]})
        out.append({"key": m, "label": _described(m, config["recipe"]),
                    "color": _COLORS.get(_colour_key(m, config["recipe"]), "grey"),
                    "data": [_e(summary["per"][(i, m)]) for i in range(n)]})
    return out


def plot(summary: dict[str, Any], anchors: dict[str, Any], stem: str,
         compared: dict[str, Any] | None = None) -> list[str]:
    from .._optional import require

    matplotlib = require("matplotlib", "studies", "lcs-cvx study report (the figures)")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    study = summary["study"]
    config = study["config"]
    methods = config["methods"]
    series = _series(summary, compared)
    pos, log_x = _positions(summary["values"])
    gaps = [abs(a - b) for a, b in zip(pos, pos[1:], strict=False) if a != b]
    width = 0.7 * (min(gaps) if gaps else 1.0) / max(1, len(series))
    fig, ax = plt.subplots(figsize=(5.2, 4.4))
    offsets = {g["key"]: (k - (len(series) - 1) / 2) * width for k, g in enumerate(series)}
    for g in series:
        offset = offsets[g["key"]]
        data = [(p + offset, [max(x, 1e-300) for x in xs]) for p, xs in zip(pos, g["data"], strict=True)]
        data = [(p, xs) for p, xs in data if xs]
        if not data:
            continue
        bp = ax.boxplot([xs for _, xs in data], positions=[p for p, _ in data], widths=width * 0.9,
                        showmeans=True, patch_artist=True, manage_ticks=False,
                        meanprops={"marker": "o", "markerfacecolor": "white",
                                   "markeredgecolor": "black", "markersize": 4},
                        medianprops={"color": "black"}, flierprops={"markersize": 3})
        for patch in bp["boxes"]:
            patch.set_facecolor(g["color"])
            patch.set_alpha(0.6)
        ax.plot([], [], "s", color=g["color"], label=g["label"])
    for m in config["reference_methods"]:
        xs = _e(summary["per"][(REFERENCE, m)])
        if xs:
            ax.axhline(statistics.median(xs), color=_COLORS.get(m, "grey"), ls="--",
                       label=f"{m} (reference, median)")
    for k, s in enumerate(_anchor_sets(study, anchors)):
        for m in methods + config["reference_methods"]:
            pts = [(p + offsets.get(m, 0.0), _anchor(s, v, f"{m}_mean"))
                   for p, v in zip(pos, summary["values"], strict=True)]
            pts = [(p, a) for p, a in pts if a is not None]
            if pts:
                ax.plot(*zip(*pts, strict=True), ls="none", marker="x" if k == 0 else "+",
                        color=_COLORS.get(m, "grey"), markersize=7, mew=1.5,
                        label=f"authors{' ' + str(k + 1) if k else ''}: {m} mean")
    ax.set_yscale("log")
    ax.set_xticks(pos)
    ax.set_xticklabels([f"{float(v):g}" for v in summary["values"]])
    label = config["sweep"]["label"]
    ax.set_xlabel(label + (" (log scale)" if log_x else ""))
    ax.set_ylabel("e_test")
    title = config["name"] + (f" — Fig. 1({config['panel']})" if config.get("panel") else "")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="major", axis="y", alpha=0.3)
    # below the axes: inside, "best" still hid the medians of some boxes
    if ax.get_legend_handles_labels()[0]:  # none when every cell timed out
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, frameon=False)
    fig.tight_layout()
    out = [f"{stem}.png", f"{stem}.pdf"]
    fig.savefig(out[0], dpi=150)
    fig.savefig(out[1])
    plt.close(fig)
    return out


def report(directory: str | os.PathLike, anchors_path: str | None = "default") -> list[str]:
    """Write the figure (PNG, PDF) and the markdown table of every study in ``directory``'s
    database; return the paths written. ``anchors_path="default"``: :func:`default_anchors_path`."""
    directory = os.fspath(directory)
    anchors = load_anchors(default_anchors_path() if anchors_path == "default" else anchors_path)
    written = []
    with Store(directory, create=False) as store:
        studies = [s for s in store.studies() if s["config"].get("kind") == "grid"]
        names = [s["name"] for s in studies]
        summaries = [summarize(store, study) for study in studies]
        for study, summary in zip(studies, summaries, strict=True):
            stem = study["name"]
            if names.count(stem) > 1:  # the same name with other settings: keep both
                stem += f"-{study['config_hash'][:8]}"
            compared = comparison(summary, summaries)
            stem_path = os.path.join(directory, stem)
            written += plot(summary, anchors, stem_path, compared)
            with open(stem_path + ".md", "w") as f:
                f.write(markdown(summary, anchors, compared))
            written.append(stem_path + ".md")
    return written
