"""Filters beyond the papers' system sizes: the vertex-free remainders and the oscillator chain.

References: exact evaluation of the remainder r(x) = f(x) - f(c) - J (x - c) at sampled and
extreme points of the set (every bound must contain it), and containment of true states of
worst-case (vertex-noise) trajectories at n = 16 and 32.
"""

from __future__ import annotations

import pytest
import torch

import diffsmf as ds
from diffsmf.linearize import (
    REMAINDERS,
    mean_value_remainder,
    resolve_remainder,
    stirling_jacobian,
)


def _rem_at(fn, x, c, J):
    return fn(x) - fn(c) - ((x - c).unsqueeze(-2) * J).sum(-1)


@pytest.mark.parametrize("name", sorted(REMAINDERS))
def test_remainders_contain_sampled_remainder(name):
    """Every named bound contains r(x) at 2,000 samples and the box corners (n = 6)."""
    sys_ = ds.systems.get("oscillator_chain", n=6, cubic=8.0)
    fn = lambda x: sys_.f(x, None, None)  # noqa: E731
    g = torch.Generator().manual_seed(0)
    box = ds.Interval(sys_.x0_set.lower - 0.2, sys_.x0_set.upper + 0.3)
    c = box.center + 0.05
    J = stirling_jacobian(fn, c, 0.1)
    R = REMAINDERS[name](fn, box, c, J)
    x = torch.cat([box.sample(2000, generator=g), box.vertices()])
    r = _rem_at(fn, x, c, J)
    assert (r >= R.lower - 1e-15).all() and (r <= R.upper + 1e-15).all()
    # and the bound is not vacuous: within a small factor of the sampled range (the
    # first-order mean-value form is the loosest)
    width = R.upper - R.lower
    span = r.amax(0) - r.amin(0)
    factor = 8.0 if name == "mean-value" else 4.0
    assert (width <= factor * span + 1e-12).all()


def test_mean_value_remainder_exact_on_affine_and_graddable():
    A = torch.tensor([[1.0, 2.0], [0.5, -1.0]], dtype=torch.float64)
    fn = lambda x: x @ A.T  # noqa: E731
    box = ds.Interval(torch.tensor([-1.0, 0.0], dtype=torch.float64),
                      torch.tensor([1.0, 2.0], dtype=torch.float64))
    R = mean_value_remainder(fn, box, box.center, A)
    assert R.radius.abs().max() < 1e-12  # exact Jacobian: zero remainder (plus rounding pad)

    def f2(x):
        return torch.stack([x[..., 0] * x[..., 1], torch.sin(x[..., 0])], -1)

    def g(c):
        b = ds.Interval(c - 0.3, c + 0.2)
        R = mean_value_remainder(f2, b, c, None)
        return torch.cat([R.lower, R.upper], -1)

    c0 = torch.tensor([0.3, -0.2], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(g, (c0,))


def test_resolve_remainder_auto_and_errors():
    assert resolve_remainder("auto", 2)[0] == "dc-vertices"
    assert resolve_remainder("auto", 8)[0] == "dc-vertices"
    assert resolve_remainder("auto", 9)[0] == "lagrange"
    assert resolve_remainder("auto", 32)[0] == "mean-value"
    with pytest.raises(ValueError, match="remainder"):
        resolve_remainder("vertices", 2)
    with pytest.raises(ValueError, match="remainder"):
        ds.filters.HSNSMF(ds.systems.get("spring_damper"), remainder="nope")


def test_oscillator_chain_shapes_and_errors():
    for n in (2, 4, 16, 32):
        s = ds.systems.get("oscillator_chain", n=n)
        tr = s.simulate(steps=3, batch=2, seed=0)
        assert tr.x.shape == (2, 4, n) and tr.y.shape == (2, 3, n // 2)
        assert torch.isfinite(tr.x).all()
    for bad in (3, 0, -2, 2.0):
        with pytest.raises(ValueError, match="n:"):
            ds.systems.get("oscillator_chain", n=bad)
    with pytest.raises(ValueError, match="damping"):
        ds.systems.get("oscillator_chain", damping=0.0)


@pytest.mark.parametrize(
    "n,name",
    [(16, "hsnsmf"), (16, "mszm"), (16, "cdsmf"), (16, "esmf"), (32, "hsnsmf"), (32, "cdsmf"),
     (32, "esmf")],
)
def test_high_dim_containment_vertex_noise(n, name):
    """Every guaranteed filter runs at n = 16 and 32 (auto remainder: vertex-free) and its
    sets contain the true states of worst-case trajectories."""
    s = ds.systems.get("oscillator_chain", n=n)
    tr = s.simulate(steps=4, batch=6, seed=1, noise="vertex")
    filt = ds.filters.by_name(name)(s)
    if name != "esmf":
        assert filt.remainder == ("lagrange" if n <= 16 else "mean-value")
    with torch.no_grad():
        res = filt(tr.y)
    assert res.sets.contains(tr.x).all()
    assert torch.isfinite(res.volume).all()


def test_diverging_filter_is_flagged_not_raised():
    """CDSMF (box-covering ellipsoids, a sqrt(n) inflation per step) diverges on the chain at
    n = 32 (unbounded from step 26 with the scaled-trace weight; the radius passes 1e40 at
    step 23, where saturated Stirling slopes of h once gave a zero strip normal). The step
    must flag the element unbounded (bounds +-inf), not raise from a constructor's NaN/inf
    check, and the audit must count those pairs as unbounded, not as violations."""
    from diffsmf.audit import containment

    s = ds.systems.get("oscillator_chain", n=32)
    tr = s.simulate(steps=28, batch=1, seed=2024, noise="vertex")
    filt = ds.filters.CDSMF(s)
    with torch.no_grad():
        res = filt(tr.y)
    assert res.bounded[:, :5].all() and not res.bounded[:, -1].any()
    assert torch.isinf(res.upper[:, -1]).all() and torch.isinf(res.volume[:, -1]).all()
    rep = containment(filt, s, trials=2, steps=28, noise="vertex", seed=2024)
    assert rep.violations == 0 and rep.unbounded > 0


def test_sanitize_remainder_flags_huge_boxes():
    """A remainder box beyond MAX_SET_RADIUS (finite, but its square overflows) is not ok;
    the other elements keep their bounds bit for bit."""
    from diffsmf.filters.base import MAX_SET_RADIUS
    from diffsmf.filters.remainder_boxes import sanitize_remainder
    from diffsmf.sets import Interval

    lo = torch.tensor([[-1.0, -2.0], [-3.0 * MAX_SET_RADIUS, 0.0], [float("nan"), 0.0]])
    R, ok = sanitize_remainder(Interval._make(lo, lo.nan_to_num(0.0).abs() + 1.0))
    assert ok.tolist() == [True, False, False]
    assert torch.equal(R.lower[0], lo[0]) and (R.lower[1:] == 0).all()
