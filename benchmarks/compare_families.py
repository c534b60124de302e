"""Every set family on three built-ins, with `ds.compare`: the table and figure of the docs page
"Comparing observers".

* ``linear_2d``: the reference toolbox's recorded data (19 steps after the first measurement);
* ``tank6``: the same, the toolbox's nonlinear six-tank test;
* ``tank_cascade:30``: one simulated trajectory with worst-case (vertex) noise, 30 steps.

There is no peer that runs these families side by side in Python (the reference toolbox is
MATLAB; its saved results are compared in ``benchmarks/cora_observers.py``). Times are ms per
step of one trajectory, one thread, this run.

    python benchmarks/compare_families.py [--out docs/figures] [--czsmf-30]
"""

from __future__ import annotations

import argparse
import platform
import subprocess
import time
from pathlib import Path

import torch

import diffsmf as ds

SMALL = ["interval", "hsnsmf", "FRad-A", "FRad-B", "VolMin-B", "zbsmf", "czsmf", "cdsmf", "ESO-B",
         "esmf", "ekf"]
LARGE = ["interval", "hsnsmf", "FRad-A", "zbsmf", "cdsmf", "ESO-B", "esmf", "ekf"]


def _data(name: str, steps: int) -> tuple[ds.System, torch.Tensor, torch.Tensor | None]:
    system = ds.systems.get(name)
    if name in ("linear_2d", "tank6"):
        y, u = ds.systems.recorded(name)  # its first row measures x_0: start after it
        return system, y[0, 1:], None if u is None else u[0, :-1]
    tr = system.simulate(steps=steps, batch=1, seed=0, noise="vertex")
    return system, tr.y[0], None if tr.u is None else tr.u[0]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("docs/figures"))
    p.add_argument("--steps", type=int, default=30)
    p.add_argument("--czsmf-30", action="store_true", help="also CZSMF at 30 states (slow)")
    a = p.parse_args()
    torch.set_num_threads(1)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    print(f"diffsmf {ds.__version__} @ {commit}, torch {torch.__version__}, "
          f"{platform.processor() or platform.machine()}, 1 thread, {time.strftime('%Y-%m-%d')}")
    for name in ("linear_2d", "tank6", "tank_cascade:30"):
        system, y, u = _data(name, a.steps)
        names = SMALL if system.n <= 6 else LARGE + (["czsmf"] if a.czsmf_30 else [])
        cmp = ds.compare(system, y, u, filters=names, progress=True)
        print(f"\n{cmp.title}")
        print(cmp.table())
        a.out.mkdir(parents=True, exist_ok=True)
        fig = a.out / f"compare_{name.replace(':', '_')}.png"
        cmp.figure(fig)
        print(f"figure: {fig}")


if __name__ == "__main__":
    main()
