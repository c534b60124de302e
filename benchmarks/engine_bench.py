"""Cost of a guaranteed filter step against a lean numpy zonotope filter, in one table.

The peer is a hand-written numpy loop of Alamo et al. (2005)'s zonotope filter on
``spring_damper`` with a closed-form remainder (the model's only nonlinearity is the cubic
``dt k0 kd x1^3``, whose Lagrange remainder about ``c1`` is ``dt k0 kd d^2 (3 c1 + d)`` for
``d = x1 - c1``, maximised in closed form), Girard's order reduction and the F-radius strip
update, one trajectory at a time: about 60 lines, the fastest honest way to write this filter
by hand. diffsmf's HSNSMF and MSZM run batched, eager and compiled (``filt.compile()``; online:
one compiled ``filt.step`` per measurement inside ``filt.streaming()``).

Printed in one table, with the targets: aten calls per eager HSNSMF step (n = 2, B = 1), the
rate ratios to the numpy loop, the eager step of a 6-state model with square roots (a cascade
of six tanks; timed first, before any compile in the process, and again after the compiled
rows), and the cold compile time per filter and batch size. Median of ``--repeats``.
The compiled online row times the numpy loop beside each of its repeats (`online_paired`, at
least ``ONLINE_REPEATS``) and reports the median of those pairs' ratios.

    python benchmarks/engine_bench.py [--steps 10] [--big 10000] [--no-compile] [--threads 1]

``--device cuda`` builds every system and filter on a GPU (``torch.set_default_device``); the
numpy loop stays on the CPU.
"""

from __future__ import annotations

import argparse
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils._python_dispatch import TorchDispatchMode

import diffsmf as ds

sys.path.insert(0, str(Path(__file__).parent))
from filters_bench import _time_torch  # noqa: E402 - the shared torch timing loop

DT, K0, KD, CD = 0.1, 1.5, 3.0, 1.24
ONLINE_STEPS = 200  # steps per repeat of the compiled online row
ONLINE_REPEATS = 9  # at least this many (numpy, diffsmf) pairs of it (about 20 ms each)
W, V = 2e-3, 1e-3
C0, R0 = np.array([0.25, 0.25]), np.array([0.15, 0.15])  # the loop's initial box


# ---------------------------------------------------------------------- numpy Alamo loop
def _f(x: np.ndarray) -> np.ndarray:
    return np.array([x[0] + DT * x[1], x[1] + DT * (-K0 * x[0] * (1 - KD * x[0] ** 2) - CD * x[1])])


def _cubic_range(c1: float, r: float) -> tuple[float, float]:
    """Range of ``d^2 (3 c1 + d)`` over ``|d| <= r`` (endpoints and stationary points)."""
    cand = [-r, r, 0.0]
    if abs(2 * c1) <= r:
        cand.append(-2 * c1)
    vals = [d * d * (3 * c1 + d) for d in cand]
    return min(vals), max(vals)


def _reduce(G: np.ndarray, order: int) -> np.ndarray:
    """Girard's reduction: keep the largest generators, box the rest."""
    n, m = G.shape
    if m <= order * n:
        return G
    score = np.abs(G).sum(0) - np.abs(G).max(0)
    idx = np.argsort(score)
    k = m - order * n + n
    return np.hstack([G[:, idx[k:]], np.diag(np.abs(G[:, idx[:k]]).sum(1))])


def numpy_alamo(y: np.ndarray, c0: np.ndarray, r0: np.ndarray, order: int = 5) -> np.ndarray:
    """Zonotope filter on one trajectory ``y [T, 1]`` -> centres ``[T+1, 2]``."""
    c, G = c0.copy(), np.diag(r0)
    h = np.array([1.0, 0.0])
    out = [c]
    for k in range(y.shape[0]):
        J = np.array([[1.0, DT], [DT * (-K0 + 3 * K0 * KD * c[0] ** 2), 1 - DT * CD]])
        r1 = np.abs(G[0]).sum()
        lo, hi = _cubic_range(c[0], r1)
        rem_lo, rem_hi = DT * K0 * KD * lo, DT * K0 * KD * hi
        c = _f(c) + np.array([0.0, (rem_lo + rem_hi) / 2])
        G = _reduce(np.hstack([J @ G, np.diag([W, W + (rem_hi - rem_lo) / 2])]), order)
        P = G @ G.T  # F-radius gain (Alamo et al. 2005)
        lam = P @ h / (h @ P @ h + V * V)
        c = c + lam * (y[k, 0] - h @ c)
        G = np.hstack([G - np.outer(lam, h @ G), (V * lam)[:, None]])
        out.append(c)
    return np.stack(out)


