"""``diffsmf fit-pwl``: fit an SCPLNN to columns of a CSV file and write the model as JSON.

    diffsmf fit-pwl data.csv --inputs x1,x2 --outputs y --eps 0.01 --out model.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("csv", type=Path, help="CSV file with a header row")
    parser.add_argument("--inputs", required=True, help="comma-separated input column names")
    parser.add_argument("--outputs", required=True, help="comma-separated output column names")
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--eps", help="target max abs error: one number or one per output")
    group.add_argument("--rel-eps", type=float, default=0.01,
                       help="target as a fraction of each output's range (default 0.01)")
    parser.add_argument("--max-regions", type=int, default=10_000)
    parser.add_argument("--outside", choices=["error", "clamp", "extrapolate"], default="error",
                        help="the model's policy for inputs outside the data's box")
    parser.add_argument("--out", type=Path, default=None, help="output JSON model file")


def _columns(header: list[str], names: str, what: str) -> list[int]:
    cols = [c.strip() for c in names.split(",") if c.strip()]
    missing = [c for c in cols if c not in header]
    if not cols or missing:
        raise SystemExit(f"fit-pwl: {what}: unknown column(s) {missing or names!r}; "
                         f"the CSV has {header}")
    return [header.index(c) for c in cols]


def main(args: argparse.Namespace) -> int:
    from diffsmf.pwl.fit import fit_scplnn

    if not args.csv.exists():
        raise SystemExit(f"fit-pwl: csv: no such file {args.csv}")
    header = [h.strip() for h in args.csv.read_text().splitlines()[0].split(",")]
    data = np.loadtxt(args.csv, delimiter=",", skiprows=1, ndmin=2)
    ins = _columns(header, args.inputs, "--inputs")
    outs = _columns(header, args.outputs, "--outputs")
    X, Y = torch.from_numpy(data[:, ins]), torch.from_numpy(data[:, outs])
    if args.eps is not None:
        eps = [float(v) for v in args.eps.split(",")]
    else:
        rng = (Y.amax(0) - Y.amin(0)).clamp_min(1e-12)
        eps = (args.rel_eps * rng).tolist()
    try:
        model, report = fit_scplnn(X, Y, eps, max_regions=args.max_regions,
                                   outside=args.outside)
    except ValueError as exc:
        raise SystemExit(f"fit-pwl: {exc}") from exc
    model.input_names = [header[i] for i in ins]
    model.output_names = [header[i] for i in outs]
    print(f"{len(X)} samples, inputs {model.input_names}, outputs {model.output_names}")
    print(report.summary())
    print(f"Lipschitz bound (2-norm): {float(model.lipschitz_bound().detach()):.6g}")
    if args.out is not None:
        args.out.write_text(json.dumps(model.to_json()))
        print(f"model written to {args.out}")
    return 0 if report.converged else 1
