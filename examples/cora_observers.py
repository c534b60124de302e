"""A CORA user's observers in diffsmf: CORA's names, its six-tank test, one comparison.

Builds the six-tank system of CORA's nonlinear observer test (``ds.systems.get("tank6")``) with
the test's recorded measurements and inflows, runs the observers a CORA user knows by their
CORA names next to diffsmf's own families (`ds.compare`), prints the table and writes the figure
of the bounds over time. Then it runs FRad-A the way CORA does (the first measurement updates
the initial set) with CORA's settings and prints its final interval hull next to the one CORA's
unit test stores.

    python examples/cora_observers.py [--out compare_tank6.png]

Measured tables: docs/results/cora.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import torch  # noqa: E402

import diffsmf as ds  # noqa: E402

OBSERVERS = ["FRad-A", "FRad-B", "VolMin-B", "CZN-A", "ESO-B", "hsnsmf", "zbsmf", "interval"]

#: CORA's saved final hull of FRad-A (test_nonlinearSysDT_observe_01_tank), lower and upper
CORA_FRAD_A = ([19.2977, 19.6140, 14.2447, 20.0893, 18.9582, 16.1726],
               [19.7877, 20.1035, 30.1689, 20.7224, 19.3789, 23.7132])


def compare(observers: list[str] = OBSERVERS) -> ds.comparison.Comparison:
    """The observers on the test's data from its second measurement on (``filt(y)`` starts
    with a prediction)."""
    system = ds.systems.get("tank6")
    y, u = ds.systems.recorded("tank6")
    return ds.compare(system, y[:, 1:], u[:, :-1], filters=observers)


def frad_a_as_cora() -> ds.Interval:
    """FRad-A with CORA's settings (order 100, PCA reduction), the first measurement first."""
    filt = ds.filters.get("FRad-A")(ds.systems.get("tank6"), order=100, reduce_method="pca")
    y, u = ds.systems.recorded("tank6")
    with torch.no_grad():
        state = filt.update(filt.initial_state(1), y[:, 0])
        for k in range(1, y.shape[1]):
            state = filt.update(filt.predict(state, u[:, k - 1]), y[:, k])
    return state.set.interval_hull()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("compare_tank6.png"))
    a = p.parse_args()
    cmp = compare()
    print(cmp.table())
    cmp.figure(a.out)
    print(f"figure: {a.out}")
    hull = frad_a_as_cora()
    print("\nFRad-A, CORA's protocol and settings: final hull per level (ours | CORA's)")
    for i in range(6):
        print(f"  x{i + 1}: [{hull.lower[0, i]:8.4f}, {hull.upper[0, i]:8.4f}]  |  "
              f"[{CORA_FRAD_A[0][i]:8.4f}, {CORA_FRAD_A[1][i]:8.4f}]")
    width = float((hull.upper - hull.lower).sum())
    cora = sum(h - lo for lo, h in zip(*CORA_FRAD_A))
    print(f"  width sum {width:.3f} | {cora:.3f}")


if __name__ == "__main__":
    main()
