"""PWL benchmark: SCPLNN vs hinging hyperplanes, scipy LinearNDInterpolator and pwlf.

    python benchmarks/pwl_bench.py [--quick] [--out out/pwl_bench.md]

For each test function: N uniform training samples, held-out uniform samples of the same box
(clamped into the training samples' bounding box so that every method is evaluated inside its
domain), SCPLNN fitted to eps = 1% of the output range (5% for the 4-D function). Baselines:

* hinging hyperplanes (Breiman 1993) with as many parameters as the SCPLNN (K = weights /
  2(n+1), at most 40),
* LinearNDInterpolator on a random subset of the samples with as many points as the SCPLNN has
  vertices (same number of values stored), and on all samples (interpolation, no compression),
* pwlf (1-D only) with as many segments as the SCPLNN has regions.

Prints a markdown table: fit seconds, regions, parameters, held-out max and RMS error.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch

from diffsmf.pwl import HingingHyperplanes, fit_scplnn

torch.set_default_dtype(torch.float64)


def franke(X: np.ndarray) -> np.ndarray:
    x, y = 9 * X[:, 0], 9 * X[:, 1]
    return (0.75 * np.exp(-((x - 2) ** 2 + (y - 2) ** 2) / 4)
            + 0.75 * np.exp(-((x + 1) ** 2) / 49 - (y + 1) / 10)
            + 0.5 * np.exp(-((x - 7) ** 2 + (y - 3) ** 2) / 4)
            - 0.2 * np.exp(-((x - 4) ** 2) - (y - 7) ** 2))


def seed004(X: np.ndarray) -> np.ndarray:  # seed 004 sec. 4: f(X) = -x1^2 x2
    return -X[:, 0] ** 2 * X[:, 1]


def friedman4(X: np.ndarray) -> np.ndarray:  # make_friedman1's smooth part, first 4 inputs
    return 10 * np.sin(np.pi * X[:, 0] * X[:, 1]) + 20 * (X[:, 2] - 0.5) ** 2 + 10 * X[:, 3]


def wave1d(X: np.ndarray) -> np.ndarray:
    return np.sin(3 * X[:, 0]) + 0.5 * X[:, 0]


CASES = {
    "Franke [0,1]^2": (franke, 2, 0.0, 1.0),
    "-x1^2 x2 [-2,2]^2": (seed004, 2, -2.0, 2.0),
    "Friedman-4 [0,1]^4": (friedman4, 4, 0.0, 1.0),
    "sin(3x)+x/2 [0,3]": (wave1d, 1, 0.0, 3.0),
}


def _errors(pred: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    e = np.abs(pred - y)
    return float(e.max()), float(np.sqrt(np.mean(e**2)))


def run_case(name: str, n_train: int, n_test: int, rng: np.random.Generator,
             hinging: bool = True) -> list[dict]:
    f, n, lo, hi = CASES[name]
    X = rng.uniform(lo, hi, size=(n_train, n))
    y = f(X)
    Xt = rng.uniform(lo, hi, size=(n_test, n))
    Xt = np.clip(Xt, X.min(0), X.max(0))
    yt = f(Xt)
    rel = 0.01 if n <= 2 else 0.05
    eps = rel * (y.max() - y.min())
    rows = []
    t0 = time.perf_counter()
    model, rep = fit_scplnn(torch.from_numpy(X), torch.from_numpy(y), eps, max_regions=50_000)
    secs = time.perf_counter() - t0
    with torch.no_grad():
        pred = model(torch.from_numpy(Xt))[:, 0].numpy()
    rows.append(dict(case=name, method=f"SCPLNN (eps = {rel:.0%} range)", seconds=secs,
                     regions=rep.regions, params=rep.parameters, train_max=float(rep.max_error[0]),
                     held=_errors(pred, yt), note=f"converged={rep.converged}"))
    if hinging:
        k = min(40, max(1, rep.parameters // (2 * (n + 1))))
        t0 = time.perf_counter()
        hh = HingingHyperplanes(n_hinges=k, n_starts=2, backfit_passes=1, seed=0).fit(X, y)
        secs = time.perf_counter() - t0
        with torch.no_grad():
            pred = hh(torch.from_numpy(Xt))[:, 0].numpy()
            tr = float((hh(torch.from_numpy(X))[:, 0] - torch.from_numpy(y)).abs().max())
        rows.append(dict(case=name, method=f"hinging hyperplanes (K={k})", seconds=secs,
                         regions=hh.n_regions(torch.from_numpy(Xt)), params=hh.n_parameters(),
                         train_max=tr, held=_errors(pred, yt),
                         note="same parameters" if k < 40 else "K capped at 40"))
    if n >= 2:
        from scipy.interpolate import LinearNDInterpolator

        for label, m in (("same vertices", rep.vertices), ("all samples", n_train)):
            idx = rng.choice(n_train, size=min(m, n_train), replace=False)
            # keep the box corners' nearest samples so the hull covers the test points
            t0 = time.perf_counter()
            try:
                interp = LinearNDInterpolator(X[idx], y[idx])
                pred = interp(Xt)
                secs = time.perf_counter() - t0
                ok = np.isfinite(pred)
                rows.append(dict(case=name, method=f"LinearNDInterpolator ({label})",
                                 seconds=secs, regions=len(interp.tri.simplices),
                                 params=len(idx), train_max=0.0 if m == n_train else math.nan,
                                 held=_errors(pred[ok], yt[ok]),
                                 note=f"{int((~ok).sum())} test pts outside hull skipped"))
            except Exception as exc:  # qhull failure in higher dims
                rows.append(dict(case=name, method=f"LinearNDInterpolator ({label})",
                                 seconds=math.nan, regions=0, params=len(idx),
                                 train_max=math.nan, held=(math.nan, math.nan),
                                 note=f"failed: {type(exc).__name__}"))
    else:
        import pwlf

        segs = rep.regions
        t0 = time.perf_counter()
        pw = pwlf.PiecewiseLinFit(X[:, 0], y, seed=0)
        pw.fitfast(segs, pop=3)
        secs = time.perf_counter() - t0
        pred = pw.predict(Xt[:, 0])
        rows.append(dict(case=name, method=f"pwlf fitfast ({segs} segments)", seconds=secs,
                         regions=segs, params=2 * segs, train_max=float(np.abs(pw.predict(X[:, 0])
                                                                          - y).max()),
                         held=_errors(pred, yt), note="breakpoints optimised"))
    return rows


def seed_table(rng: np.random.Generator, hinging: bool = True) -> list[str]:
    """Seed 004 sec. 4: -x1^2 x2 on [-2, 2]^2 for eps in {0.1, 0.03, 0.01} (101x101 grid
    samples, held-out: the 200x200 grid of cell centres), and hinging hyperplanes at the same
    number of regions."""
    t = np.linspace(-2, 2, 101)
    X = np.stack(np.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)
    y = seed004(X)
    tm = np.linspace(-2, 2, 201)
    tm = (tm[1:] + tm[:-1]) / 2
    Xh = np.stack(np.meshgrid(tm, tm, indexing="ij"), -1).reshape(-1, 2)
    yh = seed004(Xh)
    lines = ["| eps | regions | vertices | train max | held-out max | held-out RMS | seconds |"
             " HH hinges (regions) | HH train max | HH held-out max |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for eps in (0.1, 0.03, 0.01):
        model, rep = fit_scplnn(torch.from_numpy(X), torch.from_numpy(y), eps)
        with torch.no_grad():
            e = np.abs(model(torch.from_numpy(Xh))[:, 0].numpy() - yh)
        hh_txt = "| - | - | - |"
        if hinging and eps >= 0.03:
            for k in (5, 10, 15, 20, 25, 30, 40):  # smallest K reaching the SCPLNN's regions
                hh = HingingHyperplanes(n_hinges=k, n_starts=2, backfit_passes=1, seed=0)
                hh.fit(X, y)
                r = hh.n_regions(torch.from_numpy(Xh))
                if r >= rep.regions:
                    break
            with torch.no_grad():
                htr = float((hh(torch.from_numpy(X))[:, 0] - torch.from_numpy(y)).abs().max())
                hho = float(np.abs(hh(torch.from_numpy(Xh))[:, 0].numpy() - yh).max())
            hh_txt = f"| {k} ({r}) | {htr:.4f} | {hho:.4f} |"
        lines.append(f"| {eps} | {rep.regions} | {rep.vertices} | {float(rep.max_error[0]):.4f} "
                     f"| {e.max():.4f} | {np.sqrt(np.mean(e**2)):.4f} | {rep.seconds:.2f} "
                     + hh_txt)
    return lines


def timing_target(rng: np.random.Generator) -> str:
    """The target: 2-D, 10,000 samples, eps = 1% of the range, under 2 s (median of 3)."""
    X = rng.uniform(-2, 2, size=(10_000, 2))
    y = seed004(X)
    eps = 0.01 * (y.max() - y.min())
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        _, rep = fit_scplnn(torch.from_numpy(X), torch.from_numpy(y), eps)
        times.append(time.perf_counter() - t0)
    return (f"2-D target (-x1^2 x2, 10,000 samples, eps = {eps:.4f} = 1% of range): "
            f"median {np.median(times):.2f} s over 3 runs, {rep.regions} regions, "
            f"converged={rep.converged}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer samples, no hinging baseline")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    n_train = 2000 if args.quick else 10_000
    lines = ["| function | method | fit s | regions | params | train max | held-out max |"
             " held-out RMS | note |", "|---|---|---|---|---|---|---|---|---|"]
    for name in CASES:
        nt = {1: 2000, 2: n_train, 4: n_train}[CASES[name][1]]
        for r in run_case(name, nt, 20_000, rng, hinging=not args.quick):
            lines.append(f"| {r['case']} | {r['method']} | {r['seconds']:.2f} | {r['regions']} "
                         f"| {r['params']} | {r['train_max']:.4g} | {r['held'][0]:.4g} "
                         f"| {r['held'][1]:.4g} | {r['note']} |")
        print(lines[-1], flush=True)
    text = "\n".join(lines)
    seed = "\n".join(seed_table(rng, hinging=not args.quick))
    target = timing_target(rng)
    report = f"{text}\n\nSeed 004 example:\n\n{seed}\n\n{target}\n"
    print()
    print(report)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(report)


if __name__ == "__main__":
    main()
