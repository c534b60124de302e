"""Solve times of the Lipschitz-observer LMI (diffsmf.observers.lmi) for n = 2, 5, 10, 20.

For each n: a random (A, C) (l = max(1, n // 3) outputs, gamma = 0.05, eps = 0.1), solvers
CLARABEL and SCS. Columns: first solve (problem build + cvxpy canonicalisation + solve at one
alpha), re-solve (new parameter values on the cached problem, mean of 5; SCS 2), full design
(alpha search, iters=8; SCS only for n = 2) and the numpy-verified status.
Run: python benchmarks/lmi_bench.py
"""

from __future__ import annotations

import time

import numpy as np

from diffsmf.observers import lmi


def bench(n: int, solver: str) -> dict:
    rng = np.random.default_rng(n)
    l = max(1, n // 3)
    A = rng.standard_normal((n, n)) / np.sqrt(n)
    C = rng.standard_normal((l, n))
    G = 0.05**2 * np.eye(n)
    lmi._problem.cache_clear()
    t0 = time.perf_counter()
    prob, par, var = lmi._problem(n, l, n, "continuous", False, True)
    par["margin"].value = 1e-6
    par["A"].value, par["C"].value, par["Bf"].value, par["G"].value = A, C, np.eye(n), G
    par["kappa2"].value, par["alpha"].value = 1e6, 0.1
    st1 = lmi._solve(prob, solver)
    first = time.perf_counter() - t0
    times = []
    for k in range(5 if solver == "CLARABEL" else 2):
        par["A"].value = A + 0.01 * rng.standard_normal((n, n))
        par["alpha"].value = 0.05 * (k + 1)
        t0 = time.perf_counter()
        lmi._solve(prob, solver)
        times.append(time.perf_counter() - t0)
    if solver == "SCS" and n > 2:  # SCS needs ~1e4-1e5 iterations per solve here: skipped
        return dict(n=n, solver=solver, first=first, resolve=float(np.mean(times)),
                    full=float("nan"), solves=0, status=f"(one solve: {st1})", bound=float("nan"))
    t0 = time.perf_counter()
    d = lmi.design_lipschitz_observer(A, C, 0.05, 0.1, solver=solver, max_gain=1e3, iters=8)
    full = time.perf_counter() - t0
    return dict(n=n, solver=solver, first=first, resolve=float(np.mean(times)), full=full,
                solves=d.solves, status=d.status, bound=d.bound, first_status=st1)


def main() -> None:
    print("| n | solver | first solve [s] | re-solve [s] | full design [s] (solves) | status |"
          " bound |\n|---|---|---|---|---|---|---|", flush=True)
    for n in (2, 5, 10, 20):
        for s in ("CLARABEL", "SCS"):
            r = bench(n, s)
            print(f"| {r['n']} | {r['solver']} | {r['first']:.3f} | {r['resolve']:.4f} | "
                  f"{r['full']:.2f} ({r['solves']}) | {r['status']} | {r['bound']:.4g} |",
                  flush=True)


if __name__ == "__main__":
    main()
