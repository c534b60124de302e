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

from diffsmf.audit import TOL, gauge
from diffsmf.filters.base import FilterResult, SetFilter
from diffsmf.systems.system import System, Trajectory

__all__ = ["compare", "demo", "format_table", "run_filters"]

GUARANTEED = {"HSNSMF", "MSZM", "CDSMF", "ESMF", "CZSMF"}


def _build(system: System, filters: dict[str, SetFilter] | list[str]) -> dict[str, SetFilter]:
    from diffsmf.filters import by_name

    if isinstance(filters, dict):
        return dict(filters)
    return {name: by_name(name)(system) for name in filters}


def run_filters(
    system: System,
    filters: dict[str, SetFilter] | list[str],
    trials: int = 20,
    steps: int = 100,
    noise: str = "uniform",
    seed: int = 0,
) -> tuple[Trajectory, dict[str, FilterResult], dict[str, float]]:
    """Simulate once, run every filter -> (trajectory, results by name, seconds by name)."""
    filts = _build(system, filters)
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
    traj, results, seconds = run_filters(system, filters, trials, steps, noise, seed)
    return _rows(traj, results, seconds)


def _rows(traj: Trajectory, results: dict[str, FilterResult], seconds: dict[str, float]) -> list:
    rows = []
    for name, res in results.items():
        g = gauge(res.sets, traj.x)
        viol = g > 1 + TOL
        err = res.center[:, 1:] - traj.x[:, 1:]
        rows.append(
            {
                "filter": name,
                "guaranteed": name.upper() in GUARANTEED,
                "mean_volume": float(res.volume[:, 4:].mean()),
                "violations": int(viol.sum()),
                "pairs": int(viol.numel()),
                "worst_distance": float((g - 1).clamp_min(0).max()),
                "inconsistent": int((~res.consistent).sum()),
                "rmse": err.pow(2).mean((0, 1)).sqrt().tolist(),
                "seconds": seconds[name],
            }
        )
    return rows


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
    """Wang et al. 2022 comparison on ``spring_damper`` (the ``diffsmf demo`` part): table text and
    ``filters_demo.png``; see `diffsmf.demo.filters_demo` (one implementation)."""
    from diffsmf.demo import filters_demo

    Path(outdir).mkdir(parents=True, exist_ok=True)
    return filters_demo(Path(outdir), trials=trials, steps=steps, seed=seed)


def _figure(traj: Trajectory, results: dict[str, FilterResult], path: Path) -> None:
    """The comparison figure of `diffsmf.plot.comparison_figure` (one home for it):
    set size over time and, per state, the bounds minus the truth; the EKF marked as not
    guaranteed."""
    from diffsmf.plot import comparison_figure

    comparison_figure(traj.x, results, path)
