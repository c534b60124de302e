"""``diffsmf demo``: the first thing a newcomer runs.

Three parts, each a few seconds on a laptop CPU:

1. **Filters** (the main job): seed 000's comparison on the built-in ``spring_damper``:
   HS-NSMF (parallelotopes) vs MSZM (zonotopes) vs CDSMF (ellipsoids) vs EKF, a table of mean
   set area and containment, and a figure of areas and state bounds over time.
2. **Sets**: the seed 000 worked example (minimal outer parallelotope of a zonotope) and a
   strip intersection, drawn.
3. **PWL**: an SCPLNN fit of f(x) = -x1^2 x2 (seed 004) with its error certificate.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

__all__ = ["add_arguments", "main", "sets_demo"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="diffsmf-demo", help="folder for the figures")
    p.add_argument(
        "--parts",
        default="filters,sets,pwl",
        help="comma-separated parts to run: filters, sets, pwl",
    )


def sets_demo(outdir: Path) -> str:
    """Seed 000 worked example (under eq. 22) and a strip intersection; writes sets.png."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffsmf.plot import plot_set
    from diffsmf.sets import Strip, Zonotope

    f64 = torch.float64
    Z = Zonotope(
        torch.tensor([0.4, 0.15], dtype=f64),
        torch.tensor([[0.15, 0.08, 0.025, 0.0], [0.09, 0.18, 0.0, 0.025]], dtype=f64),
    )
    P = Z.to_parallelotope()
    S = Strip(torch.tensor([1.0, -1.0], dtype=f64), torch.tensor(0.30, dtype=f64), 0.08)
    PS = P.intersect_strip(S)
    ZS = Z.intersect_strip(S)
    fig, ax = plt.subplots(figsize=(5, 4.5))
    plot_set(ax, P, facecolor="none", edgecolor="C1", label="outer parallelotope")
    plot_set(ax, Z, facecolor="C0", alpha=0.35, edgecolor="C0", label="zonotope Z")
    plot_set(ax, PS, facecolor="none", edgecolor="C3", linestyle="--", label="P ∩ strip")
    plot_set(ax, ZS, facecolor="none", edgecolor="C2", linestyle=":", label="Z ∩ strip (Alamo)")
    for edge in (0.30 - 0.08, 0.30 + 0.08):  # the strip |x1 - x2 - 0.30| <= 0.08
        ax.axline((edge, 0.0), slope=1.0, color="grey", linewidth=0.8)
    ax.set_aspect("equal")
    ax.legend(fontsize=8)
    ax.set_title("seed 000 worked example and a strip intersection")
    fig.tight_layout()
    fig.savefig(outdir / "sets.png", dpi=110)
    plt.close(fig)
    rows = ("[" + ", ".join(f"{v:.4f}" for v in row) + "]" for row in P.T.tolist())
    T = "[" + ", ".join(rows) + "]"
    return (
        "Sets: seed 000 worked example (under eq. 22)\n"
        f"  minimal outer parallelotope T = {T}  (paper: [[0.1992, 0.1042], [0.1195, 0.2345]])\n"
        f"  area: zonotope {Z.volume():.4f}, parallelotope {P.volume():.4f}; after the strip "
        f"{PS.volume():.4f} (parallelotope), {ZS.volume():.4f} (zonotope)\n"
        f"  figure: {outdir / 'sets.png'}"
    )


def main(args: argparse.Namespace) -> int:
    outdir = Path(args.out)
    outdir.mkdir(parents=True, exist_ok=True)
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    unknown = set(parts) - {"filters", "sets", "pwl"}
    if unknown:
        raise SystemExit(f"--parts: unknown part(s) {sorted(unknown)}")
    for part in parts:
        t0 = time.perf_counter()
        if part == "filters":
            from diffsmf.filters.compare import demo as filters_demo

            text = filters_demo(outdir)
        elif part == "sets":
            text = sets_demo(outdir)
        else:
            from diffsmf.pwl.demo import demo as pwl_demo

            text = pwl_demo(outdir)
        print(text)
        print(f"  ({part} part: {time.perf_counter() - t0:.1f} s)\n")
    return 0
