"""Filters by name: `filters.get` takes every name and alias (CORA's observer names, the
papers' spellings) without regard to case, ``-`` or ``_``; every filter declares the family of
the sets it returns."""

from __future__ import annotations

import pytest
import torch

import diffsmf as ds
from diffsmf import filters
from diffsmf.sets import ConstrainedZonotope, Ellipsoid, Parallelotope, Zonotope, ZonotopeBundle

SET_CLASS = {"parallelotope": Parallelotope, "zonotope": Zonotope, "ellipsoid": Ellipsoid,
             "constrained-zonotope": ConstrainedZonotope, "interval": ds.Interval,
             "zonotope-bundle": ZonotopeBundle}


@pytest.mark.parametrize(("name", "cls"), [
    ("FRad-A", filters.MSZM), ("frad_a", filters.MSZM), ("CZN-A", filters.CZSMF),
    ("HS-NSMF", filters.HSNSMF), ("HSNSMF", filters.HSNSMF), ("cd-smf", filters.CDSMF),
    ("CombinedFilter", filters.CombinedFilter), ("esmf", filters.ESMF),
])
def test_get_takes_names_and_aliases(name, cls):
    assert filters.get(name) is cls
    assert filters.by_name is filters.get


def test_an_unknown_name_lists_the_names_and_the_aliases():
    msg = r"^name: unknown filter 'Hinf-G'.*'hsnsmf'.*'VolMin-B'.*'FRad-A'"
    with pytest.raises(ValueError, match=msg):
        filters.get("Hinf-G")
    with pytest.raises(ValueError, match="^name: expected a filter name"):
        filters.get(3)
    assert set(filters.ALIASES.values()) <= set(filters.names())


@pytest.mark.parametrize("name", filters.names())
def test_every_filter_declares_the_family_of_the_sets_it_returns(name):
    cls = filters.get(name)
    assert cls.set_family in filters.SET_FAMILIES
    sd = ds.systems.get("spring_damper")
    tr = sd.simulate(2, batch=1, seed=0)
    with torch.no_grad():
        res = cls(sd)(tr.y)
    assert isinstance(res.sets, SET_CLASS[cls.set_family]), (name, type(res.sets))
