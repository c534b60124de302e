"""Throughput of batched set operations vs. a straightforward per-set numpy loop.

    python benchmarks/sets_bench.py [--quick] [--budget SECONDS]

Operations (float64, CPU):
  * ``P.intersect_strip(S)``: parallelotope/strip update, Wang et al. 2022, eq. 30-41;
  * ``Z.reduce(2, "girard")``: zonotope with m = 4n generators reduced to 2n;
  * ``Z.to_parallelotope()``: Chisci 1996 minimal-volume outer parallelotope of a zonotope with
    m = 2n generators in 2-D (6 bases) and m = n + 2 = 8 in 6-D (28 bases).
For each operation, dimension n in {2, 6} and batch B in {1, 1e3, 1e5} the table gives sets per
second for the batched torch call and for a per-set numpy loop implementing the same algorithm.
Long cells are measured on a slice of the batch (torch: at most ``--budget`` seconds per cell;
numpy loop: at most 2000 sets) and extrapolated linearly; such cells are marked ``*``.
"""

from __future__ import annotations

import argparse
import itertools
import time
from collections.abc import Callable

import numpy as np
import torch

from diffsmf.sets import Parallelotope, Strip, Zonotope

torch.set_default_dtype(torch.float64)


# ---------------------------------------------------------------------- numpy references
def np_par_strip(c: np.ndarray, T: np.ndarray, a: np.ndarray, y: float, h: float):
    """One parallelotope/strip update, Wang et al. 2022, eq. 30-41, plain numpy (no margins)."""
    n = c.shape[0]
    p, cc = a / h, y / h
    T = T.copy()
    pt = p @ T
    T[:, pt < 0] *= -1
    pt = np.abs(pt)
    mid = p @ c - cc
    e_p, e_m = mid + pt.sum(), mid - pt.sum()
    if e_p < -1 or e_m > 1:
        return c, T
    rp, rm = min(1.0, e_p), min(1.0, -e_m)
    pb = 2 / (rp + rm) * p
    cb = 2 / (rp + rm) * (cc + (rp - rm) / 2)
    Tb, xb = T.copy(), c.copy()
    for i in range(n):
        if pt[i] > 0:
            rip = min(1.0, (1 - e_m) / pt[i] - 1)
            rim = min(1.0, (1 + e_p) / pt[i] - 1)
            Tb[:, i] = (rip + rim) / 2 * T[:, i]
            xb = xb + (rip - rim) / 2 * T[:, i]
    pbt = pb @ Tb
    i = int(np.argmax(pbt))
    if pbt[i] <= 1:
        return xb, Tb
    Tn = Tb - np.outer(Tb[:, i], pbt / pbt[i])
    Tn[:, i] = Tb[:, i] / pbt[i]
    return xb + Tb[:, i] * (cb - pb @ xb) / pbt[i], Tn


def np_girard(c: np.ndarray, G: np.ndarray, order: float):
    n = G.shape[0]
    target = int(order * n)
    score = np.abs(G).sum(0) - np.abs(G).max(0)
    perm = np.argsort(-score)
    keep = G[:, perm[: target - n]]
    rest = G[:, perm[target - n :]]
    return c, np.concatenate([keep, np.diag(np.abs(rest).sum(1))], 1)


def np_chisci(c: np.ndarray, G: np.ndarray):
    n, m = G.shape
    best, bestT = np.inf, None
    for S in itertools.combinations(range(m), n):
        B = G[:, S]
        d = abs(np.linalg.det(B))
        if d <= 1e-12 * np.prod(np.linalg.norm(B, axis=0)):
            continue
        s = np.abs(np.linalg.solve(B, G)).sum(1)
        v = d * np.prod(s)
        if v < best:
            best, bestT = v, B * s
    return c, bestT


# ---------------------------------------------------------------------- timing helpers
def _time(fn: Callable[[], object], min_time: float = 0.2) -> float:
    """Seconds per call (repeats until ``min_time`` has passed)."""
    fn()
    reps, t0 = 0, time.perf_counter()
    while True:
        fn()
        reps += 1
        el = time.perf_counter() - t0
        if el >= min_time:
            return el / reps


