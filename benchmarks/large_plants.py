"""Every guaranteed filter on a large plant: a cascade of tanks with square-root outflows.

The plant (the shape of CORA's tank observer tests): ``n`` tanks in a row, levels near 20,
each tank's outflow ``k sqrt(2 g x_i)`` feeding the next, a constant inflow to the first; every
second level measured with noise bounded by 0.2; process noise bounded by 0.01; the initial
box 16..24 (width 8) in every level. Each filter runs on the same vertex-noise trajectories
(the worst case of the linearisation remainders) and the table gives, per filter:

* whether it ran (an exception is a row, not a crash of the script);
* the trajectories still bounded at the last step (a lost bound is flagged, never hidden);
* the (trajectory, step) pairs whose true state left the set (must be 0);
* the mean final width sum over the bounded trajectories, against the initial box's;
* ms per step (median of the per-step times over the run) and the mean of the first and the
  last tenth of the steps, which says whether the cost is flat in time.

There is no peer in Python for these filters at this size (the reference toolbox is MATLAB);
the initial box's width sum is the reference the sets must beat.

    python benchmarks/large_plants.py [--n 30] [--steps 100] [--trials 20] [--filters ...]

``mszm-cut`` is MSZM with its strips cut to the zonotope's range (``tighten_strips=True``).
"""

from __future__ import annotations

import argparse
import platform
import subprocess
import time
from pathlib import Path

import torch

import diffsmf as ds

F64 = torch.float64
GUARANTEED = ("hsnsmf", "mszm", "mszm-cut", "cdsmf", "esmf", "czsmf", "interval")
#: Rows that are a filter with options: the name, the filter and its options.
VARIANTS = {"mszm-cut": ("mszm", {"tighten_strips": True})}


def tank_cascade(n: int) -> ds.System:
    """``n`` tanks in a row (the built-in ``tank_cascade``)."""
    return ds.systems.get("tank_cascade", n=n)


def run_one(name: str, system: ds.System, traj, steps: int) -> dict:
    """One filter over the trajectories, timed per step -> its row."""
    try:
        base, options = VARIANTS.get(name, (name, {}))
        filt = ds.filters.get(base)(system, **options)
        state, times = filt.initial_state(traj.y.shape[0]), []
        lows, highs, bounded = [], [], []
        with torch.no_grad():
            for k in range(steps):
                t0 = time.perf_counter()
                state = filt.update(filt.predict(state), traj.y[:, k])
                times.append(time.perf_counter() - t0)
                hull = state.set.interval_hull()
                lows.append(hull.lower)
                highs.append(hull.upper)
                bounded.append(state.bounded if state.bounded is not None
                               else torch.ones(hull.lower.shape[0], dtype=torch.bool))
    except Exception as exc:  # a row of the table, not a crash
        return {"filter": name, "error": f"{type(exc).__name__}: {exc}"[:80]}
    lo, hi, ok = torch.stack(lows, 1), torch.stack(highs, 1), torch.stack(bounded, 1)
    x = traj.x[:, 1 : steps + 1]
    outside = ((x < lo - 1e-9) | (x > hi + 1e-9)).any(-1) & ok
    final = ok[:, -1]
    width = (hi[:, -1] - lo[:, -1]).sum(-1)
    tenth = max(1, steps // 10)
    return {
        "filter": name,
        "bounded": f"{int(final.sum())}/{len(final)}",
        "outside": f"{int(outside.sum())}/{outside.numel()}",
        "width": float(width[final].mean()) if bool(final.any()) else float("inf"),
        "ms": 1e3 * float(torch.tensor(times).median()),
        "first": 1e3 * sum(times[:tenth]) / tenth,
        "last": 1e3 * sum(times[-tenth:]) / tenth,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=30, help="number of tanks (states)")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--trials", type=int, default=20, help="vertex-noise trajectories")
    ap.add_argument("--filters", nargs="+", default=list(GUARANTEED))
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    system = tank_cascade(a.n)
    traj = system.simulate(a.steps, batch=a.trials, seed=0, noise="vertex")
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True, cwd=Path(__file__).parent).stdout.strip()
    print(f"{time.strftime('%Y-%m-%d')}, commit {commit}, {platform.machine()}, torch "
          f"{torch.__version__}, {torch.get_num_threads()} thread(s); {a.n} tanks, "
          f"{a.trials} vertex-noise trajectories x {a.steps} steps; initial box width sum "
          f"{8.0 * a.n:g}")
    print("\n| filter | bounded at the end | outside / pairs | final width sum | ms / step "
          "(median) | ms / step, first / last tenth |")
    print("|---|---:|---:|---:|---:|---:|")
    for name in a.filters:
        r = run_one(name, system, traj, a.steps)
        if "error" in r:
            print(f"| {name} | - | - | - | - | {r['error']} |")
            continue
        print(f"| {name} | {r['bounded']} | {r['outside']} | {r['width']:.4g} | {r['ms']:.1f} | "
              f"{r['first']:.1f} / {r['last']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
