"""``diffsmf design-observer``: SCPLNN model + LMI observer design + simulation (seed 004)."""

from __future__ import annotations

import argparse
import json
import os

import numpy as np


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--system", default="vdp", choices=["vdp"],
                        help="built-in continuous-time system (seed 004 eq. 23)")
    parser.add_argument("--eps", type=float, default=0.05,
                        help="target model error bound (the certified value is used)")
    parser.add_argument("--method", default="auto", choices=["auto", "scplnn", "grid"],
                        help="model: fit_scplnn split to a certified eps, grid interpolant, "
                             "or fit_scplnn with grid fallback")
    parser.add_argument("--T", type=float, default=20.0, help="simulated time")
    parser.add_argument("--dt", type=float, default=5e-3, help="RK4 step")
    parser.add_argument("--max-gain", type=float, default=1e4, help="bound on |L|_2")
    parser.add_argument("--out", default="out/design-observer", help="output folder")


def main(args: argparse.Namespace) -> int:
    from diffsmf.observers.pipeline import design_observer_pipeline, plot_pipeline

    if not args.eps > 0:
        raise SystemExit("--eps must be positive")
    res = design_observer_pipeline(args.system, args.eps, method=args.method, T=args.T,
                                   dt=args.dt, max_gain=args.max_gain)
    print(res.summary())
    if "fallback" in res.fit:
        print("note:", res.fit["fallback"])
    os.makedirs(args.out, exist_ok=True)
    d = res.design
    summary = dict(
        fit={k: v for k, v in res.fit.items() if isinstance(v, (int, float, str, bool, list))},
        status=d.status, message=d.message, bound=d.bound, gain=d.gain, decay=d.decay,
        L=None if d.L is None else np.asarray(d.L).tolist(),
        general_status=res.design_general.status, checks=res.checks,
    )
    with open(os.path.join(args.out, "summary.json"), "w") as fh:
        json.dump(summary, fh, indent=2)
    if res.sim:
        path = os.path.join(args.out, f"observer_{args.system}.png")
        plot_pipeline(res, path)
        print("figure:", path)
    return 0 if d.feasible else 1
