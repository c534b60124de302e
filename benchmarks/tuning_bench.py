"""Full-horizon tuning cost: one epoch of HSNSMF on spring_damper, eager vs ``filt.compile()``.

An epoch is one forward over ``--batch`` trajectories x ``--steps`` steps and (for the
"forward + backward" column) the back-propagation of the mean log-volume through the whole
horizon to the learnable noise half-widths (targets: 200 epochs of 64 x 100 in under
2 minutes, forward + backward at most 2x forward). Median of ``--repeats`` epochs after a
warm-up epoch (which includes the one-off compile, printed separately). One torch thread.

"forward" is the no-grad forward (``torch.no_grad()``, what filtering runs); the forward +
backward epoch is also split into its recording forward (the forward that tuning runs, which
saves what the backward needs) and the backward itself, so the last columns give forward +
backward relative to that recording forward too.

    python benchmarks/tuning_bench.py [--batch 64] [--steps 100] [--repeats 5] [--epochs 200]
                                      [--no-eager] [--steps-per-call K [K ...]] [--tool-epochs N]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from diffsmf import filters, systems


def _epoch(filt, y: torch.Tensor, backward: bool) -> float:
    return sum(_split_epoch(filt, y, backward))


def _split_epoch(filt, y: torch.Tensor, backward: bool) -> tuple[float, float]:
    """(forward s, backward s) of one epoch; the backward is 0 without ``backward``."""
    t0 = time.perf_counter()
    if not backward:
        with torch.no_grad():
            filt(y)
        return time.perf_counter() - t0, 0.0
    filt.zero_grad(set_to_none=True)
    loss = filt(y).volume[:, 1:].log().mean()
    t1 = time.perf_counter()
    loss.backward()
    return t1 - t0, time.perf_counter() - t1


def measure(
    compiled: bool, y: torch.Tensor, repeats: int, steps_per_call: int = 1
) -> tuple[float, float, float, float]:
    """(median no-grad forward s, median forward + backward s, one-off compile s, median
    recording forward s of the forward + backward epochs) for one mode."""
    system = systems.get("spring_damper")
    filt = filters.HSNSMF(system)
    if compiled:
        filt.compile(steps_per_call=steps_per_call)
    t0 = time.perf_counter()
    _epoch(filt, y, False)
    _epoch(filt, y, True)  # warm-up: compiles the no-grad and the grad graphs
    t_compile = time.perf_counter() - t0 if compiled else 0.0
    fwd = float(np.median([_epoch(filt, y, False) for _ in range(repeats)]))
    split = [_split_epoch(filt, y, True) for _ in range(repeats)]
    both = float(np.median([a + b for a, b in split]))
    rec = float(np.median([a for a, _ in split]))
    return fwd, both, t_compile, rec


def measure_tool(compiled: bool, y: torch.Tensor, epochs: int) -> tuple[float, float]:
    """The tuning tool itself, ``diffsmf.tuning.tune`` (consistency loss: ``y`` only, batch =
    all trajectories, no validation): (s per epoch over ``epochs`` epochs, s of the first
    epoch, which includes the one-off compile)."""
    from diffsmf.tuning import tune

    filt = filters.HSNSMF(systems.get("spring_damper"))
    kw = {"batch_size": y.shape[0], "progress": False, "compile": compiled}
    t0 = time.perf_counter()
    tune(filt, y, epochs=1, **kw)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    tune(filt, y, epochs=epochs, **kw)
    return (time.perf_counter() - t0) / epochs, first


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--epochs", type=int, default=200)
    ap.add_argument("--no-eager", action="store_true", help="only the compiled rows")
    ap.add_argument("--steps-per-call", type=int, nargs="+", default=[1], metavar="K",
                    help="compiled rows with filt.compile(steps_per_call=K), one row per K")
    ap.add_argument("--tool-epochs", type=int, default=0, metavar="N",
                    help="also time diffsmf.tuning.tune itself, eager and compile=True, over N "
                    "epochs (after a first epoch that compiles)")
    ap.add_argument("--tool-only", action="store_true", help="only the diffsmf.tuning.tune rows")
    args = ap.parse_args()
    torch.set_num_threads(1)
    system = systems.get("spring_damper")
    y = system.simulate(steps=args.steps, batch=args.batch, seed=0, noise="vertex").y
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread; HSNSMF, spring_damper, "
          f"{args.batch} x {args.steps}, full-horizon back-propagation\n")
    if not args.tool_only:
        print(f"| mode | forward s | forward + backward s | ratio | {args.epochs} epochs s | "
              "one-off compile s | recording forward s | ratio to it |")
        print("|---|---:|---:|---:|---:|---:|---:|---:|")
    modes = ([] if args.no_eager else [(False, 1)]) + [(True, k) for k in args.steps_per_call]
    for compiled, k in [] if args.tool_only else modes:
        fwd, both, tc, rec = measure(compiled, y, args.repeats, k)
        name = ("compiled" + (f", {k} steps per call" if k > 1 else "")) if compiled else "eager"
        print(f"| {name} | {fwd:.3f} | {both:.3f} | {both / fwd:.2f} | {args.epochs * both:.0f} | "
              f"{tc:.0f} | {rec:.3f} | {both / rec:.2f} |", flush=True)
    if args.tool_epochs > 0:
        print(f"\n`diffsmf.tuning.tune` (consistency loss, {args.batch} x {args.steps}, one batch "
              f"per epoch, no validation), mean of {args.tool_epochs} epochs:\n")
        print(f"| mode | s per epoch | {args.epochs} epochs s | first epoch s (with compile) |")
        print("|---|---:|---:|---:|")
        for compiled in ([True] if args.no_eager else [False, True]):
            per, first = measure_tool(compiled, y, args.tool_epochs)
            name = "tune(compile=True)" if compiled else "tune() (eager)"
            print(f"| {name} | {per:.3f} | {args.epochs * per:.0f} | {first:.0f} |", flush=True)


if __name__ == "__main__":
    main()
