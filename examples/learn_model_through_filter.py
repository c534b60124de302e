"""Learn a network inside your model jointly with its noise bounds, through a guaranteed filter.

A pendulum whose physics you know except its friction: the model is the known part plus a
small tanh network of the angular velocity, and HSNSMF filters its logs. `ds.tuning.fit_loss`
(tight sets, no measurement refuted, one-step predictions that fit the data) is minimised by
Adam over the network's weights and the process-noise bound, from measurements of the angle
alone. Held-out runs show what it bought, and where the truth is known (a simulation), how
many true states the sets contain. The sets bound the *learned* model: they hold the plant's
states as far as the model and the bounds do, which data can refute but not prove.

    python examples/learn_model_through_filter.py [--epochs 30] [--out learned.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from torch import nn
from tqdm.auto import tqdm

import diffsmf as ds

F64 = torch.float64
DT = 0.05


def plant(x, u, theta=None):
    """The true pendulum (unknown to the model): gravity, viscous and Coulomb-like friction."""
    th, om = x[..., 0], x[..., 1]
    acc = -9.81 * torch.sin(th) - 0.3 * om - 2.0 * torch.tanh(3.0 * om) + u[..., 0]
    return torch.stack([th + DT * om, om + DT * acc], -1)


def h(x):
    return x[..., :1]  # the angle, measured


class PendulumWithLearnedFriction(nn.Module):
    """``f(x, u)``: the known gravity and viscous terms plus ``friction(omega)``, a 1-8-1 tanh
    network (float64; its last layer starts at zero: no friction)."""

    def __init__(self) -> None:
        super().__init__()
        self.friction = nn.Sequential(nn.Linear(1, 8), nn.Tanh(), nn.Linear(8, 1)).double()
        nn.init.zeros_(self.friction[2].weight)
        nn.init.zeros_(self.friction[2].bias)

    def forward(self, x, u, theta=None):
        th, om = x[..., 0], x[..., 1]
        fr = self.friction(om.unsqueeze(-1)).squeeze(-1)
        acc = -9.81 * torch.sin(th) - 0.3 * om + fr + u[..., 0]
        return torch.stack([th + DT * om, om + DT * acc], -1)


def _box(half: list[float]) -> ds.Interval:
    r = torch.tensor(half, dtype=F64)
    return ds.Interval(-r, r)


X0 = ds.Interval(torch.tensor([0.3, -0.2], dtype=F64), torch.tensor([0.5, 0.2], dtype=F64))
V = _box([0.005])


def logs(runs: int = 12, steps: int = 30, seed: int = 0) -> ds.systems.Trajectory:
    """Simulated logs of the plant (process noise 1e-3, measurement noise 5e-3, uniform),
    driven by sines of different phases."""
    true = ds.System(plant, h, X0, _box([1e-3, 1e-3]), V, n_inputs=1, name="pendulum")
    phase = torch.linspace(0, 6, runs, dtype=F64).reshape(runs, 1)
    u = (2.0 * torch.sin(0.3 * torch.arange(steps, dtype=F64) + phase)).unsqueeze(-1)
    return true.simulate(steps, batch=runs, seed=seed, noise="uniform", u=u)


def held_out_figures(filt: ds.filters.HSNSMF, data, held: slice) -> dict[str, float]:
    """Mean set area, consistent measurements and true states inside, on the held-out runs."""
    with torch.no_grad():
        res = filt(data.y[held], u=data.u[held])
    return {"area": float(res.volume[:, 1:].mean()),
            "consistent": float(res.consistent.double().mean()),
            "inside": float(res.sets.contains(data.x[held]).double().mean())}


def run(epochs: int = 30, runs: int = 12, steps: int = 30, seed: int = 0,
        progress: bool = True) -> dict:
    """Train on the first 2/3 of the runs, report on the rest; returns the figures, the loss
    history and the learned friction on a grid of omega."""
    torch.manual_seed(seed)
    data = logs(runs, steps, seed)
    train, held = slice(0, 2 * runs // 3), slice(2 * runs // 3, runs)
    model = PendulumWithLearnedFriction()
    system = ds.System(model, h, X0, _box([0.05, 0.05]), V, n_inputs=1, name="learned")
    filt = ds.filters.HSNSMF(system, stirling_step=0.1)
    filt.raw_measurement_noise.requires_grad_(False)  # the sensor's bound is known
    opt = torch.optim.Adam([{"params": model.parameters(), "lr": 0.05},
                            {"params": [filt.raw_process_noise], "lr": 0.1}])
    before = held_out_figures(filt, data, held)
    history = []
    for _ in tqdm(range(epochs), desc="learn", disable=not progress, leave=False):
        opt.zero_grad()
        loss, terms = ds.tuning.fit_loss(filt, data.y[train], data.u[train])
        loss.backward()
        opt.step()
        history.append({"loss": float(loss.detach()), **{k: float(v) for k, v in terms.items()}})
    omega = torch.linspace(-1.5, 1.5, 61, dtype=F64)
    with torch.no_grad():
        learned = model.friction(omega.unsqueeze(-1)).squeeze(-1)
    return {"before": before, "after": held_out_figures(filt, data, held),
            "history": history, "omega": omega, "learned": learned,
            "true": -2.0 * torch.tanh(3.0 * omega),
            "process_noise": filt.process_half_widths.detach().tolist()}


def figure(out: dict, path: str | Path) -> None:
    """The loss over the epochs, and the learned friction against the true one."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    ep = range(1, len(out["history"]) + 1)
    ax[0].plot(ep, [r["loss"] for r in out["history"]], label="fit loss")
    ax[0].plot(ep, [r["prediction"] for r in out["history"]], label="prediction term")
    ax[0].set(xlabel="epoch", ylabel="loss", title="training (8 logged runs)")
    ax[0].legend()
    ax[1].plot(out["omega"], out["true"], "k--", label="true friction (unknown to the model)")
    ax[1].plot(out["omega"], out["learned"], label="learned network")
    ax[1].set(xlabel="angular velocity omega", ylabel="friction acceleration",
              title="the network inside f")
    ax[1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=30)
    ap.add_argument("--out", default="learned_friction.png")
    a = ap.parse_args()
    out = run(epochs=a.epochs)
    for when in ("before", "after"):
        r = out[when]
        print(f"{when:>6} training, held-out runs: mean set area {r['area']:.4g}, "
              f"{100 * r['consistent']:.1f} % measurements consistent, "
              f"{100 * r['inside']:.1f} % true states inside")
    print(f"learned process-noise bound: {[round(v, 4) for v in out['process_noise']]}")
    figure(out, a.out)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
