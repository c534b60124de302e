"""PWL benchmark: SCPLNN (fit_scplnn) vs scipy LinearNDInterpolator, hinging hyperplanes and
pwlf, on the same held-out points, in the same run.

    python benchmarks/pwl_bench.py [--quick] [--repeats 3] [--out out/pwl_bench.md]

Sections (each prints a markdown table):

1. **Peak target.** ``peak(x) = exp(-3 |x|^2)`` on [-2, 2]^2 (a smooth function
   with one peak; this one was chosen because
   LinearNDInterpolator on 10,000 uniform samples reaches a held-out max of 0.008-0.009 on it,
   0.0084 as the target), 10,000 uniform samples (seed 0), held-out error on the 200 x 200
   ``linspace`` grid clamped into the samples' bounding box (every method inside its domain).
   Ours at several eps, the ``rule="interior"`` split for comparison, and a
   sharper peak exp(-10 |x|^2). Times: median of ``--repeats`` runs. Target: held-out max <=
   LinearNDInterpolator's with <= 1/5 of its vertices in < 2 s.
2. **Peers at equal size** on the same grids: hinging hyperplanes (Breiman 1993) with as
   many parameters as the SCPLNN (K <= 40), and pwlf in 1-D (sin(3x) + x/2 on [0, 3], 2,000
   samples, pwlf ``fitfast`` with the SCPLNN's number of segments; one run, pwlf is slow).
3. **Dimension table**: sum_i sin x_i on [-1, 1]^d, 20,000 uniform samples,
   eps 0.05, d = 1..6, held-out error on 20,000 other uniform points. d = 6 uses
   ``domain="box"`` (the default for n > 5 is an enclosing simplex, mostly empty space) and a
   200,000-region cap (20,000 samples are too few to pin down the vertices beyond that).
4. **Wang et al. 2009 example**: -x1^2 x2 on the 101 x 101 grid, eps 0.1 / 0.03 / 0.01, default rule
   and the old one, held-out on the 200 x 200 grid of cell centres.

Threads: torch runs with one intra-op thread here (``fit_scplnn`` always fits on one);
numpy/scipy BLAS is limited to one thread (threadpoolctl) for every method: with two OpenBLAS
threads on the loaded 2-core machine, LinearNDInterpolator's first evaluation took 62 s instead
of 0.01 s. LinearNDInterpolator (qhull) is single-threaded anyway. Timings on a shared
machine are noisy: compare ours and the peer of the same row, measured in the same run.
"""

from __future__ import annotations

import argparse
import math
import os
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from diffsmf.pwl import HingingHyperplanes, fit_scplnn

torch.set_num_threads(1)


def peak(X: np.ndarray, a: float = 3.0) -> np.ndarray:
    return np.exp(-a * (X ** 2).sum(-1))


def sharp_peak(X: np.ndarray) -> np.ndarray:
    return peak(X, 10.0)


def wang2009(X: np.ndarray) -> np.ndarray:  # Wang et al. 2009, sec. 4: f(X) = -x1^2 x2
    return -X[:, 0] ** 2 * X[:, 1]


def wave1d(X: np.ndarray) -> np.ndarray:
    return np.sin(3 * X[:, 0]) + 0.5 * X[:, 0]


