"""Matplotlib helpers: sets in the plane, bounds over time, volume curves.

Nothing here calls ``plt.show``; pass an ``Axes`` (use the Agg backend for files).

>>> import matplotlib; matplotlib.use("Agg")
>>> import matplotlib.pyplot as plt
>>> fig, ax = plt.subplots()
>>> plot_set(ax, Z, facecolor="none", edgecolor="C0")       # doctest: +SKIP
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from diffsmf.sets.constrained_zonotope import ConstrainedZonotope
from diffsmf.sets.ellipsoid import Ellipsoid
from diffsmf.sets.interval import Interval
from diffsmf.sets.parallelotope import Parallelotope
from diffsmf.sets.zonotope import Zonotope

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from diffsmf.convex import ConvexSet
    from diffsmf.filters.base import FilterResult

__all__ = [
    "bounds_figure",
    "comparison_figure",
    "observers_figure",
    "plot_bounds",
    "plot_set",
    "plot_volumes",
    "polygon_2d",
]


def _project(S: ConvexSet, dims: tuple[int, int] | None) -> ConvexSet:
    """2-D projection ``{(x_i, x_j)}`` of ``S`` (a linear map; boxes stay boxes)."""
    n = S.dim
    if dims is None:
        if n != 2:
            raise ValueError(f"dims: a {n}-D set needs dims=(i, j) to be projected")
        return S
    i, j = dims
    if not (0 <= i < n and 0 <= j < n and i != j):
        raise ValueError(f"dims: need two distinct indices in [0, {n}), got {dims}")
    if isinstance(S, Interval):
        return Interval(S.lower[..., [i, j]], S.upper[..., [i, j]])
    E = torch.zeros(2, n, dtype=S.dtype, device=S.device)
    E[0, i] = 1.0
    E[1, j] = 1.0
    return S.linear_map(E)


def polygon_2d(S: ConvexSet, dims: tuple[int, int] | None = None, k: int = 200) -> np.ndarray:
    """Closed boundary polygon ``[p, 2]`` of a 2-D set (or a 2-D projection) with batch shape [].

    Zonotopes/parallelotopes use the exact vertices (``Zonotope.vertices_2d``), boxes their 4
    corners, ellipsoids ``k`` boundary points ``c + L [cos, sin]``, constrained zonotopes (CZSMF)
    the outer polygon of their certified support in ``k`` directions
    (``ConstrainedZonotope.outer_polygon_2d``; a certified empty set raises).
    """
    if len(S.batch_shape) != 0:
        raise ValueError(f"S: plot one set (batch shape []), got {tuple(S.batch_shape)}")
    P = _project(S, dims)
    if isinstance(P, ConstrainedZonotope):
        with torch.no_grad():
            if bool(P.is_empty()):
                raise ValueError("S: the constrained zonotope is certified empty, nothing to plot")
            pts = P.outer_polygon_2d(k)
    elif isinstance(P, Interval):
        lo, up = P.lower.detach(), P.upper.detach()
        pts = torch.stack([lo, torch.stack([up[0], lo[1]]), up, torch.stack([lo[0], up[1]])], 0)
    elif isinstance(P, Parallelotope):
        pts = P.to_zonotope().vertices_2d().detach()
    elif isinstance(P, Zonotope):
        pts = P.vertices_2d().detach()
    elif isinstance(P, Ellipsoid):
        t = torch.linspace(0, 2 * math.pi, k, dtype=P.dtype)
        circle = torch.stack([torch.cos(t), torch.sin(t)], -1)
        L = P.cholesky().detach()
        pts = P.center.detach() + circle @ L.transpose(-1, -2)
    else:
        raise ValueError(f"S: cannot plot a {type(S).__name__}")
    pts = pts.cpu().numpy()
    return np.concatenate([pts, pts[:1]], 0)


def plot_set(ax: Axes, S: ConvexSet, dims: tuple[int, int] | None = None, **style: Any) -> Any:
    """Draw a 2-D set (Interval, Zonotope, Parallelotope, Ellipsoid; batch shape []) or the
    projection of an n-D set on coordinates ``dims=(i, j)``. ``style`` goes to
    ``matplotlib.patches.Polygon`` (default: no fill, edge colour C0). Returns the patch.
    """
    from matplotlib.patches import Polygon

    xy = polygon_2d(S, dims)
    kw: dict[str, Any] = {"fill": False, "edgecolor": "C0", "linewidth": 1.2}
    if "color" in style or "facecolor" in style:
        kw.pop("fill")
    kw.update(style)
    patch = Polygon(xy, closed=True, **kw)
    ax.add_patch(patch)
    ax.update_datalim(xy)
    ax.autoscale_view()
    return patch


def _np(t: Tensor) -> np.ndarray:
    return t.detach().cpu().numpy()


def plot_bounds(
    ax: Axes,
    result: FilterResult,
    dim: int,
    truth: Tensor | None = None,
    index: int = 0,
    label: str | None = None,
    **style: Any,
) -> None:
    """Lower/upper bound (and centre) of state ``dim`` over time for batch element ``index``.

    ``result.lower/upper [B, T+1, n]``; ``truth``: ``[B, T+1, n]``, ``[T+1, n]`` or ``[T+1]``
    (plotted as a black line).
    """
    lo, up = result.lower, result.upper
    if not 0 <= dim < lo.shape[-1]:
        raise ValueError(f"dim: must be in [0, {lo.shape[-1]}), got {dim}")
    k = np.arange(lo.shape[-2])
    color = style.pop("color", None)
    (line,) = ax.plot(k, _np(up[index, :, dim]), color=color, label=label, **style)
    ax.plot(k, _np(lo[index, :, dim]), color=line.get_color(), **style)
    ax.plot(
        k, _np(result.center[index, :, dim]), color=line.get_color(), linestyle=":", linewidth=0.8
    )
    if truth is not None:
        t = torch.as_tensor(truth)
        if t.dim() == 3:
            t = t[index]
        if t.dim() == 2:
            t = t[:, dim]
        ax.plot(np.arange(t.shape[0]), _np(t), color="k", linewidth=1.0, label="truth")
    ax.set_xlabel("k")
    ax.set_ylabel(f"x{dim + 1}")


def plot_volumes(
    ax: Axes, results: dict[str, FilterResult], index: int = 0, log: bool = True
) -> None:
    """Set volume over time for several filters (``{name: FilterResult}``), one line each."""
    if not results:
        raise ValueError("results: need at least one FilterResult")
    for name, res in results.items():
        v = _np(res.volume[index])
        ax.plot(np.arange(v.shape[0]), v, label=name)
    if log:
        ax.set_yscale("log")
    ax.set_xlabel("k")
    ax.set_ylabel("volume")
    ax.legend()


# ---------------------------------------------------------------------- whole figures
def _figure(figsize: tuple[float, float]) -> Figure:
    """A figure outside pyplot: no backend switch, no global state (safe in notebooks)."""
    from matplotlib.figure import Figure

    return Figure(figsize=figsize)


def _save(fig: Figure, path: str | Path | None, dpi: int) -> Figure:
    if path is not None:
        fig.savefig(Path(path), dpi=dpi)
    return fig


def bounds_figure(
    lower: np.ndarray | Tensor,
    upper: np.ndarray | Tensor,
    path: str | Path | None = None,
    consistent: np.ndarray | Tensor | None = None,
    truth: np.ndarray | Tensor | None = None,
    title: str | None = None,
    guaranteed: bool = True,
    state_names: list[str] | None = None,
    bounded: np.ndarray | Tensor | None = None,
    skipped: Sequence[int] | None = None,
) -> Figure:
    """Bounds of every state over time for one trajectory -> a Figure (saved to ``path``).

    Args:
        lower: ``[T+1, n]`` lower bounds (row 0 = the initial set).
        upper: ``[T+1, n]`` upper bounds.
        consistent: ``[T+1]`` bool; inconsistent steps are marked in red.
        truth: ``[T+1, n]`` true states, drawn when known (simulations).
        guaranteed: False for a filter whose bounds carry no guarantee (EKF); the legend
            says so.
        state_names: labels of the states (default ``x1 .. xn``).
        bounded: ``[T+1]`` bool; from the first False step on the guarantee is lost (the set
            is unbounded, its bounds are -inf / +inf): that part is shaded grey and labelled,
            and no bound is drawn there (infinite bounds are never drawn as finite ones).
        skipped: steps ``k`` (1..T) whose update was skipped (a missing measurement): marked
            by grey dotted lines (the set there is the prediction, still guaranteed).

    One row per state: left, the bounds (shaded) and the truth; right, the bound width
    ``upper - lower`` on a log scale (bounds that are tight relative to the state's size are
    invisible on the left and readable on the right).
    """
    lo, up = np.asarray(_as_np(lower), float), np.asarray(_as_np(upper), float)
    if lo.ndim != 2 or lo.shape != up.shape:
        raise ValueError(f"lower, upper: expected the same shape [T+1, n], got {lo.shape} "
                         f"and {up.shape}")
    T1, n = lo.shape
    lost = None
    if bounded is not None:
        bnd = np.asarray(_as_np(bounded), bool).reshape(-1)
        lost = int(np.flatnonzero(~bnd)[0]) if (~bnd).any() else None
    lo = np.where(np.isfinite(lo), lo, np.nan)  # an infinite bound is not drawn
    up = np.where(np.isfinite(up), up, np.nan)
    names = state_names or [f"x{i + 1}" for i in range(n)]
    k = np.arange(T1)
    label = "guaranteed bounds" if guaranteed else "bounds (NOT guaranteed)"
    bad = None if consistent is None else np.flatnonzero(~np.asarray(_as_np(consistent), bool))
    fig = _figure((11, 2.6 * n + 0.9))
    axes = fig.subplots(n, 2, squeeze=False, sharex=True)
    for i in range(n):
        ax, axw = axes[i]
        ax.fill_between(k, lo[:, i], up[:, i], color="C0", alpha=0.3, linewidth=0, label=label)
        ax.plot(k, lo[:, i], color="C0", lw=0.9)
        ax.plot(k, up[:, i], color="C0", lw=0.9)
        if truth is not None:
            t = np.asarray(_as_np(truth), float)
            ax.plot(np.arange(t.shape[0]), t[:, i], color="k", lw=1.0, label="true state")
        width = up[:, i] - lo[:, i]
        axw.semilogy(k, np.where(width > 0, width, np.nan), color="C0", lw=1.0,
                     label=f"width of the {'guaranteed ' if guaranteed else ''}bounds")
        if bad is not None and bad.size:
            for a in (ax, axw):
                for j, kk in enumerate(bad):
                    a.axvline(kk, color="C3", lw=0.6, alpha=0.7,
                              label="inconsistent step" if j == 0 else None)
        for a in (ax, axw) if skipped else ():
            for j, kk in enumerate(skipped):
                a.axvline(kk, color="0.45", lw=0.8, ls=":",
                          label="update skipped (no measurement)" if j == 0 else None)
        if lost is not None:
            for a in (ax, axw):
                a.axvspan(lost - 0.5, T1 - 0.5, color="0.6", alpha=0.35, linewidth=0,
                          label=f"guarantee lost from step {lost} (unbounded: -inf..+inf)")
        ax.set_ylabel(names[i])
        axw.set_ylabel(f"upper - lower of {names[i]}")
        ax.grid(alpha=0.3)
        axw.grid(alpha=0.3, which="both")
    for a in axes[-1]:
        a.set_xlabel("step k")
    axes[0, 0].set_title("bounds over time")
    axes[0, 1].set_title("bound width (log scale)")
    handles, labels = [], []
    for a in axes[0]:
        for h, lab in zip(*a.get_legend_handles_labels()):
            if lab not in labels:
                handles.append(h)
                labels.append(lab)
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=9,
               frameon=False)
    if title:
        fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.06 if n > 1 else 0.1, 1, 1))
    return _save(fig, path, dpi=100)


def _as_np(t: Any) -> np.ndarray:
    return _np(t) if isinstance(t, Tensor) else np.asarray(t)


def comparison_figure(
    truth: Tensor,
    results: dict[str, FilterResult],
    path: str | Path | None = None,
    guaranteed: dict[str, bool] | None = None,
    index: int = 0,
) -> Figure:
    """Filters side by side on one batch of trajectories -> a Figure (saved to ``path``).

    Panel 1: mean set area / volume over time (log scale, over the batch). Panels 2..n+1: for
    trajectory ``index`` and each state, ``upper - x`` (above 0) and ``lower - x`` (below 0)
    as a shaded band per filter, the widest drawn first: the true state is the zero line, so
    a guaranteed filter's band never leaves it. The y-axis is symmetric-logarithmic (linear
    within the typical gap, logarithmic beyond), so the wide initial set and the tight later
    bounds are both visible; nothing is clipped.

    Args:
        truth: true states ``[B, T+1, n]``.
        results: ``{name: FilterResult}`` on those trajectories.
        guaranteed: ``{name: bool}``; a filter marked False (e.g. the EKF) is dashed and
            labelled "not guaranteed" (default: every name but ``"EKF"`` is guaranteed).
    """
    if not results:
        raise ValueError("results: need at least one FilterResult")
    x = _np(truth).astype(float)
    n = x.shape[-1]
    k = np.arange(x.shape[1])
    g = {name: name.upper() != "EKF" for name in results}
    g.update(guaranteed or {})
    fig = _figure((4.6 * (1 + n), 4.4))
    axes = fig.subplots(1, 1 + n)
    widths = {name: _mean_gap(res, x, index) for name, res in results.items()}
    rank = {name: r for r, name in enumerate(sorted(widths, key=widths.__getitem__, reverse=True))}
    for j, (name, res) in enumerate(results.items()):
        style = {"color": f"C{j}", "linestyle": "-" if g[name] else "--"}
        label = name if g[name] else f"{name} (not guaranteed)"
        axes[0].semilogy(k[1:], _np(res.volume[:, 1:].mean(0)), label=label, lw=1.6, **style)
        for i in range(n):
            ax = axes[1 + i]
            up = _np(res.upper[index, :, i]) - x[index, :, i]
            lo = _np(res.lower[index, :, i]) - x[index, :, i]
            z = 2 + rank[name]  # the widest band at the back
            ax.plot(k, up, lw=1.3, zorder=z, **style)
            ax.plot(k, lo, lw=1.3, zorder=z, **style)
            if g[name]:
                ax.fill_between(k, lo, up, color=f"C{j}", alpha=0.18, lw=0, zorder=z)
    axes[0].set_ylabel("mean set area / volume")
    axes[0].set_title("set size over time (mean over trajectories)")
    for i in range(n):
        ax = axes[1 + i]
        ax.axhline(0.0, color="k", lw=1.2, zorder=20, label="true state" if i == 0 else None)
        lim = _gap_limit(results, x, index, i)
        if lim is not None:
            ax.set_yscale("symlog", linthresh=lim)
        ax.set_ylabel(f"bound - true x{i + 1}  (upper above 0, lower below)")
        ax.set_title(f"bounds of x{i + 1} relative to the truth (trajectory {index})")
    for ax in axes:
        ax.set_xlabel("step k")
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    h2, l2 = axes[1].get_legend_handles_labels()
    fig.legend(handles + h2, labels + l2, loc="lower center", ncol=len(labels) + len(l2),
               fontsize=10, frameon=False)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    return _save(fig, path, dpi=90)


def _mean_gap(res: FilterResult, x: np.ndarray, index: int) -> float:
    """Mean finite width ``upper - lower`` of trajectory ``index`` (orders the bands)."""
    d = _np(res.upper[index]) - _np(res.lower[index])
    d = d[np.isfinite(d)]
    return float(d.mean()) if d.size else float("inf")


def _gap_limit(results: dict[str, FilterResult], x: np.ndarray, index: int, i: int) -> float | None:
    """Linear range of a bounds-minus-truth panel's symmetric-log axis: a tenth of the widest
    filter's median gap after the first 3 steps (wider bands and the initial set go on the
    logarithmic part), or None when no gap is finite and positive."""
    gaps = []
    for res in results.values():
        d = np.abs(np.concatenate([_np(res.upper[index, 3:, i]) - x[index, 3:, i],
                                   _np(res.lower[index, 3:, i]) - x[index, 3:, i]]))
        d = d[np.isfinite(d) & (d > 0)]
        if d.size:
            gaps.append(float(np.median(d)))
    return 0.1 * max(gaps) if gaps else None


def observers_figure(
    results: dict[str, FilterResult],
    path: str | Path | None = None,
    trajectory: int = 0,
    states: Sequence[int] | None = None,
    title: str = "",
) -> Figure:
    """Observers on the same data (`diffsmf.comparison.compare`) -> a Figure (saved to
    ``path``).

    Panel 1: the interval hull's width sum over time per observer (log scale); steps where
    an observer's set is unbounded are left out of its line and marked by a cross at the
    top. Panels 2..: the lower and upper bounds of ``states`` (default the first four) for
    ``trajectory``, one colour per observer (a dashed line from the eleventh on), the widest
    drawn first, in a frame of twice the
    observers' median initial range (a set that outgrows it is cut at the frame).

    Args:
        results: ``{name: FilterResult}``, each with ``lower``/``upper [B, T+1, n]``.
        trajectory: the batch index drawn in the state panels.
        states: the state indices drawn (default ``0 .. min(n, 4) - 1``).
    """
    if not results:
        raise ValueError("results: no observer ran, nothing to draw")
    first = next(iter(results.values()))
    n = first.lower.shape[-1]
    states = list(range(min(n, 4))) if states is None else list(states)
    if any(not 0 <= i < n for i in states):
        raise ValueError(f"states: indices must be in 0..{n - 1}, got {states}")
    fig = _figure((8.0, 2.2 * (1 + len(states))))
    axes = fig.subplots(1 + len(states), 1, sharex=True, squeeze=False)[:, 0]
    order = sorted(results, key=lambda k: -_finite_mean_width(results[k]))
    colors = {name: f"C{i % 10}" for i, name in enumerate(results)}
    styles = {name: ("-", "--", ":")[min(i // 10, 2)] for i, name in enumerate(results)}
    ax = axes[0]
    top = max(_finite_max_width(r) for r in results.values())
    lost = False
    for name in results:
        w = _np((results[name].upper - results[name].lower).sum(-1)).mean(0)
        t = np.arange(len(w))
        ok = np.isfinite(w)
        ax.semilogy(t[ok], w[ok], color=colors[name], ls=styles[name], label=name)
        if (~ok).any():
            ax.plot(t[~ok], np.full((~ok).sum(), top), "x", color=colors[name])
            lost = True
    if lost:
        ax.plot([], [], "x", color="0.3", label="x: set unbounded")
    ax.set_ylabel("width sum")
    ax.legend(fontsize=7, ncol=min(len(results), 4))
    if title:
        ax.set_title(title, fontsize=9)
    for ax, i in zip(axes[1:], states):
        # the common view: the observers' median initial range, padded by half of it (a set
        # that outgrows it is cut at the frame, its width stays readable in panel 1)
        lo0 = np.median([float(results[k].lower[trajectory, 0, i]) for k in results])
        hi0 = np.median([float(results[k].upper[trajectory, 0, i]) for k in results])
        pad = 0.5 * (hi0 - lo0) if hi0 > lo0 else 1.0
        ax.set_ylim(lo0 - pad, hi0 + pad)
        for name in order:
            lo = _np(results[name].lower[trajectory, :, i])
            up = _np(results[name].upper[trajectory, :, i])
            t = np.arange(len(lo))
            ok = np.isfinite(lo) & np.isfinite(up)
            ax.fill_between(t[ok], lo[ok], up[ok], color=colors[name], alpha=0.25, lw=0)
            ax.plot(t[ok], lo[ok], color=colors[name], ls=styles[name], lw=0.8)
            ax.plot(t[ok], up[ok], color=colors[name], ls=styles[name], lw=0.8)
        ax.set_ylabel(f"x{i + 1}")
    axes[-1].set_xlabel("step k")
    fig.tight_layout()
    return _save(fig, path, 120)


def _finite_max_width(res: FilterResult) -> float:
    w = _np((res.upper - res.lower).sum(-1)).mean(0)
    w = w[np.isfinite(w)]
    return float(w.max()) if w.size else 1.0


def _finite_mean_width(res: FilterResult) -> float:
    w = _np((res.upper - res.lower).sum(-1))
    w = w[np.isfinite(w)]
    return float(w.mean()) if w.size else math.inf
