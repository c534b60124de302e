"""Scale invariance of the guaranteed filters (docs/which_filter.md, "Scale invariance").

For a diagonal change of state coordinates ``x' = D x`` (``System.rescaled``: ``f' = D f(D^-1
x')``, ``h' = h(D^-1 x')``, the sets mapped by D), filtering the same measurements with the
scaled system must give D times the sets, up to rounding: the filters' rules (Stirling step,
DC split, Minkowski weights, reduction scores, tie rules) may not depend on the units of the
states. D is drawn by hypothesis with factors from 1e-3 to 1e3 per state.
"""

from __future__ import annotations

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from diffsmf import filters, systems
from diffsmf.systems import scale_set

GUARANTEED = ["hsnsmf", "mszm", "cdsmf", "esmf", "czsmf"]

_FACTORS = st.lists(st.floats(-3.0, 3.0), min_size=2, max_size=2).map(
    lambda e: torch.tensor([10.0**v for v in e], dtype=torch.float64)
)

_CACHE: dict = {}


def _base(system_name: str, filter_name: str, steps: int):
    """(system, y, hull lower / upper of the unscaled run), computed once per case."""
    key = (system_name, filter_name, steps)
    if key not in _CACHE:
        sys_ = systems.get(system_name)
        traj = sys_.simulate(steps, batch=2, seed=5, noise="vertex")
        with torch.no_grad():
            res = filters.by_name(filter_name)(sys_)(traj.y)
        _CACHE[key] = (sys_, traj, res)
    return _CACHE[key]


def _assert_scaled(res, res_d, d: torch.Tensor, rtol: float = 1e-5) -> None:
    """``res_d``'s hull is ``d`` times ``res``'s: per state, to ``rtol`` of the set's width
    (plus the float64 resolution of the bounds' magnitudes). "Up to rounding": the outward
    margins for float64 rounding have an absolute floor (``ROUND_REL = 1e-12`` in the units of
    the run), so runs in units 1e-3 apart differ by about 1e-9 absolute, 1e-6 of these widths;
    a rule that depends on the units changes the sets by far more (percent, or divergence)."""
    assert bool((res_d.bounded == res.bounded).all())
    lo, hi = res.lower, res.upper
    ok = res.bounded.unsqueeze(-1)
    tol = rtol * (hi - lo) + 1e-12 * (lo.abs() + hi.abs())
    for got, want in ((res_d.lower / d, lo), (res_d.upper / d, hi)):
        err = torch.where(ok, (got - want).abs() - tol, torch.zeros_like(lo))
        assert float(err.max()) <= 0, f"largest excess {float(err.max()):.3e}"


@pytest.mark.parametrize("filter_name", GUARANTEED)
@settings(max_examples=4, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(d=_FACTORS)
def test_scaled_system_gives_scaled_sets(filter_name, d):
    sys_, traj, res = _base("spring_damper", filter_name, 12)
    with torch.no_grad():
        res_d = filters.by_name(filter_name)(sys_.rescaled(d))(traj.y)
    _assert_scaled(res, res_d, d)


@settings(max_examples=3, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(d=_FACTORS)
def test_combined_filter_set_part_is_scale_invariant(d):
    sys_, traj, _ = _base("spring_damper", "hsnsmf", 12)
    with torch.no_grad():
        res = filters.CombinedFilter(sys_)(traj.y)
        res_d = filters.CombinedFilter(sys_.rescaled(d))(traj.y)
    _assert_scaled(res, res_d, d)
    want = scale_set(res.sets, d).shape
    assert torch.allclose(res_d.sets.shape, want, rtol=1e-5, atol=1e-12 * float(want.abs().max()))


@pytest.mark.parametrize("filter_name", ["hsnsmf", "cdsmf", "esmf"])
def test_cstr_in_other_units(filter_name):
    """The badly scaled CSTR with Ca in mmol/L and the temperatures in hK: D times the sets."""
    sys_, traj, res = _base("cstr", filter_name, 15)
    d = torch.tensor([1e3, 1e-2, 1.0], dtype=torch.float64)
    with torch.no_grad():
        res_d = filters.by_name(filter_name)(sys_.rescaled(d))(traj.y)
    _assert_scaled(res, res_d, d)


def test_rescaled_system_maps_sets_and_model():
    sys_ = systems.get("cstr")
    d = torch.tensor([10.0, 0.5, 2.0], dtype=torch.float64)
    s2 = sys_.rescaled(d)
    x = sys_.x0_set.sample(4, torch.Generator().manual_seed(0))
    assert torch.allclose(s2.f(x * d, None, None), sys_.f(x, None, None) * d, rtol=1e-14)
    assert torch.allclose(s2.h(x * d), sys_.h(x), rtol=1e-14)
    assert torch.allclose(s2.x0_set.lower, sys_.x0_set.lower * d)
    assert torch.allclose(s2.process_noise.upper, sys_.process_noise.upper * d)
    with pytest.raises(ValueError, match="scale"):
        sys_.rescaled([1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match="scale"):
        sys_.rescaled([1.0, 1.0])
