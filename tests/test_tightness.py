"""Tightness report (diffsmf/tightness.py) against a 1-D filter whose set is exact."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from diffsmf.filters.base import FilterState, SetFilter
from diffsmf.sets import Interval
from diffsmf.systems import System
from diffsmf.tightness import inner_bounds, tightness

A, W, V = 0.8, 0.05, 0.1


def _system() -> System:
    one = torch.ones(1, dtype=torch.float64)
    return System(
        f=lambda x, u, th: A * x + u,
        h=lambda x: x,
        x0_set=Interval(-one, one),
        process_noise=Interval(-W * one, W * one),
        measurement_noise=Interval(-V * one, V * one),
        inputs=lambda k: torch.tensor([0.1 * k], dtype=torch.float64),
    )


class Exact1D(SetFilter):
    """In 1-D the feasible set is an interval and this interval filter is exact; ``scale``
    rescales the posterior about its centre (> 1 loose, < 1 broken)."""

    def __init__(self, system: System, scale: float = 1.0) -> None:
        super().__init__(system)
        self.scale = scale

    def _predict(self, state: FilterState, u: Tensor | None = None) -> FilterState:
        s, w = state.set, self.process_noise_box()
        return state.replace(
            set=Interval._make(A * s.lower + u + w.lower, A * s.upper + u + w.upper)
        )

    def _update(self, state: FilterState, y: Tensor) -> FilterState:
        s, v = state.set, self.measurement_noise_box()
        lo, hi = torch.maximum(s.lower, y - v.upper), torch.minimum(s.upper, y - v.lower)
        c, r = (lo + hi) / 2, (hi - lo) / 2 * self.scale
        return state.replace(set=Interval._make(c - r, c + r), consistent=(lo <= hi).all(-1))


@pytest.fixture(scope="module")
def setup():
    s = _system()
    tr = s.simulate(12, batch=2, seed=1, noise="vertex")
    inner = inner_bounds(Exact1D(s), s, tr, [1, 5, 12], starts=2)
    return s, tr, inner


def test_exact_filter_has_ratio_one(setup):
    s, tr, inner = setup
    rep = tightness(Exact1D(s), s, tr, [1, 5, 12], inner=inner)
    assert rep.failures == []
    for r in rep.rows:
        # the optimiser reaches both ends of the exact feasible interval
        assert r["ratio"] == pytest.approx(1.0, abs=1e-6)
        assert r["inner"] == pytest.approx(r["outer"], abs=1e-7)
    assert "containment failures: 0" in rep.table()


def test_loose_and_broken_filters_are_detected(setup):
    s, tr, inner = setup
    loose = tightness(Exact1D(s, scale=1.5), s, tr, [1, 5, 12], inner=inner)
    # inflating an outer set keeps it outer and only grows later sets: ratio >= 1.5
    assert all(r["ratio"] >= 1.5 - 1e-6 for r in loose.rows)
    assert loose.failures == []
    broken = tightness(Exact1D(s, scale=0.5), s, tr, [1, 5, 12], inner=inner)
    assert len(broken.failures) > 0  # feasible states found outside a too-small set
    assert all(r["ratio"] <= 0.5 + 1e-6 for r in broken.rows)


def test_bad_arguments(setup):
    s, tr, _ = setup
    with pytest.raises(ValueError, match="steps"):
        inner_bounds(Exact1D(s), s, tr, [0])
    with pytest.raises(ValueError, match="directions"):
        inner_bounds(Exact1D(s), s, tr, [1], directions=torch.ones(2, 3))
