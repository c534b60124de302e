"""MSZM reduction order: tightness vs cost (MSZM's default order is chosen from
this measured table).

For each system and order q (at most ``q * n`` generators after each step, Girard reduction,
F-radius strips) the filter runs on the same ``--batch`` trajectories (worst-case vertex
noise, seed 0) for ``--steps`` steps. Tightness is relative to order 60, which never reduces
within the horizon (the generator count grows by at most 4 per step here, 2 + 4 * 25 < 120):

* width: mean over steps 1..T and trajectories of the summed interval-hull widths, divided by
  the same mean at order 60;
* volume: the same with the zonotope volume (exact in 2-D).

Cost: ms per filter step for the whole batch (forward over all steps, no gradient), median of
``--repeats`` runs, 1 torch thread.

Systems: ``spring_damper`` and ``bilinear`` (built-ins, ``u=traj.u``), the 2-state linear
system of ``tests/test_linear_references.py`` (two outputs, box noise), and for the cost in
higher dimension ``fermenter`` (n = 3, m = 3) and ``oscillator_chain`` (n = 8, m = 4; the
zonotope volume is then the documented upper bound of ``Zonotope.volume``). Order 60 never
reduces in 25 steps on any of them (at most n + 25 (n + m) generators <= 60 n).

    python benchmarks/mszm_order_bench.py [--steps 25] [--batch 10] [--repeats 5]
        [--systems spring_damper bilinear linear fermenter oscillator_chain]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

import diffsmf as ds

F64 = torch.float64
ORDERS = (2, 3, 5, 8, 12, 20)
FULL = 60


def linear_system() -> ds.System:
    A = torch.tensor([[0.9, 0.2], [-0.1, 0.95]], dtype=F64)
    C = torch.tensor([[1.0, 0.5], [0.0, 1.0]], dtype=F64)
    W, V = torch.tensor([0.02, 0.01], dtype=F64), torch.tensor([0.05, 0.08], dtype=F64)
    c0, r0 = torch.tensor([0.5, -0.3], dtype=F64), torch.tensor([0.2, 0.2], dtype=F64)
    return ds.System(lambda x, u=None, theta=None: x @ A.T, lambda x: x @ C.T,
                     ds.Interval(c0 - r0, c0 + r0), ds.Interval(-W, W), ds.Interval(-V, V),
                     name="linear")


def run(system: ds.System, traj, order: int, repeats: int) -> tuple[float, float, float]:
    """(mean width, mean volume, ms per step) for one order."""
    filt = ds.filters.MSZM(system, order=order)
    times = []
    with torch.no_grad():
        for _ in range(repeats):
            t0 = time.perf_counter()
            res = filt(traj.y, u=traj.u)
            times.append(time.perf_counter() - t0)
    assert res.sets.contains(traj.x).all(), "containment violated"
    width = (res.upper - res.lower)[:, 1:].sum(-1).mean().item()
    vol = res.volume[:, 1:].mean().item()
    return width, vol, 1e3 * statistics.median(times) / traj.y.shape[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=25)
    ap.add_argument("--batch", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--systems", nargs="*",
                    default=["spring_damper", "bilinear", "linear", "fermenter",
                             "oscillator_chain"])
    args = ap.parse_args()
    torch.set_num_threads(1)
    systems = {name: linear_system() if name == "linear" else ds.systems.get(name)
               for name in args.systems}
    print(f"MSZM order vs tightness/cost: steps={args.steps}, batch={args.batch}, "
          f"median of {args.repeats}, 1 thread; ratios relative to order {FULL} (no reduction)")
    print("| system | order | width / full | volume / full | ms / step |")
    print("|---|---:|---:|---:|---:|")
    for name, s in systems.items():
        tr = s.simulate(steps=args.steps, batch=args.batch, seed=0, noise="vertex")
        w0, v0, t0 = run(s, tr, FULL, args.repeats)
        for q in ORDERS:
            w, v, t = run(s, tr, q, args.repeats)
            print(f"| {name} | {q} | {w / w0:.4f} | {v / v0:.4f} | {t:.2f} |")
        print(f"| {name} | {FULL} | 1 | 1 | {t0:.2f} |")


if __name__ == "__main__":
    main()
