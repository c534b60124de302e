"""Angle outputs (``System(..., angle_outputs=[i])``): bearings and headings compared modulo
2 pi. Every filter builds its strip / innovation on the branch that the predicted measurement
picks (``y' = h(c) + wrap(y - h(c))``), so measurements that a sensor reports wrapped into
``[-pi, pi)`` keep the sets guaranteed when the prediction and the measurement lie on
opposite sides of the cut. References: the true simulated states (containment), and the same
data without the declaration (the strips then miss: flagged inconsistent).
"""

from __future__ import annotations

import math

import pytest
import torch

import diffsmf as ds
from diffsmf import filters, systems
from diffsmf.filters.strips import angle_ambiguous
from diffsmf.sets import Interval
from diffsmf.systems import wrap_angle

F64 = torch.float64
SET_FILTERS = ["hsnsmf", "mszm", "cdsmf", "esmf", "czsmf"]


def _heading_system(angle: bool) -> ds.System:
    """A heading that turns through +pi: ``th+ = th + 0.1 rate``, ``rate+ = rate``, ``y = th``."""

    def f(x, u=None, theta=None):
        return torch.stack([x[..., 0] + 0.1 * x[..., 1], x[..., 1]], -1)

    def h(x):
        return x[..., 0:1]

    x0 = Interval(torch.tensor([math.pi - 0.12, 0.45], dtype=F64),
                  torch.tensor([math.pi - 0.08, 0.55], dtype=F64))
    w = Interval(torch.full((2,), -1e-3, dtype=F64), torch.full((2,), 1e-3, dtype=F64))
    v = Interval(torch.tensor([-0.01], dtype=F64), torch.tensor([0.01], dtype=F64))
    return ds.System(f, h, x0, w, v, name="heading", angle_outputs=[0] if angle else None)


def _inside(traj, res) -> torch.Tensor:
    return ((traj.x >= res.lower - 1e-9) & (traj.x <= res.upper + 1e-9)).all(-1)


def test_wrap_angle_range_and_values():
    a = torch.tensor([-math.pi, math.pi, 3 * math.pi + 0.1, -0.5, 7.0], dtype=F64)
    w = wrap_angle(a)
    assert bool(((w >= -math.pi) & (w < math.pi)).all())
    assert torch.allclose(torch.cos(w), torch.cos(a)) and torch.allclose(torch.sin(w), torch.sin(a))
    assert w[0] == -math.pi and w[1] == -math.pi and w[3] == -0.5


def test_simulated_angle_outputs_are_wrapped_and_cross_the_cut():
    traj = _heading_system(True).simulate(12, batch=3, seed=1, noise="vertex")
    y = traj.y[..., 0]
    assert bool(((y >= -math.pi) & (y < math.pi)).all())
    assert bool((y > 3.0).any() and (y < -3.0).any())  # both sides of the cut
    assert bool((traj.x[:, -1, 0] > math.pi).all())  # the state itself is not wrapped


@pytest.mark.parametrize("name", SET_FILTERS)
def test_set_filters_contain_the_state_across_the_cut(name):
    sys_ = _heading_system(True)
    traj = sys_.simulate(12, batch=3, seed=1, noise="vertex")
    with torch.no_grad():
        res = filters.by_name(name)(sys_)(traj.y)
    assert bool(res.bounded.all()) and bool(res.consistent.all())
    assert bool(_inside(traj, res).all())
    assert float((res.upper - res.lower)[:, -1, 0].max()) < 0.1  # the measurement was used


@pytest.mark.parametrize("name", ["hsnsmf", "esmf"])
def test_without_the_declaration_the_wrapped_data_is_inconsistent(name):
    traj = _heading_system(True).simulate(12, batch=3, seed=1, noise="vertex")
    with torch.no_grad():
        res = filters.by_name(name)(_heading_system(False))(traj.y)
    assert not bool(res.consistent.all())


@pytest.mark.parametrize("name", ["ekf", "combined"])
def test_point_filters_wrap_the_innovation(name):
    sys_ = _heading_system(True)
    traj = sys_.simulate(12, batch=3, seed=1, noise="vertex")
    with torch.no_grad():
        res = filters.by_name(name)(sys_)(traj.y)
    err = (res.center[:, -1, 0] - traj.x[:, -1, 0]).abs()
    assert float(err.max()) < 0.05  # unwrapped innovation would pull it by 2 pi
    if name == "combined":
        assert bool(_inside(traj, res).all())


def test_innovation_wraps_only_angle_outputs():
    sys_ = systems.get("unicycle_rb")
    y = torch.tensor([[10.0, -3.1]], dtype=F64)
    yp = torch.tensor([[4.0, 3.1]], dtype=F64)
    d = sys_.innovation(y, yp)
    assert d[0, 0] == 6.0 and abs(float(d[0, 1]) - (2 * math.pi - 6.2)) < 1e-12


def test_ambiguous_bearing_drops_the_strip():
    """A set whose bearing range about h(c) reaches pi: the strip is all of R^n (inf)."""
    sys_ = systems.get("unicycle_rb")
    c = torch.zeros(1, 3, dtype=F64)
    H = torch.tensor([[[-1.0, 0.0, 0.0], [0.0, 0.05, -1.0]]], dtype=F64)
    E = Interval(torch.zeros(1, 2, dtype=F64), torch.zeros(1, 2, dtype=F64))
    V = sys_.measurement_noise
    narrow = Interval(c - 0.1, c + 0.1)
    wide = Interval(c - torch.tensor([0.1, 0.1, 3.2], dtype=F64), c + 0.1)
    assert not bool(angle_ambiguous(sys_, narrow, c, H, E, V).any())
    amb = angle_ambiguous(sys_, wide, c, H, E, V)
    assert amb.tolist() == [[False, True]]


@pytest.mark.parametrize("name", ["hsnsmf", "esmf"])
def test_unicycle_range_bearing_across_the_cut(name):
    """Range and body-frame bearing with the heading near pi: the bearing is wrapped within
    a few steps; 0 outside, no unbounded step, every measurement consistent."""
    sys_ = systems.get("unicycle_rb", heading0=3.0)
    traj = sys_.simulate(30, batch=2, seed=4, noise="vertex")
    b = traj.y[..., 1]
    assert bool((b > 3.0).any() or (b < -3.0).any())
    with torch.no_grad():
        res = filters.by_name(name)(sys_)(traj.y, u=traj.u)
    assert bool(res.bounded.all()) and bool(res.consistent.all())
    assert bool(_inside(traj, res).all())


def test_angle_outputs_validated_and_shown():
    sys_ = systems.get("unicycle_rb")
    assert sys_.angle_outputs == (1,) and "angle_outputs=[1]" in repr(sys_)
    base = _heading_system(False)
    for bad, msg in (([1], "angle_outputs"), ([0, 0], "repeated"), ("x", "angle_outputs"),
                     (3, "angle_outputs"), ([0.5], "angle_outputs")):
        with pytest.raises(ValueError, match=msg):
            ds.System(base.f, base.h, base.x0_set, base.process_noise, base.measurement_noise,
                      angle_outputs=bad)
