"""The CPU-or-GPU figure and table of the docs from ``tools/device-check``'s throughput tables.

Reads ``throughput_cpu.md`` (one and all cores) and ``throughput_cuda.md`` from ``--results``
(default ``studies/results/device``) and writes the comparison table (markdown, to stdout) and
the plot of samples per second against the batch size (``--plot``).

    python -m studies.solvers.device_report --plot docs/assets/cpu-or-gpu-throughput.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

__all__ = ["main", "read_throughput"]

LOSSES = ("violation", "prediction")


def read_throughput(path: Path) -> dict[tuple[str, str, int], float]:
    """``{(loss, "cpu 1" | "cpu 16" | "cuda", batch): samples/s}`` of one ``lcs-cvx bench
    --throughput`` table."""
    out = {}
    for line in path.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 8 and cells[0].startswith("(") and cells[6][:1].isdigit():
            where = cells[2] if cells[2] != "cpu" else f"cpu {cells[4]}"
            out[(cells[1], where, int(cells[5].replace(",", "")))] = float(cells[6].replace(",", ""))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--results", default="studies/results/device")
    p.add_argument("--plot", default=None, help="write the figure here (PNG)")
    args = p.parse_args(argv)
    root = Path(args.results)
    rates = read_throughput(root / "throughput_cpu.md") | read_throughput(root / "throughput_cuda.md")
    cores = max(int(w.split()[1]) for _, w, _ in rates if w.startswith("cpu"))
    kinds = ("cpu 1", f"cpu {cores}", "cuda")
    labels = {"cpu 1": "1 core", f"cpu {cores}": f"{cores} cores", "cuda": "GPU"}
    print(f"| loss | batch | 1 core | {cores} cores | GPU | GPU / 1 core | GPU / {cores} cores |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for loss in LOSSES:
        for b in sorted({b for (l_, _, b) in rates if l_ == loss}):
            one, many, gpu = (rates[(loss, k, b)] for k in kinds)
            print(f"| {loss} | {b:,} | {one / 1e6:.2f} M | {many / 1e6:.2f} M | {gpu / 1e6:.2f} M | "
                  f"{gpu / one:.2f} | {gpu / many:.2f} |")
    if args.plot:
        fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
        for ax, loss in zip(axes, LOSSES, strict=True):
            for kind, style in zip(kinds, ("o-", "s-", "^-"), strict=True):
                pts = sorted((b, r) for (l_, k, b), r in rates.items() if l_ == loss and k == kind)
                ax.plot([b for b, _ in pts], [r for _, r in pts], style, label=labels[kind])
            ax.set(xscale="log", yscale="log", xlabel="batch (samples per call)",
                   title=f"{loss} loss + gradient, (10, 4, 4), float64")
            ax.grid(True, which="both", alpha=0.3)
        axes[0].set_ylabel("samples / s")
        axes[0].legend()
        fig.tight_layout()
        fig.savefig(args.plot, dpi=110)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