def _median_time(fn: Callable[[], object], repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def _predict(model: torch.nn.Module, X: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return model(torch.from_numpy(X))[:, 0].numpy()


def peak_grid(X: np.ndarray) -> np.ndarray:
    t = np.linspace(-2, 2, 200)
    G = np.stack(np.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)
    return np.clip(G, X.min(0), X.max(0))


def peak_section(repeats: int, quick: bool) -> tuple[list[str], list[str]]:
    from scipy.interpolate import LinearNDInterpolator

    rng = np.random.default_rng(0)
    X = rng.uniform(-2, 2, size=(10_000, 2))
    G = peak_grid(X)
    lines = ["| function | method | eps | vertices | regions | fit s (median) | train max "
             "| held-out est. (report) | held-out max (grid) | vs LinearND: error ratio "
             "| vertex ratio | time ratio |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    peers = []
    for fname, f in (("exp(-3|x|^2)", peak), ("exp(-10|x|^2)", sharp_peak)):
        y, yg = f(X), f(G)
        t_l, interp = _median_time(lambda y=y: LinearNDInterpolator(X, y), repeats)
        t_e, pred = _median_time(lambda interp=interp: interp(G), repeats)
        ok = np.isfinite(pred)
        l_err = float(np.abs(pred[ok] - yg[ok]).max())
        l_time = t_l + t_e
        lines.append(f"| {fname} | LinearNDInterpolator (all samples) | - | {len(X)} | "
                     f"{len(interp.tri.simplices)} | {l_time:.3f} (build + grid eval) | 0 | - | "
                     f"{l_err:.4f} | 1 | 1 | 1 |")
        eps_list = (0.01, 0.005, 0.004) if not quick else (0.005,)
        rules = [("rivara", e) for e in eps_list] + [("interior", 0.005)]
        if fname != "exp(-3|x|^2)":
            rules = [("rivara", 0.005), ("rivara", 0.004), ("interior", 0.005)]
        for rule, eps in rules:
            def run(rule=rule, eps=eps, y=y):
                return fit_scplnn(torch.from_numpy(X), torch.from_numpy(y), eps, rule=rule)
            t, (model, rep) = _median_time(run, repeats)
            err = float(np.abs(_predict(model, G) - yg).max())
            est = ("-" if rep.heldout_max_error is None
                   else f"{float(rep.heldout_max_error[0]):.4f}")
            name = "SCPLNN" + (" (rule='interior')" if rule == "interior" else "")
            lines.append(f"| {fname} | {name} | {eps} | {rep.vertices} | {rep.regions} | "
                         f"{t:.3f} | {float(rep.max_error[0]):.4f} | {est} | {err:.4f} | "
                         f"{err / l_err:.2f} | {rep.vertices / len(X):.3f} | "
                         f"{t / l_time:.2f} |")
            print(lines[-1], flush=True)
        if fname == "exp(-3|x|^2)" and not quick:  # hinging hyperplanes on the same grid
            model, rep = fit_scplnn(torch.from_numpy(X), torch.from_numpy(y), 0.005)
            k = min(40, max(1, rep.parameters // 6))
            t0 = time.perf_counter()
            hh = HingingHyperplanes(n_hinges=k, n_starts=2, backfit_passes=1, seed=0).fit(X, y)
            secs = time.perf_counter() - t0
            peers.append(f"| {fname} 2-D, 10k samples | hinging hyperplanes (K={k}) | "
                         f"{hh.n_parameters()} | {secs:.2f} | "
                         f"{float(np.abs(_predict(hh, G) - yg).max()):.4f} | SCPLNN eps 0.005: "
                         f"{rep.parameters} params, "
                         f"{float(np.abs(_predict(model, G) - yg).max()):.4f} |")
            print(peers[-1], flush=True)
    return lines, peers


def pwlf_section(quick: bool) -> list[str]:
    rng = np.random.default_rng(1)
    X = rng.uniform(0, 3, size=(2000, 1))
    y = wave1d(X)
    xt = np.linspace(X.min(), X.max(), 20_000)[:, None]
    yt = wave1d(xt)
    out = []
    for eps in (0.05,):
        t0 = time.perf_counter()
        model, rep = fit_scplnn(torch.from_numpy(X), torch.from_numpy(y), eps)
        secs = time.perf_counter() - t0
        err = float(np.abs(_predict(model, xt) - yt).max())
        ours = f"SCPLNN eps {eps}: {rep.parameters} params, {secs:.3f} s, {err:.4f}"
        hh = HingingHyperplanes(n_hinges=max(1, rep.parameters // 4), n_starts=2,
                                backfit_passes=1, seed=0)
        t0 = time.perf_counter()
        hh.fit(X, y)
        hs = time.perf_counter() - t0
        out.append(f"| sin(3x)+x/2 1-D, 2k samples | hinging hyperplanes (K={hh.n_hinges}) | "
                   f"{hh.n_parameters()} | {hs:.2f} | "
                   f"{float(np.abs(_predict(hh, xt) - yt).max()):.4f} | {ours} |")
        if not quick:
            import pwlf

            t0 = time.perf_counter()
            pw = pwlf.PiecewiseLinFit(X[:, 0], y, seed=0)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                pw.fitfast(rep.regions, pop=2)
            ps = time.perf_counter() - t0
            out.append(f"| sin(3x)+x/2 1-D, 2k samples | pwlf fitfast ({rep.regions} segments, "
                       f"breakpoints optimised) | {2 * rep.regions} | {ps:.2f} | "
                       f"{float(np.abs(pw.predict(xt[:, 0]) - yt).max()):.4f} | {ours}; "
                       f"time ratio pwlf / SCPLNN {ps / secs:.0f}x |")
        print(out[-1], flush=True)
    return out


def dimension_section(dims: list[int], n_train: int = 20_000) -> list[str]:
    lines = ["| d | fit s | regions | vertices | rounds | train max | held-out est. | test max "
             "| test RMS | converged | stop |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for d in dims:
        g = torch.Generator().manual_seed(d)
        X = torch.rand(n_train, d, generator=g, dtype=torch.float64) * 2 - 1
        Xt = torch.rand(20_000, d, generator=g, dtype=torch.float64) * 2 - 1
        Xt = torch.maximum(torch.minimum(Xt, X.amax(0)), X.amin(0))
        t0 = time.perf_counter()
        kw = {} if d < 6 else dict(domain="box", max_regions=200_000)  # see the docstring
        model, rep = fit_scplnn(X, torch.sin(X).sum(-1), 0.05, **kw)
        secs = time.perf_counter() - t0
        with torch.no_grad():
            e = (model(Xt)[:, 0] - torch.sin(Xt).sum(-1)).abs()
        est = "-" if rep.heldout_max_error is None else f"{float(rep.heldout_max_error[0]):.4f}"
        lines.append(f"| {d} | {secs:.2f} | {rep.regions} | {rep.vertices} | {rep.rounds} | "
                     f"{float(rep.max_error[0]):.4f} | {est} | {float(e.max()):.4f} | "
                     f"{float(e.pow(2).mean().sqrt()):.4f} | {rep.converged} | "
                     f"{rep.stop_reason} |")
        print(lines[-1], flush=True)
    return lines


def seed_section() -> list[str]:
    t = np.linspace(-2, 2, 101)
    X = np.stack(np.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)
    y = wang2009(X)
    tm = np.linspace(-2, 2, 201)
    tm = (tm[1:] + tm[:-1]) / 2
    Xh = np.stack(np.meshgrid(tm, tm, indexing="ij"), -1).reshape(-1, 2)
    yh = wang2009(Xh)
    lines = ["| rule | eps | regions | vertices | train max | held-out est. | held-out max "
             "(grid) | held-out RMS | s | converged |", "|---|---|---|---|---|---|---|---|---|---|"]
    for rule in ("rivara", "interior"):
        for eps in (0.1, 0.03, 0.01):
            model, rep = fit_scplnn(torch.from_numpy(X), torch.from_numpy(y), eps, rule=rule)
            e = np.abs(_predict(model, Xh) - yh)
            est = ("-" if rep.heldout_max_error is None
                   else f"{float(rep.heldout_max_error[0]):.4f}")
            lines.append(f"| {rule} | {eps} | {rep.regions} | {rep.vertices} | "
                         f"{float(rep.max_error[0]):.4f} | {est} | {e.max():.4f} | "
                         f"{np.sqrt(np.mean(e ** 2)):.4f} | {rep.seconds:.2f} | "
                         f"{rep.converged} |")
            print(lines[-1], flush=True)
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer cases, no pwlf, d <= 4")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--dims", default=None, help="comma-separated d for the dimension table")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1, user_api="blas"):  # numpy/scipy BLAS on one thread as well
        _run(args)


def _run(args: argparse.Namespace) -> None:
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan
    head = (f"torch {torch.__version__}, torch threads {torch.get_num_threads()}, BLAS threads 1, "
            f"{os.cpu_count()} CPUs, load average at start {load:.1f}")
    print(head, flush=True)
    peak_lines, peers = peak_section(args.repeats, args.quick)
    peers = (["| case | method | params | fit s | held-out max | SCPLNN (same run) |",
              "|---|---|---|---|---|---|"] + peers + pwlf_section(args.quick))
    dims = ([int(v) for v in args.dims.split(",")] if args.dims else
            ([1, 2, 3, 4] if args.quick else [1, 2, 3, 4, 5, 6]))
    dim_lines = dimension_section(dims)
    seed = seed_section()
    report = "\n".join([head, "", "1. Peak target (10,000 samples, 200x200 grid):", "",
                        *peak_lines, "", "2. Peers:", "", *peers, "",
                        "3. sum sin x_i on [-1, 1]^d, 20,000 samples, eps 0.05:", "",
                        *dim_lines, "",
                        "4. Wang et al. 2009 (-x1^2 x2, 101x101 grid):", "", *seed, ""])
    print()
    print(report)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(report)


if __name__ == "__main__":
    main()
