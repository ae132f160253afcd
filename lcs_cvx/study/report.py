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

A study whose config has ``compare = NAME`` is reported beside the study of that name in the
same database (:mod:`lcs_cvx.study.compare`).
"""

from __future__ import annotations

import json
import math
import os
import statistics
from pathlib import Path
from typing import Any

from .._checks import LCSInputError
from ._stats import anchor, e_tests, fmt, stat
from .cells import REFERENCE, expand
from .compare import compare_columns, comparison, described, value_index
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
        d = described(m, config["recipe"]) if compared is not None else m
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
        extra_head, extra_rows, compare_notes = compare_columns(summary, compared, sets)
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
        cells = [fmt(v), f"{len(rows)}/{expected}",
                 fmt(stat([float(r["modes"]) for r in rows], statistics.fmean)),
                 fmt(stat([r["sigma_min"] for r in rows], statistics.fmean))]
        for m in methods:
            xs = e_tests(summary["per"][(i, m)])
            cells += [fmt(stat(xs, statistics.fmean)), fmt(stat(xs, statistics.median))]
        cells += [fmt(anchor(s, v, metric)) for _, s, metric in anchor_cols]
        cells += extra_rows[i]
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    for m in refs:
        xs = e_tests(summary["per"][(REFERENCE, m)])
        lines.append(f"- Reference `{m}` (trained once per trial, independent of {label}): "
                     f"{len(xs)}/{config['trials']} cells, mean {fmt(stat(xs, statistics.fmean))}, "
                     f"median {fmt(stat(xs, statistics.median))}.")
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
                 "data": [e_tests(summary["per"][(i, m)]) for i in range(n)]}
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
            idx = [value_index(other["values"], v) for v in summary["values"]]
            out.append({"key": ("compared", m2), "color": color,
                        "label": described(m2, oconfig["recipe"], compared["name"]),
                        "data": [e_tests(other["per"][(j, m2)]) if j is not None else [] for j in idx]})
        out.append({"key": m, "label": described(m, config["recipe"]),
                    "color": _COLORS.get(_colour_key(m, config["recipe"]), "grey"),
                    "data": [e_tests(summary["per"][(i, m)]) for i in range(n)]})
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
        xs = e_tests(summary["per"][(REFERENCE, m)])
        if xs:
            ax.axhline(statistics.median(xs), color=_COLORS.get(m, "grey"), ls="--",
                       label=f"{m} (reference, median)")
    for k, s in enumerate(_anchor_sets(study, anchors)):
        for m in methods + config["reference_methods"]:
            pts = [(p + offsets.get(m, 0.0), anchor(s, v, f"{m}_mean"))
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
