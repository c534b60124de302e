"""Wang et al. 2009, sec. 3.1 / 4: SCPLNN fits of f(X) = -x1^2 x2 on [-2, 2]^2.

    python examples/pwl_fit.py [--out out/pwl]

1. Adaptive fits for eps in {0.1, 0.03, 0.01} on a 101x101 grid of samples: regions, vertices,
   max training error, held-out error on the 200x200 grid of cell centres, time.
2. The split rules on random samples: "rivara" (default: conforming longest-edge bisection
   of every region above eps, with held-out samples), "interior" (Wang et al. 2009's rule,
   longest-edge cut near faces; the earlier default), "edge", and "paper" (Wang et al. 2009
   literally: always connect the sample to the region's vertices).
3. Wang et al. 2009's comparison with hinging hyperplanes ("model 3") at the same number of regions
and
   at the same number of parameters.
4. A figure of the eps = 0.1 partition over its held-out error (out/pwl/pwl_fit.png).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from diffsmf.pwl import HingingHyperplanes, fit_scplnn

torch.set_default_dtype(torch.float64)


def f(X: torch.Tensor) -> torch.Tensor:
    return -X[..., 0] ** 2 * X[..., 1]


def grids() -> tuple[torch.Tensor, torch.Tensor]:
    t = torch.linspace(-2, 2, 101)
    X = torch.stack(torch.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)
    tm = torch.linspace(-2, 2, 201)
    tm = (tm[1:] + tm[:-1]) / 2
    Xh = torch.stack(torch.meshgrid(tm, tm, indexing="ij"), -1).reshape(-1, 2)
    return X, Xh


def held_out(model: torch.nn.Module, Xh: torch.Tensor) -> tuple[float, float]:
    with torch.no_grad():
        e = (model(Xh)[:, 0] - f(Xh)).abs()
    return float(e.max()), float(e.pow(2).mean().sqrt())


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=Path("out/pwl"))
    args = ap.parse_args()
    X, Xh = grids()
    y = f(X)
    print("1. adaptive fits (101x101 grid samples; held-out = 200x200 cell centres)")
    print("| eps | regions | vertices | train max | held-out max | held-out RMS | Lipschitz | s |")
    print("|---|---|---|---|---|---|---|---|")
    models = {}
    for eps in (0.1, 0.03, 0.01):
        model, rep = fit_scplnn(X, y, eps)
        models[eps] = (model, rep)
        hm, hr = held_out(model, Xh)
        print(f"| {eps} | {rep.regions} | {rep.vertices} | {float(rep.max_error[0]):.4f} | "
              f"{hm:.4f} | {hr:.4f} | {float(model.lipschitz_bound().detach()):.3f} | "
              f"{rep.seconds:.2f} |")
    print("\n2. split rules at eps = 0.1 (10,000 uniform random samples, max 40 rounds)")
    print("| rule | converged | regions | vertices | train max | held-out max | s |")
    print("|---|---|---|---|---|---|---|")
    Xr = torch.rand(10_000, 2, generator=torch.Generator().manual_seed(0)) * 4 - 2
    for rule in ("rivara", "interior", "edge", "paper"):
        model, rep = fit_scplnn(Xr, f(Xr), 0.1, rule=rule, max_rounds=40, max_regions=20_000)
        hm, _ = held_out(model, Xh)
        print(f"| {rule} | {rep.converged} | {rep.regions} | {rep.vertices} | "
              f"{float(rep.max_error[0]):.4f} | {hm:.4f} | {rep.seconds:.2f} |")
    print("\n3. SCPLNN vs hinging hyperplanes (Wang et al. 2009 'model 3')")
    print("| SCPLNN eps | SCPLNN regions / params | SCPLNN train max | HH K | HH regions / params "
          "| HH train max | HH held-out max |")
    print("|---|---|---|---|---|---|---|")
    for eps in (1.0, 0.3, 0.1):
        model, rep = fit_scplnn(X, y, eps)
        hm, _ = held_out(model, Xh)
        k_par = max(1, rep.parameters // 6)
        ks = sorted({k_par} | {k for k in (4, 6, 8, 10, 14, 18, 24, 30, 40)})
        reached = None
        for k in ks:
            hh = HingingHyperplanes(n_hinges=k, n_starts=2, backfit_passes=1, seed=0).fit(X, y)
            r = hh.n_regions(Xh)
            with torch.no_grad():
                tr = float((hh(X)[:, 0] - y).abs().max())
            hho, _ = held_out(hh, Xh)
            tag = []
            if k == k_par:
                tag.append("same params")
            if reached is None and r >= rep.regions:
                reached = k
                tag.append("same regions")
            if tag:
                print(f"| {eps} | {rep.regions} / {rep.parameters} | "
                      f"{float(rep.max_error[0]):.4f} (held {hm:.4f}) | {k} ({', '.join(tag)}) | "
                      f"{r} / {hh.n_parameters()} | {tr:.4f} | {hho:.4f} |")
            if reached is not None and k >= k_par:
                break
    model, rep = models[0.1]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    args.out.mkdir(parents=True, exist_ok=True)
    t = torch.linspace(-2, 2, 301)
    G = torch.stack(torch.meshgrid(t, t, indexing="ij"), -1)
    with torch.no_grad():
        err = (model(G)[..., 0] - f(G)).abs().numpy()
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    im = ax.pcolormesh(G[..., 0], G[..., 1], err, shading="auto", cmap="viridis")
    ax.triplot(model.vertices[:, 0], model.vertices[:, 1], model.simplices.numpy(), color="w",
               lw=0.3)
    fig.colorbar(im, ax=ax, label="|f - SCPLNN|")
    ax.set(title=f"-x1^2 x2, eps = 0.1: {rep.regions} regions", xlabel="x1", ylabel="x2")
    fig.tight_layout()
    fig.savefig(args.out / "pwl_fit.png", dpi=80)
    print(f"\nfigure: {args.out / 'pwl_fit.png'} (max grid error {np.max(err):.4f})")


if __name__ == "__main__":
    main()
