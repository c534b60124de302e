"""MSZM's strip weights (CORA's FRad-A/B/C, VolMin-A/B) as a user meets them: differentiable in
the noise bounds, the same sets batched as alone, options checked by name. Their containment
is in tests/test_filters_containment.py, their reproduction of CORA in
tests/test_cora_observers.py."""

from __future__ import annotations

import pytest
import torch
from conftest import gradcheck_noise_bounds

import diffsmf as ds

WEIGHTS = ["volume", "bravo", "wang", "combastel"]


@pytest.mark.parametrize("weight", WEIGHTS)
def test_gradcheck_noise_bounds(weight):
    s = ds.systems.get("spring_damper")
    tr = s.simulate(steps=3, batch=2, seed=6, noise="vertex")
    assert gradcheck_noise_bounds(ds.filters.MSZM(s, strip_method=weight), tr)


@pytest.mark.parametrize("weight", WEIGHTS)
def test_batch_elements_behave_as_if_run_alone(weight):
    s = ds.systems.get("bilinear")
    tr = s.simulate(steps=6, batch=3, seed=5, noise="vertex")
    filt = ds.filters.MSZM(s, strip_method=weight)
    with torch.no_grad():
        res = filt(tr.y, u=tr.u)
        for b in range(3):
            one = filt(tr.y[b:b + 1], u=None if tr.u is None else tr.u[b:b + 1])
            torch.testing.assert_close(one.lower[0], res.lower[b], atol=1e-12, rtol=1e-10)
            torch.testing.assert_close(one.upper[0], res.upper[b], atol=1e-12, rtol=1e-10)


def test_gains_use_every_measurement_at_once_and_tighten():
    """FRad-B and FRad-C take all strips in one gain: on a system with two outputs the set
    after the update is inside the predicted one's hull and smaller in volume."""
    s = ds.systems.get("mismatch_quadratic")
    assert s.m >= 2
    tr = s.simulate(steps=2, batch=4, seed=1, noise="vertex")
    for weight in ("wang", "combastel"):
        filt = ds.filters.MSZM(s, strip_method=weight)
        with torch.no_grad():
            pred = filt.predict(filt.initial_state(4), None if tr.u is None else tr.u[:, 0])
            new = filt.update(pred, tr.y[:, 0])
        assert (new.set.volume() < pred.set.volume()).all()
        assert pred.set.interval_hull().contains(new.set.center).all()


def test_bad_strip_weights_name_the_argument():
    s = ds.systems.get("spring_damper")
    with pytest.raises(ValueError, match=r"^strip_method: unknown strip weight 'FRad-B'.*wang"):
        ds.filters.MSZM(s, strip_method="FRad-B")
    with pytest.raises(ValueError, match="^tighten_strips: .*all strips at once"):
        ds.filters.MSZM(s, strip_method="wang", tighten_strips=True)
    with pytest.raises(ValueError, match=r"^method: unknown strip method 'wang'"):
        ds.Zonotope(torch.zeros(2), torch.eye(2)).intersect_strip(
            ds.Strip(torch.ones(2), 0.0, 1.0), method="wang")