def time_numpy(system: ds.System, steps: int, trajectories: int, repeats: int) -> float:
    """Median trajectory-steps/s of the numpy loop."""
    traj = system.simulate(steps=steps, batch=trajectories, seed=0, noise="uniform")
    y = traj.y.numpy()
    numpy_alamo(y[0, :2], C0, R0)
    rates = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for i in range(trajectories):
            numpy_alamo(y[i], C0, R0)
        rates.append(trajectories * steps / (time.perf_counter() - t0))
    return float(np.median(rates))


def online_paired(name: str, system: ds.System, steps: int, repeats: int) -> tuple[float, ...]:
    """The compiled online row with the peer timed beside it: ``repeats`` pairs, each the
    numpy loop over one log of ``steps`` measurements and then ``steps`` compiled
    ``filt.step`` calls inside ``filt.streaming()`` on the same log (B = 1) -> (median of the
    pairs' rate ratios, median diffsmf and numpy rates in trajectory-steps/s, cold compile s).

    A pair's two timings are milliseconds apart, while the rows of the table span minutes
    over which this shared machine's load drifts (the numpy loop alone gave 19,900-31,100
    trajectory-steps/s in runs of one day); a ratio to a peer timed minutes earlier measured
    the drift as much as the step."""
    traj = system.simulate(steps=steps, batch=1, seed=0, noise="uniform")
    y = traj.y.numpy()[0]
    filt = ds.filters.by_name(name)(system)
    filt.compile(retain_memory=True)  # as the other compiled rows (process-wide opt-in)

    def run(T: int) -> None:
        st = filt.initial_state(batch=1)
        for k in range(T):
            st = filt.step(st, None, traj.y[:, k])

    ratios, ours, peer = [], [], []
    with torch.no_grad(), filt.streaming():
        t0 = time.perf_counter()
        run(3)  # captures and compiles the step
        t_compile = time.perf_counter() - t0
        numpy_alamo(y[:2], C0, R0)
        for _ in range(repeats):
            t0 = time.perf_counter()
            numpy_alamo(y, C0, R0)
            t1 = time.perf_counter()
            run(steps)
            t2 = time.perf_counter()
            ratios.append((t1 - t0) / (t2 - t1))
            ours.append(steps / (t2 - t1))
            peer.append(steps / (t1 - t0))
    return (float(np.median(ratios)), float(np.median(ours)), float(np.median(peer)),
            t_compile)


