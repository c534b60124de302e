"""Never a false bound, never a dead batch.

Where a set diverges, its element's guaranteed set is all of R^n everywhere (``sets``,
``lower`` / ``upper``, ``volume``, ``consistent``); numerical events (a domain exit, an atan2
branch cut, a degenerate strip, an overflow) are flagged per trajectory and step
(``FilterResult.events``), and the other trajectories finish with the sets of a run without
the one that met the event.
"""

from __future__ import annotations

import math

import pytest
import torch

import diffsmf as ds
from diffsmf.filters import FilterEvent, describe_events, event_text
from diffsmf.utils import numerical_events

F64 = torch.float64
ALL = ["hsnsmf", "mszm", "cdsmf", "esmf", "czsmf", "combined", "ekf"]
GUARANTEED = ["hsnsmf", "mszm", "cdsmf", "esmf", "czsmf"]


def _box(lo, hi) -> ds.Interval:
    return ds.Interval(torch.tensor(lo, dtype=F64), torch.tensor(hi, dtype=F64))


def _cubic_system(a: float) -> ds.System:
    """``x1+ = 0.5 x1 - 0.1 x1^3`` (stable near 0, unmeasured), ``x2+ = 0.5 x2``, ``y = x2``:
    from an initial box |x1| <= 4 every linearising filter's set diverges (the exact image of
    [-4, 4] is [-4.4, 4.4] already), while the true states from |x1| <= 1 go to 0."""

    def f(x, u=None, theta=None):
        x1, x2 = x[..., 0], x[..., 1]
        return torch.stack([0.5 * x1 - 0.1 * x1**3, 0.5 * x2], -1)

    def h(x):
        return x[..., 1:2]

    return ds.System(f, h, _box([-a, -0.2], [a, 0.2]), _box([-1e-3] * 2, [1e-3] * 2),
                     _box([-0.5], [0.5]), name="cubic")


@pytest.mark.parametrize("name", ALL)
def test_unbounded_means_unbounded_for_every_filter(name):
    s = _cubic_system(4.0)
    tr = _cubic_system(1.0).simulate(steps=12, batch=3, seed=0)
    with torch.no_grad():
        res = ds.filters.by_name(name)(s)(tr.y)
    b = res.bounded
    if name in GUARANTEED + ["combined"]:
        assert not b[:, -1].any()  # every trajectory's set diverged
        assert ((res.events[:, -1] & (FilterEvent.DIVERGED | FilterEvent.NON_FINITE)) != 0).all()
    # no finite bound misses the truth, and where the set is unbounded it is R^n everywhere
    finite = torch.isfinite(res.lower) & torch.isfinite(res.upper)
    if name != "ekf":  # the EKF's 3-sigma bounds carry no guarantee
        assert not (((tr.x < res.lower) | (tr.x > res.upper)) & finite).any()
        assert bool(res.sets.contains(tr.x).all())
    u = ~b
    assert torch.isinf(res.lower[u]).all() and (res.lower[u] < 0).all()
    assert torch.isinf(res.upper[u]).all() and (res.upper[u] > 0).all()
    assert torch.isinf(res.volume[u]).all() and res.consistent[u].all()
    hull = res.sets.interval_hull()
    assert torch.equal(hull.lower[u], res.lower[u]) and torch.equal(hull.upper[u], res.upper[u])
    assert torch.isinf(res.sets.volume()[u]).all()
    if u.any():  # indexing keeps the meaning; a far point is inside an unbounded element
        i, k = (int(v) for v in u.nonzero()[0])
        far = torch.full((s.n,), 1e30, dtype=F64)
        assert bool(res.sets[i, k].contains(far))
        assert bool(res.sets[i].contains(far.expand(b.shape[1], -1))[k])
        assert isinstance(res.sets, type(ds.filters.by_name(name)(s).initial_state().set))


