"""``diffsmf fit-pwl``: fit an SCPLNN to columns of a CSV file and write the model as JSON.

    diffsmf fit-pwl data.csv --inputs x1,x2 --outputs y --eps 0.01 --out model.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from diffsmf.pwl.fit import fit_scplnn


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("csv", type=Path, help="CSV file with a header row")
    parser.add_argument("--inputs", required=True, help="comma-separated input column names")
    parser.add_argument("--outputs", required=True, help="comma-separated output column names")
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--eps", help="target max abs error: one number or one per output")
    group.add_argument("--rel-eps", type=float, default=0.01,
                       help="target as a fraction of each output's range (default 0.01)")
    parser.add_argument("--max-regions", type=int, default=None,
                        help="cap on the number of simplices (default: 10,000 x max(1, n!/2))")
    parser.add_argument("--outside", choices=["error", "clamp", "extrapolate"], default="error",
                        help="the model's policy for inputs outside the data's box")
    parser.add_argument("--out", type=Path, default=None, help="output JSON model file")


def _columns(header: list[str], names: str, what: str) -> list[int]:
    cols = [c.strip() for c in names.split(",") if c.strip()]
    missing = [c for c in cols if c not in header]
    if not cols or missing:
        raise ValueError(f"{what}: unknown column(s) {missing or names!r}; "
                         f"the CSV has {header}")
    return [header.index(c) for c in cols]


def read_csv(path: Path) -> tuple[list[str], np.ndarray]:
    """Header and numeric data ``[rows, columns]`` of a CSV file. ValueError naming the file,
    row and column for a missing header, no data rows, a ragged row or a non-numeric or blank
    cell (FileNotFoundError for a missing file)."""
    import csv

    if not path.exists():
        raise FileNotFoundError(2, "no such CSV file", str(path))
    if path.is_dir():
        raise ValueError(f"csv: {path} is a folder, not a CSV file")
    with path.open(newline="") as fh:
        rows = [r for r in csv.reader(fh) if any(c.strip() for c in r)]
    if not rows:
        raise ValueError(f"csv: {path} is empty (expected a header row and data rows)")
    header = [h.strip() for h in rows[0]]
    if len(rows) == 1:
        raise ValueError(f"csv: {path} has a header but no data rows")
    data = np.empty((len(rows) - 1, len(header)))
    for i, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise ValueError(f"csv: {path} line {i} has {len(row)} cells, the header has "
                             f"{len(header)}")
        for j, cell in enumerate(row):
            try:
                data[i - 2, j] = float(cell)
            except ValueError:
                what = "a blank cell" if not cell.strip() else f"{cell.strip()!r} is not a number"
                raise ValueError(f"csv: {path} line {i}, column {header[j]!r}: {what}") from None
    return header, data


def main(args: argparse.Namespace) -> int:
    """Read the CSV, fit, print the report, write the model JSON; exit status 0 if the fit
    converged, 1 if not. User errors raise ValueError / FileNotFoundError, which the
    ``diffsmf`` command prints as one line (exit 2)."""
    if args.out is not None:
        parent = args.out.resolve().parent
        if not parent.is_dir():
            raise ValueError(f"--out: folder {parent} does not exist")
        if args.out.is_dir():
            raise ValueError(f"--out: {args.out} is a folder; give a file name (model.json)")
    header, data = read_csv(args.csv)
    ins = _columns(header, args.inputs, "--inputs")
    outs = _columns(header, args.outputs, "--outputs")
    X, Y = torch.from_numpy(data[:, ins]), torch.from_numpy(data[:, outs])
    if args.eps is not None:
        try:
            eps = [float(v) for v in args.eps.split(",")]
        except ValueError:
            raise ValueError(f"--eps: expected numbers separated by commas, got {args.eps!r}"
                             ) from None
    else:
        if not args.rel_eps > 0:
            raise ValueError(f"--rel-eps: must be > 0, got {args.rel_eps}")
        rng = (Y.amax(0) - Y.amin(0)).clamp_min(1e-12)
        eps = (args.rel_eps * rng).tolist()
    if args.max_regions is not None and args.max_regions < 1:
        raise ValueError(f"--max-regions: must be >= 1, got {args.max_regions}")
    model, report = fit_scplnn(X, Y, eps, max_regions=args.max_regions, outside=args.outside)
    model.input_names = [header[i] for i in ins]
    model.output_names = [header[i] for i in outs]
    print(f"{len(X)} samples, inputs {model.input_names}, outputs {model.output_names}")
    print(report.summary())
    print(f"Lipschitz bound (2-norm): {float(model.lipschitz_bound().detach()):.6g}")
    if args.out is not None:
        args.out.write_text(json.dumps(model.to_json()))
        print(f"model written to {args.out}")
    return 0 if report.converged else 1