# ---------------------------------------------------------------------- diffsmf figures
class _Count(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.n = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # noqa: ANN001
        self.n += 1
        return func(*args, **(kwargs or {}))


def aten_calls(name: str) -> int:
    """aten calls of one eager step (predict + update) of ``name`` on spring_damper, B = 1."""
    system = ds.systems.get("spring_damper")
    traj = system.simulate(steps=5, batch=1, seed=0, noise="vertex")
    filt = ds.filters.by_name(name)(system)
    with torch.no_grad():
        st = filt.initial_state(1)
        for k in range(3):
            st = filt.update(filt.predict(st, None), traj.y[:, k])
        count = _Count()
        with count:
            filt.update(filt.predict(st, None), traj.y[:, 3])
    return count.n


def six_tanks() -> ds.System:
    """A cascade of six tanks (Torricelli outflow ``a sqrt(x)``), the last level measured."""
    a = torch.tensor([0.5, 0.45, 0.4, 0.42, 0.38, 0.35], dtype=torch.float64)

    def f(x: torch.Tensor) -> torch.Tensor:
        out = a * torch.sqrt(x)
        inflow = torch.cat([torch.full_like(x[..., :1], 0.4), out[..., :-1]], -1)
        return x + 0.05 * (inflow - out)

    def h(x: torch.Tensor) -> torch.Tensor:
        return x[..., -1:]

    x0 = ds.Interval([0.6] * 6, [1.0] * 6)
    return ds.System(f, h, x0, ds.Interval([-1e-3] * 6, [1e-3] * 6), ds.Interval([-0.01], [0.01]),
                     name="six_tanks")


def eager_step_ms(system: ds.System, name: str, steps: int, repeats: int) -> float:
    traj = system.simulate(steps=steps, batch=1, seed=0, noise="vertex")
    filt = ds.filters.by_name(name)(system)
    times = []
    with torch.no_grad():
        filt(traj.y[:, :2])
        for _ in range(repeats):
            t0 = time.perf_counter()
            filt(traj.y)
            times.append((time.perf_counter() - t0) / steps)
    return 1e3 * float(np.median(times))


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--big", type=int, default=10_000, help="the large batch")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--numpy-trajectories", type=int, default=100)
    ap.add_argument("--filters", nargs="+", default=["hsnsmf", "mszm"])
    ap.add_argument("--no-compile", action="store_true", help="skip the compiled rows")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu", help="torch device of the filters (cpu, cuda)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.set_default_dtype(torch.float64)
    if args.device != "cpu":  # a default device is a torch-function mode on every torch call
        torch.set_default_device(args.device)
    machine = platform.processor() or platform.machine()
    print(f"{time.strftime('%Y-%m-%d')}, commit {_commit()}, {machine}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} thread(s)")
    system = ds.systems.get("spring_damper")
    ref = time_numpy(system, args.steps, args.numpy_trajectories, args.repeats)
    print(f"numpy Alamo loop: {ref:,.0f} trajectory-steps/s")
    rows: list[tuple[str, str, str, str]] = []
    # the six tanks first, before any compile in this process: after Inductor's compiles of
    # the rows below, the same eager step ran 5-25 % slower, spread over every op (a larger,
    # more fragmented process; not Python's collector, which the loop pauses). The figure
    # after the compiled rows is printed beside it.
    tanks_ms = eager_step_ms(six_tanks(), "hsnsmf", args.steps, args.repeats)
    for name in args.filters:
        calls = aten_calls(name)
        rows.append((f"{name}: aten calls per eager step (n = 2, B = 1)", f"{calls}",
                     "<= 300" if name == "hsnsmf" else "-", ""))
        for batch, compiled, online, target in (
            (1, False, False, ">= 0.1x"), (args.big, False, False, ">= 20x"),
            (args.big, True, False, ">= 100x"), (1, True, True, ">= 1x"),
        ):
            if compiled and args.no_compile:
                continue
            steps = args.steps if batch <= 1000 or compiled else max(2, args.steps // 5)
            if online:  # a step of ~0.04-0.1 ms: the peer timed beside it, many repeats
                ratio, rate, peer, tc = online_paired(
                    name, system, max(steps, ONLINE_STEPS), max(args.repeats, ONLINE_REPEATS))
                rows.append((f"{name}: compiled online, B = 1", f"{ratio:.3g}x", target,
                             f"{rate:,.0f} traj-steps/s; paired numpy loop {peer:,.0f}"))
            else:
                rate, tc = _time_torch(name, system, batch, steps, compiled=compiled,
                                       repeats=args.repeats)
                mode = "compiled" if compiled else "eager"
                rows.append((f"{name}: {mode}, B = {batch}", f"{rate / ref:.3g}x", target,
                             f"{rate:,.0f} traj-steps/s"))
            if compiled:
                rows.append((f"{name}: cold compile, B = {batch}", f"{tc:.1f} s", "<= 15 s", ""))
            print(rows[-1], flush=True)
    after = "" if args.no_compile else (
        f"{eager_step_ms(six_tanks(), 'hsnsmf', args.steps, args.repeats):.1f} ms after the "
        "compiled rows")
    rows.append(("hsnsmf: eager step, 6 states with square roots, B = 1", f"{tanks_ms:.1f} ms",
                 "<= 4 ms", after))
    print("\n| figure | measured | target | note |\n|---|---:|---:|---|")
    for r in rows:
        print("| " + " | ".join(r) + " |")
    print(f"\nratios: diffsmf trajectory-steps/s over the numpy loop's ({ref:,.0f}), same run, "
          f"median of {args.repeats}; the online rows: median of "
          f"{max(args.repeats, ONLINE_REPEATS)} ratios to the numpy loop timed beside each.")


if __name__ == "__main__":
    main()
