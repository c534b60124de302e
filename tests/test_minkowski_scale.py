"""The learnable Minkowski-weight scale of CDSMF and ESMF (``minkowski_scale``).

Each Minkowski sum of the prediction uses ``p = minkowski_scale * p_rule`` in
``S(p) = (1 + 1/p) S1 + (1 + p) S2``; any ``p > 0`` is an outer bound, so any scale keeps the
guarantee. Checked here: scale 1 is bit-identical to the rule (default filter and the old
``minkowski_sum(method=...)`` code path); containment of the true state on vertex-noise
trajectories for scales 0.3 and 3; finite gradients and gradcheck; bad inputs; use in ``tune``.
"""

from __future__ import annotations

import pytest
import torch
from test_remainder_margin import _traj, gradcheck_raw

import diffsmf as ds
from diffsmf import filters, systems
from diffsmf.audit import containment
from diffsmf.filters import base as filters_base
from diffsmf.filters import cdsmf as cdsmf_mod
from diffsmf.filters import esmf as esmf_mod

NAMES = ["cdsmf", "esmf"]




def _rule_sum(E1, E2, method, scale):
    """The code path before ``minkowski_scale``: the rule's weight chosen inside the sum."""
    return E1.minkowski_sum(E2, method=method)


@pytest.mark.parametrize("system_name", ["spring_damper", "mismatch_quadratic"])
@pytest.mark.parametrize("filter_name", NAMES)
def test_scale_one_is_bit_identical(filter_name, system_name, monkeypatch):
    sys_ = systems.get(system_name)
    _, y, u = _traj(sys_, 6, 8, seed=3)
    cls = filters.by_name(filter_name)
    with torch.no_grad():
        default = cls(sys_)(y, u=u)
        explicit = cls(sys_, minkowski_scale=torch.tensor(1.0))(y, u=u)
        for mod in (cdsmf_mod, esmf_mod):
            monkeypatch.setattr(mod, "scaled_minkowski_sum", _rule_sum)
        without = cls(sys_)(y, u=u)
    for other in (explicit, without):
        assert torch.equal(default.sets.center, other.sets.center)
        assert torch.equal(default.sets.shape, other.sets.shape)
        assert torch.equal(default.volume, other.volume)
        assert torch.equal(default.consistent, other.consistent)


def test_scaled_sum_uses_scaled_rule_weight():
    from diffsmf.sets.ellipsoid import Ellipsoid, minkowski_weight

    g = torch.Generator().manual_seed(0)
    A = torch.randn(4, 3, 3, generator=g)
    B = torch.randn(4, 3, 3, generator=g)
    E1 = Ellipsoid(torch.zeros(4, 3), A @ A.mT + 0.1 * torch.eye(3))
    E2 = Ellipsoid(torch.ones(4, 3), B @ B.mT + 0.1 * torch.eye(3))
    for method in ("trace", "volume"):
        s = torch.tensor(2.5)
        got = filters_base.scaled_minkowski_sum(E1, E2, method, s)
        ref = E1.minkowski_sum(E2, p=minkowski_weight(E1.shape, E2.shape, method) * 2.5)
        assert torch.equal(got.shape, ref.shape) and torch.equal(got.center, ref.center)
        one = filters_base.scaled_minkowski_sum(E1, E2, method, torch.tensor(1.0))
        assert torch.equal(one.shape, E1.minkowski_sum(E2, method=method).shape)
        # the rule's weight minimises its criterion: scaling it away never does better
        if method == "trace":
            tr = lambda E: torch.diagonal(E.shape, dim1=-2, dim2=-1).sum(-1)  # noqa: E731
            assert (tr(got) >= tr(one) * (1 - 1e-12)).all()


@pytest.mark.parametrize("scale", [0.3, 3.0])
@pytest.mark.parametrize(
    "system_name,steps", [("spring_damper", 10), ("mismatch_quadratic", 10), ("bilinear", 10)]
)
@pytest.mark.parametrize("filter_name", NAMES)
def test_containment_with_scale(filter_name, system_name, steps, scale):
    sys_ = systems.get(system_name)
    filt = filters.by_name(filter_name)(sys_, minkowski_scale=scale)
    trials = 200
    rep = containment(filt, sys_, trials=trials, steps=steps, noise="vertex", seed=23)
    assert rep.pairs >= trials * (steps + 1) * 0.9  # non-finite trajectories are dropped
    assert rep.violations == 0, str(rep)
    assert rep.inconsistent == 0, str(rep)


