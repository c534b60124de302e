r"""``diffsmf compare``: several observers on the same data, side by side.

    diffsmf compare --system tank6 --filters interval,hsnsmf,FRad-A,FRad-B,czsmf --out cmp/
    diffsmf compare --model my_model.py:make_system --data log.csv --outputs y1 --out cmp/

The data: with --model, a logged trajectory (--data, --outputs, --inputs as in diffsmf filter);
with --system, a built-in system and its recorded data where it has some (linear_2d and tank6
carry the reference toolbox's recorded measurements), else --data, else one simulated
trajectory (--steps, --seed, worst-case vertex noise). Observer names: any of
diffsmf.filters.names(presets=True), e.g. hsnsmf, mszm, czsmf, interval, cdsmf, FRad-B.

Prints a table (final interval-hull width sum, its mean over time, bounded steps, inconsistent
steps, ms per step) and writes to --out: comparison.csv (the table), comparison.png (the width
sum and the bounds of the first states over time). An observer that raises is a row with its
error. Exit status 0, or 2 for a user error (one line on stderr).
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import torch

import diffsmf as ds
from diffsmf.cli.filter import _names, load_model, read_log
from diffsmf.comparison import DEFAULT_FILTERS, compare

__all__ = ["add_arguments", "main"]

_COLUMNS = ("filter", "family", "guaranteed", "final_width_sum", "mean_width_sum", "bounded",
            "pairs", "inconsistent", "ms_per_step", "error")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``diffsmf compare``."""
    a = parser.add_argument
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--system", metavar="NAME",
                     help="built-in system (diffsmf.systems.names(); NAME:N for a sized one)")
    src.add_argument("--model", metavar="FILE.py:FUNC",
                     help="your model: FUNC() returns a diffsmf.System")
    a("--data", default=None, type=Path, metavar="FILE",
      help="logged data (CSV/npz/npy, as diffsmf filter); required with --model")
    a("--outputs", default=None, metavar="COLS", help="measurement columns of --data")
    a("--inputs", default=None, metavar="COLS", help="input columns of --data")
    a("--filters", default=",".join(DEFAULT_FILTERS), metavar="NAMES",
      help="comma-separated observer names")
    a("--steps", default=50, type=int, help="steps of the simulated trajectory (no data)")
    a("--seed", default=0, type=int, help="seed of the simulated trajectory (no data)")
    a("--out", default="diffsmf-compare", type=Path, help="output folder (created)")
    a("--no-figure", dest="figure", action="store_false", help="do not write comparison.png")


def _data(args: argparse.Namespace) -> tuple[ds.System, torch.Tensor, torch.Tensor | None, str]:
    """The system, ``y [T, m]``, ``u [T, p]`` or None, and where the data came from."""
    if args.model is not None:
        system = load_model(args.model)
        if args.data is None:
            raise ValueError("--data: name the logged data of your model (with --outputs)")
    else:
        ds.systems.check_name(args.system, "--system")
        system = ds.systems.get(args.system)
    if args.data is not None:
        y, u = read_log(system, args.data, _names(args.outputs), _names(args.inputs))
        return system, y, u, str(args.data)
    base = args.system.partition(":")[0]
    if base in ("linear_2d", "tank6"):  # the first row measures x_0: filters start after it
        y, u = ds.systems.recorded(base)
        return system, y[0, 1:], None if u is None else u[0, :-1], "recorded data"
    if args.steps < 1:
        raise ValueError(f"--steps: must be >= 1, got {args.steps}")
    tr = system.simulate(steps=args.steps, batch=1, seed=args.seed, noise="vertex")
    return system, tr.y[0], None if tr.u is None else tr.u[0], (
        f"one simulated trajectory (vertex noise, seed {args.seed})")


def main(args: argparse.Namespace) -> int:
    """Run ``diffsmf compare``; 0 on success."""
    names = _names(args.filters)
    if not names:
        raise ValueError("--filters: name at least one observer")
    for name in names:
        try:
            ds.filters.get(name)
        except ValueError:
            raise ValueError(f"--filters: unknown observer {name!r}; choose from "
                             f"{ds.filters.names(presets=True)}") from None
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out: {str(out)!r} exists and is not a folder")
    system, y, u, source = _data(args)
    result = compare(system, y, u, filters=names, progress=True)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "comparison.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=_COLUMNS)
        w.writeheader()
        for row in result.rows:
            w.writerow({k: row.get(k) for k in _COLUMNS})
    print(f"{system.name}: {y.shape[0]} steps of {source}")
    print(result.table())
    files = ["comparison.csv"]
    if args.figure and result.results:
        result.figure(out / "comparison.png")
        files.append("comparison.png")
    print(f"wrote {', '.join(str(out / f) for f in files)}")
    return 0