def test_consistent_is_never_false_against_an_unbounded_prediction():
    s = _cubic_system(4.0)
    tr = _cubic_system(1.0).simulate(steps=12, batch=2, seed=1)
    y = tr.y + 100.0  # data no bounded set could explain: inconsistent until the divergence
    res = ds.filters.HSNSMF(s)(y)
    assert not res.consistent[:, 1].any()
    assert res.consistent[~res.bounded].all() and (~res.bounded).any()


def test_online_state_guaranteed_set():
    s = _cubic_system(4.0)
    tr = _cubic_system(1.0).simulate(steps=12, batch=2, seed=0)
    filt = ds.filters.ESMF(s)
    st = filt.initial_state(batch=2)
    for k in range(12):
        st = filt.step(st, None, tr.y[:, k])
    assert not st.bounded.any()
    hull = st.guaranteed_set.interval_hull()
    assert torch.isinf(hull.lower).all() and torch.isinf(hull.upper).all()
    assert bool(st.guaranteed_set.contains(tr.x[:, -1]).all())
    assert (st.events & FilterEvent.DIVERGED).all()


# ------------------------------------------------------------------ one trajectory, one event
def _sqrt_system() -> ds.System:
    """x1 integrates the unmeasured x2; ``f`` has ``sqrt(2 - x1)``. Trajectory 0 drifts
    towards x1 = 2 (its true state stays below 1.5, but its set leaves the domain of the
    square root), trajectory 1 away from it."""
    dt = 0.1

    def f(x, u=None, theta=None):
        x1, x2 = x[..., 0], x[..., 1]
        return torch.stack([x1 + dt * x2, 0.9 * x2 + dt * 0.01 * torch.sqrt(2.0 - x1)], -1)

    def h(x):
        return x[..., 1:2]

    return ds.System(f, h, _box([-0.1, -1.6], [0.1, 1.6]), _box([-0.05, -1e-3], [0.05, 1e-3]),
                     _box([-1e-2], [1e-2]), name="sqrt")


def _run_noise_free(s: ds.System, x: torch.Tensor, T: int) -> tuple[torch.Tensor, torch.Tensor]:
    xs, ys = [x], []
    for _ in range(T):
        x = s.f(x, None, None)
        xs.append(x)
        ys.append(s.h(x))
    return torch.stack(xs, 1), torch.stack(ys, 1)


