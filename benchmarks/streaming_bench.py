"""``forward`` of a compiled filter, with and without ``streaming()``, in the same process.

Outside ``streaming()`` the compiled step runs through Dynamo (guards checked on the first
calls of each ``forward``); inside it, in no-grad mode, ``forward`` calls the step captured
with ``make_fx`` and compiled by Inductor, without Dynamo (``diffsmf/filters/streaming.py``).
Both paths are compiled once first (their compile + first-run times are printed), the final
sets are compared, then ``--repeats`` interleaved runs of each are timed (A B A B) and the
medians printed, on ``spring_damper`` with one torch thread.

    python benchmarks/streaming_bench.py [--filters ekf combined hsnsmf] [--batch 1]
        [--steps 100] [--repeats 9]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from diffsmf import filters, systems


def _seconds(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def row(name: str, batch: int, steps: int, repeats: int) -> str:
    """One table row: compile times, ms per step of both paths, speed-up, set difference."""
    system = systems.get("spring_damper")
    filt = filters.by_name(name)(system).compile()
    y = system.simulate(steps, batch, seed=0).y

    def streamed():
        with filt.streaming():
            return filt(y)

    with torch.no_grad():
        t_dynamo = _seconds(lambda: filt(y))
        t_direct = _seconds(streamed)
        a, b = filt(y), streamed()
        diff = max((a.lower - b.lower).abs().max().item(), (a.upper - b.upper).abs().max().item())
        plain, stream = [], []
        for _ in range(repeats):
            plain.append(_seconds(lambda: filt(y)) / steps * 1e3)
            stream.append(_seconds(streamed) / steps * 1e3)
    mp, ms = statistics.median(plain), statistics.median(stream)
    return (f"| {name} | {t_dynamo:.1f} | {t_direct:.1f} | {mp:.3f} | {ms:.3f} | "
            f"{mp / ms:.2f}x | {diff:.1e} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--filters", nargs="+", default=["ekf", "combined", "hsnsmf"])
    ap.add_argument("--batch", type=int, default=1)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=9)
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(f"torch {torch.__version__}, 1 thread; spring_damper, B = {args.batch}, "
          f"{args.steps} steps, median of {args.repeats} interleaved runs\n")
    print("| filter | compile + first run, Dynamo [s] | same, make_fx [s] | `forward` [ms/step] "
          "| in `streaming()` [ms/step] | speed-up | max set difference |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name in args.filters:
        print(row(name, args.batch, args.steps, args.repeats), flush=True)


if __name__ == "__main__":
    main()
