"""``diffsmf demo``: the first thing a newcomer runs.

Three parts, each a few seconds on a laptop CPU:

1. **Filters** (the main job): Wang et al. 2022's comparison on the built-in ``spring_damper``:
   HS-NSMF (parallelotopes) vs MSZM (zonotopes) vs CDSMF (ellipsoids) vs EKF, a table of mean
   set area and containment, and a figure of areas and state bounds over time.
2. **Sets**: the Wang et al. 2022 worked example (minimal outer parallelotope of a zonotope) and a
   strip intersection, drawn.
3. **PWL**: an SCPLNN fit of f(x) = -x1^2 x2 (Wang et al. 2009) with its error certificate.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from diffsmf.cli.pwl_demo import demo as pwl_demo
from diffsmf.comparison import demo as filters_demo
from diffsmf.plot import plot_set
from diffsmf.sets import Strip, Zonotope

__all__ = ["add_arguments", "filters_demo", "main", "sets_demo"]


PARTS = ("filters", "sets", "pwl")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of ``diffsmf demo``."""
    p.add_argument("--out", default="diffsmf-demo", help="folder for the figures (created)")
    p.add_argument(
        "--parts",
        default="filters,sets,pwl",
        help="comma-separated parts to run: filters, sets, pwl",
    )
    p.add_argument("--trials", type=int, default=10, help="trajectories of the filters part")
    p.add_argument("--steps", type=int, default=60, help="horizon of the filters part")
    p.add_argument(
        "--seed", type=int, default=0, help="seed of the simulated trajectories (filters part)"
    )


def sets_demo(outdir: Path) -> str:
    """Wang et al. 2022 worked example (under eq. 22) and a strip intersection; writes sets.png."""
    from matplotlib.figure import Figure

    f64 = torch.float64
    Z = Zonotope(
        torch.tensor([0.4, 0.15], dtype=f64),
        torch.tensor([[0.15, 0.08, 0.025, 0.0], [0.09, 0.18, 0.0, 0.025]], dtype=f64),
    )
    P = Z.to_parallelotope()
    S = Strip(torch.tensor([1.0, -1.0], dtype=f64), torch.tensor(0.30, dtype=f64), 0.08)
    PS = P.intersect_strip(S)
    ZS = Z.intersect_strip(S)
    fig = Figure(figsize=(6.4, 5.6))  # no pyplot: no backend switch, no global state
    ax = fig.subplots()
    plot_set(ax, P, facecolor="none", edgecolor="C1", linewidth=1.6,
             label="P: minimal outer parallelotope of Z")
    plot_set(ax, Z, facecolor="C0", alpha=0.35, edgecolor="C0", label="zonotope Z")
    plot_set(ax, PS, facecolor="none", edgecolor="C3", linestyle="--", linewidth=1.6,
             label="outer parallelotope of P ∩ strip\n(a bound: may extend beyond P)")
    plot_set(ax, ZS, facecolor="none", edgecolor="C2", linestyle=":", linewidth=1.8,
             label="outer zonotope of Z ∩ strip (Alamo)")
    for j, edge in enumerate((0.30 - 0.08, 0.30 + 0.08)):  # the strip |x1 - x2 - 0.30| <= 0.08
        ax.axline((edge, 0.0), slope=1.0, color="grey", linewidth=0.8,
                  label="strip |x1 - x2 - 0.30| <= 0.08" if j == 0 else None)
    ax.set_aspect("equal")
    ax.set_xlabel("x1")
    ax.set_ylabel("x2")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0)
    ax.set_title("Wang et al. 2022 worked example (eq. 22) and a strip intersection", fontsize=10)
    fig.tight_layout()
    fig.savefig(outdir / "sets.png", dpi=110, bbox_inches="tight")
    rows = ("[" + ", ".join(f"{v:.4f}" for v in row) + "]" for row in P.T.tolist())
    T = "[" + ", ".join(rows) + "]"
    return (
        "Sets: Wang et al. 2022 worked example (under eq. 22)\n"
        f"  minimal outer parallelotope T = {T}  (paper: [[0.1992, 0.1042], [0.1195, 0.2345]])\n"
        f"  area: zonotope {Z.volume():.4f}, parallelotope {P.volume():.4f}; after the strip "
        f"{PS.volume():.4f} (parallelotope), {ZS.volume():.4f} (zonotope)\n"
        f"  figure: {outdir / 'sets.png'}"
    )


def main(args: argparse.Namespace) -> int:
    """Run the demo parts; print their text and where the figures are."""
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    unknown = set(parts) - set(PARTS)
    if unknown or not parts:
        raise ValueError(f"--parts: unknown part(s) {sorted(unknown)}; choose from {list(PARTS)}")
    for name in ("trials", "steps"):
        if getattr(args, name, 1) < 1:
            raise ValueError(f"--{name}: must be >= 1, got {getattr(args, name)}")
    outdir = Path(args.out)
    if outdir.exists() and not outdir.is_dir():
        raise ValueError(f"--out: {str(outdir)!r} exists and is not a folder")
    outdir.mkdir(parents=True, exist_ok=True)
    for i, part in enumerate(parts, 1):
        t0 = time.perf_counter()
        print(f"[{i}/{len(parts)}] running the {part} part ...", flush=True)
        if part == "filters":
            text = filters_demo(outdir, getattr(args, "trials", 10), getattr(args, "steps", 60),
                                getattr(args, "seed", 0))
        elif part == "sets":
            text = sets_demo(outdir)
        else:
            text = pwl_demo(outdir)
        print(text)
        print(f"  ({part} part: {time.perf_counter() - t0:.1f} s)\n")
    return 0
