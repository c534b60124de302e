"""Divergence is flagged, never a crash or a NaN: ``FilterResult.bounded``.

A system designed for the purpose: ``x1`` is unmeasured and integrates ``x2``, and the model
has a pole at ``x1 = 2``. Trajectory A drifts towards the pole (its true state stays below
1.7, but the uncertainty of the unmeasured ``x1`` grows until the set reaches the pole, where
no bounded guaranteed set exists); trajectory B drifts away and stays bounded. Plus the
built-in fermenter with an initial set that contains the pole of its growth rate.
"""

from __future__ import annotations

import pytest
import torch

import diffsmf as ds

F64 = torch.float64
GUARANTEED = ["hsnsmf", "mszm", "cdsmf", "esmf"]


def _pole_system() -> ds.System:
    dt = 0.1

    def f(x, u=None, theta=None):
        x1, x2 = x[..., 0], x[..., 1]
        return torch.stack([x1 + dt * x2, 0.9 * x2 + dt * 0.01 / (2.0 - x1)], -1)

    def h(x):
        return x[..., 1:2]

    x0 = ds.Interval(torch.tensor([-0.1, -1.6], dtype=F64), torch.tensor([0.1, 1.6], dtype=F64))
    W = ds.Interval(torch.tensor([-0.05, -1e-3], dtype=F64), torch.tensor([0.05, 1e-3],
                                                                           dtype=F64))
    V = ds.Interval(torch.tensor([-1e-2], dtype=F64), torch.tensor([1e-2], dtype=F64))
    return ds.System(f, h, x0, W, V, name="pole")


def _two_trajectories(s: ds.System, T: int) -> tuple[torch.Tensor, torch.Tensor]:
    """True states ``[2, T+1, 2]`` from x0 = (0, +1.5) and (0, -1.5), measurements ``[2, T, 1]``
    (vertex-free: noise 0, inside every bound)."""
    x = torch.tensor([[0.0, 1.5], [0.0, -1.5]], dtype=F64)
    xs, ys = [x], []
    for _ in range(T):
        x = s.f(x, None, None)
        xs.append(x)
        ys.append(s.h(x))
    return torch.stack(xs, 1), torch.stack(ys, 1)


