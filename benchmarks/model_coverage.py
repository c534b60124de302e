"""Coverage: 36 ordinary ways of writing a model in torch, each run through HSNSMF and MSZM.

Each model is a 2-state system ``x+ = 0.9 x + 0.05 g(x)``, ``y = x1 + v`` (or the written
``f`` itself), run for ``--steps`` steps on ``--trials`` vertex-noise trajectories. A row
passes when both filters run and every true state lies in their sets.

    python benchmarks/model_coverage.py [--trials 8] [--steps 10] [--gradients]

``--gradients`` instead checks that the gradients of the log set volume in the filter's
parameters and in a network's weights are finite, for HSNSMF and MSZM with the default and
the Lagrange remainder (``--trials`` trajectories x ``--steps`` steps; 3 x 6 is plenty).
"""

from __future__ import annotations

import argparse
import time

import torch
import torch.nn.functional as F
from torch import nn

import diffsmf as ds

M = torch.tensor([[0.5, -0.3], [0.2, 0.4]], dtype=torch.float64)


def _mlp(act: nn.Module) -> nn.Module:
    torch.manual_seed(0)
    net = nn.Sequential(nn.Linear(2, 8), act, nn.Linear(8, 2)).double()
    with torch.no_grad():
        for p in net.parameters():
            p.mul_(0.5)
    return net


