"""The report of the differentiable-paths comparison (:mod:`studies.solvers.differentiable_paths`):
its tables, summary and figure from the rows' records."""

from __future__ import annotations

import platform
from importlib.metadata import version
from pathlib import Path

import lcs_cvx

from .differentiable_paths_cells import (
    DATE,
    EPS,
    GAMMA,
    LOSSES,
    MACHINE,
    PATH_NOTES,
    PERTURB,
    REPEATS,
    SKIP_SECONDS,
)


def fmt_err(x: float | None) -> str:
    return "–" if x is None else f"{x:.1e}"


def cell_text(r: dict) -> str:
    if r["status"] == "ok":
        return f"{r['samples_per_s']:,.0f}"
    if r["status"] == "skipped":
        return "skipped: > 60 s per call"
    return "error"


def versions() -> str:
    names = ("torch", "cvxpy", "cvxpylayers", "diffcp", "clarabel", "scs", "ecos", "qpth",
             "proxsuite", "casadi")
    parts = [f"lcs_cvx {lcs_cvx.__version__}"]
    for n in names:
        try:
            parts.append(f"{n} {version(n)}")
        except Exception:
            parts.append(f"{n} ?")
    return ", ".join(parts)


def report(done: dict, out: Path, stem: str, sizes, batches, paths, smoke: bool) -> None:
    cmd = "python -m studies.solvers.differentiable_paths --out " + str(out) + (" --smoke" if smoke else "")
    lines = [
        "# Differentiable solver paths: loss + gradient",
        "",
        f"Command: `{cmd}` (resumable: one JSON line per (loss, size, path, batch) in "
        f"`{stem}.jsonl`).  ",
        f"Date: {DATE}. Machine: {MACHINE} ({platform.machine()}, Python "
        f"{platform.python_version()}).  ",
        f"Versions: {versions()}.",
        "",
        "One call = the loss on a batch and `.backward()` to all nine parameters "
        "(`A, B, C, d, D, E, G, H, c`). samples/s = batch / median time per call (median of "
        f"≥ {REPEATS} repeats after a warm-up, one thread). Agreement with `fast` on the same "
        "batch: **Δλ** = max |λ − λ_fast|, **Δloss** = |L − L_fast| / (1 + |L_fast|), "
        "**Δgrad** = max over parameters of max |g − g_fast| / (1 + max |g_fast|). "
        f"Data: `random_lcs(stiffness=0.5, seed=0)`, `make_dataset(noise=1e-2, seed=1)`, the "
        f"model = truth + {PERTURB} N(0, 1) per parameter; γ = {GAMMA:g}, ε = {EPS:g}. A path "
        f"is not run at batch {max(batches):,} when one call would take > {SKIP_SECONDS:.0f} s "
        "(estimated from its rate at 200; for the batched `qpth` from one call at 5,000).",
        "",
        "Paths: " + "; ".join(f"`{p}`: {PATH_NOTES[p]}" for p in paths) + ".",
        "",
    ]
    for loss in LOSSES:
        title = "violation loss (V), eq. (9)" if loss == "violation" else "prediction loss (P), eq. (6)"
        lines += [f"## {title}", ""]
        for size in sizes:
            mid = sorted(batches)[len(batches) // 2] if len(batches) > 2 else max(batches)
            lines += [f"### (n_x, n_u, n_λ) = {size}", "",
                      "| path | " + " | ".join(f"samples/s @ {b:,}" for b in batches)
                      + f" | × fast @ {mid} | Δλ @ {mid} | Δloss @ {mid} | Δgrad @ {mid} | notes |",
                      "|---|" + "---:|" * len(batches) + "---:|---:|---:|---:|---|"]
            fast_mid = done.get((loss, size, "fast", mid), {}).get("samples_per_s")
            for path in paths:
                rows = [done.get((loss, size, path, b)) for b in batches]
                cells, notes = [], []
                for b, r in zip(batches, rows, strict=True):
                    if r is None:
                        cells.append("–")
                        continue
                    cells.append(cell_text(r))
                    if r["status"] == "error":
                        notes.append(f"batch {b:,}: {r['error']}")
                    elif r["status"] == "skipped":
                        notes.append(f"batch {b:,}: {r['note']}")
                    else:
                        if b != mid and (r["max_dlam"] > 1e-6 or r["rel_dgrad"] > 1e-6):
                            notes.append(f"batch {b:,}: Δλ {fmt_err(r['max_dlam'])}, "
                                         f"Δgrad {fmt_err(r['rel_dgrad'])}")
                        if r["median_s"] > SKIP_SECONDS:
                            notes.append(f"batch {b:,}: one call took {r['median_s']:.0f} s "
                                         f"(> {SKIP_SECONDS:.0f} s; run because the estimate "
                                         "from batch 200 was below)")
                rm = done.get((loss, size, path, mid))
                ok = rm is not None and rm["status"] == "ok"
                ratio = f"{rm['samples_per_s'] / fast_mid:.2g}" if ok and fast_mid else "–"
                lines.append(
                    f"| {path} | " + " | ".join(cells) + f" | {ratio} | "
                    f"{fmt_err(rm.get('max_dlam')) if ok else '–'} | {fmt_err(rm.get('rel_dloss')) if ok else '–'} | "
                    f"{fmt_err(rm.get('rel_dgrad')) if ok else '–'} | {'; '.join(notes)} |")
            lines.append("")
    lines += ["## Summary", "", summary(done, sizes, batches, paths), ""]
    (out / f"{stem}.md").write_text("\n".join(lines))
    try:
        plot(done, out / f"{stem}.png", sizes, batches, paths)
    except ImportError:  # matplotlib is in the [studies] extra
        pass


def summary(done: dict, sizes, batches, paths) -> str:
    mid = 200 if 200 in batches else max(batches)
    out = []
    for loss in LOSSES:
        for size in sizes:
            fast = done.get((loss, size, "fast", mid), {}).get("samples_per_s")
            if not fast:
                continue
            others = []
            for p in paths[1:]:
                r = done.get((loss, size, p, mid))
                if r is None:
                    continue
                if r["status"] != "ok":
                    others.append(f"{p} {r['status']}")
                    continue
                acc = "agrees" if r["rel_dgrad"] <= 1e-6 and r["max_dlam"] <= 1e-6 else (
                    f"Δλ {r['max_dlam']:.0e}, Δgrad {r['rel_dgrad']:.0e}")
                others.append(f"{p} {fast / r['samples_per_s']:,.0f}× slower ({acc})")
            out.append(f"- {loss}, n_λ = {size[2]}, batch {mid}: fast {fast:,.0f} samples/s; "
                       + "; ".join(others) + ".")
    bad = []
    for (loss, size, p, b), r in sorted(done.items(), key=lambda kv: str(kv[0])):
        if r["status"] == "ok" and p in paths and (r["max_dlam"] > 1e-3 or r["rel_dgrad"] > 1e-3):
            bad.append(f"{p} ({loss}, n_λ = {size[2]}, batch {b:,}: Δλ {r['max_dlam']:.1e}, "
                       f"Δgrad {r['rel_dgrad']:.1e})")
        elif r["status"] == "error" and p in paths:
            bad.append(f"{p} ({loss}, n_λ = {size[2]}, batch {b:,}: {r['error']})")
    if bad:
        out.append("- Inaccurate or failed (Δλ or Δgrad above 1e-3, or an error): "
                   + "; ".join(bad) + ".")
    fastest = {}
    for loss in LOSSES:
        for size in sizes:
            rates = {p: done.get((loss, size, p, mid), {}).get("samples_per_s") for p in paths[1:]}
            rates = {p: v for p, v in rates.items() if v}
            if rates:
                fastest[(loss, size[2])] = max(rates, key=rates.get)
    if fastest:
        out.append("- Fastest path after `fast` at batch " + f"{mid}: " + ", ".join(
            f"{p} ({loss}, n_λ = {n})" for (loss, n), p in fastest.items()) + ".")
    return "\n".join(out)


def plot(done: dict, path: Path, sizes, batches, paths) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(LOSSES), figsize=(12, 5), sharey=True)
    styles = ("-", "--", ":")
    for ax, loss in zip(axes, LOSSES, strict=True):
        for k, p in enumerate(paths):
            for s, size in enumerate(sizes):
                pts = [(b, done[(loss, size, p, b)]["samples_per_s"]) for b in batches
                       if done.get((loss, size, p, b), {}).get("status") == "ok"]
                if pts:
                    xs, ys = zip(*pts, strict=True)
                    ax.plot(xs, ys, styles[s % 3], marker="o", color=f"C{k}", ms=4,
                            label=f"{p}, n_λ={size[2]}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("batch size")
        ax.set_title(f"{loss} loss: loss + gradient")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("samples/s (one thread)")
    axes[-1].legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
