"""System-level checks: ``print(system)``, non-finite simulations, mismatched dimensions, and
the CSTR and unicycle built-ins."""

from __future__ import annotations

import math

import pytest
import torch

import diffsmf as ds
from diffsmf import filters, systems
from diffsmf.sets import Interval

F64 = torch.float64


def _box(lo, hi) -> Interval:
    return Interval(torch.tensor(lo, dtype=F64), torch.tensor(hi, dtype=F64))


def test_repr_shows_dimensions_and_sets():
    s = systems.get("mismatch_quadratic")
    text = repr(s)
    assert text != "System()"
    for part in ("name='mismatch_quadratic'", "n=2", "m=2", "x0_set=Ellipsoid(dim=2)",
                 "process_noise=Interval(dim=2)", "parameters=Interval(dim=1)"):
        assert part in text
    assert "n_inputs=2" in repr(systems.get("bilinear"))


def test_simulate_raises_on_a_diverging_trajectory_naming_f_step_and_trajectory():
    def f(x, u=None, theta=None):
        return x * x  # escapes to inf from |x| > 1

    def h(x):
        return x[..., :1]

    s = ds.System(f, h, _box([0.5], [0.5]), None, None)
    x0 = torch.tensor([[0.5], [3.0]], dtype=F64)
    with pytest.raises(ValueError, match=r"^f: .* at step \d+ in trajectory\(ies\) 1 of 2"):
        s.simulate(20, batch=2, x0=x0)
    tr = s.simulate(20, batch=1, x0=x0[:1])  # the bounded one is fine
    assert bool(torch.isfinite(tr.x).all())


def test_simulate_raises_on_nan_measurements_naming_h():
    def f(x, u=None, theta=None):
        return x - 0.3

    def h(x):
        return torch.sqrt(x[..., :1])  # NaN once x < 0

    s = ds.System(f, h, _box([1.0], [1.0]), None, None)
    with pytest.raises(ValueError, match=r"^h: the measurement y_4 .* at step 4"):
        s.simulate(6, batch=1)


def test_x0_of_the_wrong_dimension_is_named():
    def f(x, u=None, theta=None):
        return 0.9 * x

    def h(x):
        return x[..., :1]

    W = _box([-0.1] * 3, [0.1] * 3)
    with pytest.raises(ValueError, match=r"^x0_set: has dim 2, but process_noise has dim 3"):
        ds.System(f, h, _box([0.0, 0.0], [1.0, 1.0]), W, None)
    # f that only takes 2 states: the noise is the wrong one
    def f2(x, u=None, theta=None):
        return torch.stack([x[..., 0], x[..., 1]], -1)

    with pytest.raises(ValueError, match=r"^process_noise: must be a diffsmf set of dim 2"):
        ds.System(f2, h, _box([0.0, 0.0], [1.0, 1.0]), W, None)


def test_simulate_checks_x0():
    s = systems.get("spring_damper")
    with pytest.raises(ValueError, match="^x0: expected shape"):
        s.simulate(3, batch=2, x0=torch.zeros(3, dtype=F64))
    with pytest.raises(ValueError, match="^x0: contains NaN"):
        s.simulate(3, batch=1, x0=torch.tensor([math.nan, 0.0], dtype=F64))


def test_cstr_is_badly_scaled_and_the_default_filter_stays_bounded():
    """HSNSMF with defaults on the CSTR (Ca ~ 0.9 mol/L, T ~ 320 K): bounded, 0 outside, and
    the unmeasured concentration bounded tightly (the absolute Stirling step and the isotropic
    DC ball diverged here). 150 steps of 3 trajectories; docs/which_filter.md has 1,000."""
    s = systems.get("cstr")
    x = s.simulate(300, batch=1, seed=0).x[0, -1]
    assert abs(float(x[0]) - 0.918) < 0.05 and abs(float(x[1]) - 319.1) < 2.0
    traj = s.simulate(150, batch=3, seed=2024, noise="vertex")
    with torch.no_grad():
        res = filters.HSNSMF(s)(traj.y)
    assert bool(res.bounded.all()) and bool(res.consistent.all())
    inside = ((traj.x >= res.lower - 1e-9) & (traj.x <= res.upper + 1e-9)).all(-1)
    assert bool(inside.all())
    assert float((res.upper - res.lower)[:, 50:, 0].mean()) < 0.3


def test_cstr_and_unicycle_are_registered_with_checked_arguments():
    assert {"cstr", "unicycle_rb"} <= set(systems.names())
    with pytest.raises(ValueError, match="dt"):
        systems.get("cstr", dt=0.0)
    with pytest.raises(ValueError, match="substeps"):
        systems.get("cstr", substeps=0)
    with pytest.raises(ValueError, match="dt"):
        systems.get("unicycle_rb", dt=-1.0)
