"""Windowed tuning (diffsmf/tuning/windows.py): truncated back-propagation with carried states."""

from __future__ import annotations

import pytest
import torch

import diffsmf as ds
from diffsmf.tuning import LossWeights, tune
from diffsmf.tuning.loop import Data
from diffsmf.tuning.losses import filter_with_predictions, total_loss
from diffsmf.tuning.windows import WindowCache, cat_states, take_state, windowed_loss


@pytest.fixture(scope="module")
def sd():
    s = ds.systems.get("spring_damper")
    tr = s.simulate(12, batch=6, seed=1, noise="vertex")
    return s, Data(tr.y, tr.x)


def _full(filt, data):
    return total_loss(
        filter_with_predictions(filt, data.y), None, LossWeights(),
        use_containment=False, use_consistency=True,
    )


@pytest.mark.parametrize("length", [4, 5, 12])
def test_first_windowed_loss_equals_the_full_pass(sd, length):
    """With fresh start states the windows replay the full recursion: same loss value."""
    s, data = sd
    f = ds.filters.HSNSMF(s, process_noise=2 * s.process_noise.interval_hull().radius)
    cache = WindowCache(f, data, length)
    idx = torch.arange(len(data))
    lw, tw = windowed_loss(
        f, data, idx, cache, LossWeights(), use_containment=False, use_consistency=True
    )
    lf, tf = _full(f, data)
    assert torch.allclose(lw, lf, rtol=1e-10, atol=1e-12)
    for k in tf:
        assert torch.allclose(torch.as_tensor(tw[k]), tf[k], rtol=1e-10, atol=1e-12)


def test_cache_holds_the_full_pass_states_at_window_starts(sd):
    s, data = sd
    f = ds.filters.HSNSMF(s)
    cache = WindowCache(f, data, 5)
    assert cache.bounds == [(0, 5), (5, 10), (10, 12)]
    ref = filter_with_predictions(f, data.y).result.sets
    for w, (start, _) in enumerate(cache.bounds[1:], 1):
        got = cache.starts[w].set
        assert torch.allclose(got.center, ref[:, start].center, atol=1e-13)
        assert torch.allclose(got.T, ref[:, start].T, atol=1e-13)
    # a training pass stores the end of window w as the start of w + 1 (detached)
    idx = torch.tensor([4, 1])
    windowed_loss(f, data.take(idx), idx, cache, LossWeights(), use_containment=False,
                  use_consistency=True)
    assert not cache.starts[1].set.center.requires_grad
    assert torch.allclose(cache.starts[2].set.center[idx], ref[idx, 10].center, atol=1e-13)


def test_window_covering_the_horizon_is_the_full_gradient(sd):
    s, data = sd
    out = []
    for window in (None, 12):
        f = ds.filters.HSNSMF(s, process_noise=3 * s.process_noise.interval_hull().radius)
        rep, f = tune(f, Data(data.y), params=("process_noise",), loss="consistency",
                      epochs=2, batch_size=6, lr=0.1, progress=False, window=window)
        out.append(f.process_noise.detach())
        assert rep.window == window
    assert torch.allclose(out[0], out[1], rtol=1e-10)


def test_windowed_tuning_shrinks_oversized_bounds_and_stays_guaranteed(sd):
    s, data = sd
    b = s.process_noise.interval_hull().radius
    f = ds.filters.HSNSMF(s, process_noise=4 * b)
    before = f(data.y).volume[:, 1:].mean()
    rep, f = tune(f, Data(data.y), params=("process_noise",), loss="consistency",
                  epochs=6, batch_size=6, lr=0.2, progress=False, window=4)
    with torch.no_grad():
        res = f(data.y)
    assert res.volume[:, 1:].mean() < before
    test = s.simulate(12, batch=200, seed=9, noise="vertex")
    ok = torch.isfinite(test.x).all(-1).all(-1)
    if (f.process_noise >= b - 1e-15).all():  # bounds still cover the truth: guaranteed
        with torch.no_grad():
            r = f(test.y[ok])
        assert r.sets.contains(test.x[ok]).all()


def test_state_helpers_and_validation(sd):
    s, data = sd
    f = ds.filters.HSNSMF(s)
    a, b = f.initial_state(2), f.initial_state(3)
    c = cat_states([a, b])
    assert c.set.batch_shape == (5,) and c.consistent.shape == (5,)
    assert torch.equal(take_state(c, slice(2, 5)).set.center, b.set.center)
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="window"):
            WindowCache(f, data, bad)
    with pytest.raises(ValueError, match="state"):
        filter_with_predictions(f, data.y, state=f.initial_state(2))