def _same_as_alone(name: str, s: ds.System, res, y: torch.Tensor) -> None:
    """Trajectory 1 of ``res`` equals a run of trajectory 1 alone (bit for bit; CZSMF's
    batched LPs to rounding)."""
    alone = ds.filters.by_name(name)(s)(y[1:])
    assert torch.equal(alone.bounded[0], res.bounded[1])
    assert torch.equal(alone.events[0], res.events[1])
    b = res.bounded[1]
    if name == "czsmf":
        torch.testing.assert_close(alone.lower[0], res.lower[1], rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(alone.upper[0], res.upper[1], rtol=1e-9, atol=1e-12)
    else:
        assert torch.equal(alone.lower[0][b], res.lower[1][b])
        assert torch.equal(alone.upper[0][b], res.upper[1][b])


@pytest.mark.parametrize("name", ALL)
def test_domain_exit_flags_one_trajectory_others_unchanged(name):
    s = _sqrt_system()
    x, y = _run_noise_free(s, torch.tensor([[0.0, 1.5], [0.0, -1.5]], dtype=F64), 30)
    assert x[0, :, 0].max() < 1.5
    res = ds.filters.by_name(name)(s)(y)  # the run completes: nothing raised
    assert not torch.isnan(res.lower).any() and not torch.isnan(res.upper).any()
    if name in ("hsnsmf", "mszm", "czsmf", "cdsmf"):
        assert (res.events[0, -1] & FilterEvent.DOMAIN) != 0  # the square root's domain
        assert any(line.startswith("trajectory 0, step ") and "domain" in line
                   for line in describe_events(res.events))
        assert not res.bounded[0, -1]
    if name in ("hsnsmf", "mszm", "czsmf"):
        assert res.events[1, -1] == 0 and res.bounded[1].all()
    finite = torch.isfinite(res.lower)
    if name != "ekf":
        assert not (((x < res.lower - 1e-12) | (x > res.upper + 1e-12)) & finite).any()
    _same_as_alone(name, s, res, y)


def _bearing_system() -> ds.System:
    """``(px, py, vy)``: py moves by the unmeasured vy; range and bearing to the origin.
    Trajectory 0 (vy = +0.1) crosses the negative x-axis, where atan2 has its branch cut;
    trajectory 1 (vy = -0.1) moves away from it."""

    def f(x, u=None, theta=None):
        return torch.stack([x[..., 0], x[..., 1] + x[..., 2], x[..., 2]], -1)

    def h(x):
        px, py = x[..., 0], x[..., 1]
        return torch.stack([torch.sqrt(px * px + py * py), torch.atan2(py, px)], -1)

    return ds.System(f, h, _box([-2.2, -1.2, -0.12], [-1.8, -0.8, 0.12]),
                     _box([-1e-4] * 3, [1e-4] * 3), _box([-1e-2] * 2, [1e-2] * 2),
                     name="bearing")


@pytest.mark.parametrize("name", ALL)
def test_atan2_branch_cut_is_an_event_not_an_exception(name):
    s = _bearing_system()
    x0 = torch.tensor([[-2.0, -1.0, 0.1], [-2.0, -1.0, -0.1]], dtype=F64)
    x, y = _run_noise_free(s, x0, 20)
    assert (x[0, :, 1] > 0).any() and (x[1, :, 1] < 0).all()
    res = ds.filters.by_name(name)(s)(y)
    if name == "hsnsmf":  # at the cut the bearing's enclosure is [-pi, pi]: a weak strip
        assert res.bounded.all()
    if name not in ("ekf", "combined"):  # the guaranteed filters (combined: nonlinear h)
        finite = torch.isfinite(res.lower)
        assert not (((x < res.lower - 1e-12) | (x > res.upper + 1e-12)) & finite).any()
    _same_as_alone(name, s, res, y)


def test_atan2_branch_cut_is_enclosed_by_the_hull_of_both_sides():
    """Over a box that meets the cut, atan2 jumps by 2 pi: its enclosure is [-pi, pi] and its
    Jacobian enclosure unbounded (the remainders fall back to a zeroth-order bound); no
    exception, inside a filter or not."""
    from diffsmf.interval import enclose

    box = _box([[-1.0, -0.5]], [[-0.5, 0.5]])
    E = enclose(lambda x: torch.atan2(x[..., 1:2], x[..., 0:1]), box, 1)
    assert float(E.val.lower) <= -math.pi + 1e-12 and float(E.val.upper) >= math.pi - 1e-12
    assert torch.isinf(E.grad.upper).all()


def test_interval_domain_nan_per_element_inside_filters_error_outside():
    x = _box([[-1.0], [4.0]], [[1.0], [9.0]])
    with pytest.raises(ValueError, match="sqrt needs lower >= 0"):
        x.sqrt()
    with numerical_events():
        r = x.sqrt()
        lg = x.log()
    assert torch.isnan(r.lower[0]).all() and torch.isnan(lg.lower[0]).all()
    assert float(r.lower[1]) <= 2.0 and float(r.upper[1]) >= 3.0  # the other row: unchanged
    assert float(r.upper[1]) - 3.0 < 1e-12


def test_zero_strip_normal_is_skipped_and_flagged():
    """``h = x1^2``: at the centre x1 = 0 the Stirling slope is exactly 0, a strip with a zero
    normal (it raised "normal: must be non-zero" before). The update is skipped for that
    component, flagged DEGENERATE_STRIP, and the set stays guaranteed and bounded."""

    def f(x, u=None, theta=None):
        return 0.9 * x

    def h(x):
        return torch.stack([x[..., 0] ** 2, x[..., 1]], -1)

    s = ds.System(f, h, _box([-1.0, -1.0], [1.0, 1.0]), _box([-1e-3] * 2, [1e-3] * 2),
                  _box([-1e-2] * 2, [1e-2] * 2), name="square")
    tr = s.simulate(steps=5, batch=2, seed=0)
    for name in ("hsnsmf", "cdsmf", "mszm"):
        res = ds.filters.by_name(name)(s)(tr.y)
        assert res.bounded.all()
        assert ((res.events[:, 1] & FilterEvent.DEGENERATE_STRIP) != 0).all()
        assert bool(res.sets.contains(tr.x).all())


def test_event_text():
    assert event_text(0) == "none"
    both = event_text(FilterEvent.DIVERGED | FilterEvent.DEGENERATE_STRIP)
    assert "unbounded" in both and "degenerate" in both
    ev = torch.zeros(2, 4, dtype=torch.int64)
    ev[1, 2:] = int(FilterEvent.DOMAIN)
    lines = describe_events(ev)
    assert lines == [f"trajectory 1, step 2: domain: {event_text(FilterEvent.DOMAIN)}"]
    assert describe_events(ev[0]) == []


def test_gauge_of_an_unbounded_element_is_zero():
    """Audits and comparison tables (``audit.gauge``) count no violation at an unbounded
    element, whatever its placeholder."""
    from diffsmf.audit import gauge

    s = _cubic_system(4.0)
    tr = _cubic_system(1.0).simulate(steps=12, batch=2, seed=0)
    far = tr.x + torch.tensor([0.0, 100.0], dtype=F64)  # outside every finite set
    res = ds.filters.HSNSMF(s)(tr.y)
    g = gauge(res.sets, far)
    assert (g[~res.bounded] == 0).all() and (g[res.bounded] > 1).all()


def test_eigh_of_a_batch_with_a_non_finite_matrix():
    """LAPACK fails the whole batch for one non-finite matrix; ``linalg.eigh`` / ``eigvalsh``
    give NaN for that matrix only (a filter flags it), the others as before."""
    from diffsmf import linalg

    A = torch.randn(3, 4, 4, dtype=F64, generator=torch.Generator().manual_seed(0))
    S = A @ A.mT
    S[1, 0, 0] = torch.nan
    ev, V = linalg.eigh(S)
    assert torch.isnan(ev[1]).all() and torch.isnan(V[1]).all()
    ref = torch.linalg.eigvalsh(S[[0, 2]])
    torch.testing.assert_close(ev[[0, 2]], ref)
    torch.testing.assert_close(linalg.eigvalsh(S)[[0, 2]], ref)


def test_interval_product_keeps_nan_of_a_domain_exit():
    """A NaN enclosure (a domain exit or branch cut) times anything stays NaN: a product must
    not turn it into 0 (the Lagrange remainder of atan2 over a box meeting its cut came out
    as +-1e-14 and ESMF's bounds missed the truth); 0 * inf is still 0."""
    a = ds.Interval._make(torch.tensor([float("nan"), 0.0], dtype=F64),
                          torch.tensor([float("nan"), 0.0], dtype=F64))
    b = ds.Interval._make(torch.tensor([1.0, -float("inf")], dtype=F64),
                          torch.tensor([2.0, float("inf")], dtype=F64))
    p = a * b
    assert torch.isnan(p.lower[0]) and torch.isnan(p.upper[0])
    assert abs(float(p.lower[1])) < 1e-300 and abs(float(p.upper[1])) < 1e-300


@pytest.mark.parametrize("name", ["esmf", "hsnsmf"])
def test_bearing_through_the_branch_cut_vertex_noise_contained(name):
    s = _bearing_system()
    tr = s.simulate(steps=12, batch=200, seed=1, noise="vertex")
    with torch.no_grad():
        res = ds.filters.by_name(name)(s)(tr.y)
    assert bool(res.sets.contains(tr.x).all())
    finite = torch.isfinite(res.lower)
    assert not (((tr.x < res.lower - 1e-12) | (tr.x > res.upper + 1e-12)) & finite).any()
