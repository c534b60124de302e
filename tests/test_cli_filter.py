"""``diffsmf filter``: a user's model file and logged data -> bounds.csv / .npz, bounds.png,
summary.json; the bounds equal the batched filter's and contain the simulated truth."""

from __future__ import annotations

import csv
import json
import textwrap

import numpy as np
import pytest
import torch

import diffsmf as ds
from diffsmf.cli import main
from diffsmf.cli.filter import load_model

T = 8

MODEL = textwrap.dedent(
    """
    import torch
    import diffsmf as ds

    def f(x, u, theta=None):
        x1, x2 = x[..., 0], x[..., 1]
        return torch.stack([x1 + 0.1 * x2, 0.95 * x2 - 0.1 * torch.sin(x1) + 0.1 * u[..., 0]], -1)

    def h(x):
        return x[..., :1] + 0.1 * x[..., 1:] ** 2

    def make_system():
        X0 = ds.Interval([0.4, -0.1], [0.6, 0.1])
        W = ds.Interval([-1e-3, -1e-3], [1e-3, 1e-3])
        V = ds.Interval([-1e-2], [1e-2])
        return ds.System(f, h, X0, W, V, n_inputs=1, name="toy")

    def make_scheduled():
        s = make_system()
        return ds.System(s.f, s.h, s.x0_set, s.process_noise, s.measurement_noise,
                         inputs=lambda k: torch.tensor([0.5]), name="toy_sched")

    def make_autonomous():
        s = make_system()
        return ds.System(lambda x, u, th=None: s.f(x, torch.zeros_like(x[..., :1])), s.h,
                         s.x0_set, s.process_noise, s.measurement_noise, name="toy_auto")

    def not_a_system():
        return 42

    def make_diverging():
        # x1 unmeasured, 0.5 x1 - 0.1 x1^3: from |x1| <= 4 every linearising filter's set
        # diverges (the exact image of [-4, 4] is [-4.4, 4.4]); the truth is stable near 0
        def f(x, u=None, theta=None):
            return torch.stack([0.5 * x[..., 0] - 0.1 * x[..., 0] ** 3, 0.5 * x[..., 1]], -1)

        return ds.System(f, lambda x: x[..., 1:2], ds.Interval([-4.0, -0.2], [4.0, 0.2]),
                         ds.Interval([-1e-3, -1e-3], [1e-3, 1e-3]), ds.Interval([-0.5], [0.5]),
                         name="diverging")

    def make_branchy():
        s = make_system()
        return ds.System(lambda x, u, th=None: s.f(x, u) if float(x.sum()) > 0 else -s.f(x, u), s.h,
                         s.x0_set, s.process_noise, s.measurement_noise, n_inputs=1,
                         name="branchy")
    """
)


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    d = tmp_path_factory.mktemp("filter_cli")
    model = d / "my_model.py"
    model.write_text(MODEL)
    system = load_model(f"{model}:make_system")
    U = 0.5 * torch.cos(torch.arange(T, dtype=torch.float64)).reshape(1, T, 1)
    traj = system.simulate(T, batch=1, seed=3, noise="vertex", u=U)
    log = d / "log.csv"
    with log.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["time", "u1", "y1", "note"])
        for k in range(T):
            w.writerow([f"{k * 0.1:.1f}", repr(float(U[0, k, 0])), repr(float(traj.y[0, k, 0])),
                        "ok"])
    return d, model, log, system, traj


def _run(*argv: str) -> int:
    return main(["filter", *argv, "--quiet"])


def _read_bounds(path):
    with path.open() as fh:
        rows = list(csv.reader(fh))
    return rows[0], np.array(rows[1:], dtype=float)


