"""Several filters on the same data, side by side.

* ``compare(system, y, u, filters=[...])`` (``ds.compare``): the observers on *your* data
  (recorded or simulated), as the nonlinear observer comparison of Holzinger & Althoff (2026)
  tabulates them: final interval-hull width sum, its mean over time, bounded steps and ms
  per step, with a figure of the bounds over time (`Comparison`).
* ``compare_simulated(system, names, trials, steps)``: simulates one batch of trajectories
  and runs every filter on it; each row reports the mean set area (volume) after step 3
  (Wang et al. 2022 compares the areas "for every k > 3"), the containment violations (see
  `diffsmf.audit`), the worst normalised distance outside, the number of inconsistent steps
  and the wall time.
* ``demo``: the ``diffsmf demo`` part.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from diffsmf import systems
from diffsmf.audit import TOL, gauge
from diffsmf.filters import by_name, get, is_guaranteed
from diffsmf.filters.base import FilterResult, SetFilter
from diffsmf.plot import comparison_figure, observers_figure
from diffsmf.systems.system import System, Trajectory
from diffsmf.utils import progress_bar

__all__ = [
    "Comparison", "DEFAULT_FILTERS", "build_filters", "compare", "compare_simulated", "demo",
    "format_table", "guarantees", "rows", "run_filters",
]


#: The observers `compare` runs when none are named: one per set family that is cheap at any
#: size (the constrained zonotopes of CZSMF are the tightest and cost the most; name them)
DEFAULT_FILTERS = ("interval", "hsnsmf", "mszm", "cdsmf")


@dataclass
class Comparison:
    """The result of `compare`: one row per observer and its `FilterResult`.

    rows: dicts with ``filter``, ``family`` (`diffsmf.filters.SET_FAMILIES`), ``guaranteed``,
    ``final_width_sum`` (the interval hull's width sum at the last step, mean over the
    trajectories; inf where a trajectory's set became unbounded), ``mean_width_sum`` (the
    same over steps 1..T), ``bounded`` (bounded (trajectory, step) pairs), ``pairs`` (all of
    them), ``inconsistent`` (steps whose measurement missed the predicted set),
    ``ms_per_step`` (wall time of the run over T, all trajectories at once) and ``error`` (the
    exception's text where the observer raised, else None; its numbers are then NaN).
    results: ``{name: FilterResult}`` of the observers that ran.
    """

    rows: list[dict]
    results: dict[str, FilterResult] = field(default_factory=dict)
    title: str = ""

    def table(self) -> str:
        """The rows as a plain-text table."""
        head = (f"{'observer':<10} {'family':<20} {'final width sum':>15} "
                f"{'mean width sum':>14} {'bounded':>13} {'inconsistent':>12} {'ms/step':>8}")
        lines = [head, "-" * len(head)]
        for r in self.rows:
            if r["error"] is not None:
                lines.append(f"{r['filter']:<10} {r['family']:<20} raised: {r['error']}")
                continue
            tag = "" if r["guaranteed"] else "  (not guaranteed)"
            lines.append(
                f"{r['filter']:<10} {r['family']:<20} {r['final_width_sum']:>15.4g} "
                f"{r['mean_width_sum']:>14.4g} {r['bounded']:>6}/{r['pairs']:<6} "
                f"{r['inconsistent']:>12d} {r['ms_per_step']:>8.2f}{tag}"
            )
        return "\n".join(lines)

    def figure(self, path: str | Path | None = None, trajectory: int = 0,
               states: list[int] | None = None) -> Any:
        """The bounds over time of every observer (`diffsmf.plot.observers_figure`) for
        ``trajectory``, the width sum in the first panel and up to four ``states``
        (default: the first four) below -> a Figure, saved to ``path`` when given."""
        return observers_figure(self.results, path, trajectory=trajectory, states=states,
                                title=self.title)


def compare(
    system: System,
    y: Tensor,
    u: Tensor | None = None,
    filters: dict[str, SetFilter] | list[str] | tuple[str, ...] = DEFAULT_FILTERS,
    *,
    progress: bool = False,
) -> Comparison:
    """Run several observers on the same data -> `Comparison` (``.rows``, ``.table()``,
    ``.figure(path)``).

    Args:
        system: the `System` (a built-in, ``ds.systems.get(name)``, or your own).
        y: measurements ``[T, m]`` or ``[B, T, m]`` (``y[:, k-1]`` measures ``x_k``; see
            `diffsmf.systems.recorded` for data whose first row measures ``x_0``).
        u: inputs ``[T, p]`` or ``[B, T, p]``, or None (the system's schedule, if any).
        filters: names (any of `diffsmf.filters.names` or CORA's observer names, e.g.
            ``"FRad-B"``), or ``{label: filter}`` for filters with your own settings.
        progress: a progress bar over the observers (``True``, or a bar factory,
            `diffsmf.utils.progress_bar`).

    An observer that raises is a row with its error, not a failure of the comparison; a
    trajectory whose set becomes unbounded counts as unbounded (inf widths), never as a
    finite number.

    Raises:
        ValueError: naming ``y``, ``u`` or ``filters`` (an unknown name, a wrong shape).
    """
    y, u = _batched(system, y, u)
    filts = _named_filters(system, filters)
    rows_, results = [], {}
    bar = progress_bar(progress, len(filts), "observers", "observer")
    for name in filts:
        row, res = _observer_row(name, filts[name], system, y, u)
        rows_.append(row)
        if res is not None:
            results[name] = res
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    B = y.shape[0]
    return Comparison(rows_, results, f"{system.name}: {y.shape[1]} steps, {B} "
                                      f"{'trajectory' if B == 1 else 'trajectories'}")


def _batched(system: System, y: Any, u: Any) -> tuple[Tensor, Tensor | None]:
    """``y [B, T, m]`` and ``u [B, T, p]`` (or None) from 2-D or 3-D input, checked."""
    dt = system.x0_set.dtype
    y = torch.as_tensor(y, dtype=dt)
    if y.dim() == 2:
        y = y.unsqueeze(0)
    if y.dim() != 3 or y.shape[-1] != system.m or y.shape[1] == 0:
        raise ValueError(f"y: expected [T, {system.m}] or [B, T, {system.m}] measurements of "
                         f"{system.name!r}, got {tuple(y.shape)}")
    if u is not None:
        u = torch.as_tensor(u, dtype=dt)
        u = u.unsqueeze(0) if u.dim() == 2 else u
        if u.dim() != 3 or u.shape[:2] != y.shape[:2]:
            raise ValueError(f"u: expected inputs [T, p] or [B, T, p] with the T (and B) of y "
                             f"{tuple(y.shape[:2])}, got {tuple(u.shape)}")
        u = u.expand(y.shape[0], *u.shape[1:])
    return y, u


def _named_filters(system: System, filters: Any) -> dict[str, SetFilter]:
    if isinstance(filters, dict):
        return dict(filters)
    if isinstance(filters, str) or not len(filters):
        raise ValueError(f"filters: expected a list of filter names, got {filters!r}")
    out = {}
    for name in filters:
        try:
            cls = get(name)
        except ValueError as exc:
            raise ValueError(f"filters: {str(exc).removeprefix('name: ')}") from None
        out[name] = cls
    return out


def _observer_row(name: str, filt: Any, system: System, y: Tensor, u: Tensor | None
                  ) -> tuple[dict, FilterResult | None]:
    """Build (when given a class or preset) and run one observer -> (row, result or None)."""
    B, T = y.shape[:2]
    row: dict[str, Any] = {"filter": name, "family": getattr(filt, "set_family", "?"),
                           "guaranteed": is_guaranteed(filt), "pairs": B * T, "error": None}
    try:
        filt = filt if isinstance(filt, SetFilter) else filt(system)
        t0 = time.perf_counter()
        with torch.no_grad():
            res = filt(y, u=u)
        seconds = time.perf_counter() - t0
    except Exception as exc:  # a row of the table, not a crash of the comparison
        row.update(final_width_sum=math.nan, mean_width_sum=math.nan, bounded=0,
                   inconsistent=0, ms_per_step=math.nan,
                   error=f"{type(exc).__name__}: {str(exc).splitlines()[0][:120]}")
        return row, None
    width = (res.upper - res.lower).sum(-1)  # [B, T+1], inf where unbounded
    row.update(
        final_width_sum=float(width[:, -1].mean()),
        mean_width_sum=float(width[:, 1:].mean()),
        bounded=int(res.bounded[:, 1:].sum()),
        inconsistent=int((~res.consistent[:, 1:]).sum()),
        ms_per_step=1e3 * seconds / T,
    )
    return row, res


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


def compare_simulated(
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
    """The rows of `compare_simulated` from the outputs of `run_filters` and `guarantees`."""
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
    """Plain-text table of `compare_simulated` rows."""
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