@pytest.mark.parametrize("filter_name", NAMES)
@pytest.mark.parametrize("bad", [0.0, -0.5, float("nan"), float("inf"), [1.0, 2.0], "x"])
def test_bad_scale_raises(filter_name, bad):
    sys_ = systems.get("spring_damper")
    with pytest.raises(ValueError, match="minkowski_scale"):
        filters.by_name(filter_name)(sys_, minkowski_scale=bad)


@pytest.mark.parametrize("filter_name", NAMES)
def test_scale_value_and_setter(filter_name):
    sys_ = systems.get("spring_damper")
    f = filters.by_name(filter_name)(sys_, minkowski_scale=0.4)
    v = f.minkowski_scale.detach()
    assert v.shape == () and float(v) == pytest.approx(0.4)
    assert f.raw_minkowski_scale.requires_grad
    assert float(filters.by_name(filter_name)(sys_).minkowski_scale.detach()) == 1.0  # exactly
    f.minkowski_scale = 2.0
    assert float(f.minkowski_scale.detach()) == pytest.approx(2.0)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="minkowski_scale"):
            f.minkowski_scale = bad


@pytest.mark.parametrize("system_name", ["spring_damper", "mismatch_quadratic"])
@pytest.mark.parametrize("filter_name", NAMES)
def test_log_volume_gradient_is_finite(filter_name, system_name):
    sys_ = systems.get(system_name)
    _, y, u = _traj(sys_, 8, 6, seed=2)
    for scale in (1.0, 0.3, 3.0):
        f = filters.by_name(filter_name)(sys_, minkowski_scale=scale)
        loss = torch.log(f(y, u=u).volume[:, 1:]).mean()
        (g,) = torch.autograd.grad(loss, f.raw_minkowski_scale)
        assert g.shape == () and torch.isfinite(g)
        # ESMF on mismatch_quadratic (m = n, precise measurements): the update keeps the
        # measurement ellipsoid itself (smaller than any family member), so the posterior
        # does not depend on the prior and the gradient is exactly 0; elsewhere it is not
        if not (filter_name == "esmf" and system_name == "mismatch_quadratic"):
            assert float(g) != 0.0


def test_gradcheck_cdsmf_scale_short_horizon():
    sys_ = systems.get("spring_damper")
    _, y, _ = _traj(sys_, 3, 2, seed=4)
    f = filters.CDSMF(sys_, minkowski_scale=0.7)
    assert gradcheck_raw(f, "minkowski_scale", y)


def test_tune_moves_minkowski_scale():
    from diffsmf.tuning.loop import Data, resolve_params, tune

    sys_ = systems.get("spring_damper")
    x, y, _ = _traj(sys_, 6, 6, seed=1)
    f = filters.CDSMF(sys_)
    rep, f = tune(
        f, Data(y=y, x=x), params=("minkowski_scale",), loss="containment",
        epochs=2, batch_size=6, lr=0.1, progress=False,
    )
    assert rep.params == ["minkowski_scale"] and rep.nonfinite_steps == 0
    assert rep.initial["minkowski_scale"] == [1.0]
    assert rep.final["minkowski_scale"] != [1.0]
    v = float(f.minkowski_scale.detach())
    assert v != 1.0 and v > 0
    # filters without the scale skip the name, like the other optional parameters
    chosen, skipped = resolve_params(ds.filters.HSNSMF(sys_), ("stirling_step", "minkowski_scale"))
    assert skipped == ["minkowski_scale"] and list(chosen) == ["stirling_step"]


@pytest.mark.parametrize("filter_name", NAMES)
def test_scalar_scale_state_dict(filter_name):
    """A scalar hyperparameter's scale is stored as ``[1]`` (a 0-d module buffer makes
    torch.compile restart its trace) and reads back as a scalar; a state dict saved with the
    old 0-d scale still loads, with its value."""
    sys_ = systems.get("spring_damper")
    filt = filters.by_name(filter_name)(sys_, minkowski_scale=0.5)
    assert filt.minkowski_scale.shape == ()
    assert filt.minkowski_scale_scale.shape == (1,)
    sd = filt.state_dict()
    sd["minkowski_scale_scale"] = torch.tensor(2.0, dtype=torch.float64)  # old format
    fresh = filters.by_name(filter_name)(sys_)
    fresh.load_state_dict(sd)
    assert fresh.minkowski_scale.shape == ()
    assert float(fresh.minkowski_scale.detach()) == pytest.approx(2.0, rel=1e-15)
    fresh.minkowski_scale = 3.0
    assert float(fresh.minkowski_scale.detach()) == pytest.approx(3.0, rel=1e-15)
    with pytest.raises(RuntimeError, match="size mismatch"):
        sd["minkowski_scale_scale"] = torch.ones(2, dtype=torch.float64)
        fresh.load_state_dict(sd)
