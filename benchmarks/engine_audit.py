"""Containment audit of the guaranteed filters on models the engine encloses, vertex noise.

One row per model class, with the bound the engine uses for it: ReLU, tanh and SiLU networks
(dynamics ``0.9 x + 0.1 net(x)``), a saturated actuator (``clamp``), a ring of coupled states
(``roll``, ``tanh``, ``clamp``) at n = 16 and 32, a branch on the state (``torch.where``,
zeroth-order bound) and a fitted SCPLNN (the pendulum of ``examples/pendulum_scplnn.py``, with
its certified error). Prints outside / pairs, unbounded and mean volume per row.

    python benchmarks/engine_audit.py [--trials 1000] [--steps 50] [--filters hsnsmf mszm]
"""

from __future__ import annotations

import argparse
import importlib.util
import platform
import subprocess
import time
from pathlib import Path

import torch
from tqdm import tqdm

import diffsmf as ds
from diffsmf.audit import containment


def _box(n: int, r: float) -> ds.Interval:
    return ds.Interval(-r * torch.ones(n), r * torch.ones(n))


def mlp_system(act: str, seed: int = 0) -> ds.System:
    """``x+ = 0.9 x + 0.1 net(x)``, ``y = x1 + relu(x2) / 10``, 2 states."""
    torch.manual_seed(seed)
    layer = {"relu": torch.nn.ReLU, "tanh": torch.nn.Tanh, "silu": torch.nn.SiLU}[act]
    net = torch.nn.Sequential(torch.nn.Linear(2, 16), layer(), torch.nn.Linear(16, 16), layer(),
                              torch.nn.Linear(16, 2)).double()
    with torch.no_grad():
        for p in net.parameters():
            p.mul_(0.5)

    def f(x: torch.Tensor) -> torch.Tensor:
        return 0.9 * x + 0.1 * net(x)

    def h(x: torch.Tensor) -> torch.Tensor:
        return x[..., :1] + 0.1 * torch.relu(x[..., 1:])

    return ds.System(f, h, _box(2, 0.5), _box(2, 0.01), _box(1, 0.02), name=f"mlp_{act}")


def actuator_system() -> ds.System:
    """A damped oscillator driven through a saturated feedback ``clamp(-k x, -u_max, u_max)``."""
    dt = 0.1

    def f(x: torch.Tensor) -> torch.Tensor:
        u = torch.clamp(-1.5 * x[..., :1] - 0.8 * x[..., 1:], -0.3, 0.3)
        return torch.cat([x[..., :1] + dt * x[..., 1:], x[..., 1:] + dt * (-x[..., :1] + u)], -1)

    return ds.System(f, lambda x: x[..., :1], _box(2, 0.5), _box(2, 2e-3), _box(1, 0.01),
                     name="saturated_actuator")


def ring_system(n: int) -> ds.System:
    """A ring of coupled states: ``roll`` coupling, ``tanh`` and ``clamp``; every other state
    measured through ``relu``."""

    def f(x: torch.Tensor) -> torch.Tensor:
        return 0.8 * x + 0.1 * torch.tanh(torch.roll(x, 1, -1)) - 0.05 * torch.clamp(x, -0.3, 0.3)

    def h(x: torch.Tensor) -> torch.Tensor:
        return x[..., ::2] + 0.1 * torch.relu(x[..., 1::2])

    return ds.System(f, h, _box(n, 0.5), _box(n, 0.01), _box(n // 2, 0.02), name=f"ring_{n}")


def branch_system() -> ds.System:
    """A piecewise model written with ``torch.where`` on the state (zeroth-order bound where
    the branch is undecided over the set)."""

    def f(x: torch.Tensor) -> torch.Tensor:
        gain = torch.where(x[..., :1] > 0, 0.5 * x[..., 1:], 0.3 * x[..., 1:])
        return torch.cat([0.9 * x[..., :1] + 0.1 * x[..., 1:], 0.7 * x[..., 1:] + 0.1 * gain], -1)

    return ds.System(f, lambda x: x, _box(2, 0.5), _box(2, 0.01), _box(2, 0.02),
                     name="branch_on_state")


def scplnn_systems() -> tuple[ds.System, ds.System]:
    """(the fitted pendulum with its certified error, the true pendulum)."""
    path = Path(__file__).parent.parent / "examples" / "pendulum_scplnn.py"
    spec = importlib.util.spec_from_file_location("pendulum_scplnn", path)
    ex = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ex)  # type: ignore[union-attr]
    model, _report, cert, X, Y = ex.fit(20_000, 0.004, 0)
    return ex.model_system(model, cert, X, Y), ex.true_system()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=1000)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--filters", nargs="+", default=["hsnsmf", "mszm"])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--models", nargs="+", default=None,
                    help="only these rows (names as printed, e.g. ring_16 pendulum)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.set_default_dtype(torch.float64)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()
    print(f"{time.strftime('%Y-%m-%d')}, commit {commit}, {platform.machine()}, "
          f"{torch.get_num_threads()} thread(s), vertex noise, {args.trials} trajectories x "
          f"{args.steps} steps")
    fitted, truth = scplnn_systems()
    rows = [(mlp_system("relu"), None), (mlp_system("tanh"), None), (mlp_system("silu"), None),
            (actuator_system(), None), (ring_system(16), None), (ring_system(32), None),
            (branch_system(), None), (fitted, truth)]
    print("\n| model | filter | outside / pairs | unbounded | mean volume | seconds |")
    print("|---|---|---:|---:|---:|---:|")
    if args.models:
        rows = [r for r in rows if any(m in r[0].name for m in args.models)]
    for system, true_system in tqdm(rows, desc="models"):
        for name in args.filters:
            filt = ds.filters.by_name(name)(system)
            t0 = time.perf_counter()
            rep = containment(filt, true_system or system, trials=args.trials, steps=args.steps,
                              noise="vertex", progress=True)  # chunked: bounded memory
            dt = time.perf_counter() - t0
            print(f"| {system.name} | {name} | {rep.violations} / {rep.pairs} | {rep.unbounded} "
                  f"| {rep.mean_volume:.4g} | {dt:.0f} |", flush=True)


if __name__ == "__main__":
    main()
