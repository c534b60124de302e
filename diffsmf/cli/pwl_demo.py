"""PWL part of ``diffsmf demo``: fit f(X) = -x1^2 x2 (Wang et al. 2009, sec. 4) and draw the
partition."""

from __future__ import annotations

from pathlib import Path

import torch

from diffsmf.pwl.fit import fit_scplnn


def demo(outdir: Path) -> str:
    """Fit -x1^2 x2 on a 41x41 grid of [-2, 2]^2 to eps = 0.1; write ``pwl_demo.png`` (partition
    over the held-out error) into ``outdir`` and return a summary."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    t = torch.linspace(-2, 2, 41, dtype=torch.float64)
    X = torch.stack(torch.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)
    f = lambda Z: -Z[..., 0] ** 2 * Z[..., 1]  # noqa: E731
    model, report = fit_scplnn(X, f(X), 0.1)
    tm = torch.linspace(-2, 2, 201, dtype=torch.float64)
    G = torch.stack(torch.meshgrid(tm, tm, indexing="ij"), -1)
    with torch.no_grad():
        err = (model(G)[..., 0] - f(G)).abs()
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    im = ax.pcolormesh(G[..., 0], G[..., 1], err, shading="auto", cmap="viridis")
    V = model.vertices
    ax.triplot(V[:, 0], V[:, 1], model.simplices.numpy(), color="w", lw=0.4)
    fig.colorbar(im, ax=ax, label="|f - SCPLNN| on a 201x201 grid")
    ax.set(title=f"SCPLNN fit of -x1^2 x2: {report.regions} regions", xlabel="x1", ylabel="x2")
    fig.tight_layout()
    fig.savefig(outdir / "pwl_demo.png", dpi=90)
    plt.close(fig)
    return (f"PWL: {report.summary()}\n"
            f"     held-out max error on a 201x201 grid: {float(err.max()):.4f}; "
            f"Lipschitz bound {float(model.lipschitz_bound().detach()):.3f}; "
            f"figure {outdir / 'pwl_demo.png'}")