def make_inputs(op: str, n: int, B: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    if op == "strip":
        c = torch.randn(B, n, generator=g)
        T = torch.randn(B, n, n, generator=g) + 2 * torch.eye(n)
        a = torch.randn(B, n, generator=g)
        y = (a * c).sum(-1) + 0.3 * torch.randn(B, generator=g)
        h = 0.2 + torch.rand(B, generator=g)
        return (Parallelotope(c, T), Strip(a, y, h))
    m = 4 * n if op == "reduce" else (2 * n if n == 2 else n + 2)
    return (Zonotope(torch.randn(B, n, generator=g), torch.randn(B, n, m, generator=g)),)


def torch_call(op: str, args):
    if op == "strip":
        return args[0].intersect_strip(args[1])
    if op == "reduce":
        return args[0].reduce(2, "girard")
    return args[0].to_parallelotope()


def numpy_loop(op: str, args, k: int) -> Callable[[], None]:
    if op == "strip":
        P, S = args
        c, T = P.center[:k].numpy(), P.T[:k].numpy()
        a, y, h = S.normal[:k].numpy(), S.offset[:k].numpy(), S.halfwidth[:k].numpy()
        return lambda: [np_par_strip(c[i], T[i], a[i], y[i], h[i]) for i in range(k)]
    Z = args[0]
    c, G = Z.center[:k].numpy(), Z.generators[:k].numpy()
    if op == "reduce":
        return lambda: [np_girard(c[i], G[i], 2) for i in range(k)]
    return lambda: [np_chisci(c[i], G[i]) for i in range(k)]


def bench_cell(
    op: str, n: int, B: int, budget: float, np_cap: int
) -> tuple[float, bool, float, bool]:
    """(torch sets/s, torch extrapolated?, numpy sets/s, numpy extrapolated?)."""
    # torch: probe a small slice to estimate the cost, then measure a slice that fits the budget
    probe = min(B, 1000)
    t_probe = _time(lambda: torch_call(op, make_inputs(op, n, probe)), min_time=0.05)
    est = t_probe * B / probe
    Bt = B if est <= budget else max(probe, int(B * budget / est))
    args = make_inputs(op, n, Bt)
    t = _time(lambda: torch_call(op, args), min_time=0.2 if Bt < 10_000 else 0.0)
    torch_rate = Bt / t
    k = min(B, np_cap)
    np_args = make_inputs(op, n, k)
    tn = _time(numpy_loop(op, np_args, k), min_time=0.2 if k < 100 else 0.0)
    return torch_rate, Bt < B, k / tn, k < B


def fmt(rate: float, extrap: bool) -> str:
    s = f"{rate:,.0f}" if rate >= 100 else f"{rate:,.1f}"
    return s + ("*" if extrap else "")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="B in {1, 1e3} only")
    ap.add_argument("--budget", type=float, default=6.0, help="max seconds per torch cell")
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    ap.add_argument("--np-cap", type=int, default=2000, help="max sets in the numpy loop")
    args = ap.parse_args(argv)
    # one thread by default: the numpy loop is single-threaded too, and on a loaded 2-core
    # machine torch's intra-op threads contend badly (up to 50x slower elementwise ops)
    torch.set_num_threads(args.threads)
    Bs = [1, 1000] if args.quick else [1, 1000, 100_000]
    names = {
        "strip": "Parallelotope.intersect_strip",
        "reduce": "Zonotope.reduce(2, girard)",
        "chisci": "Zonotope.to_parallelotope",
    }
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, float64, CPU")
    header = "| operation | n | B | torch batched (sets/s) | numpy loop (sets/s) | ratio |"
    print(header)
    print("|---|---|---|---|---|---|")
    t0 = time.perf_counter()
    for op in ("strip", "reduce", "chisci"):
        for n in (2, 6):
            for B in Bs:
                tr, te, nr, ne = bench_cell(op, n, B, args.budget, args.np_cap)
                print(
                    f"| {names[op]} | {n} | {B:,} | {fmt(tr, te)} | {fmt(nr, ne)} | "
                    f"{tr / nr:,.1f}x |",
                    flush=True,
                )
    print(
        f"\n* measured on a slice of the batch and extrapolated linearly; "
        f"total {time.perf_counter() - t0:.0f} s"
    )


if __name__ == "__main__":
    main()
