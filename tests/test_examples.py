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


def test_learning_a_network_through_the_filter_fits_and_plots(tmp_path):
    ex = _load("learn_model_through_filter")
    out = ex.run(epochs=4, runs=6, steps=10, progress=False)
    hist = out["history"]
    assert len(hist) == 4 and all(torch.isfinite(torch.tensor(r["loss"])) for r in hist)
    assert hist[-1]["prediction"] < hist[0]["prediction"]  # the network moved towards the data
    assert {"area", "consistent", "inside"} <= set(out["after"])
    path = tmp_path / "learned.png"
    ex.figure(out, path)
    assert path.stat().st_size > 10_000


def test_cora_observers_example_compares_and_matches_cora(tmp_path):
    ex = _load("cora_observers")
    cmp = ex.compare(["FRad-A", "VolMin-B", "ESO-B"])
    assert [r["filter"] for r in cmp.rows] == ["FRad-A", "VolMin-B", "ESO-B"]
    assert all(r["error"] is None and r["bounded"] == r["pairs"] for r in cmp.rows)
    cmp.figure(tmp_path / "c.png")
    hull = ex.frad_a_as_cora()
    width = float((hull.upper - hull.lower).sum())
    cora = sum(h - lo for lo, h in zip(*ex.CORA_FRAD_A))
    assert abs(width / cora - 1) < 0.05
