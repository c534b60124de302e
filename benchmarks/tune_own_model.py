"""``diffsmf tune --model ... --data ...`` on a user's model file and CSV logs, audited.

A pendulum (explicit Euler, one input, the sine of the angle measured) is written to a model
file whose bounds are a guess ``--guess`` times the true ones; ``--runs`` logs of ``--steps``
steps are simulated with the true bounds (uniform or vertex noise) and written as CSV files.
``diffsmf tune`` runs on the first logs (in-process, as on the command line) and writes
``bounds.json``; then

* the written bounds / the true ones (the target: within 1.5x from a 5x guess),
* ``diffsmf filter --bounds`` on every held-out log: its exit status, and the true states
  against the bounds it wrote (``bounds.csv``),
* the exact containment (``sets.contains``) of the held-out true states in HSNSMF's sets with
  the written bounds, and the same with the true bounds (how much the margin costs in area).

No other tool tunes set-membership noise bounds from logs, so there is no peer column; the
true bounds are the reference.

    python benchmarks/tune_own_model.py [--seeds 3] [--runs 12] [--held 4] [--steps 60]
                                        [--epochs 30] [--guess 5]
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import json
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np
import torch

import diffsmf as ds
from diffsmf.cli import main as cli
from diffsmf.tuning import bound_sets, read_bounds

MODEL = textwrap.dedent(
    """
    import torch
    import diffsmf as ds

    DT = 0.05
    F64 = torch.float64

    def f(x, u, theta=None):
        th, om = x[..., 0], x[..., 1]
        return torch.stack([th + DT * om,
                            om + DT * (-9.81 * torch.sin(th) - 0.3 * om + u[..., 0])], -1)

    def h(x):
        return torch.sin(x[..., :1])

    def make_system(scale=1.0):
        X0 = ds.Interval(torch.tensor([0.3, -0.2], dtype=F64),
                         torch.tensor([0.5, 0.2], dtype=F64))
        w = scale * torch.tensor([1e-3, 2e-3], dtype=F64)
        v = scale * torch.tensor([0.01], dtype=F64)
        return ds.System(f, h, X0, ds.Interval(-w, w), ds.Interval(-v, v), n_inputs=1,
                         name="pendulum")

    def make_guess():
        return make_system(GUESS)
    """
)
TRUE = torch.tensor([1e-3, 2e-3, 1e-2], dtype=torch.float64)


def _write_logs(folder: Path, tr, runs: int) -> list[str]:
    files = []
    for r in range(runs):
        path = folder / f"run{r}.csv"
        with path.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["time", "u", "y"])
            for k in range(tr.y.shape[1]):
                w.writerow([f"{0.05 * (k + 1):.2f}", repr(float(tr.u[r, k, 0])),
                            repr(float(tr.y[r, k, 0]))])
        files.append(str(path))
    return files


def one_row(noise: str, seed: int, a: argparse.Namespace) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        (d / "pendulum.py").write_text(MODEL.replace("GUESS", repr(float(a.guess))))
        ns: dict = {}
        exec(MODEL.replace("GUESS", "1.0"), ns)  # noqa: S102 - this script's own model text
        system = ns["make_system"]()
        phase = torch.linspace(0, 6, a.runs, dtype=torch.float64).reshape(a.runs, 1)
        u = (0.5 * torch.sin(0.2 * torch.arange(a.steps, dtype=torch.float64) + phase))
        tr = system.simulate(a.steps, batch=a.runs, seed=seed, noise=noise, u=u.unsqueeze(-1))
        files = _write_logs(d, tr, a.runs)
        train, held = files[: a.runs - a.held], list(range(a.runs - a.held, a.runs))
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()):  # the command's own summary
            rc = cli(["tune", "--model", f"{d}/pendulum.py:make_guess", "--data", *train,
                      "--outputs", "y", "--inputs", "u", "--params",
                      "process_noise,measurement_noise", "--epochs", str(a.epochs),
                      "--window", "10", "--lr", "0.2", "--seed", str(seed), "--out",
                      str(d / "tuned"), "--no-progress"])
        seconds = time.perf_counter() - t0
        assert rc == 0
        doc = json.loads((d / "tuned" / "bounds.json").read_text())
        half = read_bounds(d / "tuned" / "bounds.json", 2, 1)
        ratio = torch.cat([half["process_noise"], half["measurement_noise"]]) / TRUE
        tuned = torch.tensor(doc["tuned"]["measurement_noise"]) / TRUE[2]
        cli_ok, cli_out = 0, 0
        for r in held:
            rc = cli(["filter", "--model", f"{d}/pendulum.py:make_guess", "--data", files[r],
                      "--outputs", "y", "--inputs", "u", "--bounds",
                      str(d / "tuned" / "bounds.json"), "--out", str(d / f"f{r}"),
                      "--quiet", "--no-figure"])
            cli_ok += rc == 0
            b = np.genfromtxt(d / f"f{r}" / "bounds.csv", delimiter=",", names=True)
            x = tr.x[r].numpy()
            for i in range(2):
                cli_out += int(((x[:, i] < b[f"lower_{i}"]) | (x[:, i] > b[f"upper_{i}"])).sum())
        sets = bound_sets(d / "tuned" / "bounds.json")
        mine = ds.System(system.f, system.h, system.x0_set, sets["process_noise"],
                         sets["measurement_noise"], n_inputs=1)
        with torch.no_grad():
            res = ds.filters.HSNSMF(mine)(tr.y[held], u=tr.u[held])
            ref = ds.filters.HSNSMF(system)(tr.y[held], u=tr.u[held])
        return {
            "noise": noise, "seed": seed, "seconds": seconds,
            "tuned": float(tuned), "scale": float(doc.get("consistency_scale", 1.0)),
            "written": float(ratio.max()), "written_min": float(ratio.min()),
            "cli_ok": cli_ok, "cli_out": cli_out, "held": len(held),
            "outside": int((~res.sets.contains(tr.x[held])).sum()),
            "pairs": int(tr.x[held].shape[0] * tr.x[held].shape[1]),
            "area_ratio": float(res.volume[:, 1:].mean() / ref.volume[:, 1:].mean()),
        }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--runs", type=int, default=12)
    ap.add_argument("--held", type=int, default=4)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--epochs", type=int, default=30)
    ap.add_argument("--guess", type=float, default=5.0)
    a = ap.parse_args()
    torch.set_num_threads(1)
    print(f"pendulum, guess {a.guess:g} x the true bounds, {a.runs - a.held} logs tuned, "
          f"{a.held} held out, {a.steps} steps; torch threads: {torch.get_num_threads()}")
    print("| noise | seed | tuned / true | consistency scale | written / true | diffsmf filter "
          "exit 0 | true states outside its bounds | outside the sets (exact) | area vs true "
          "bounds | tune time |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for noise in ("uniform", "vertex"):
        for seed in range(a.seeds):
            r = one_row(noise, seed, a)
            print(f"| {r['noise']} | {r['seed']} | {r['tuned']:.3f} | {r['scale']:.3f} | "
                  f"{r['written_min']:.3f}-{r['written']:.3f} | {r['cli_ok']} of {r['held']} | "
                  f"{r['cli_out']} | {r['outside']} of {r['pairs']} | {r['area_ratio']:.3f}x | "
                  f"{r['seconds']:.1f} s |", flush=True)


if __name__ == "__main__":
    main()
