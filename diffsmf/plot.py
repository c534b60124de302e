"""Matplotlib helpers: sets in the plane, bounds over time, volume curves.

Nothing here calls ``plt.show``; pass an ``Axes`` (use the Agg backend for files).

>>> import matplotlib; matplotlib.use("Agg")
>>> import matplotlib.pyplot as plt
>>> fig, ax = plt.subplots()
>>> plot_set(ax, Z, facecolor="none", edgecolor="C0")       # doctest: +SKIP
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.axes import Axes

    from diffsmf.filters.base import FilterResult
    from diffsmf.sets.base import ConvexSet

__all__ = ["plot_set", "polygon_2d", "plot_bounds", "plot_volumes"]


def _project(S: ConvexSet, dims: tuple[int, int] | None) -> ConvexSet:
    """2-D projection ``{(x_i, x_j)}`` of ``S`` (a linear map; boxes stay boxes)."""
    from diffsmf.sets.interval import Interval

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
    corners, ellipsoids ``k`` boundary points ``c + L [cos, sin]``.
    """
    from diffsmf.sets.ellipsoid import Ellipsoid
    from diffsmf.sets.interval import Interval
    from diffsmf.sets.parallelotope import Parallelotope
    from diffsmf.sets.zonotope import Zonotope

    if len(S.batch_shape) != 0:
        raise ValueError(f"S: plot one set (batch shape []), got {tuple(S.batch_shape)}")
    P = _project(S, dims)
    if isinstance(P, Interval):
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
