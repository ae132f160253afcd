"""Where a loss + ``backward()`` call's time goes, at one size, batch 200, one torch thread: the
compiled kernel alone, the one-call ``violation_value_and_grad``, ``violation_loss`` (the loss as
an autograd node) and ``violation_loss(...).backward()``, beside torch's own floor: the loss's
autograd node (``CompiledLoss``) on given gradients, with no kernel call, and its backward to
the nine parameters, and a backward through one multiplication.

    python -m studies.loss_call_costs [--size 10,4,1] [--out studies/results]

Each is the best of 5 repeats of the mean of 2,000 calls (``timeit``). Writes
``OUT/loss_call_costs.md``.
"""

from __future__ import annotations

import argparse
import os
import timeit

import torch

from lcs_cvx._kernels import calls
from lcs_cvx.bench import perturbed
from lcs_cvx.data import make_dataset, random_lcs
from lcs_cvx.losses import MAX_ITER, STALL, VIOLATION_TOL, violation_loss
from lcs_cvx.value_and_grad import violation_value_and_grad


def costs(size: tuple[int, int, int], number: int = 2000) -> dict[str, float]:
    """Microseconds per call of each piece (module docstring)."""
    torch.set_num_threads(1)
    truth = random_lcs(*size, stiffness=0.5, seed=0)
    data = make_dataset(truth, 200, noise=1e-2, seed=1)
    model = perturbed(truth, 0.05, 2)
    x, u, xn = data.x, data.u, data.x_next
    params, arrays, s = calls.model_arrays(model)
    A, B, C, d, D, E, G, H, c = arrays
    xa, ua, xna = calls.as_arrays(x, u, xn)
    kernel = calls.compiled().violation
    grads = tuple(torch.zeros_like(p) for p in params)
    leaf = torch.zeros((), dtype=torch.float64, requires_grad=True)

    def loss_backward() -> None:
        model.zero_grad(set_to_none=True)
        violation_loss(model, x, u, xn).backward()

    def nothing_backward() -> None:
        model.zero_grad(set_to_none=True)
        calls.CompiledLoss.apply(calls.scalar(1.0), grads, *params).backward()

    def one_multiplication() -> None:
        leaf.grad = None
        (leaf * 1.0).backward()

    pieces = {
        "compiled kernel": lambda: kernel(A, B, C, d, D, E, c, G, H, float(s), xa, ua, xna, 1e-2, 1e-4,
                                          VIOLATION_TOL, MAX_ITER, STALL, calls.COLD),
        "violation_value_and_grad": lambda: violation_value_and_grad(model, x, u, xn),
        "violation_loss (the autograd node)": lambda: violation_loss(model, x, u, xn),
        "violation_loss + backward()": loss_backward,
        "torch alone: the loss's node on given gradients, + backward() to the 9 parameters": nothing_backward,
        "torch: one multiplication, + backward()": one_multiplication,
    }
    out = {}
    for name, fn in pieces.items():
        fn()
        out[name] = 1e6 * min(timeit.repeat(fn, number=number, repeat=5)) / number
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="10,4,1", help="n_x,n_u,n_lam (default 10,4,1)")
    ap.add_argument("--out", default=os.path.join("studies", "results"))
    args = ap.parse_args(argv)
    size = tuple(int(v) for v in args.size.split(","))
    lines = [f"# Where a loss + backward() call's time goes, {size}, batch 200", "",
             f"`python -m studies.loss_call_costs --size {args.size}` (best of 5 repeats of the mean of "
             "2,000 calls, one torch thread).", "", "| call | µs |", "|---|---:|"]
    for name, us in costs(size).items():
        lines.append(f"| {name} | {us:.0f} |")
        print(lines[-1], flush=True)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "loss_call_costs.md"), "w") as fh:
        fh.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
