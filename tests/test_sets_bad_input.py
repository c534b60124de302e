"""Every set type names the argument of a bad point, direction or sample count (no raw
broadcasting errors, no silent use of ``True`` as a count)."""

from __future__ import annotations

import pytest
import torch

import diffsmf as ds


def _sets() -> dict[str, ds.sets.ConvexSet]:
    z = torch.zeros(2, dtype=torch.float64)
    eye = torch.eye(2, dtype=torch.float64)
    return {
        "Interval": ds.Interval(z - 1, z + 1),
        "Zonotope": ds.Zonotope(z, eye),
        "Parallelotope": ds.Parallelotope(z, eye),
        "Ellipsoid": ds.Ellipsoid(z, eye),
        "ConstrainedZonotope": ds.ConstrainedZonotope(z, eye, torch.ones(1, 2), torch.zeros(1)),
        "Strip": ds.Strip(torch.tensor([1.0, 0.0]), torch.tensor(0.0), torch.tensor(1.0)),
    }


@pytest.mark.parametrize("name", list(_sets()))
def test_points_and_directions_of_the_wrong_dimension(name):
    S = _sets()[name]
    with pytest.raises(ValueError, match=r"x: expected \[\.\.\., 2\], got \(3,\)"):
        S.contains(torch.zeros(3))
    with pytest.raises(ValueError, match=r"d: expected \[\.\.\., 2\], got \(4, 3\)"):
        S.support(torch.zeros(4, 3))
    assert S.contains(torch.zeros(5, 2)).shape == (5,)  # batches of points still broadcast


@pytest.mark.parametrize("name", [k for k in _sets() if k != "Strip"])
@pytest.mark.parametrize("k", [-1, True, 2.0, "3"])
def test_sample_counts(name, k):
    S = _sets()[name]
    for draw in (S.sample, S.sample_extreme):
        with pytest.raises(ValueError, match="k: must be an integer >= 0"):
            draw(k)
    assert S.sample(0).shape == (0, 2)
    assert S.sample_extreme(3).shape == (3, 2)
