"""PWL bad input: degenerate and conflicting samples, model JSON validation, CLI user
errors. Each case asserts the error type and that the message names the argument."""

import json
import time
import warnings

import numpy as np
import pytest
import torch

from diffsmf.pwl import SCPLNN, fit_scplnn

F64 = torch.float64




def test_one_sample_and_copies_of_one_point_raise_naming_X():
    with pytest.raises(ValueError, match=r"^X: .*same point"):
        fit_scplnn(torch.tensor([[0.3, 0.4]], dtype=F64), torch.tensor([1.0]), 0.1)
    with pytest.raises(ValueError, match=r"^X: all 50 samples"):
        fit_scplnn(torch.full((50, 2), 0.7, dtype=F64), torch.ones(50, dtype=F64), 0.1)
    with pytest.raises(ValueError, match=r"^X: all 5 samples"):
        fit_scplnn(torch.ones(5, dtype=F64), torch.arange(5.0, dtype=F64), 0.1)  # 1-D X


def test_eps_that_is_not_a_number_is_named():
    """``eps="a"`` raised torch's raw ``TypeError: new(): invalid data type 'str'``."""
    X = torch.rand(40, 2, dtype=F64, generator=torch.Generator().manual_seed(0))
    y = X.sum(-1)
    for eps in ("a", None, [0.1, "b"], float("nan"), -0.1, [0.1, 0.2]):
        with pytest.raises(ValueError, match=r"^eps: expected a positive number or one per output"):
            fit_scplnn(X, y, eps)


def test_collinear_inputs_raise_or_warn_in_report():
    t = torch.linspace(0, 1, 200, dtype=F64)
    X = torch.stack([t, 1 - 2 * t], -1)
    with pytest.raises(ValueError, match=r"^X: .*1-dimensional affine subspace"):
        fit_scplnn(X, t ** 2, 0.01)
    Xc = torch.stack([t, torch.full_like(t, 3.0)], -1)  # a constant input
    with pytest.raises(ValueError, match=r"^X: "):
        fit_scplnn(Xc, t ** 2, 0.01)
    with pytest.warns(UserWarning, match="affine subspace"):
        model, rep = fit_scplnn(X, t ** 2, 0.01, degenerate="warn")
    assert any("affine subspace" in w for w in rep.warnings)
    assert "warning:" in rep.summary()
    with torch.no_grad():
        assert float((model(X)[:, 0] - t ** 2).abs().max()) < 0.01


def test_conflicting_duplicates_fast_and_flagged():
    torch.manual_seed(0)
    X = torch.randint(0, 5, (200, 2)).double()
    y = torch.randint(0, 5, (200,)).double()
    t0 = time.perf_counter()
    with pytest.warns(UserWarning, match="eps unreachable"):
        model, rep = fit_scplnn(X, y, eps=0.5)
    assert time.perf_counter() - t0 < 5
    assert not rep.converged and "unreachable" in rep.stop_reason
    assert any("conflicting" in w for w in rep.warnings)
    # the best possible at a repeated X is the mean of its Y: the model is within eps of it
    uniq, inv = torch.unique(X, dim=0, return_inverse=True)
    mean = torch.zeros(len(uniq), dtype=F64).index_add_(0, inv, y) / torch.bincount(inv)
    with torch.no_grad():
        assert float((model(uniq)[:, 0] - mean).abs().max()) < 0.5
    for rule in ("interior", "edge"):  # the older rules: no singular matrix, flagged too
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            _, r = fit_scplnn(X, y, eps=0.5, rule=rule)
        assert not r.converged and r.warnings


def test_consistent_duplicates_are_fine():
    X = torch.rand(300, 2, generator=torch.Generator().manual_seed(3), dtype=F64)
    X = torch.cat([X, X[:100]])  # exact copies with the same y
    y = X.sum(-1) ** 2
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model, rep = fit_scplnn(X, y, 0.01)
    assert rep.converged and not rep.warnings


def _json_model():
    X = torch.rand(400, 2, generator=torch.Generator().manual_seed(4), dtype=F64) * 2 - 1
    model, _ = fit_scplnn(X, (X ** 2).sum(-1), 0.1)
    return model.to_json()


