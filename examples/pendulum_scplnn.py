"""Samples of a pendulum -> fit_scplnn -> HSNSMF on the fitted model, audited on the true pendulum.

The true system is a damped pendulum, one RK4 step of ``dt`` per sample time::

    theta'' = -(g / l) sin(theta) - c theta',   x = [theta, omega],   y = theta + v,  |v| <= 0.05

with bounded process noise ``|w_i| <= 0.002``. The SCPLNN is fitted (least squares, Wang et al.
2009, sec. 3.1.2) to ``--samples`` uniform samples of the one-step map on the domain
``[-1.5, 1.5] x [-4, 4]``; ``fit_scplnn`` splits every region until its certified error (vertex
mismatch plus ``r' H r / 8`` with an interval Hessian bound of the RK4 map,
``diffsmf.pwl.simplex_error``) is below ``--eps``. The certificate is checked against the
samples and added to the process noise (``diffsmf.pwl.as_system``). HSNSMF filters the model
system; the true pendulum's states are audited for containment (vertex noise).

    python examples/pendulum_scplnn.py [--trials 100] [--steps 100] [--eps 0.004]
        [--out docs/figures/pendulum_scplnn.png]

HSNSMF runs with its default remainder: the engine encloses the PWL model as one operation,
with exact enclosures of its values and generalised gradients (``SCPLNN.interval_enclosure``),
and bounds it to first order where the set meets several pieces.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

import diffsmf as ds  # noqa: E402
from diffsmf.audit import containment  # noqa: E402
from diffsmf.plot import plot_set  # noqa: E402
from diffsmf.pwl import as_system, certify_error, fit_scplnn, simplex_error  # noqa: E402
from diffsmf.pwl.certified import simplex_hessian_bound  # noqa: E402

G_L, DAMPING, DT = 9.81, 0.5, 0.05
F64 = torch.float64  # set bounds in float64: 0.002 in float32 is 0.0020000000949949026
DOMAIN = (torch.tensor([-1.5, -4.0], dtype=F64), torch.tensor([1.5, 4.0], dtype=F64))
W_BOUND, V_BOUND = 0.002, 0.05
X0 = ds.Interval([0.6, -0.3], [1.0, 0.3])


def _rhs(z):
    return torch.cat([z[..., 1:2], -G_L * torch.sin(z[..., 0:1]) - DAMPING * z[..., 1:2]], -1)


def pendulum(x):
    """One RK4 step of the damped pendulum: ``x [..., 2] -> [..., 2]`` (torch ops, jets too)."""
    k1 = _rhs(x)
    k2 = _rhs(x + (0.5 * DT) * k1)
    k3 = _rhs(x + (0.5 * DT) * k2)
    k4 = _rhs(x + DT * k3)
    return x + (DT / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def angle(x):
    return x[..., :1]


def true_system() -> ds.System:
    w = torch.full((2,), W_BOUND, dtype=F64)
    return ds.System(lambda x, u, th: pendulum(x), angle, X0, ds.Interval(-w, w),
                     ds.Interval([-V_BOUND], [V_BOUND]),
                     name="pendulum")


def fit(samples: int = 20_000, eps: float = 0.004, seed: int = 0):
    """Samples -> fitted SCPLNN with certified error -> (model, report, certificate, X, Y)."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = DOMAIN
    X = lo + torch.rand(samples, 2, generator=g, dtype=torch.float64) * (hi - lo)
    Y = pendulum(X)
    hb = simplex_hessian_bound(pendulum)
    model, report = fit_scplnn(X, Y, eps=eps, domain=DOMAIN,
                               region_bound=lambda V, W: simplex_error(V, W, pendulum, hb))
    return model, report, certify_error(model, pendulum, hb), X, Y


def model_system(model, cert, X, Y) -> ds.System:
    w = torch.full((2,), W_BOUND, dtype=F64)
    return as_system(model, angle, X0, ds.Interval(-w, w),
                     ds.Interval([-V_BOUND], [V_BOUND]),
                     certificate=cert, samples=(X, Y), name="pendulum SCPLNN")


