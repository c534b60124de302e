"""CZSMF tightness and cost: markdown tables on stdout.

1. Linear system (``tests/test_czsmf.py::linear_system``, 2 states, 1 output, box noise):
   summed interval-hull widths of CZSMF over the horizon divided by those of the exact
   feasible set (per-coordinate HiGHS LPs on the stacked x0, w, v constraints), for several
   reduction caps; "none" = no reduction (must be 1 to ~1e-9).
2. Wang et al. 2022 examples (``spring_damper``, ``bilinear``): mean set area over steps 1..T of
   HSNSMF (parallelotope, exact area), MSZM (zonotope, exact area) and CZSMF (the area of the
   outer polygon of 64 support directions, an upper bound of its true area, and its interval
   hull area), uniform noise.
3. ``--parts chain``: caps at n = 8 (``oscillator_chain``, 4 outputs; the default caps are
   308 generators and 28 constraints there): mean over steps 1..T of the geometric mean
   hull width ``vol(hull)^(1/n)`` relative to the default caps, and time per step over the
   whole run (growth phase included), vertex noise. HSNSMF and MSZM as references. (The
   ``"lp"`` elimination is not in it: its ranking solves 2 q range LPs per eliminated
   constraint; its (308, 28) row had not finished 4 x 50 steps after 10 minutes, about 4x the
   default's whole run.)
4. Time per step at batch 1, 100 and 10,000 (``--big-steps`` steps at 10,000, after the
   warm-up steps that grow the sets to their caps; at 10,000 the warm-up runs at batch
   ``--tile-from`` 100 and is tiled).
5. ``--parts compiled``: eager against ``filt.compile()`` (whole ``forward`` on
   ``--compiled-steps`` uniform-noise steps of spring_damper at ``--compiled-batch``; median
   of three runs after the first, compiled call), HSNSMF and the ``--cost-configs`` CZSMF
   caps (default: the (30, 5) propagation caps), with the first compiled call and the mean
   volumes of both.

    python benchmarks/czsmf_bench.py --steps 30 --trials 4 --seed-steps 50 --seed-trials 10
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

import diffsmf as ds
from diffsmf.filters.czsmf import CZSMF

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_czsmf import C_LIN, exact_hulls, linear_system  # noqa: E402

CONFIGS = {
    "none": dict(max_generators=None, max_constraints=None),
    "default (80, 10, hull)": {},
    "(40, 6, hull)": dict(max_generators=40, max_constraints=6),
    "(20, 4, hull)": dict(max_generators=20, max_constraints=4),
    "(40, 6, propagation)": dict(max_generators=40, max_constraints=6, elimination="propagation"),
    "(30, 5, propagation)": dict(max_generators=30, max_constraints=5, elimination="propagation"),
    "(12, 3, propagation)": dict(max_generators=12, max_constraints=3, elimination="propagation"),
}


def linear_table(steps: int, trials: int) -> None:
    system = linear_system()
    traj = system.simulate(steps=steps, batch=trials, seed=4, noise="uniform")
    exact = [exact_hulls(system, traj.y[i].numpy(), C_LIN.numpy()) for i in range(trials)]
    W = np.stack([hi - lo for lo, hi in exact])[:, 1:]
    print(f"\nLinear system, {trials} trajectories x {steps} steps, uniform noise\n")
    print(
        "| CZSMF caps (generators, constraints, elimination) | mean width / exact | "
        "worst step | time per step [s] |"
    )
    print("|---|---:|---:|---:|")
    for label, kw in CONFIGS.items():
        filt = CZSMF(system, **kw)
        t0 = time.perf_counter()
        with torch.no_grad():
            res = filt(traj.y)
        dt = (time.perf_counter() - t0) / steps
        w = (res.upper - res.lower).numpy()[:, 1:]
        ratio = float((w.sum((1, 2)) / W.sum((1, 2))).mean())
        worst = float((w.sum(-1) / W.sum(-1)).max())
        print(f"| {label} | {ratio:.6f} | {worst:.4f} | {dt:.3f} |", flush=True)
    for name, cls in (("MSZM (order 5)", ds.filters.MSZM), ("HSNSMF", ds.filters.HSNSMF)):
        with torch.no_grad():
            res = cls(system)(traj.y)
        w = (res.upper - res.lower).numpy()[:, 1:]
        print(
            f"| {name} (reference) | {float((w.sum((1, 2)) / W.sum((1, 2))).mean()):.4f} | "
            f"{float((w.sum(-1) / W.sum(-1)).max()):.4f} | |",
            flush=True,
        )


def seed_table(steps: int, trials: int) -> None:
    print(
        f"\nWang et al. 2022 examples, {trials} trajectories x {steps} steps, uniform noise "
        "(mean over steps 1..T)\n"
    )
    print("| system | filter | mean area | mean hull area | time per step [s] |")
    print("|---|---|---:|---:|---:|")
    for name in ("spring_damper", "bilinear"):
        system = ds.systems.get(name)
        traj = system.simulate(steps=steps, batch=trials, seed=0, noise="uniform")
        filts = [("HSNSMF", ds.filters.HSNSMF(system)), ("MSZM", ds.filters.MSZM(system))]
        filts += [(f"CZSMF {k}", CZSMF(system, **v)) for k, v in CONFIGS.items() if k != "none"]
        for label, filt in filts:
            t0 = time.perf_counter()
            with torch.no_grad():
                res = filt(traj.y, u=traj.u)
            dt = (time.perf_counter() - t0) / steps
            hull = float((res.upper - res.lower).prod(-1)[:, 1:].mean())
            if isinstance(filt, CZSMF):
                with torch.no_grad():
                    area = float(res.sets[:, 1:].outer_polygon_area(64).mean())
            else:
                area = float(res.volume[:, 1:].mean())
            print(f"| {name} | {label} | {area:.4e} | {hull:.4e} | {dt:.3f} |", flush=True)


#: CZSMF rows of the cost table (``--cost-configs``: any keys of ``CONFIGS``)
COST_KEYS = ["(12, 3, propagation)", "(30, 5, propagation)", "default (80, 10, hull)"]

CHAIN_CONFIGS = {
    "default (35 n + c = 308, 4 + 6 m = 28, hull)": {},
    "(460, 28, hull)": dict(max_generators=460, max_constraints=28),
    "(308, 16, hull)": dict(max_generators=308, max_constraints=16),
    "(148, 28, hull)": dict(max_generators=148, max_constraints=28),
    "(108, 28, hull)": dict(max_generators=108, max_constraints=28),
    "(108, 16, hull)": dict(max_generators=108, max_constraints=16),
    "(68, 16, hull)": dict(max_generators=68, max_constraints=16),
    "(68, 16, propagation)": dict(max_generators=68, max_constraints=16, elimination="propagation"),
}


def chain_table(steps: int, trials: int, n: int) -> None:
    """Tightness vs cost of the CZSMF caps on ``oscillator_chain`` (``n`` states)."""
    system = ds.systems.get("oscillator_chain", n=n)
    traj = system.simulate(steps=steps, batch=trials, seed=0, noise="vertex")
    print(
        f"\noscillator_chain n = {n}, {trials} trajectories x {steps} steps, vertex noise "
        "(mean over steps 1..T of vol(hull)^(1/n), relative to the default caps)\n"
    )
    print("| filter | mean width / default | mean vol(hull)^(1/n) | time per step [s] |")
    print("|---|---:|---:|---:|")
    filts = [(f"CZSMF {k}", CZSMF(system, **v)) for k, v in CHAIN_CONFIGS.items()]
    filts += [("HSNSMF", ds.filters.HSNSMF(system)), ("MSZM", ds.filters.MSZM(system))]
    ref = None
    for label, filt in filts:
        t0 = time.perf_counter()
        with torch.no_grad():
            res = filt(traj.y, u=traj.u)
        dt = (time.perf_counter() - t0) / steps
        gw = (res.upper - res.lower).clamp_min(0).log().mean(-1).exp()[:, 1:].mean()
        ref = gw if ref is None else ref
        print(f"| {label} | {float(gw / ref):.4f} | {float(gw):.4e} | {dt:.3f} |", flush=True)


def _tile(state, reps: int):
    """``state`` with its batch repeated ``reps`` times (the sets' batch indexing)."""
    from diffsmf.filters.base import FilterState

    idx = torch.arange(state.consistent.shape[0]).repeat(reps)
    return FilterState(
        state.set[idx], state.consistent[idx], {k: v[idx] for k, v in state.extras.items()},
        None if state.bounded is None else state.bounded[idx],
    )


def cost_table(
    big_steps: int, tile_from: int, keys: list[str] | None = None,
    batches: tuple[int, ...] = (1, 100, 10_000),
) -> None:
    """Steady-state time per step: the filter first runs ``warm`` steps online (CZSMF reaches
    its caps), then ``steps`` more steps are timed. At batch 10,000 the warm-up runs at batch
    ``tile_from`` and its state and the measurements of the timed steps are tiled to 10,000
    (the default caps' warm-up alone would take most of an hour at 10,000; the timed steps do
    the same work per set). ``batches``: the batches to time (20 timed steps at 1, 10 at 100,
    ``big_steps`` otherwise); each row is also given relative to HSNSMF at its batch."""
    print(f"\nTime per step at the fixed size (spring_damper, uniform noise, "
          f"{torch.get_num_threads()} thread(s))\n")
    print("| filter | batch | timed steps (after warm-up) | time per step [s] | vs HSNSMF |")
    print("|---|---:|---:|---:|---:|")
    system = ds.systems.get("spring_damper")
    for batch in batches:
        steps = {1: 20, 100: 10}.get(batch, big_steps)
        base = float("nan")
        filts = [("HSNSMF", ds.filters.HSNSMF(system)), ("MSZM", ds.filters.MSZM(system))]
        filts += [(f"CZSMF {k}", CZSMF(system, **CONFIGS[k])) for k in keys or COST_KEYS]
        small = min(batch, tile_from) if tile_from > 0 else batch
        reps = batch // small
        if small * reps != batch:
            raise ValueError(f"--tile-from: {tile_from} does not divide the batch {batch}")
        for label, filt in filts:
            warm = 40 if label.startswith("CZSMF") and "(12, 3" not in label else 6
            traj = system.simulate(steps=warm + steps, batch=small, seed=0, noise="uniform")
            y = traj.y.repeat(reps, 1, 1)
            u = None if traj.u is None else traj.u.repeat(reps, 1, 1)
            with torch.no_grad():
                st = filt.initial_state(batch=small)
                for k in range(warm + steps):
                    if k == warm:
                        st = _tile(st, reps)
                        t0 = time.perf_counter()
                    uk = None if u is None else u[: st.consistent.shape[0], k]
                    st = filt.update(filt.predict(st, uk), y[: st.consistent.shape[0], k])
            dt = (time.perf_counter() - t0) / steps
            if label == "HSNSMF":  # the first row of each batch
                base = dt
            print(f"| {label} | {batch} | {steps} | {dt:.4f} | {dt / base:.1f}x |", flush=True)


def compiled_table(batch: int, steps: int, keys: list[str] | None = None) -> None:
    """Eager vs compiled ``forward`` per step (HSNSMF and CZSMF caps), same data and run."""
    print(f"\nEager vs compiled forward (spring_damper, uniform noise, batch {batch}, {steps} "
          "steps; median of 3 runs after the first)\n")
    print("| filter | eager ms/step | compiled ms/step | speed-up | first compiled call s | "
          "mean volume eager / compiled |")
    print("|---|---:|---:|---:|---:|---|")
    system = ds.systems.get("spring_damper")
    traj = system.simulate(steps=steps, batch=batch, seed=0, noise="uniform")
    makers = [("HSNSMF", lambda: ds.filters.HSNSMF(system))]
    makers += [(f"CZSMF {k}", lambda k=k: CZSMF(system, **CONFIGS[k]))
               for k in keys or ["(30, 5, propagation)"]]
    for label, make in makers:
        eager, comp = make(), make().compile()
        with torch.no_grad():
            t0 = time.perf_counter()
            rc = comp(traj.y)
            first = time.perf_counter() - t0
            te, tc = [], []
            for _ in range(3):
                t0 = time.perf_counter()
                re_ = eager(traj.y)
                te.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                rc = comp(traj.y)
                tc.append(time.perf_counter() - t0)
        me, mc = (1e3 * float(np.median(t)) / steps for t in (te, tc))
        print(f"| {label} | {me:.2f} | {mc:.2f} | {me / mc:.1f}x | {first:.0f} | "
              f"{re_.volume[:, 1:].mean():.4e} / {rc.volume[:, 1:].mean():.4e} |", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--trials", type=int, default=4)
    ap.add_argument("--seed-steps", type=int, default=50)
    ap.add_argument("--seed-trials", type=int, default=10)
    ap.add_argument("--big-steps", type=int, default=2)
    ap.add_argument("--tile-from", type=int, default=100,
                    help="warm-up batch that is tiled to the 10,000 of the last rows (0: none)")
    ap.add_argument("--parts", nargs="*", default=["linear", "seed", "cost"],
                    help="linear | seed | cost | chain (the n = 8 caps table, about 15 min) | "
                    "compiled (eager vs compile(); CZSMF compiles for minutes)")
    ap.add_argument("--compiled-batch", type=int, default=100)
    ap.add_argument("--compiled-steps", type=int, default=60)
    ap.add_argument("--chain-steps", type=int, default=50)
    ap.add_argument("--chain-trials", type=int, default=4)
    ap.add_argument("--chain-n", type=int, default=8)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--cost-batches", type=int, nargs="+", default=[1, 100, 10_000],
                    help="batches of the cost table (the default caps take minutes per step at "
                    "10,000)")
    ap.add_argument("--cost-configs", nargs="*", default=None, metavar="KEY",
                    help=f"CZSMF rows of the cost table (default {COST_KEYS}; keys of CONFIGS)")
    args = ap.parse_args()
    torch.set_default_dtype(torch.float64)
    torch.set_num_threads(args.threads)
    if "linear" in args.parts:
        linear_table(args.steps, args.trials)
    if "seed" in args.parts:
        seed_table(args.seed_steps, args.seed_trials)
    if "chain" in args.parts:
        chain_table(args.chain_steps, args.chain_trials, args.chain_n)
    bad = [k for k in args.cost_configs or [] if k not in CONFIGS]
    if bad:
        ap.error(f"--cost-configs: unknown {bad}; choose from {list(CONFIGS)}")
    if "cost" in args.parts:
        cost_table(args.big_steps, args.tile_from, args.cost_configs, tuple(args.cost_batches))
    if "compiled" in args.parts:
        compiled_table(args.compiled_batch, args.compiled_steps, args.cost_configs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