def _bad(d, path, value):
    d = json.loads(json.dumps(d))
    obj = d
    for k in path[:-1]:
        obj = obj[k]
    obj[path[-1]] = value
    return d


@pytest.mark.parametrize("path,value,field", [
    (("domain", "upper"), [-5.0, -5.0], "domain"),         # upper < lower
    (("weights", 0, 0), float("nan"), "weights"),
    (("weights", 1, 0), "abc", "weights"),
    (("weights", 2, 0), None, "weights"),
    (("vertices", 0, 1), "x", "vertices"),
    (("simplices", 0, 0), 10 ** 6, "simplices"),
    (("simplices", 0, 0), 1.5, "simplices"),
    (("outside",), "wrap", "outside"),
    (("format",), "other", "format"),
    (("regions", 0, "b"), [123.0], "regions"),
])
def test_model_json_validated_on_load(path, value, field):
    d = _bad(_json_model(), path, value)
    with pytest.raises(ValueError, match=rf"^{field}:"):
        SCPLNN.from_json(d)
    if not (isinstance(value, float) and value != value):  # NaN is not valid JSON text
        with pytest.raises(ValueError, match=rf"^{field}:"):
            SCPLNN.from_json(json.dumps(d))


def test_model_json_truncated_and_valid(tmp_path):
    d = _json_model()
    text = json.dumps(d)
    with pytest.raises(ValueError, match=r"^data: not valid JSON"):
        SCPLNN.from_json(text[: len(text) // 2])
    p = tmp_path / "m.json"
    p.write_text(text[:-3])
    with pytest.raises(ValueError, match=r"^data: "):
        SCPLNN.from_json(p)
    with pytest.raises(FileNotFoundError):
        SCPLNN.from_json(tmp_path / "missing.json")
    m = SCPLNN.from_json(text)  # the intact model still loads
    assert m.n_regions == len(d["regions"])
    with pytest.raises(ValueError, match=r"^weight: "):
        SCPLNN(m.vertices, m.simplices, torch.full_like(m.weight.detach(), float("nan")))


# ---------------------------------------------------------------- CLI
def _run(argv, capsys):
    from diffsmf.cli import main

    capsys.readouterr()
    try:
        rc = main(argv)
    except SystemExit as exc:
        rc = exc.code
    return rc, capsys.readouterr().err.strip()


def _csv(tmp_path, text):
    p = tmp_path / "d.csv"
    p.write_text(text)
    return str(p)


@pytest.mark.parametrize("text,needle", [
    ("x1,x2,y\n0,0,1\n1,abc,2\n0,1,3\n", "'abc' is not a number"),
    ("x1,x2,y\n0,0,1\n1,,2\n0,1,3\n", "blank cell"),
    ("x1,x2,y\n", "no data rows"),
    ("", "empty"),
    ("x1,x2,y\n0,0,1\n1,2\n", "cells"),
])
def test_cli_bad_csv_one_line_exit_2(tmp_path, capsys, text, needle):
    rc, err = _run(["fit-pwl", _csv(tmp_path, text), "--inputs", "x1,x2", "--outputs", "y",
                    "--eps", "0.1"], capsys)
    assert rc == 2 and len(err.splitlines()) == 1 and "csv" in err and needle in err
    assert "Traceback" not in err


def test_cli_missing_out_folder_and_bad_eps(tmp_path, capsys):
    rng = np.random.default_rng(0)
    X = rng.uniform(-1, 1, size=(200, 2))
    body = "x1,x2,y\n" + "\n".join(f"{a},{b},{a * b}" for a, b in X)
    csv = _csv(tmp_path, body)
    rc, err = _run(["fit-pwl", csv, "--inputs", "x1,x2", "--outputs", "y", "--eps", "0.1",
                    "--out", str(tmp_path / "nope" / "m.json")], capsys)
    assert rc == 2 and "--out" in err and "does not exist" in err and len(err.splitlines()) == 1
    rc, err = _run(["fit-pwl", csv, "--inputs", "x1,x2", "--outputs", "y", "--eps", "a,b"],
                   capsys)
    assert rc == 2 and "--eps" in err
    rc, err = _run(["fit-pwl", str(tmp_path / "missing.csv"), "--inputs", "x1", "--outputs",
                    "y"], capsys)
    assert rc == 2 and "missing.csv" in err and len(err.splitlines()) == 1