def make_filter(system: ds.System, y: torch.Tensor):
    """HSNSMF with its default remainder on the fitted model. Returns (filter, note)."""
    return ds.filters.HSNSMF(system), "HSNSMF (default remainder)"


def run(trials: int = 100, steps: int = 100, samples: int = 20_000, eps: float = 0.004,
        seed: int = 0) -> dict:
    """Fit, build the certified system, audit HSNSMF on the true pendulum (vertex noise)."""
    t0 = time.perf_counter()
    model, report, cert, X, Y = fit(samples, eps, seed)
    fit_s = time.perf_counter() - t0
    system = model_system(model, cert, X, Y)
    truth = true_system()
    traj = truth.simulate(steps=steps, batch=trials, seed=seed, noise="vertex")
    filt, note = make_filter(system, traj.y)
    audit = containment(filt, truth, trials=trials, steps=steps, noise="vertex", seed=seed)
    with torch.no_grad():
        res = filt(traj.y[:1])
    inside = bool(((traj.x >= DOMAIN[0]) & (traj.x <= DOMAIN[1])).all())
    return dict(model=model, report=report, certificate=cert, system=system, truth=truth,
                traj=traj, filter=filt, note=note, audit=audit, first=res, fit_seconds=fit_s,
                states_in_domain=inside)


def figure(out: dict, path: str | Path, every: int = 5) -> None:
    """Phase plane of the first trajectory (sets every ``every`` steps, true states) and the
    angle over time with the sets' bounds."""
    traj, res = out["traj"], out["first"]
    x = traj.x[0]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.5))
    T = x.shape[0] - 1
    for k in range(1, T + 1, every):
        plot_set(ax, res.sets[0, k], fill=False, edgecolor="tab:blue", lw=0.8,
                 label=f"HSNSMF set (every {every} steps)" if k == 1 else None)
    ax.plot(x[:, 0], x[:, 1], ".-", color="k", ms=2.5, lw=0.6, label="true state")
    ax.set_xlabel("theta [rad]")
    ax.set_ylabel("omega [rad/s]")
    ax.set_title(f"Pendulum, SCPLNN model ({out['model'].n_regions} regions): sets and true "
                 "states", fontsize=9)
    ax.legend(fontsize=8, loc="upper right")
    box = res.sets[0].interval_hull()
    t = torch.arange(T + 1) * DT
    bx.fill_between(t, box.lower[:, 0], box.upper[:, 0], color="tab:blue", alpha=0.3,
                    label="set bounds on theta")
    bx.plot(t, x[:, 0], color="k", lw=0.8, label="true theta")
    bx.plot(t[1:], traj.y[0, :, 0], "x", color="tab:red", ms=2.5, label="measurement")
    bx.set_xlabel("t [s]")
    bx.set_ylabel("theta [rad]")
    bx.legend(fontsize=8)
    a = out["audit"]
    bx.set_title(f"{a.violations}/{a.pairs} pairs outside, mean area {a.mean_volume:.3g}",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--trials", type=int, default=100)
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--samples", type=int, default=20_000)
    p.add_argument("--eps", type=float, default=0.004)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="docs/figures/pendulum_scplnn.png")
    a = p.parse_args()
    out = run(a.trials, a.steps, a.samples, a.eps, a.seed)
    print(out["report"].summary())
    print(f"fit + certificate: {out['fit_seconds']:.2f} s; certified error per output "
          f"{out['certificate'].bound.tolist()}")
    print(out["note"])
    print(out["audit"])
    print(f"true states inside the model's domain: {out['states_in_domain']}")
    print(f"mean set area (steps 1..T): {out['audit'].mean_volume:.4g}")
    figure(out, a.out)
    print(f"figure: {a.out}")


if __name__ == "__main__":
    main()