@pytest.mark.parametrize("name", GUARANTEED)
def test_unbounded_row_flagged_other_row_unaffected(name):
    s = _pole_system()
    x, y = _two_trajectories(s, 30)
    assert x[0, :, 0].max() < 1.7  # the true state never reaches the pole
    filt = ds.filters.by_name(name)(s)
    res = filt(y)
    assert not torch.isnan(res.lower).any() and not torch.isnan(res.upper).any()
    assert not res.bounded[0, -1]  # A: the set reached the pole -> flagged
    k = int((~res.bounded[0]).nonzero()[0])  # first flagged step; flags are sticky
    assert (~res.bounded[0, k:]).all() and res.bounded[0, :k].all()
    assert torch.isinf(res.lower[0, k:]).all() and torch.isinf(res.upper[0, k:]).all()
    assert torch.isinf(res.volume[0, k:]).all()
    # B: unaffected by A -- the same bounds and flags as a run of B alone (an ellipsoidal
    # set of B, looser, may itself reach the pole late in the horizon: then it is flagged too)
    assert res.bounded[1, : k + 1].all()
    alone = ds.filters.by_name(name)(s)(y[1:])
    assert torch.equal(alone.bounded[0], res.bounded[1])
    torch.testing.assert_close(alone.lower[0], res.lower[1], rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(alone.upper[0], res.upper[1], rtol=1e-9, atol=1e-12)
    inside = (res.lower[1] - 1e-12 <= x[1]) & (x[1] <= res.upper[1] + 1e-12)
    assert inside.all()  # guaranteed (trivially where flagged: the bounds are infinite)


@pytest.mark.parametrize("name", ["hsnsmf", "cdsmf"])
def test_gradients_finite_for_bounded_rows(name):
    s = _pole_system()
    _, y = _two_trajectories(s, 25)
    filt = ds.filters.by_name(name)(s)
    res = filt(y)
    assert not res.bounded[0, -1]
    keep = res.bounded[1]  # B's bounded steps (all of them for HSNSMF)
    assert keep[:15].all()
    loss = res.volume[1, 1:][keep[1:]].log().mean()
    loss.backward()
    grads = [p.grad for p in filt.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)


def test_fermenter_large_initial_set_flagged_not_raised():
    """The fermenter's growth rate has a pole at S = -1.27: an initial box reaching it has no
    bounded guaranteed prediction. Before, the run raised mid-way and the batch was lost."""
    s = ds.systems.get("fermenter")
    big = ds.Interval(s.x0_set.center - 3.0, s.x0_set.center + 3.0)
    tr = s.simulate(steps=5, batch=3, seed=0)
    for name in ("hsnsmf", "esmf"):
        res = ds.filters.by_name(name)(s, initial_set=big)(tr.y, u=tr.u)
        assert not torch.isnan(res.lower).any()
        assert not res.bounded[:, -1].any()
        assert torch.isinf(res.upper[:, -1]).all()


@pytest.mark.parametrize("bad", [[1e-3, 1e-3], [float("nan")], [-1e-3], "x", [[1e-3]]])
def test_noise_override_errors_name_the_argument(bad):
    s = ds.systems.get("spring_damper")  # m = 1 output
    with pytest.raises(ValueError, match="measurement_noise"):
        ds.filters.HSNSMF(s, measurement_noise=bad)
    with pytest.raises(ValueError, match="process_noise"):
        ds.filters.CDSMF(s, process_noise=[1e-3, 1e-3, 1e-3] if bad != "x" else "x")
    with pytest.raises(ValueError, match="measurement_half_widths"):  # the current name
        ds.filters.MSZM(s, measurement_half_widths=bad)


def _tank_cascade(n: int = 6) -> ds.System:
    """Tanks in a row with square-root outflows, every second level measured (the built-in
    ``tank_cascade``): the ellipsoidal sets of ESMF grow until they leave sqrt's domain
    (levels below 0)."""
    return ds.systems.get("tank_cascade", n=n)

def test_esmf_on_a_tank_cascade_flags_each_trajectory_and_never_raises():
    """Three measured levels make the update's factorisations LAPACK's (m >= 3); a diverged
    element used to fail the whole batch with a linalg.cholesky error. Now each trajectory is
    flagged on its own, and the batch gives each row what it gives alone."""
    s = _tank_cascade(6)
    tr = s.simulate(12, batch=2, seed=0, noise="vertex")
    filt = ds.filters.ESMF(s)
    with torch.no_grad():
        res = filt(tr.y)
        alone = [filt(tr.y[b : b + 1]) for b in range(2)]
    assert not bool(res.bounded[:, -1].all())  # the guarantee was lost, and said so
    for b in range(2):
        assert torch.equal(res.bounded[b], alone[b].bounded[0])
        # the same up to rounding (batched and single products round differently, and the
        # rounding may move the discrete rho choice of a later step)
        for got, want in ((res.lower[b], alone[b].lower[0]), (res.upper[b], alone[b].upper[0])):
            assert torch.equal(torch.isinf(got), torch.isinf(want))
            fin = torch.isfinite(want)
            assert torch.allclose(got[fin], want[fin], rtol=1e-6, atol=0)
        lost = ~res.bounded[b]
        assert bool(torch.isinf(res.lower[b][lost]).all())  # -inf, never a finite placeholder
    assert bool(res.sets.contains(tr.x).all())
    assert any("domain" in line for line in ds.filters.describe_events(res.events))


def test_linalg_cholesky_gives_nan_for_a_non_pd_element_only():
    from diffsmf import linalg

    A = torch.randn(3, 4, 4, dtype=F64, generator=torch.Generator().manual_seed(0))
    S = A @ A.mT + 0.1 * torch.eye(4, dtype=F64)
    S[1, 0, 0] = -1.0  # not positive definite
    S[2, 3, 3] = float("nan")
    L = linalg.cholesky(S)
    assert torch.equal(L[0], torch.linalg.cholesky(S[0]))
    assert bool(torch.isnan(L[1]).all()) and bool(torch.isnan(L[2]).all())


def test_mszm_with_tightened_strips_is_tighter_on_a_tank_cascade():
    """Every second level measured: the published strip family keeps the measured levels no
    narrower than the strips, the cut strips follow the overlap (0 outside either way)."""
    s = _tank_cascade(6)
    tr = s.simulate(10, batch=2, seed=0, noise="vertex")
    with torch.no_grad():
        plain = ds.filters.MSZM(s)(tr.y)
        cut = ds.filters.MSZM(s, tighten_strips=True)(tr.y)
    for res in (plain, cut):
        assert bool(res.bounded.all()) and bool(res.sets.contains(tr.x).all())
    width = lambda r: (r.upper[:, -1] - r.lower[:, -1]).sum(-1)  # noqa: E731
    assert bool((width(cut) < 0.8 * width(plain)).all()), (width(cut), width(plain))
    with pytest.raises(ValueError, match="tighten_strips: expected True or False"):
        ds.filters.MSZM(s, tighten_strips="yes")
