"""The micro-measurements behind the fast kernels' design choices (one torch thread).

    python studies/kernel_micro.py

Prints a markdown table: each row a choice the kernels make (lcs_cvx/_kernels/arrays.py) and the
two alternatives' times per call, median of 7 repeats.
"""

import statistics
import timeit

import numpy as np
import torch


def per_call(fn, number: int = 2000) -> float:
    """Median seconds per call over 7 repeats of ``number`` calls."""
    return statistics.median(timeit.repeat(fn, number=number, repeat=7)) / number


def main() -> None:
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    rows = []

    n = 4  # SMALL_N: one LU call against Cholesky + solve for tiny SPD matrices
    X = torch.from_numpy(rng.standard_normal((200, n, n)))
    M = X @ X.mT + n * torch.eye(n, dtype=torch.float64)
    b = torch.from_numpy(rng.standard_normal((200, n, 1)))
    rows.append(("batched solve, 200 SPD 4x4 (SMALL_N)", "torch LU (solve_ex)",
                 per_call(lambda: torch.linalg.solve_ex(M.mT, b)), "torch Cholesky + cholesky_solve",
                 per_call(lambda: torch.cholesky_solve(b, torch.linalg.cholesky_ex(M)[0]))))
    Mc = M.contiguous()
    rows.append(("symmetric M to LAPACK", "M.mT view (column-major, no copy)",
                 per_call(lambda: torch.linalg.solve_ex(M.mT, b)), "row-major M",
                 per_call(lambda: torch.linalg.solve_ex(Mc, b))))
    Mn, bn = M.numpy(), b.numpy()
    rows.append(("batched solve, 200 x 4x4 (NUMPY_SOLVE_WORK)", "numpy.linalg.solve",
                 per_call(lambda: np.linalg.solve(Mn, bn)), "torch.linalg.solve_ex",
                 per_call(lambda: torch.linalg.solve_ex(M, b))))
    a, c = rng.random((200, 4)), rng.random((200, 4))
    ta, tc = torch.from_numpy(a), torch.from_numpy(c)
    rows.append(("elementwise a + b, 200 x 4", "NumPy", per_call(lambda: a + c, 20000),
                 "torch", per_call(lambda: ta + tc, 20000)))
    rows.append(("max |a_ij| over a short row, 200 x 4 (amax_abs)", "transposed copy, axis 0",
                 per_call(lambda: np.abs(np.ascontiguousarray(a.T)).max(axis=0), 20000),
                 "axis 1", per_call(lambda: np.abs(a).max(axis=1), 20000)))
    m = rng.random((200, 8)) > 0.5
    ones8 = np.ones(8)
    rows.append(("row counts of a bool 200 x 8 (count_rows)", "product with ones",
                 per_call(lambda: m.astype(np.float64) @ ones8, 20000), "sum(1)",
                 per_call(lambda: m.sum(1), 20000)))
    g = rng.random((200, 10))
    ones200 = np.ones(200)
    rows.append(("column sums of 200 x 10 (colsum)", "product with ones",
                 per_call(lambda: ones200 @ g, 20000), "sum(0)", per_call(lambda: g.sum(0), 20000)))

    # alone, torch's LU wins at this size; inside the kernel NumPy's avoids a round trip through
    # torch: the whole fast violation loss + backward, (10, 4, 4), batch 200, both ways
    import lcs_cvx
    from lcs_cvx._kernels import arrays

    truth = lcs_cvx.random_lcs(10, 4, 4, seed=0)
    data = lcs_cvx.make_dataset(truth, 200, noise=0.01, seed=1)
    model = lcs_cvx.LCS(10, 4, 4, seed=2)

    def loss_call() -> None:
        lcs_cvx.violation_loss(model, data.x, data.u, data.x_next).backward()

    kept = arrays.NUMPY_SOLVE_WORK
    t_np, t_torch = [], []
    for _ in range(7):  # interleaved
        arrays.NUMPY_SOLVE_WORK = kept
        t_np.append(per_call(loss_call, 50))
        arrays.NUMPY_SOLVE_WORK = 0
        t_torch.append(per_call(loss_call, 50))
    arrays.NUMPY_SOLVE_WORK = kept
    rows.append(("the same, inside violation loss + backward, (10, 4, 4), batch 200",
                 "NumPy's LU", statistics.median(t_np), "torch's LU", statistics.median(t_torch)))

    print("| choice | kept | us | alternative | us | ratio |")
    print("|---|---|---:|---|---:|---:|")
    for what, kept, t_kept, alt, t_alt in rows:
        print(f"| {what} | {kept} | {t_kept * 1e6:.1f} | {alt} | {t_alt * 1e6:.1f} | {t_alt / t_kept:.2f} |")


if __name__ == "__main__":
    main()
