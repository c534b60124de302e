"""The example scripts that run in seconds, imported from examples/ and run small."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_czsmf_example_runs_contains_and_plots(tmp_path):
    ex = _load("czsmf_spring_damper")
    traj, out = ex.run(steps=4, trials=2, seed=3)
    assert set(out) == set(ex.FILTERS)
    for name, r in out.items():
        assert r["contained"], name
        a = r["area"][:, 1:]
        assert torch.isfinite(a).all() and (a > 0).all(), name
    for name in ("CZSMF default caps", "CZSMF (30, 5, propagation)"):
        # the 64 directions include the 4 axes, so the outer polygon lies in the hull box
        hull = out[name]["result"].volume
        assert (out[name]["area"] <= hull * (1 + 1e-12)).all(), name
    path = tmp_path / "cz.png"
    ex.figure(traj, out, path, (2, 4))
    assert path.stat().st_size > 10_000
