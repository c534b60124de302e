"""Side-by-side comparison of filters on one system (Wang et al. 2022, sec. 4 style) and the demo.

``compare(system, ["hsnsmf", "mszm", "cdsmf"], trials=20, steps=100)`` simulates one batch of
trajectories and runs every filter on the same data; each row reports the mean set area
(volume) after step 3 (Wang et al. 2022 compares the areas "for every k > 3"), the containment
violations (see `diffsmf.audit`), the worst normalised distance outside, the number of
inconsistent steps and the wall time.
"""

from __future__ import annotations

import time
from pathlib import Path

import torch

from diffsmf import systems
from diffsmf.audit import TOL, gauge
from diffsmf.filters import by_name, is_guaranteed
from diffsmf.filters.base import FilterResult, SetFilter
from diffsmf.plot import comparison_figure
from diffsmf.systems.system import System, Trajectory

__all__ = [
    "build_filters", "compare", "demo", "format_table", "guarantees", "rows", "run_filters",
]


def build_filters(
    system: System, filters: dict[str, SetFilter] | list[str]
) -> dict[str, SetFilter]:
    """``{name: filter}``: a dict is copied, a list of names is built on ``system`` (`by_name`)."""
    if isinstance(filters, dict):
        return dict(filters)
    return {name: by_name(name)(system) for name in filters}


def guarantees(filters: dict[str, SetFilter]) -> dict[str, bool]:
    """``{name: filter.guaranteed}`` (see `diffsmf.filters.is_guaranteed`)."""
    return {name: is_guaranteed(f) for name, f in filters.items()}


def run_filters(
    system: System,
    filters: dict[str, SetFilter] | list[str],
    trials: int = 20,
    steps: int = 100,
    noise: str = "uniform",
    seed: int = 0,
) -> tuple[Trajectory, dict[str, FilterResult], dict[str, float]]:
    """Simulate once, run every filter -> (trajectory, results by name, seconds by name)."""
    filts = build_filters(system, filters)
    traj = system.simulate(steps=steps, batch=trials, seed=seed, noise=noise)
    results, seconds = {}, {}
    for name, f in filts.items():
        t0 = time.perf_counter()
        with torch.no_grad():
            results[name] = f(traj.y, u=traj.u)
        seconds[name] = time.perf_counter() - t0
    return traj, results, seconds


def compare(
    system: System,
    filters: dict[str, SetFilter] | list[str],
    trials: int = 20,
    steps: int = 100,
    noise: str = "uniform",
    seed: int = 0,
) -> list[dict]:
    """One row per filter: name, guaranteed, mean_volume (k > 3), violations, pairs,
    worst_distance, inconsistent, rmse (per state, of the set centre), seconds."""
    filts = build_filters(system, filters)
    traj, results, seconds = run_filters(system, filts, trials, steps, noise, seed)
    return rows(traj, results, seconds, guarantees(filts))


def rows(
    traj: Trajectory,
    results: dict[str, FilterResult],
    seconds: dict[str, float],
    guaranteed: dict[str, bool],
) -> list[dict]:
    """The rows of `compare` from the outputs of `run_filters` and `guarantees`."""
    table = []
    for name, res in results.items():
        g = gauge(res.sets, traj.x)
        viol = g > 1 + TOL
        err = res.center[:, 1:] - traj.x[:, 1:]
        table.append(
            {
                "filter": name,
                "guaranteed": guaranteed[name],
                "mean_volume": float(res.volume[:, 4:].mean()),
                "violations": int(viol.sum()),
                "pairs": int(viol.numel()),
                "worst_distance": float((g - 1).clamp_min(0).max()),
                "inconsistent": int((~res.consistent).sum()),
                "rmse": err.pow(2).mean((0, 1)).sqrt().tolist(),
                "seconds": seconds[name],
            }
        )
    return table


def format_table(rows: list[dict]) -> str:
    """Plain-text table of `compare` rows."""
    head = (
        f"{'filter':<8} {'mean area/volume (k>3)':>23} {'outside/pairs':>15} "
        f"{'worst dist.':>11} {'inconsistent':>12} {'time [s]':>9}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        out = f"{r['violations']}/{r['pairs']}"
        tag = "" if r["guaranteed"] else "  (not guaranteed)"
        lines.append(
            f"{r['filter']:<8} {r['mean_volume']:>23.4e} {out:>15} {r['worst_distance']:>11.2e} "
            f"{r['inconsistent']:>12d} {r['seconds']:>9.2f}{tag}"
        )
    return "\n".join(lines)


def demo(outdir: Path, trials: int = 10, steps: int = 60, seed: int = 0) -> str:
    """Wang et al. 2022 comparison on ``spring_damper`` (the ``diffsmf demo`` filters part):
    table text and figure ``filters_demo.png`` in ``outdir`` (created).

    HSNSMF, MSZM, CDSMF (guaranteed) and the EKF (not guaranteed: its 3-sigma ellipsoid) on
    ``trials`` worst-case (vertex-noise) trajectories; the figure
    (`diffsmf.plot.comparison_figure`) shows the mean set area over time and, for
    trajectory 0, each state's bounds relative to the true state.
    """
    system = systems.get("spring_damper")
    filts = build_filters(system, ["HSNSMF", "MSZM", "CDSMF", "EKF"])
    traj, results, seconds = run_filters(system, filts, trials, steps, "vertex", seed)
    table = rows(traj, results, seconds, guarantees(filts))
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    fig_path = outdir / "filters_demo.png"
    comparison_figure(traj.x, results, fig_path, guarantees(filts))
    text = [
        f"Wang et al. 2022 comparison on spring_damper: {trials} trajectories x {steps} steps, "
        "worst-case (vertex) noise.",
        "Each filter bounds the state by a set; smaller area = tighter bound. 'outside' counts",
        "(trajectory, step) pairs whose true state left the set (0 is required of a guaranteed",
        "filter); the EKF's set is its 3-sigma ellipsoid, shown for reference only.",
        "",
        format_table(table),
        "",
        f"Figure (set area over time; x1, x2 bounds minus the truth, trajectory 0): {fig_path}",
    ]
    return "\n".join(text)
