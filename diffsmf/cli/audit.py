"""``diffsmf audit``: containment audit of a filter on a built-in system (`diffsmf.audit`).

    diffsmf audit --system spring_damper --filter hsnsmf --trials 1000
"""

from __future__ import annotations

import argparse
import json
import re
import warnings
from dataclasses import asdict

from diffsmf import filters, systems
from diffsmf.audit import TOL, containment, gaussian_note, has_gaussian_noise

__all__ = ["add_arguments", "main"]


def _positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (so ``--trials 0`` is a one-line usage error)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {v}")
    return v


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``diffsmf audit``."""
    parser.add_argument(
        "--system", required=True,
        help="built-in system name (see diffsmf.systems.names()); NAME:N for a sized system, "
        "e.g. oscillator_chain:16",
    )
    parser.add_argument(
        "--filter", required=True, help="hsnsmf | mszm | cdsmf | esmf | czsmf | ekf | combined"
    )
    parser.add_argument(
        "--trials", type=_positive_int, default=1000, help="simulated trajectories (one batch)"
    )
    parser.add_argument(
        "--steps", type=_positive_int, default=None,
        help="horizon in steps (default: the system's paper horizon, else 100)",
    )
    parser.add_argument(
        "--noise", choices=["vertex", "uniform", "both"], default="both",
        help="noise draw: vertex (worst case), uniform, or both one after the other",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated trajectories")
    parser.add_argument("--json", action="store_true", help="print JSON lines instead of text")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def main(args: argparse.Namespace) -> int:
    """Run the audit; exit status 1 when a guaranteed filter has a violation on a system whose
    noise is bounded only (with Gaussian noise, pairs outside are expected and noted)."""
    systems.check_name(args.system, option="--system")
    try:
        cls = filters.by_name(args.filter)
    except ValueError:
        raise ValueError(
            f"--filter: unknown filter {args.filter!r}; choose from {filters.names(presets=True)}"
        ) from None
    system = systems.get(args.system)
    filt = cls(system)
    noises = ["vertex", "uniform"] if args.noise == "both" else [args.noise]
    bad = False
    reports = []
    gaussian = has_gaussian_noise(system)
    with warnings.catch_warnings():  # said once below, not once per noise kind
        said = re.escape(f"containment: {gaussian_note(system)}")
        warnings.filterwarnings("ignore", message=said)
        for noise in noises:
            reports.append(
                containment(
                    filt, system, args.trials, args.steps, noise, args.seed,
                    progress=not getattr(args, "quiet", True),
                )
            )
    # a violation fails the run only for a guaranteed filter on bounded noise
    must_hold = filters.is_guaranteed(filt) and not gaussian
    for rep in reports:
        print(json.dumps(asdict(rep)) if args.json else rep)
        bad |= rep.violations > 0 and must_hold
    if not args.json:
        guaranteed = ", ".join(
            sorted(n for n in filters.names() if filters.is_guaranteed(filters.by_name(n)))
        )
        print(
            "A pair is outside when the true state's normalised distance from the set exceeds "
            f"{TOL:g}; guaranteed filters ({guaranteed}) must show 0."
        )
        if gaussian:
            print(f"Note: {gaussian_note(system)}; they do not fail the audit.")
    return 1 if bad else 0

