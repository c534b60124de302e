"""``diffsmf design-observer --model FILE.py:FUNC``: any ContinuousModel, one-line
user errors with exit status 2, defaults in --help; ContinuousModel checks and the interval
Hessian bound."""

import json
import textwrap

import numpy as np
import pytest
import torch

from diffsmf.cli import main
from diffsmf.cli.observer import load_observer_model
from diffsmf.observers import ContinuousModel
from diffsmf.observers.pipeline import certified_error, fit_nonlinearity, interval_hess_bound

MODEL = textwrap.dedent('''
    import numpy as np
    import torch
    from diffsmf.observers import ContinuousModel


    def make_model():
        """Duffing oscillator x1' = x2, x2' = -x1 - 0.5 x2 - 0.3 x1^3 + u, y = x1."""
        return ContinuousModel(
            name="duffing", A=np.array([[0.0, 1.0], [-1.0, -0.5]]), B=np.array([[0.0], [1.0]]),
            C=np.array([[1.0, 0.0]]), B_f=np.array([[0.0], [1.0]]), H=np.array([[1.0, 0.0]]),
            phi=lambda z: -0.3 * z**3, hess_bound=None,
            lower=np.array([-2.0]), upper=np.array([2.0]),
            x0=np.array([1.0, 0.0]), xhat0=np.array([0.0, 0.0]),
            u=lambda t: 0.5 * torch.sin(t).reshape(1))


    def not_a_model():
        return 42


    def broken():
        raise RuntimeError("boom")


    def bad_shape():
        m = make_model()
        return ContinuousModel(**{**m.__dict__, "C": np.ones((1, 3))})
''')


@pytest.fixture
def model_file(tmp_path):
    path = tmp_path / "my_model.py"
    path.write_text(MODEL)
    return path


def test_design_observer_with_user_model(model_file, tmp_path, capsys):
    out = tmp_path / "run"
    rc = main(["design-observer", "--model", f"{model_file}:make_model", "--eps", "0.1",
               "--T", "4", "--dt", "0.01", "--seed", "3", "--quiet", "--out", str(out)])
    assert rc == 0
    assert capsys.readouterr().out == ""  # --quiet: nothing on stdout
    s = json.loads((out / "summary.json").read_text())
    assert s["system"] == "duffing" and s["status"] == "verified" and s["settings"]["seed"] == 3
    assert s["fit"]["certified_error"] <= 0.1 and s["bound"] > 0
    c = s["checks"]  # the certified bound holds in simulation (on this model too)
    assert c["state_in_domain"] and c["within_envelope"] and c["within_bound_after"]
    assert c["max_model_error"] <= s["fit"]["certified_error"]
    assert (out / "observer_duffing.png").stat().st_size > 0


@pytest.mark.parametrize("spec,words", [
    ("{dir}/missing.py:make_model", ["missing.py"]),
    ("{file}", ["FILE.py:FUNC"]),
    ("{file}:nope", ["nope", "make_model"]),
    ("{file}:not_a_model", ["ContinuousModel", "int"]),
    ("{file}:broken", ["broken", "boom"]),
    ("{file}:bad_shape", ["ContinuousModel.C"]),
])
def test_model_errors_are_one_line_exit_2(model_file, tmp_path, capsys, spec, words):
    spec = spec.format(dir=tmp_path, file=model_file)
    rc = main(["design-observer", "--model", spec, "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and "--model" in err
    for w in words:
        assert w in err
    with pytest.raises((ValueError, FileNotFoundError)):  # what the module raises itself
        load_observer_model(spec)


@pytest.mark.parametrize("argv,word", [
    (["--system", "pendulum"], "pendulum"),
    (["--eps", "-1"], "--eps"),
    (["--dt", "5", "--T", "1"], "--dt"),
    (["--samples", "0"], "--samples"),
    (["--system", "vdp", "--model", "x.py:f"], "--model"),
])
def test_bad_options_are_one_line_exit_2(tmp_path, capsys, argv, word):
    rc = main(["design-observer", *argv, "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert word in err


def test_help_shows_defaults_seed_quiet_and_the_model_contract(capsys):
    assert main(["design-observer", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    for text in ("--model FILE.py:FUNC", "ContinuousModel", "--seed", "--quiet",
                 "(default: 0.05)", "(default: 4000)", "(default: out/design-observer)"):
        assert text in out


def test_continuous_model_checks_name_the_field(model_file):
    m = load_observer_model(f"{model_file}:make_model")
    fields = dict(m.__dict__)
    for name, value in [("A", np.ones((2, 3))), ("B", np.ones((3, 1))), ("B_f", np.ones(2)),
                        ("H", np.ones((1, 3))), ("lower", np.array([3.0])),
                        ("x0", np.array([np.nan, 0.0])), ("phi", 3.0), ("hess_bound", "x")]:
        with pytest.raises(ValueError, match=rf"ContinuousModel\.{name}\b"):
            ContinuousModel(**{**fields, name: value})


def test_interval_hessian_bound_is_certified():
    """hess_bound=None: interval arithmetic bounds |Hess phi|_2 on each simplex, checked against
    autograd Hessians at random points of the simplices; the certified eps then bounds dense
    samples of |phi - f̂|."""
    def phi(x):
        return torch.stack([torch.sin(x[..., 0]) * x[..., 1], torch.tanh(x[..., 1]) * x[..., 0]],
                           -1)

    hb = interval_hess_bound(phi)
    g = torch.Generator().manual_seed(0)
    V = torch.rand(40, 3, 2, generator=g, dtype=torch.float64) * 4 - 2  # 40 random triangles
    bound = hb(V)  # [40, 2]
    w = torch.distributions.Dirichlet(torch.ones(3, dtype=torch.float64)).sample((40, 25))
    X = torch.einsum("msk,mkd->msd", w, V)  # 25 points in each triangle
    for i in range(2):
        Hs = torch.func.vmap(torch.func.hessian(lambda x, i=i: phi(x)[i]))(X.reshape(-1, 2))
        norms = torch.linalg.matrix_norm(Hs, ord=2).reshape(40, 25)
        assert torch.all(norms <= bound[:, i, None])
    m = ContinuousModel(
        name="t", A=-np.eye(2), B=np.zeros((2, 0)), C=np.array([[1.0, 0.0]]), B_f=np.eye(2),
        H=np.eye(2), phi=phi, hess_bound=None, lower=-np.ones(2), upper=np.ones(2),
        x0=np.zeros(2), xhat0=np.zeros(2), u=lambda t: torch.zeros(0, dtype=torch.float64))
    model, info = fit_nonlinearity(m, 0.2, method="grid")
    Xs = torch.rand(20000, 2, generator=g, dtype=torch.float64) * 2 - 1
    with torch.no_grad():
        sampled = float((phi(Xs) - model(Xs)).norm(dim=-1).max())
    assert sampled <= info["certified_error"] <= 0.2
    assert info["certified_error"] == pytest.approx(certified_error(model, phi, m.hess_bound))
