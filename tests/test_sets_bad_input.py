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


def test_empty_sets_refused_where_a_filter_would_start_from_them():
    """An empty constrained zonotope as x0_set, a noise set or a filter's initial_set raises,
    naming the argument (before: CZSMF, MSZM and CDSMF reported plausible, "consistent" sets
    from the empty ``{xi : xi_1 + xi_2 = 5}``, growing to 1e76 for CZSMF)."""
    sd = ds.systems.get("spring_damper")
    eye = torch.eye(2, dtype=torch.float64)
    empty2 = ds.ConstrainedZonotope(torch.zeros(2), eye, torch.ones(1, 2), torch.tensor([5.0]))
    empty1 = ds.ConstrainedZonotope(torch.zeros(1), torch.eye(1), torch.ones(1, 1),
                                    torch.tensor([5.0]))
    assert bool(empty2.is_empty()) and bool(empty1.is_empty())
    with pytest.raises(ValueError, match=r"^x0_set: is empty \(a ConstrainedZonotope"):
        ds.System(sd.f, sd.h, empty2, sd.process_noise, sd.measurement_noise)
    with pytest.raises(ValueError, match=r"^process_noise: is empty"):
        ds.System(sd.f, sd.h, sd.x0_set, empty2, sd.measurement_noise)
    with pytest.raises(ValueError, match=r"^measurement_noise: is empty"):
        ds.System(sd.f, sd.h, sd.x0_set, sd.process_noise, empty1)
    for name in ("hsnsmf", "mszm", "cdsmf", "esmf", "ekf", "czsmf"):
        with pytest.raises(ValueError, match=r"^initial_set: is empty"):
            ds.filters.by_name(name)(sd, initial_set=empty2)
    # a non-empty constrained zonotope passes (the constraint holds at xi = 0)
    ok = ds.ConstrainedZonotope(torch.zeros(2), eye, torch.ones(1, 2), torch.zeros(1))
    ds.System(sd.f, sd.h, ok, sd.process_noise, sd.measurement_noise)
    ds.filters.CZSMF(sd, initial_set=ok)