def _stack(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.stack([a, b], -1)


#: name -> g(x [..., 2]) -> [..., 2]
WAYS = {
    # shape ops
    "roll": lambda x: torch.roll(x, 1, -1) * x,
    "flip": lambda x: x.flip(-1) ** 2,
    "einsum": lambda x: torch.einsum("ij,...j->...i", M, x),
    "unsqueeze": lambda x: (x.unsqueeze(-1) * x.unsqueeze(-2)).sum(-1),
    "reshape": lambda x: x.reshape(*x.shape[:-1], 2, 1).squeeze(-1) * x[..., :1],
    "unbind": lambda x: _stack(*[a * b for a, b in zip(x.unbind(-1), x.flip(-1).unbind(-1))]),
    "cumsum": lambda x: torch.cumsum(x, -1) * 0.5,
    "prod": lambda x: x.prod(-1, keepdim=True).expand(x.shape),
    "vector_norm": lambda x: torch.linalg.vector_norm(x, dim=-1, keepdim=True) * x,
    # elementwise
    "log1p": lambda x: torch.log1p(x ** 2),
    "expm1": lambda x: torch.expm1(x),
    "tan": lambda x: torch.tan(0.5 * x),
    "cosh": lambda x: torch.cosh(x) - 1,
    "asin": lambda x: torch.asin(0.5 * x),
    "erf": lambda x: torch.erf(x),
    "rsqrt": lambda x: torch.rsqrt(1 + x ** 2),
    "softplus": lambda x: F.softplus(x),
    # non-smooth
    "relu": lambda x: torch.relu(x),
    "clamp": lambda x: torch.clamp(x, -0.2, 0.2),
    "maximum": lambda x: torch.maximum(x, x.flip(-1)),
    "abs near 0": lambda x: x.abs(),
    "where on the state": lambda x: torch.where(x > 0, x, 0.5 * x),
    # networks
    "MLP ReLU": _mlp(nn.ReLU()),
    "MLP SiLU": _mlp(nn.SiLU()),
    "MLP GELU": _mlp(nn.GELU()),
    "MLP ELU": _mlp(nn.ELU()),
    "MLP LeakyReLU": _mlp(nn.LeakyReLU()),
    "MLP Softplus": _mlp(nn.Softplus()),
    # what worked before
    "polynomial": lambda x: _stack(x[..., 0] * x[..., 1], x[..., 0] ** 2),
    "sin cos": lambda x: _stack(torch.sin(x[..., 0]), torch.cos(x[..., 1])),
    "exp": lambda x: torch.exp(0.5 * x) - 1,
    "tanh": lambda x: torch.tanh(x),
    "sigmoid": lambda x: torch.sigmoid(x) - 0.5,
    "matmul": lambda x: x @ M,
    "linear": lambda x: F.linear(x, M),
    "atan2": lambda x: _stack(torch.atan2(x[..., 1], x[..., 0] + 3.0), x[..., 0]),
}


def system(g: object) -> ds.System:
    def f(x: torch.Tensor) -> torch.Tensor:  # f(x): the input and parameter are not needed
        return 0.9 * x + 0.05 * g(x)

    def h(x: torch.Tensor) -> torch.Tensor:
        return x[..., :1]

    r = torch.full((2,), 0.5, dtype=torch.float64)
    w = torch.full((2,), 1e-3, dtype=torch.float64)
    v = torch.full((1,), 1e-2, dtype=torch.float64)
    return ds.System(f, h, ds.Interval(-r, r), ds.Interval(-w, w), ds.Interval(-v, v))


def finite_gradients(g: object, filt: str, remainder: str, trials: int, steps: int) -> bool:
    """Whether the log set volume's gradients in ``filt``'s parameters and ``g``'s weights
    (a network's) are finite on ``trials`` vertex-noise trajectories of ``steps`` steps."""
    s = system(g)
    y = s.simulate(steps=steps, batch=trials, seed=0, noise="vertex").y
    f = ds.filters.by_name(filt)(s, remainder=remainder)
    f(y).volume[:, 1:].log().mean().backward()
    leaves = [*f.parameters(), *(g.parameters() if isinstance(g, nn.Module) else [])]
    return all(bool(torch.isfinite(p.grad).all()) for p in leaves if p.grad is not None)


def gradients_table(trials: int, steps: int) -> None:
    cases = [(f, r) for f in ("hsnsmf", "mszm") for r in ("auto", "lagrange")]
    print("| model | " + " | ".join(f"{f} {r}" for f, r in cases) + " |")
    print("|---" * (len(cases) + 1) + "|")
    bad = 0
    for name, g in WAYS.items():
        cells = ["finite" if finite_gradients(g, f, r, trials, steps) else "NOT FINITE"
                 for f, r in cases]
        bad += cells.count("NOT FINITE")
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)
    print(f"\n{len(WAYS) * len(cases) - bad} of {len(WAYS) * len(cases)} (model, filter, "
          f"remainder) cases give finite gradients ({trials} trajectories x {steps} steps).")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=8)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--gradients", action="store_true",
                    help="check finite gradients instead of containment")
    args = ap.parse_args()
    torch.set_num_threads(1)
    torch.set_default_dtype(torch.float64)
    if args.gradients:
        gradients_table(args.trials, args.steps)
        return
    ok = 0
    print("| model | HSNSMF | MSZM |\n|---|---|---|")
    for name, g in WAYS.items():
        cells = []
        try:
            s = system(g)
            tr = s.simulate(steps=args.steps, batch=args.trials, seed=0, noise="vertex")
            for filt in ("hsnsmf", "mszm"):
                t0 = time.perf_counter()
                with torch.no_grad():
                    res = ds.filters.by_name(filt)(s)(tr.y)
                inside = bool(res.sets.contains(tr.x.detach()).all())
                cells.append(f"{'contained' if inside else 'NOT CONTAINED'} "
                             f"({time.perf_counter() - t0:.1f} s)")
            ok += all(c.startswith("contained") for c in cells)
        except Exception as exc:  # noqa: BLE001 - the row reports what failed
            cells = [f"{type(exc).__name__}: {str(exc)[:60]}"] * 2
        print(f"| {name} | {cells[0]} | {cells[1]} |", flush=True)
    print(f"\n{ok} of {len(WAYS)} ways run and are contained by both filters "
          f"({args.trials} vertex-noise trajectories x {args.steps} steps).")


if __name__ == "__main__":
    main()