def test_csv_run_writes_bounds_figure_and_summary(case):
    d, model, log, system, traj = case
    out = d / "run"  # does not exist yet: created
    rc = _run("--model", f"{model}:make_system", "--data", str(log), "--outputs", "y1",
              "--inputs", "u1", "--filter", "hsnsmf", "--out", str(out))
    assert rc == 0
    head, b = _read_bounds(out / "bounds.csv")
    assert head == ["step", "lower_0", "lower_1", "upper_0", "upper_1", "consistent", "bounded"]
    assert b.shape == (T + 1, 7)
    assert (b[:, 6] == 1).all()
    np.testing.assert_array_equal(b[:, 0], np.arange(T + 1))
    x = traj.x[0].numpy()
    assert (b[:, 1:3] <= x).all() and (x <= b[:, 3:5]).all()  # guaranteed: contains the truth
    assert (b[:, 5] == 1).all()
    hull0 = system.x0_set.interval_hull()  # row 0: the initial set (outward-rounded hull)
    np.testing.assert_allclose(b[0, 1:3], hull0.lower.numpy(), rtol=0, atol=1e-12)
    assert (b[0, 1:3] <= hull0.lower.numpy()).all() and (b[0, 3:5] >= hull0.upper.numpy()).all()
    # the online loop of the CLI is the filter's forward, bit for bit (17 digits in the CSV)
    with torch.no_grad():
        res = ds.filters.HSNSMF(system)(traj.y, u=traj.u)
    np.testing.assert_array_equal(b[:, 1:3], res.lower[0].numpy())
    np.testing.assert_array_equal(b[:, 3:5], res.upper[0].numpy())
    s = json.loads((out / "summary.json").read_text())
    assert s["filter"] == "HSNSMF" and s["guaranteed"] is True
    assert s["steps"] == T and s["inconsistent_steps"] == [] and s["seconds"] > 0
    assert s["unbounded_steps"] == []
    assert s["outputs"] == ["y1"] and s["inputs"] == ["u1"]
    assert s["settings"]["measurement_noise"] == pytest.approx([1e-2])
    assert (out / "bounds.png").stat().st_size > 10_000


def test_npz_output_npy_and_npz_input_and_noise_override(case):
    d, model, log, system, traj = case
    y, u = traj.y[0].numpy(), traj.u[0].numpy()
    np.savez(d / "log.npz", y=y, u=u)
    np.save(d / "log.npy", np.concatenate([u, y], 1))
    outs = []
    for data, cols in ((d / "log.npz", ("y", "u")), (d / "log.npy", ("1", "0"))):
        out = d / f"run_{data.suffix[1:]}"
        rc = _run("--model", f"{model}:make_system", "--data", str(data), "--outputs", cols[0],
                  "--inputs", cols[1], "--filter", "cdsmf", "--out", str(out), "--format", "npz",
                  "--no-figure")
        assert rc == 0
        z = np.load(out / "bounds.npz")
        assert z["lower"].shape == (T + 1, 2) and z["consistent"].dtype == bool
        assert not (out / "bounds.png").exists()
        outs.append(z["upper"] - z["lower"])
    np.testing.assert_array_equal(outs[0], outs[1])
    # larger measurement-noise bound -> wider (or equal) sets, recorded in the summary
    out = d / "run_wide"
    assert _run("--model", f"{model}:make_system", "--data", str(d / "log.npz"), "--outputs",
                "y", "--inputs", "u", "--filter", "cdsmf", "--out", str(out), "--format", "npz",
                "--no-figure", "--measurement-noise", "0.05") == 0
    z = np.load(out / "bounds.npz")
    assert ((z["upper"] - z["lower"])[1:] >= outs[0][1:] - 1e-12).all()
    assert (z["upper"] - z["lower"])[-1].sum() > outs[0][-1].sum()
    s = json.loads((out / "summary.json").read_text())
    assert s["settings"]["measurement_noise"] == pytest.approx([0.05])


def test_schedule_inputs_skip_missing_and_ekf_not_guaranteed(case, capsys):
    d, model, log, system, traj = case
    # the model's own schedule supplies u when --inputs is left out
    out = d / "run_sched"
    # (exit 1: the log was driven by other inputs, so some measurements are inconsistent)
    assert _run("--model", f"{model}:make_scheduled", "--data", str(log), "--outputs", "y1",
                "--out", str(out), "--no-figure") in (0, 1)
    s = json.loads((out / "summary.json").read_text())
    assert s["inputs"] == "schedule" and s["exit_status"] == (1 if s["inconsistent_steps"] else 0)
    # a blank measurement: error by default, skipped update with --skip-missing
    text = log.read_text().splitlines()
    cells = text[3].split(",")
    cells[2] = ""
    text[3] = ",".join(cells)
    holes = d / "holes.csv"
    holes.write_text("\n".join(text) + "\n")
    out = d / "run_holes"
    assert main(["filter", "--model", f"{model}:make_system", "--data", str(holes), "--outputs",
                 "y1", "--inputs", "u1", "--out", str(out), "--skip-missing", "--filter", "ekf"]
                ) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["skipped_updates"] == [3] and s["guaranteed"] is False
    assert "not a guaranteed filter" in capsys.readouterr().out


