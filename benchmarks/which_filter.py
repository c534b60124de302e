"""The "Which filter?" table (docs/which_filter.md): every guaranteed filter with its defaults
on the bounded built-in systems, the badly scaled CSTR and the range-and-bearing unicycle.

For each (system, filter) one batch of ``--trials`` vertex-noise trajectories runs over the
system's horizon (``--steps-for NAME=T`` overrides one, ``--trials-for NAME=B`` the batch).
Columns: bounded (trajectories whose set stayed bounded over the whole horizon, and the first
step where one did not), outside (trajectory-steps whose true state is outside a bounded set,
box test with 1e-9 slack), mean width of the interval hull per state over the bounded steps
after the first measurement, and the cost per filter step (wall time of ``forward`` at that
batch, eager, divided by the steps; and per trajectory-step). The header prints the command,
date, commit, machine and thread count.

    OMP_NUM_THREADS=1 python benchmarks/which_filter.py --trials 10
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import subprocess
import sys
import time

import torch

from diffsmf import filters, systems

SYSTEMS = ["bilinear", "spring_damper", "mismatch_quadratic", "vdp", "fermenter", "cstr",
           "unicycle_rb"]
FILTERS = ["hsnsmf", "mszm", "cdsmf", "esmf", "czsmf"]


def _pairs(items: list[str]) -> dict[str, int]:
    out = {}
    for it in items:
        name, _, val = it.partition("=")
        out[name] = int(val)
    return out


def header(argv: list[str]) -> str:
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                                text=True, check=False).stdout.strip() or "unknown"
    except OSError:
        commit = "unknown"
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return (
        f"Command: `{' '.join(['python', *argv])}`  \n"
        f"Date: {now}, commit {commit}, {platform.processor() or platform.machine()} "
        f"({os.cpu_count()} cores, shared), torch {torch.__version__}, "
        f"{torch.get_num_threads()} thread(s)."
    )


def row(sname: str, fname: str, trials: int, steps: int, seed: int) -> str:
    sys_ = systems.get(sname)
    tr = sys_.simulate(steps, batch=trials, seed=seed, noise="vertex")
    filt = filters.by_name(fname)(sys_)
    t0 = time.perf_counter()
    try:
        with torch.no_grad():
            res = filt(tr.y, u=tr.u)
    except Exception as exc:  # a numerical event that stops the batch: say so in the row
        msg = f"{type(exc).__name__}: {exc}".replace("|", "/")
        return f"| {sname} | {type(filt).__name__} | {trials} x {steps} | raised: {msg} | | | | |"
    wall = time.perf_counter() - t0
    b = res.bounded
    all_b = b.all(1)
    lost = (~b).any(0).nonzero()
    first = f", first lost at step {int(lost[0])}" if len(lost) else ""
    inside = ((tr.x >= res.lower - 1e-9) & (tr.x <= res.upper + 1e-9)).all(-1) | ~b
    w = (res.upper - res.lower)[:, 1:]
    wb = torch.where(b[:, 1:].unsqueeze(-1), w, torch.full_like(w, torch.nan))
    widths = ", ".join(f"{v:.3g}" for v in wb.nanmean((0, 1)).tolist())
    ms = wall / steps * 1e3
    return (
        f"| {sname} | {type(filt).__name__} | {trials} x {steps} | {int(all_b.sum())} / {trials}"
        f"{first} | {int((~inside).sum())} | {widths} | {ms:.1f} | {ms / trials:.2f} |"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=10)
    ap.add_argument("--trials-for", nargs="*", default=[], metavar="NAME=B")
    ap.add_argument("--steps-for", nargs="*", default=[], metavar="NAME=T")
    ap.add_argument("--systems", nargs="*", default=SYSTEMS)
    ap.add_argument("--filters", nargs="*", default=FILTERS)
    ap.add_argument("--seed", type=int, default=2024)
    args = ap.parse_args()
    trials_for, steps_for = _pairs(args.trials_for), _pairs(args.steps_for)
    print(header(sys.argv))
    print()
    print("| system | filter | trajectories x steps | bounded | outside | mean width per state "
          "| ms / step | ms / trajectory-step |")
    print("|---|---|---|---|---:|---|---:|---:|")
    for sname in args.systems:
        steps = steps_for.get(sname, systems.get(sname).horizon)
        for fname in args.filters:
            print(row(sname, fname, trials_for.get(sname, args.trials), steps, args.seed),
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
