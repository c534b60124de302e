"""CZSMF (constrained zonotopes, Scott et al. 2016) against HSNSMF and MSZM on spring_damper.

Filters ``--trials`` uniform-noise trajectories of ``--steps`` steps of the Wang et al. 2022
spring-damper with HSNSMF, MSZM, CZSMF with its default caps and CZSMF with the cheaper
``(30, 5, propagation)`` caps, and prints per filter the mean set area over steps 1..T, the time
per step and whether every true state lies in its set. Areas: HSNSMF and MSZM their exact
planar areas (``res.volume``); CZSMF the area of its outer polygon over 64 support directions
(``ConstrainedZonotope.outer_polygon_area``, an upper bound of the true area; ``res.volume`` of a
CZSMF set is its interval-hull area, the documented proxy). Writes a figure: the four sets of
the first trajectory at two steps (a panel each), with the true state, and the mean area over
time.

    python examples/czsmf_spring_damper.py [--steps 40] [--trials 10] [--out FIGURE.png]

Measured tables (more systems, costs at batch 1 to 10,000): docs/constrained_zonotopes.md.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

import diffsmf as ds  # noqa: E402
from diffsmf.plot import plot_set  # noqa: E402

FILTERS = {
    "HSNSMF": lambda s: ds.filters.HSNSMF(s),
    "MSZM": lambda s: ds.filters.MSZM(s),
    "CZSMF default caps": lambda s: ds.filters.CZSMF(s),
    "CZSMF (30, 5, propagation)": lambda s: ds.filters.CZSMF(
        s, max_generators=30, max_constraints=5, elimination="propagation"
    ),
}


def areas(res: ds.filters.FilterResult) -> torch.Tensor:
    """Set area per trajectory and step ``[B, T+1]``: exact for zonotopes and parallelotopes,
    the outer support polygon for constrained zonotopes."""
    S = res.sets
    if not isinstance(S, ds.ConstrainedZonotope):
        return res.volume
    return S.outer_polygon_area(64)


def run(steps: int, trials: int, seed: int = 0) -> tuple[ds.Trajectory, dict[str, dict]]:
    """Simulate and filter -> ``(trajectories, {filter: {result, area [B, T+1], seconds}})``."""
    system = ds.systems.get("spring_damper")
    traj = system.simulate(steps=steps, batch=trials, seed=seed, noise="uniform")
    out = {}
    for name, make in FILTERS.items():
        filt = make(system)
        t0 = time.perf_counter()
        with torch.no_grad():
            res = filt(traj.y)
            seconds = time.perf_counter() - t0
            out[name] = {"result": res, "area": areas(res), "seconds": seconds,
                         "contained": bool(res.sets.contains(traj.x, atol=1e-9).all())}
    return traj, out


def figure(traj: ds.Trajectory, out: dict[str, dict], path: str | Path, at: tuple[int, int]):
    """The first trajectory's sets at steps ``at`` (one panel each) and the mean area over time."""
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    for ax, k in zip(axes[:2], at):
        for i, (name, r) in enumerate(out.items()):
            plot_set(ax, r["result"].sets[0, k], edgecolor=f"C{i}", label=name)
        x = traj.x[0, k]
        ax.plot(x[0], x[1], "k+", ms=10, label="true state")
        ax.set_xlabel("x1 (position)")
        ax.set_ylabel("x2 (velocity)")
        ax.set_title(f"trajectory 0, step k = {k}")
    ax1 = axes[2]
    steps = torch.arange(traj.y.shape[1] + 1)
    for i, (name, r) in enumerate(out.items()):
        ax1.semilogy(steps[1:], r["area"][:, 1:].mean(0), color=f"C{i}", label=name)
    ax1.set_xlabel("step k")
    ax1.set_ylabel("mean set area")
    ax1.set_title(f"mean over {traj.y.shape[0]} trajectories")
    ax1.legend(fontsize=8)
    handles, labels = axes[0].get_legend_handles_labels()  # one legend for the set panels
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=9)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--trials", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="czsmf_spring_damper.png")
    args = ap.parse_args()
    if args.steps < 4 or args.trials < 1:
        ap.error("--steps must be >= 4 and --trials >= 1")
    torch.set_default_dtype(torch.float64)
    traj, out = run(args.steps, args.trials, args.seed)
    base = float(out["HSNSMF"]["area"][:, 1:].mean())
    print(f"spring_damper, {args.trials} uniform-noise trajectories x {args.steps} steps\n")
    print("| filter | mean area, steps 1..T | vs HSNSMF | time per step [ms] | all states inside |")
    print("|---|---:|---:|---:|---|")
    for name, r in out.items():
        a = float(r["area"][:, 1:].mean())
        ms = 1000 * r["seconds"] / args.steps
        print(f"| {name} | {a:.4e} | {a / base - 1:+.1%} | {ms:.1f} | {r['contained']} |")
    figure(traj, out, args.out, (3, args.steps // 2))
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
