r"""The report of the PWA regression comparison: e_test and training time against the number of
hybrid modes in the training data, ours beside the authors' published numbers.

For every grid study in ``DIR/studies.sqlite`` (``studies/configs/pwa_compare*.toml``) it writes
``DIR/<name>_vs_modes.png`` and ``.pdf`` -- (a) e_test, (b) training wall time (log axes), the
median over trials of each method at the mean mode count of each swept n_lambda, the bars
spanning the interquartile range, timed-out cells at the time limit as open triangles, cells
whose own fit failed (``status = "failed"``: PARC merging all its clusters away) as crosses in a
circle at the seconds until the failure, and the authors' published numbers
(:mod:`studies.pwa.authors`) as crosses -- and ``DIR/<name>_vs_modes.md``: the table per
n_lambda ("failed" where every cell of a method failed, as the authors' table has at 2,021
modes; "timed out" counts apart), the authors' numbers beside ours at the nearest mode count,
and the comparison's targets (violation loss, best recipe, against PARC: >= 10x more accurate
and >= 10x faster at every mode count; at >= 2,021 modes PARC fails or is >= 100x slower),
checked on the medians.

    python -m studies.pwa.report DIR
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
from typing import Any

from lcs_cvx import LCSInputError
from lcs_cvx.study.report import failed_cells, summarize
from lcs_cvx.study.store import Store

from .authors import PUBLISHED, SOURCE

__all__ = ["collect", "markdown", "plot", "write_report", "main", "LABELS", "BEST", "PARC"]

#: The method the targets are checked for, and the one it is checked against.
BEST, PARC = "violation@best", "parc"
#: Display names of the methods (a method not listed is shown by its name).
LABELS = {
    "violation": "violation (paper recipe)",
    "violation@best": "violation (best recipe)",
    "prediction": "prediction (paper recipe)",
    "prediction@best": "prediction (best recipe)",
    "parc": "PARC",
    "mlp": "MLP (validation-tuned)",
    "affine": "affine (least squares)",
}
_COLORS = {"violation": "tab:orange", "violation@best": "tab:red", "prediction": "tab:blue",
           "prediction@best": "tab:cyan", "parc": "tab:green", "mlp": "tab:purple",
           "affine": "tab:gray"}
#: Targets: accuracy and speed ratios (PARC / ours) at every mode count; the slowdown of PARC
#: from :data:`LARGE_MODES` modes on, unless it fails (its fit fails or times out).
ACCURACY_TARGET, SPEED_TARGET, LARGE_TARGET, LARGE_MODES = 10.0, 10.0, 100.0, 2021


def _label(m: str) -> str:
    return LABELS.get(m, m)


def _median(xs: list[float]) -> float | None:
    return statistics.median(xs) if xs else None


def _quartiles(xs: list[float]) -> tuple[float, float]:
    if len(xs) < 2:
        return xs[0], xs[0]
    q = statistics.quantiles(xs, n=4, method="inclusive")
    return q[0], q[2]


def collect(store: Store, study: dict[str, Any]) -> dict[str, Any]:
    """The study's cells per swept value and method: ``{"config", "points": [{"value",
    "modes" (mean over the value's cells), "methods": {m: {"expected", "e_test" [...], "time"
    [...] (fit wall time of finished cells), "timeouts" [...] (wall time of timed-out cells),
    "limit", "failed" [...] (fit wall time until the failure of cells whose own fit failed),
    "errors" [...] (their distinct messages, shortened)}}}], "n_cells", "n_done", "cell_time",
    "failures"}``."""
    s = summarize(store, study)
    config = study["config"]
    per_method = config.get("method_trials", {})
    points = []
    for i, value in enumerate(s["values"]):
        rows = [r for m in config["methods"] for r in s["per"][(i, m)]]
        modes = [r["modes"] for r in rows if r["modes"] is not None]
        methods = {}
        for m in config["methods"]:
            cells = s["per"][(i, m)]
            ok = [r for r in cells if r["status"] not in ("timeout", "failed")]
            out = [r for r in cells if r["status"] == "timeout"]
            bad = [r for r in cells if r["status"] == "failed"]
            methods[m] = {
                "expected": per_method.get(m, config["trials"]),
                "e_test": [r["e_test"] for r in ok if r["e_test"] is not None],
                "time": [r["fit_wall_time"] for r in ok if r["fit_wall_time"] is not None],
                "timeouts": [r["wall_time"] for r in out],
                "limit": max((r["time_limit"] for r in out if r["time_limit"]), default=None),
                "failed": [r["fit_wall_time"] or 0.0 for r in bad],
                "errors": failed_cells(bad)[1],
            }
        points.append({"value": value, "modes": statistics.fmean(modes) if modes else None,
                       "methods": methods})
    return {"study": study, "config": config, "points": points, "n_cells": s["n_cells"],
            "n_done": s["n_done"], "cell_time": s["cell_time"], "failures": s["failures"]}


def _fmt(v: Any, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    if isinstance(v, float):
        return f"{v:.{digits}g}" if abs(v) < 1e3 else f"{v:,.0f}"
    return f"{v:,}" if isinstance(v, int) else str(v)


def _n(d: dict[str, Any]) -> int:
    """The stored cells of a method at a point: finished, timed out and failed."""
    return len(d["e_test"]) + len(d["timeouts"]) + len(d["failed"])


def _e_cell(d: dict[str, Any]) -> str:
    """Median e_test; ``"failed"`` where every stored cell's fit failed, else the count of
    failed cells beside the median."""
    if d["failed"] and not d["e_test"] and not d["timeouts"]:
        return "failed"
    e = _fmt(_median(d["e_test"]))
    return e + (f" ({len(d['failed'])} failed)" if d["failed"] else "")


def _time_cell(d: dict[str, Any]) -> str:
    t = _fmt(_median(d["time"]), 3)
    notes = []
    if d["timeouts"]:
        limit = f" ≥ {d['limit']:g} s" if d["limit"] else ""
        notes.append(f"{len(d['timeouts'])} timed out{limit}")
    if d["failed"]:
        notes.append(f"{len(d['failed'])} failed after {_fmt(_median(d['failed']), 3)} s")
    return t + (f" ({'; '.join(notes)})" if notes else "")


#: An authors' mode count is compared with our swept value of the nearest mean mode count, if
#: it lies within this factor.
NEAR = 2.0


def _nearest(points: list[dict[str, Any]], modes: float) -> dict[str, Any] | None:
    have = [p for p in points if p["modes"] and abs(math.log(p["modes"] / modes)) <= math.log(NEAR)]
    return min(have, key=lambda p: abs(math.log(p["modes"] / modes)), default=None)


def _targets(r: dict[str, Any]) -> list[str]:
    """The target check, one line per swept value (needs BEST and PARC among the methods)."""
    methods = r["config"]["methods"]
    if BEST not in methods or PARC not in methods:
        return [f"- Targets not checked: the study lacks `{BEST}` or `{PARC}`."]
    head = ["n_λ", "modes", f"e_test PARC / {_label(BEST)}", f"time PARC / {_label(BEST)}",
            "accuracy ≥ 10×", "speed ≥ 10×", "≥ 2,021 modes: PARC fails or ≥ 100× slower"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for p in r["points"]:
        best, parc = p["methods"][BEST], p["methods"][PARC]
        e_b, e_p = _median(best["e_test"]), _median(parc["e_test"])
        t_b, t_p = _median(best["time"]), _median(parc["time"])
        n_out, n_bad, n_parc = len(parc["timeouts"]), len(parc["failed"]), _n(parc)
        # most PARC cells did not finish: PARC fails here (its fit failed, or it timed out)
        failed = n_out + n_bad > 0 and (n_out + n_bad) * 2 >= n_parc
        how = "timed out" if not n_bad else ("failed" if not n_out else "failed or timed out")
        if failed and n_out and parc["limit"] and t_b:  # cells timed out: a lower bound
            t_ratio, t_text = parc["limit"] / t_b, f"≥ {parc['limit'] / t_b:.0f} ({how})"
        elif failed:  # its fit failed: no training time to compare
            t_ratio, t_text = None, f"– (PARC {how})"
        else:
            t_ratio = t_p / t_b if t_p and t_b else None
            t_text = _fmt(t_ratio, 3)
        e_ratio = e_p / e_b if e_p and e_b and not failed else None
        e_text = f"– (PARC {how})" if failed else _fmt(e_ratio, 3)
        if not (best["e_test"] and n_parc):
            acc = speed = large = "no data"
        else:
            acc = f"PARC {how}" if failed else ("yes" if e_ratio and e_ratio >= ACCURACY_TARGET else "**no**")
            if failed and t_ratio is None:
                speed = f"PARC {how}"
            else:
                speed = "yes" if t_ratio and t_ratio >= SPEED_TARGET else "**no**"
            if p["modes"] is None or p["modes"] < LARGE_MODES:
                large = "n/a"
            else:
                large = "yes" if failed or (t_ratio and t_ratio >= LARGE_TARGET) else "**no**"
        lines.append("| " + " | ".join([_fmt(p["value"]), _fmt(p["modes"], 4), e_text, t_text,
                                        acc, speed, large]) + " |")
    return lines


def markdown(r: dict[str, Any]) -> str:
    study, config = r["study"], r["config"]
    methods = config["methods"]
    limit = config.get("time_limit")
    lines = [f"# {config['name']}: e_test and training time against the number of modes", "",
             f"config `{study['path']}` (hash `{study['config_hash']}`), trials: {config['trials']}"
             + (f" ({', '.join(f'{m}: {n}' for m, n in config.get('method_trials', {}).items())})"
                if config.get("method_trials") else "")
             + (f", time limit {limit:g} s per cell" if limit else "")
             + f"; {r['n_done']}/{r['n_cells']} cells done, {r['cell_time']:.1f} s of cell wall "
             f"time. Median over trials; e_test on the {config['data']['n_test']:,}-sample "
             "noiseless test set, time = training wall time of one cell on one thread.", ""]
    if config.get("description"):
        lines += [config["description"].strip(), ""]
    head = ["n_λ", "modes (mean)"]
    for m in methods:
        head += [f"{_label(m)}: e_test", f"{_label(m)}: time (s)"]
    lines += ["## Ours", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for p in r["points"]:
        cells = [_fmt(p["value"]), _fmt(p["modes"], 4)]
        for m in methods:
            d = p["methods"][m]
            n = _n(d)
            cells += [_e_cell(d) + (f" ({n}/{d['expected']})" if n != d["expected"] else ""),
                      _time_cell(d)]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "## The authors' published numbers beside ours", "",
              f"Authors: {SOURCE}. Ours: the swept n_λ whose mean mode count is nearest, if "
              f"within a factor {NEAR:g} (else –).", ""]
    ours = [m for m in ("violation", BEST, PARC) if m in methods]
    head = ["authors: modes", "ours: n_λ (modes)", "authors: violation time (s)"]
    head += [f"ours: {_label(m)} time (s)" for m in ours if m != PARC]
    head += ["authors: PARC time (s)"] + ([f"ours: {_label(PARC)} time (s)"] if PARC in ours else [])
    head += ["authors: violation e_test"] + [f"ours: {_label(m)} e_test" for m in ours if m != PARC]
    head += ["authors: PARC e_test"] + ([f"ours: {_label(PARC)} e_test"] if PARC in ours else [])
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for modes, t_v, t_p, e_v, e_p in PUBLISHED:
        p = _nearest(r["points"], modes)
        d = p["methods"] if p is not None else None

        def time_of(m: str, d: dict[str, Any] | None = d) -> str:
            return _time_cell(d[m]) if d is not None else "–"

        def e_of(m: str, d: dict[str, Any] | None = d) -> str:
            return _e_cell(d[m]) if d is not None else "–"

        row = [_fmt(modes), f"{_fmt(p['value'])} ({_fmt(p['modes'], 4)})" if p else "–", _fmt(t_v, 3)]
        row += [time_of(m) for m in ours if m != PARC]
        row += ["failed" if t_p is None else _fmt(t_p, 4)] + ([time_of(PARC)] if PARC in ours else [])
        row += [_fmt(e_v)] + [e_of(m) for m in ours if m != PARC]
        row += ["–" if e_p is None else _fmt(e_p)] + ([e_of(PARC)] if PARC in ours else [])
        lines.append("| " + " | ".join(row) + " |")
    lines += ["", "## Targets", "",
              f"{_label(BEST)} against PARC, on the medians: ≥ {ACCURACY_TARGET:g}× more accurate and "
              f"≥ {SPEED_TARGET:g}× faster to train at every mode count; from {LARGE_MODES:,} modes "
              f"on, PARC fails (its fit fails or times out) or is ≥ {LARGE_TARGET:g}× slower. A "
              "point where most PARC cells failed or timed out counts as failed; where cells "
              "timed out, its speed ratio is then a lower bound (time limit / our time).", ""]
    lines += _targets(r)
    failed_notes = [f"{_label(m)} at n_λ = {_fmt(p['value'])}: {len(d['failed'])} cells "
                    f"({'; '.join(d['errors'])})"
                    for p in r["points"] for m, d in p["methods"].items() if d["failed"]]
    if failed_notes:
        lines += ["", "- Failed (the method's own fit raised; no e_test, left out of the "
                  "medians; recorded once, not retried): " + ", ".join(failed_notes) + "."]
    failed = {f["key"] for f in r["failures"]}
    if failed:
        lines += ["", f"- Failures logged: {len(failed)} cells (see the `failures` table); they "
                  "are retried by the next `lcs-cvx study run`."]
    return "\n".join(lines).rstrip() + "\n"


def plot(r: dict[str, Any], stem: str) -> list[str]:
    """The two panels of the module docstring, written to ``stem.png`` and ``stem.pdf``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    config = r["config"]
    methods = config["methods"]
    fig, (ax_e, ax_t) = plt.subplots(1, 2, figsize=(11, 4.6))
    for k, m in enumerate(methods):
        color, shift = _COLORS.get(m, "black"), 1.0 + 0.035 * (k - (len(methods) - 1) / 2)
        for ax, key in ((ax_e, "e_test"), (ax_t, "time")):
            pts = [(p["modes"] * shift, p["methods"][m][key]) for p in r["points"]
                   if p["modes"] and p["methods"][m][key]]
            if not pts:
                continue
            xs = [x for x, _ in pts]
            meds = [statistics.median(v) for _, v in pts]
            quart = [_quartiles(sorted(v)) for _, v in pts]
            err = [[md - q[0] for md, q in zip(meds, quart, strict=True)],
                   [q[1] - md for md, q in zip(meds, quart, strict=True)]]
            ax.errorbar(xs, meds, yerr=err, color=color, marker="o", ms=4, lw=1.2, capsize=2,
                        label=_label(m))
        outs = [(p["modes"] * shift, p["methods"][m]["limit"] or max(p["methods"][m]["timeouts"]))
                for p in r["points"] if p["modes"] and p["methods"][m]["timeouts"]]
        if outs:
            ax_t.plot(*zip(*outs, strict=True), ls="none", marker="^", mfc="none", mec=color,
                      ms=9, mew=1.5, label=f"{_label(m)}: timed out (at the limit)")
        bad = [(p["modes"] * shift, max(_median(p["methods"][m]["failed"]), 1e-3))
               for p in r["points"] if p["modes"] and p["methods"][m]["failed"]]
        if bad:
            ax_t.plot(*zip(*bad, strict=True), ls="none", marker="$\\otimes$", color=color,
                      ms=11, label=f"{_label(m)}: fit failed (at the seconds until it failed)")
    modes = [p[0] for p in PUBLISHED]
    ax_e.plot(modes, [p[3] for p in PUBLISHED], "x", color="black", ms=8, mew=1.5,
              label="authors (published): violation")
    ax_t.plot(modes, [p[1] for p in PUBLISHED], "x", color="black", ms=8, mew=1.5,
              label="authors (published): violation")
    done = [p for p in PUBLISHED if p[2] is not None]
    ax_e.plot([p[0] for p in done], [p[4] for p in done], "+", color="darkgreen", ms=10, mew=2,
              label="authors (published): PARC")
    ax_t.plot([p[0] for p in done], [p[2] for p in done], "+", color="darkgreen", ms=10, mew=2,
              label="authors (published): PARC")
    for p in PUBLISHED:
        if p[2] is None:
            ax_t.annotate("authors: PARC\nfailed", (p[0], done[-1][2]), fontsize=7,
                          color="darkgreen", ha="center", xytext=(0, 14), textcoords="offset points",
                          arrowprops={"arrowstyle": "->", "color": "darkgreen"})
    if config.get("time_limit"):
        ax_t.axhline(config["time_limit"], color="grey", ls="--", lw=0.8,
                     label="time limit per cell")
    for ax, ylabel in ((ax_e, "e_test (median, IQR bars)"), (ax_t, "training time (s, median)")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("modes in the training data")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="major", alpha=0.3)
    ax_e.set_title("(a) test error", fontsize=10)
    ax_t.set_title("(b) training time", fontsize=10)
    handles, labels = ax_t.get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=7, frameon=False)
    fig.suptitle(f"{config['name']}: PWA regression, n_x = {config['system']['n_x']}, "
                 f"n_u = {config['system']['n_u']}, N = {config['data']['n_train']:,}", fontsize=10)
    fig.tight_layout(rect=(0, 0.14, 1, 1))
    out = [f"{stem}.png", f"{stem}.pdf"]
    fig.savefig(out[0], dpi=150)
    fig.savefig(out[1])
    plt.close(fig)
    return out


def write_report(directory: str | os.PathLike) -> list[str]:
    """Write the figure and the table of every grid study in ``directory``'s database; return
    the paths written."""
    directory = os.fspath(directory)
    written = []
    with Store(directory, create=False) as store:
        studies = [s for s in store.studies() if s["config"].get("kind") == "grid"]
        names = [s["name"] for s in studies]
        for study in studies:
            stem = study["name"]
            if names.count(stem) > 1:
                stem += f"-{study['config_hash'][:8]}"
            stem = os.path.join(directory, stem + "_vs_modes")
            r = collect(store, study)
            written += plot(r, stem)
            with open(stem + ".md", "w") as f:
                f.write(markdown(r))
            written.append(stem + ".md")
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m studies.pwa.report", description=__doc__.split("\n\n")[0])
    parser.add_argument("dir", help="output directory of lcs-cvx study run (holds studies.sqlite)")
    args = parser.parse_args(argv)
    try:
        written = write_report(args.dir)
    except LCSInputError as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 2
    for path in written:
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
