"""Full containment audit: every guaranteed filter on every bounded built-in system.

For each (system, filter, noise in {vertex, uniform}) one batch of ``--trials`` trajectories
runs over the system's horizon (``system.horizon``: the papers' horizons), and the table lists
the (trajectory, step) pairs outside the set (tolerance 1e-9 on the normalised distance, see
:mod:`diffsmf.audit`), the worst normalised distance outside, the mean volume and the wall
time. ``--trials-for fermenter=100`` lowers the count for a slow system (stated in the table).
Output: a markdown table on stdout (pasted into docs/filters.md).

    python benchmarks/filters_audit.py --trials 1000 --trials-for fermenter=100
"""

from __future__ import annotations

import argparse
import sys

import torch

from diffsmf import filters, systems
from diffsmf.audit import containment


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=1000)
    ap.add_argument("--trials-for", nargs="*", default=[], help="NAME=COUNT overrides")
    ap.add_argument("--steps", type=int, default=None, help="override every horizon")
    ap.add_argument("--systems", nargs="*", default=None)
    ap.add_argument("--filters", nargs="*", default=["hsnsmf", "mszm", "cdsmf", "esmf"])
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--noises", nargs="+", default=["vertex", "uniform"],
                    choices=["vertex", "uniform"], help="noise kinds (default both)")
    ap.add_argument(
        "--progress", action="store_true",
        help="progress bars on stderr; filters each batch in chunks of 100 trajectories "
        "(same trajectories; CZSMF runs faster in chunks: its LP batches then fit in cache)",
    )
    args = ap.parse_args()
    torch.set_default_dtype(torch.float64)
    override = {k: int(v) for k, v in (s.split("=") for s in args.trials_for)}
    names = args.systems or systems.names()
    print("| system | filter | noise | trajectories x steps | outside / pairs | worst dist. "
          "| mean volume | inconsistent | time [s] |")
    print("|---|---|---|---|---:|---:|---:|---:|---:|")
    bad = 0
    for sname in names:
        system = systems.get(sname)
        if system.process_cov is not None or system.measurement_cov is not None:
            print(f"| {sname} | - | - | - | skipped: Gaussian noise, no guaranteed bound | | | | |")
            continue
        trials = override.get(sname, args.trials)
        for fname in args.filters:
            for noise in args.noises:
                filt = filters.by_name(fname)(system)
                rep = containment(
                    filt, system, trials, args.steps, noise, args.seed, progress=args.progress
                )
                bad += rep.violations
                print(
                    f"| {sname} | {rep.filter} | {noise} | {rep.trials} x {rep.steps} | "
                    f"{rep.violations} / {rep.pairs} | {rep.worst_distance:.1e} | "
                    f"{rep.mean_volume:.3e} | {rep.inconsistent} | {rep.seconds:.0f} |",
                    flush=True,
                )
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
