"""Full observer design vs ONE direct cvxpy + Clarabel solve of the same LMI.

For each n in (2, 5, 10, 20, 30): a random (A, C) (A ~ N(0, 1/n), l = max(1, n // 3) outputs),
gamma = 0.05, eps = 0.1, |L|_2 <= 1000 (general structure, continuous time).

- "direct": build a fresh cvxpy problem of the documented 3-block LMI (docs/observers.md,
  3n x 3n) with constant data at the decay rate the design chose, and solve it once with
  Clarabel's default settings (build + canonicalisation + solve), as a user writing cvxpy by
  hand would; its bound sqrt(mu / alpha) eps is printed beside the design's.
- "direct (design's settings)": the same, with the Clarabel options the design would use for
  an LMI of 3n rows (faer factorisation from 32 rows, dropped zeros): the like-for-like ratio.
- "design": ``design_lipschitz_observer`` from scratch (the problem cache cleared, so its
  first solve includes canonicalisation): alpha search, numpy verification, everything.

Times are medians over ``--repeats`` runs (n >= 20: over min(repeats, 2)); the ratio is
design / direct of the medians, measured in the same process one after the other. The machine
may be shared: the load average is printed with the table.
Run: python benchmarks/lmi_bench.py [--sizes 2 5 10 20 30] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
import warnings

import cvxpy as cp
import numpy as np

from diffsmf.observers import design_lipschitz_observer, lmi

GAMMA, EPS, KAPPA = 0.05, 0.1, 1000.0


def system(n: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(n)
    l = max(1, n // 3)
    return rng.standard_normal((n, n)) / np.sqrt(n), rng.standard_normal((l, n))


def direct_solve(A: np.ndarray, C: np.ndarray, alpha: float,
                 options: dict | None = None) -> tuple[float, str, float]:
    """One fresh cvxpy problem of the 3-block LMI at fixed alpha (docs/observers.md), Clarabel
    defaults (or ``options``). Returns (seconds, status, bound = eps sqrt(mu / (alpha
    lambda_min(P))))."""
    t0 = time.perf_counter()
    n, l = A.shape[0], C.shape[0]
    P = cp.Variable((n, n), symmetric=True)
    Y = cp.Variable((n, l))
    lam, mu = cp.Variable(nonneg=True), cp.Variable(nonneg=True)
    PAL = P @ A - Y @ C
    I, Z = np.eye(n), np.zeros((n, n))
    M = cp.bmat([[PAL + PAL.T + alpha * P + lam * GAMMA**2 * I, P, P],
                 [P, -lam * I, Z],
                 [P, Z, -mu * I]])
    M = 0.5 * (M + M.T)
    cons = [P >> I, M << -1e-6 * np.eye(3 * n),
            cp.bmat([[KAPPA * np.eye(l), Y.T], [Y, KAPPA * I]]) >> 0]
    prob = cp.Problem(cp.Minimize(mu), cons)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prob.solve(solver="CLARABEL", **(options or {}))
    sec = time.perf_counter() - t0
    bound = float("nan")
    if prob.status in ("optimal", "optimal_inaccurate"):
        bound = EPS * float(np.sqrt(mu.value / (alpha * np.linalg.eigvalsh(P.value)[0])))
    return sec, str(prob.status), bound


def bench(n: int, repeats: int) -> dict:
    A, C = system(n)
    reps = repeats if n < 20 else min(repeats, 2)
    t_design, t_direct, t_same, d = [], [], [], None
    same = lmi._solver_options("CLARABEL", 3 * n)  # the design's options for 3n rows
    for _ in range(reps):
        lmi._problem.cache_clear()
        t0 = time.perf_counter()
        d = design_lipschitz_observer(A, C, GAMMA, EPS, max_gain=KAPPA)
        t_design.append(time.perf_counter() - t0)
        sec, st, bound_direct = direct_solve(A, C, d.decay)
        t_direct.append(sec)
        t_same.append(direct_solve(A, C, d.decay, same)[0])
    med_design, med_direct = statistics.median(t_design), statistics.median(t_direct)
    med_same = statistics.median(t_same)
    return dict(n=n, l=C.shape[0], design=med_design, direct=med_direct, same=med_same,
                ratio=med_design / med_direct, ratio_same=med_design / med_same,
                opts="faer" if same.get("direct_solve_method") == "faer" else "qdldl",
                solves=d.solves, status=d.status,
                bound=d.bound, direct_status=st, bound_direct=bound_direct, decay=d.decay,
                reps=reps)


def threads() -> str:
    info = [f"{os.cpu_count()} CPUs"]
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "RAYON_NUM_THREADS"):
        if var in os.environ:
            info.append(f"{var}={os.environ[var]}")
    try:
        from threadpoolctl import threadpool_info

        info += [f"{p['internal_api']} {p['num_threads']} threads" for p in threadpool_info()]
    except ImportError:
        pass
    return ", ".join(info)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[2, 5, 10, 20, 30])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    print(f"# {platform.processor() or platform.machine()}, {threads()}, cvxpy {cp.__version__}, "
          f"load average at start {os.getloadavg()[0]:.2f}")
    print("| n | l | one direct solve [s] | full design [s] | ratio | direct, design's settings"
          " [s] | ratio | design solves | status | bound (design) | bound (direct, same alpha) |"
          " alpha | repeats |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|",
          flush=True)
    for n in args.sizes:
        r = bench(n, args.repeats)
        print(f"| {r['n']} | {r['l']} | {r['direct']:.3f} | {r['design']:.3f} | "
              f"{r['ratio']:.2f} | {r['same']:.3f} ({r['opts']}) | {r['ratio_same']:.2f} | "
              f"{r['solves']} | {r['status']} | {r['bound']:.5g} | "
              f"{r['bound_direct']:.5g} ({r['direct_status']}) | {r['decay']:.4g} | "
              f"{r['reps']} |", flush=True)
    print(f"# load average at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