def _error(capsys, *argv: str) -> str:
    rc = main(["filter", *argv, "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("diffsmf filter: error: ")
    assert "Traceback" not in err
    return lines[0]


@pytest.mark.parametrize(
    "data, outputs, inputs, expect",
    [
        ("missing.csv", "y1", "u1", ["--data", "missing.csv"]),
        ("log.csv", "y9", "u1", ["--outputs", "'y9'", "columns there"]),
        ("log.csv", "y1", "u7", ["--inputs", "'u7'"]),
        ("log.csv", "y1,u1", "u1", ["--outputs", "2 measurement", "h(x) has 1"]),
        ("text.csv", "y1", "u1", ["--data", "line 3", "'y1'", "'abc' is not a number"]),
        ("blank.csv", "y1", "u1", ["--data", "line 2", "'u1'", "blank"]),
        ("header.csv", "y1", "u1", ["--data", "header but no data rows"]),
        ("empty.csv", "y1", "u1", ["--data", "is empty"]),
        ("ragged.csv", "y1", "u1", ["--data", "line 3 has 1 cells"]),
        ("inf.csv", "y1", "u1", ["--data", "line 2", "finite"]),
        ("log.csv", "y1", None, ["--inputs", "n_inputs=1", "no inputs schedule"]),
        ("log.npy", "y1", "u1", ["--outputs", "'y1'", "columns there: ['0', '1']"]),
        ("bad.npz", "y1", "u1", ["--data", "cannot read"]),
    ],
)
def test_data_errors_are_one_line(case, capsys, data, outputs, inputs, expect):
    d, model, *_ = case
    (d / "text.csv").write_text("u1,y1\n0.1,0.2\n0.1,abc\n")
    (d / "blank.csv").write_text("u1,y1\n,0.2\n")
    (d / "header.csv").write_text("u1,y1\n")
    (d / "empty.csv").write_text("")
    (d / "ragged.csv").write_text("u1,y1\n0.1,0.2\n0.3\n")
    (d / "inf.csv").write_text("u1,y1\n0.1,inf\n")
    (d / "bad.npz").write_text("not a zip")
    np.save(d / "log.npy", np.zeros((T, 2)))
    argv = ["--model", f"{model}:make_system", "--data", str(d / data), "--outputs", outputs,
            "--out", str(d / "err")]
    if inputs:
        argv += ["--inputs", inputs]
    line = _error(capsys, *argv)
    for piece in expect:
        assert piece in line, line


@pytest.mark.parametrize(
    "spec, expect",
    [
        ("{d}/my_model.py", ["--model", "FILE.py:FUNCTION"]),
        ("{d}/nope.py:make_system", ["--model", "no such model file", "nope.py"]),
        ("{d}/my_model.py:make_sytem", ["--model", "no function 'make_sytem'", "make_system"]),
        ("{d}/my_model.py:not_a_system", ["--model", "must return a diffsmf.System", "int"]),
        ("{d}/broken.py:make_system", ["--model", "importing", "NameError"]),
        ("{d}/log.csv:make_system", ["--model", "not a Python file"]),
        ("{d}/my_model.py:make_autonomous", ["--inputs", "has no inputs"]),
        ("{d}/my_model.py:make_branchy", ["f:", "reads a value of the state in Python"]),
        ("{d}/dynamics.py:f", ["--model", "f must take no arguments", "takes x, u",
                               "make_system()"]),
    ],
)
def test_model_errors_are_one_line(case, capsys, spec, expect):
    d, model, log, *_ = case
    (d / "broken.py").write_text("x = undefined_name\n")
    (d / "dynamics.py").write_text("def f(x, u, theta=None):\n    return x\n")
    line = _error(capsys, "--model", spec.format(d=d), "--data", str(log), "--outputs", "y1",
                  "--inputs", "u1", "--out", str(d / "err"))
    for piece in expect:
        assert piece in line, line


def test_option_errors_are_one_line(case, capsys):
    d, model, log, *_ = case
    base = ["--model", f"{model}:make_system", "--data", str(log), "--outputs", "y1",
            "--inputs", "u1"]
    (d / "a_file").write_text("x")
    assert "--out" in _error(capsys, *base, "--out", str(d / "a_file"))
    assert "--filter: unknown filter 'kalman'" in _error(capsys, *base, "--filter", "kalman")
    assert "--process-noise" in _error(capsys, *base, "--process-noise", "0.1,0.2,0.3")
    assert "--measurement-noise" in _error(capsys, *base, "--measurement-noise", "-1")
    assert "--format" in _error(capsys, *base, "--format", "xlsx")
    assert "--process-noise: the CombinedFilter filter does not take" in _error(
        capsys, *base, "--filter", "combined", "--process-noise", "0.01")
    assert "--outputs" in _error(capsys, "--model", f"{model}:make_system", "--data", str(log))


def test_load_model_returns_the_system(case):
    d, model, *_ = case
    s = load_model(f"{model}:make_system")
    assert isinstance(s, ds.System) and s.n == 2 and s.m == 1 and s.n_inputs == 1


# ------------------------------------------------------------------ a lost guarantee
@pytest.fixture(scope="module")
def diverging(case):
    d, model, *_ = case
    s = load_model(f"{model}:make_diverging")
    small = ds.System(s.f, s.h, ds.Interval([-1.0, -0.2], [1.0, 0.2]), s.process_noise,
                      s.measurement_noise)
    traj = small.simulate(12, batch=1, seed=0)  # true states from |x1| <= 1: in s's X0
    log = d / "diverging.csv"
    np.savetxt(log, traj.y[0].numpy(), delimiter=",", header="y", comments="")
    return d, model, log, traj


@pytest.mark.parametrize("name", ["hsnsmf", "mszm", "cdsmf", "esmf", "czsmf", "combined",
                                  "interval"])
def test_unbounded_steps_are_inf_never_a_finite_placeholder(diverging, capsys, name):
    d, model, log, traj = diverging
    out = d / f"div_{name}"
    rc = _run("--model", f"{model}:make_diverging", "--data", str(log), "--outputs", "y",
              "--filter", name, "--out", str(out), "--no-figure")
    assert rc == 3  # the guarantee was lost
    err = capsys.readouterr().err
    assert "warning: the guarantee was lost at step" in err  # said even with --quiet
    head, b = _read_bounds(out / "bounds.csv")
    assert head[-1] == "bounded"
    unb = b[:, -1] == 0
    assert unb.any() and unb[-1]
    lo, up = b[:, 1:3], b[:, 3:5]
    assert np.isneginf(lo[unb]).all() and np.isposinf(up[unb]).all()
    assert np.isfinite(lo[~unb]).all()
    x = traj.x[0].numpy()
    assert ((lo <= x) & (x <= up)).all()  # no finite bound misses the truth
    assert (b[unb, 5] == 1).all()  # never inconsistent against an unbounded set
    s = json.loads((out / "summary.json").read_text())
    k = int(np.flatnonzero(unb)[0])
    assert s["bounded"] is False and s["guarantee_lost_at_step"] == k
    assert s["unbounded_steps"][0] == k and s["exit_status"] == 3
    assert s["events"] and s["events"][0].startswith(f"trajectory 0, step {k}: ")


def test_figure_marks_lost_guarantee_and_state_names(diverging, capsys):
    d, model, log, traj = diverging
    out = d / "div_names"
    rc = _run("--model", f"{model}:make_diverging", "--data", str(log), "--outputs", "y",
              "--out", str(out), "--state-names", "conc,temp", "--format", "csv")
    assert rc == 3
    head, _ = _read_bounds(out / "bounds.csv")
    assert head[1:5] == ["lower_conc", "lower_temp", "upper_conc", "upper_temp"]
    assert json.loads((out / "summary.json").read_text())["state_names"] == ["conc", "temp"]
    assert (out / "bounds.png").stat().st_size > 10_000
    from diffsmf.plot import bounds_figure

    lo = np.array([[0.0, 1.0], [-np.inf, -np.inf]])
    fig = bounds_figure(lo, -lo + 1, state_names=["conc", "temp"], bounded=[True, False])
    labels = {a.get_ylabel() for a in fig.axes}
    assert {"conc", "temp"} <= labels
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert any("guarantee lost from step 1" in t for t in legend)
    capsys.readouterr()
    bad = _error(capsys, "--model", f"{model}:make_diverging", "--data", str(log), "--outputs",
                 "y", "--out", str(out), "--state-names", "a")
    assert "--state-names: expected 2 names" in bad


def test_inconsistent_steps_warn_with_quiet_and_exit_1(case, capsys):
    d, model, log, system, traj = case
    out = d / "run_incons"
    rc = _run("--model", f"{model}:make_system", "--data", str(log), "--outputs", "y1",
              "--inputs", "u1", "--out", str(out), "--no-figure", "--measurement-noise", "1e-9")
    err = capsys.readouterr().err
    s = json.loads((out / "summary.json").read_text())
    assert s["inconsistent_steps"]
    assert rc == 1 and s["exit_status"] == 1
    assert "warning:" in err and "inconsistent step(s)" in err


def test_a_numerical_failure_is_not_a_user_error(case, capsys, monkeypatch):
    d, model, log, *_ = case

    def boom(self, state, u=None):
        raise RuntimeError("linalg: the algorithm failed to converge")

    monkeypatch.setattr(ds.filters.HSNSMF, "predict", boom)
    rc = main(["filter", "--model", f"{model}:make_system", "--data", str(log), "--outputs",
               "y1", "--inputs", "u1", "--out", str(d / "boom"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 4 and len(err) == 1
    assert err[0].startswith("diffsmf filter: numerical failure at step 1: RuntimeError")
    assert "error:" not in err[0] and "Traceback" not in err[0]
