"""Remainder bounds as named types that carry their settings (`diffsmf.linearize`), and the base
of the linearising filters that takes them."""

from __future__ import annotations

import pytest
import torch

import diffsmf as ds
from diffsmf.filters.linearising import LinearisingFilter
from diffsmf.linearize import (
    Auto,
    DCVertices,
    Lagrange,
    MeanValue,
    RemainderBound,
    dc_remainder,
    lagrange_remainder,
    resolve_remainder,
)
from diffsmf.sets import Zonotope

LINEARISING = ["hsnsmf", "mszm", "cdsmf", "esmf", "czsmf"]


def _run(filt, traj):
    res = filt(traj.y, u=traj.u)
    return res.lower, res.upper


@pytest.mark.parametrize("name", LINEARISING)
def test_every_linearising_filter_shares_the_base(name):
    cls = ds.filters.get(name)
    assert issubclass(cls, LinearisingFilter) and cls.guaranteed
    filt = cls(ds.systems.get("spring_damper"))
    assert isinstance(filt.remainder_fn, RemainderBound)
    assert filt.remainder == filt.remainder_fn.name


@pytest.mark.parametrize("name", ["hsnsmf", "cdsmf", "esmf"])
def test_a_type_gives_the_sets_of_its_name_to_the_bit(name):
    system = ds.systems.get("spring_damper")
    traj = system.simulate(8, batch=3, seed=2, noise="vertex")
    cls = ds.filters.get(name)
    for spelled, typed in (("dc-vertices", DCVertices()), ("lagrange", Lagrange()),
                           ("mean-value", MeanValue()), ("auto", Auto())):
        a, b = _run(cls(system, remainder=spelled), traj), _run(cls(system, remainder=typed), traj)
        assert all(torch.equal(x, y) for x, y in zip(a, b)), spelled


def test_settings_change_the_bound_and_keep_it_guaranteed():
    def fn(x):
        return torch.stack([torch.sin(3 * x[..., 0]) * x[..., 1], x[..., 2] ** 3], -1)

    G = torch.tensor([[0.3, 0.1, 0.0, 0.2], [0.0, 0.2, 0.1, -0.1], [0.1, 0.0, 0.3, 0.1]])
    Z = Zonotope(torch.tensor([0.2, -0.1, 0.4]), G.double())
    c = Z.center
    full = DCVertices()(fn, Z, c)  # 16 sign vectors: the zonotope's own vertices
    hull = DCVertices(max_vertices=8)(fn, Z, c)  # too few: the hull's corners, with Lagrange
    flat = DCVertices(max_tangents=1)(fn, Z, c)  # tangent planes at the centre only
    assert torch.equal(full.lower, dc_remainder(fn, Z, c).lower)
    assert not torch.equal(full.width, hull.width) and not torch.equal(full.width, flat.width)
    s = torch.rand(20000, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    x = c + (2 * s - 1) @ Z.generators.T
    J = ds.linearize.jacobian(fn, c)
    r = fn(x) - fn(c) - (x - c) @ J.T
    for R in (full, hull, flat, lagrange_remainder(fn, Z, c)):
        assert (r >= R.lower).all() and (r <= R.upper).all()


def test_auto_resolves_by_dimension_with_its_own_thresholds():
    assert resolve_remainder("auto", 8)[0] == "dc-vertices"
    assert resolve_remainder("auto", 9)[0] == "lagrange"
    assert resolve_remainder("auto", 17)[0] == "mean-value"
    assert resolve_remainder(Auto(vertex_max_n=2), 3)[0] == "lagrange"
    assert resolve_remainder(Auto(vertex_max_n=2, lagrange_max_n=2), 3)[0] == "mean-value"
    assert resolve_remainder("dc", 2) == ("dc-vertices", DCVertices())


@pytest.mark.parametrize("bad, match", [
    ("taylor", "remainder: unknown method 'taylor'"),
    (lagrange_remainder, "remainder: expected a method name or a RemainderBound"),
    (3, "remainder: expected a method name or a RemainderBound"),
])
def test_a_bad_remainder_names_the_argument(bad, match):
    with pytest.raises(ValueError, match=match):
        ds.filters.HSNSMF(ds.systems.get("spring_damper"), remainder=bad)


def test_bad_settings_name_the_field():
    with pytest.raises(ValueError, match="max_vertices: must be an integer >= 1"):
        DCVertices(max_vertices=0)


def test_esmf_refuses_a_stirling_step_by_name():
    with pytest.raises(ValueError, match="stirling_step: ESMF linearises with the autograd"):
        ds.filters.ESMF(ds.systems.get("spring_damper"), stirling_step=0.1)


def test_the_enclosure_type_has_one_name_and_the_old_one_warns():
    from diffsmf.interval.engine import Enclosure

    assert ds.linearize.Enclosure is Enclosure
    with pytest.warns(DeprecationWarning, match="renamed Enclosure"):
        assert ds.linearize.Jet is Enclosure
    with pytest.raises(AttributeError, match="no attribute 'Jett'"):
        ds.linearize.Jett  # noqa: B018
