"""Every figure the package writes is written, non-empty and not blank."""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")

import matplotlib.image as mpimg  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

import diffsmf as ds  # noqa: E402
from diffsmf import plot  # noqa: E402


def _assert_drawn(path, min_bytes: int = 5_000, min_ink: float = 0.01) -> np.ndarray:
    """The PNG exists, is not tiny, and has non-background pixels (something was drawn)."""
    assert path.is_file(), path
    assert path.stat().st_size > min_bytes, (path, path.stat().st_size)
    img = mpimg.imread(path)[..., :3]
    ink = (np.abs(img - img[0, 0]).sum(-1) > 0.1).mean()
    assert ink > min_ink, (path, ink)
    return img


def test_demo_figures(tmp_path):
    from diffsmf.cli.demo import main

    args = argparse.Namespace(out=str(tmp_path), parts="filters,sets", trials=2, steps=8, seed=0)
    assert main(args) == 0
    _assert_drawn(tmp_path / "filters_demo.png")
    _assert_drawn(tmp_path / "sets.png")


def test_comparison_figure_labels_every_panel_and_marks_the_ekf(tmp_path):
    system = ds.systems.get("spring_damper")
    traj = system.simulate(6, batch=2, seed=0)
    with torch.no_grad():
        results = {n: ds.filters.by_name(n)(system)(traj.y) for n in ("HSNSMF", "EKF")}
    fig = plot.comparison_figure(traj.x, results, tmp_path / "cmp.png")
    _assert_drawn(tmp_path / "cmp.png")
    axes = fig.axes
    assert len(axes) == 1 + system.n
    assert all(ax.get_ylabel() and ax.get_xlabel() for ax in axes)
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert "EKF (not guaranteed)" in labels and "HSNSMF" in labels and "true state" in labels
    assert fig.legends[0].get_texts()[0].get_fontsize() >= 9
    # panels 2..: bounds relative to the truth -> a guaranteed filter's upper curve is >= 0
    upper_line = axes[1].get_lines()[0]
    assert (np.asarray(upper_line.get_ydata()) >= -1e-12).all()


def test_bounds_figure(tmp_path):
    T, n = 12, 3
    rng = np.random.default_rng(0)
    mid = np.cumsum(rng.normal(size=(T + 1, n)), 0)
    lo, up = mid - 0.1, mid + 0.1
    consistent = np.ones(T + 1, bool)
    consistent[5] = False
    fig = plot.bounds_figure(lo, up, tmp_path / "b.png", consistent=consistent, truth=mid,
                             title="t", guaranteed=False)
    _assert_drawn(tmp_path / "b.png")
    assert len(fig.axes) == 2 * n and all(ax.get_ylabel() for ax in fig.axes)
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert "bounds (NOT guaranteed)" in labels and "inconsistent step" in labels
    assert "true state" in labels and "update skipped (no measurement)" not in labels
    fig = plot.bounds_figure(lo, up, skipped=[3, 7])
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert labels.count("update skipped (no measurement)") == 1
    marks = [ln.get_xdata()[0] for ln in fig.axes[0].lines if ln.get_linestyle() == ":"]
    assert marks == [3, 7]
    with pytest.raises(ValueError, match="lower, upper"):
        plot.bounds_figure(lo, up[:, :2], tmp_path / "bad.png")


def test_plot_helpers_draw_sets_bounds_and_volumes(tmp_path):
    system = ds.systems.get("spring_damper")
    traj = system.simulate(5, batch=1, seed=0)
    with torch.no_grad():
        res = ds.filters.HSNSMF(system)(traj.y)
    fig, ax = plt.subplots(1, 3, figsize=(12, 4))
    plot.plot_set(ax[0], system.x0_set, facecolor="C0", alpha=0.3)
    plot.plot_set(ax[0], res.sets[0, -1])
    plot.plot_bounds(ax[1], res, 0, truth=traj.x)
    plot.plot_volumes(ax[2], {"HSNSMF": res})
    fig.savefig(tmp_path / "helpers.png")
    plt.close(fig)
    _assert_drawn(tmp_path / "helpers.png")
