"""A tiny exact interval filter for a linear 2-D system, used by the training tests.

System: x_k = A x_{k-1} + w,  y_k = x_{k,1} + v  (A with non-negative entries, so the interval
hull of A X is exact), W = [-0.02, 0.02]^2, V = [-0.01, 0.01], X0 = [-1, 1]^2.
Predict: box hull of A X (+) W; update: intersect coordinate 1 with [y - rV, y + rV]
(exact: the posterior box is the set of states consistent with the box prior and y).
"""

from __future__ import annotations

import torch
from torch import Tensor

from diffsmf.filters.base import FilterState, SetFilter
from diffsmf.sets import Interval
from diffsmf.systems import System

A = torch.tensor([[0.9, 0.1], [0.05, 0.8]], dtype=torch.float64)
W_BOUND, V_BOUND = 0.02, 0.01


def toy_system() -> System:
    return System(
        f=lambda x, u, th: x @ A.T,
        h=lambda x: x[..., :1],
        x0_set=Interval(-torch.ones(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64)),
        process_noise=Interval(
            -W_BOUND * torch.ones(2, dtype=torch.float64),
            W_BOUND * torch.ones(2, dtype=torch.float64),
        ),
        measurement_noise=Interval(
            -V_BOUND * torch.ones(1, dtype=torch.float64),
            V_BOUND * torch.ones(1, dtype=torch.float64),
        ),
        name="toy",
    )


class ToyIntervalFilter(SetFilter):
    """Exact box filter of `toy_system` (A >= 0 elementwise)."""

    def _predict(self, state: FilterState, u: Tensor | None = None) -> FilterState:
        s = state.set
        w = self.process_noise_box()
        lo = s.lower @ A.T + w.lower
        hi = s.upper @ A.T + w.upper
        return state.replace(set=Interval._make(lo, hi))

    def _update(self, state: FilterState, y: Tensor) -> FilterState:
        s = state.set
        v = self.measurement_noise_box()
        lo1 = torch.maximum(s.lower[..., :1], y - v.upper)
        hi1 = torch.minimum(s.upper[..., :1], y - v.lower)
        ok = (lo1 <= hi1).all(-1)
        lo = torch.cat([lo1, s.lower[..., 1:]], -1)
        hi = torch.cat([hi1, s.upper[..., 1:]], -1)
        keep = ok.unsqueeze(-1)
        new = Interval._make(torch.where(keep, lo, s.lower), torch.where(keep, hi, s.upper))
        return state.replace(set=new, consistent=ok)


def test_toy_filter_contains_vertex_noise_trajectories():
    sys_ = toy_system()
    traj = sys_.simulate(30, batch=200, seed=3, noise="vertex")
    res = ToyIntervalFilter(sys_)(traj.y)
    assert res.sets.contains(traj.x).all()
    assert res.consistent.all()
    # shrinking the measurement bound below the truth must make some step inconsistent
    f = ToyIntervalFilter(sys_, measurement_noise=torch.tensor([0.2 * V_BOUND]))
    assert not f(traj.y).consistent.all()
