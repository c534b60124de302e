r"""``diffsmf design-observer``: SCPLNN model + LMI observer design + simulation (Wang et al. 2009).

    diffsmf design-observer --system vdp --eps 0.05 --out run/
    diffsmf design-observer --model my_model.py:make_model --eps 0.1 --out run/

The model: make_model() (any name, no arguments) returns a
diffsmf.observers.ContinuousModel, the continuous-time system
x' = A x + B_f phi(H x) + B u(t), y = C x, with fields name, A [n, n], B [n, p], C [l, n],
B_f [n, r], H [q, n], phi (torch function [..., q] -> [..., r]), hess_bound (None: certified
by interval arithmetic), lower/upper [q] (the box domain of H x where the model error is
certified), x0/xhat0 [n] (true and observer initial states) and u (t -> [p]).
See docs/observers.md ("Your own model").

Pipeline: samples of phi (--samples, --seed) -> SCPLNN model with a certified error <= --eps
-> LMI gain (structured f = B_f phi(H x), and the general Lipschitz form for comparison) ->
simulation of system and observer over --T with RK4 step --dt -> checks.
Writes to --out: summary.json (fit, design status, bound, gain L, checks) and
observer_NAME.png (states, estimates, |e(t)| against the guaranteed envelope and bound).
Exit status: 0 if the structured design is verified, 1 if not (infeasible / unverified),
2 for a user error (one line).
"""

from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path

import numpy as np

from diffsmf.observers.pipeline import (
    ContinuousModel,
    design_observer_pipeline,
    plot_pipeline,
)
from diffsmf.utils import load_object

__all__ = ["add_arguments", "load_observer_model", "main"]

SYSTEMS = ("vdp",)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_mutually_exclusive_group()
    src.add_argument("--system", default=None, metavar="NAME",
                     help=f"built-in continuous-time system: {', '.join(SYSTEMS)} "
                          "(Wang et al. 2009, eq. 23); the default when --model is not given")
    src.add_argument("--model", default=None, metavar="FILE.py:FUNC",
                     help="your model: FUNC() in FILE.py returns a "
                          "diffsmf.observers.ContinuousModel")
    parser.add_argument("--eps", type=float, default=0.05,
                        help="target model error bound (the certified value is used)")
    parser.add_argument("--method", default="auto", choices=["auto", "scplnn", "grid"],
                        help="model: fit_scplnn split to a certified eps, grid interpolant, "
                             "or fit_scplnn with grid fallback")
    parser.add_argument("--samples", type=int, default=4000,
                        help="uniform random samples of phi for fit_scplnn")
    parser.add_argument("--seed", type=int, default=0, help="seed of the samples")
    parser.add_argument("--T", type=float, default=20.0, help="simulated time")
    parser.add_argument("--dt", type=float, default=5e-3, help="RK4 step")
    parser.add_argument("--max-gain", type=float, default=1e4, help="bound on |L|_2")
    parser.add_argument("--out", default="out/design-observer", help="output folder")
    parser.add_argument("--quiet", action="store_true",
                        help="no progress bars and no summary on stdout")


def load_observer_model(spec: str, what: str = "--model"):
    """``"path/to/file.py:FUNC"`` -> the `ContinuousModel` that
    ``FUNC()`` returns.

    Raises ``FileNotFoundError`` (missing file) or ``ValueError`` (malformed spec, not a .py
    file, import failure, no such function, FUNC() failing or returning something else), each
    naming ``what`` and the problem in one line.
    """
    model = load_object(str(spec), what)
    if not isinstance(model, ContinuousModel):
        func = str(spec).rpartition(":")[2]
        raise ValueError(f"{what}: {func}() must return a diffsmf.observers.ContinuousModel, "
                         f"got {type(model).__name__}")
    return model


def _check_args(args: argparse.Namespace) -> None:
    for name in ("eps", "T", "dt", "max_gain"):
        v = getattr(args, name)
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"--{name.replace('_', '-')} must be a positive number, got {v}")
    if args.dt > args.T:
        raise ValueError(f"--dt must be <= --T, got --dt {args.dt} and --T {args.T}")
    if args.samples < 1:
        raise ValueError(f"--samples must be >= 1, got {args.samples}")


def main(args: argparse.Namespace) -> int:
    _check_args(args)
    quiet = bool(getattr(args, "quiet", False))
    model = getattr(args, "model", None)
    if model is not None:
        system = load_observer_model(model)
    else:
        system = args.system or "vdp"
        if system not in SYSTEMS:
            raise ValueError(f"--system: unknown system {system!r} (built-in: "
                             f"{', '.join(SYSTEMS)}; or --model FILE.py:FUNC)")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(20, "--out: not a folder", str(out))
    res = design_observer_pipeline(system, args.eps, method=args.method, T=args.T, dt=args.dt,
                                   max_gain=args.max_gain, samples=args.samples,
                                   seed=getattr(args, "seed", 0), progress=not quiet)
    if not quiet:
        print(res.summary())
        if "fallback" in res.fit:
            print("note:", res.fit["fallback"])
    os.makedirs(out, exist_ok=True)
    d = res.design
    summary = dict(
        system=res.system.name,
        fit={k: v for k, v in res.fit.items() if isinstance(v, (int, float, str, bool, list))},
        status=d.status, message=d.message, solver_status=d.solver_status,
        bound=d.bound if np.isfinite(d.bound) else None, gain=d.gain if np.isfinite(d.gain)
        else None, decay=d.decay, L=None if d.L is None or not d.feasible
        else np.asarray(d.L).tolist(), solves=d.solves,
        general_status=res.design_general.status, checks=res.checks,
        settings=dict(eps=args.eps, method=args.method, samples=args.samples,
                      seed=getattr(args, "seed", 0), T=args.T, dt=args.dt,
                      max_gain=args.max_gain),
    )
    with open(out / "summary.json", "w") as fh:
        json.dump(summary, fh, indent=2)
    if res.sim:
        path = out / f"observer_{_safe(res.system.name)}.png"
        plot_pipeline(res, str(path))
        if not quiet:
            print("figure:", path)
    return 0 if d.feasible else 1


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in str(name)) or "model"
