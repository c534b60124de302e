"""``ds.compare`` and ``diffsmf compare``: several observers on the same data, one table.

The rows are checked against the `FilterResult` of each observer run on its own (the table
says what the filters say), an observer that raises is a row, a lost bound is inf, and the
command line reports user errors in one line."""

from __future__ import annotations

import csv
import math

import pytest
import torch

import diffsmf as ds
from diffsmf.cli import main


@pytest.fixture(scope="module")
def linear():
    s = ds.systems.get("linear_2d")
    y, _ = ds.systems.recorded("linear_2d")
    return s, y[0, 1:]


def test_rows_are_what_each_observer_gives_alone(linear):
    s, y = linear
    names = ["interval", "hsnsmf", "FRad-A", "FRad-B", "VolMin-B", "czsmf"]
    cmp = ds.compare(s, y, filters=names)
    assert [r["filter"] for r in cmp.rows] == names
    for row in cmp.rows:
        with torch.no_grad():
            res = ds.filters.get(row["filter"])(s)(y.unsqueeze(0))
        width = (res.upper - res.lower).sum(-1)[0]
        assert row["error"] is None and row["guaranteed"]
        assert row["final_width_sum"] == pytest.approx(float(width[-1]), rel=1e-12)
        assert row["mean_width_sum"] == pytest.approx(float(width[1:].mean()), rel=1e-12)
        assert row["bounded"] == row["pairs"] == y.shape[0]
        assert row["family"] == ds.filters.get(row["filter"]).set_family
        assert row["ms_per_step"] > 0
    text = cmp.table()
    assert all(n in text for n in names) and "final width sum" in text


def test_a_lost_bound_is_inf_and_a_raising_observer_is_a_row(tmp_path):
    s = ds.systems.get("tank6")
    y, u = ds.systems.recorded("tank6")

    def broken(system):
        raise RuntimeError("not today")

    cmp = ds.compare(s, y[:, 1:], u[:, :-1], filters={"cdsmf": ds.filters.CDSMF(s),
                                                      "broken": broken})
    cd, bad = cmp.rows
    assert cd["final_width_sum"] == math.inf and cd["bounded"] < cd["pairs"]
    assert bad["error"] == "RuntimeError: not today" and math.isnan(bad["final_width_sum"])
    assert "raised: RuntimeError: not today" in cmp.table()
    assert list(cmp.results) == ["cdsmf"]
    cmp.figure(tmp_path / "f.png")
    assert (tmp_path / "f.png").stat().st_size > 10_000


def test_bad_input_names_the_argument(linear):
    s, y = linear
    with pytest.raises(ValueError, match=r"^y: expected \[T, 1\]"):
        ds.compare(s, torch.zeros(5, 2))
    with pytest.raises(ValueError, match="^u: expected inputs"):
        ds.compare(s, y, torch.zeros(3, 1))
    with pytest.raises(ValueError, match="^filters: unknown filter 'Hinf-G'"):
        ds.compare(s, y, filters=["hsnsmf", "Hinf-G"])
    with pytest.raises(ValueError, match="^filters: expected a list"):
        ds.compare(s, y, filters="hsnsmf")


def test_cli_compare_writes_the_table_and_the_figure(tmp_path, capsys):
    out = tmp_path / "cmp"
    rc = main(["compare", "--system", "linear_2d", "--filters", "FRad-A,VolMin-B,czsmf",
               "--out", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "linear_2d: 19 steps of recorded data" in text and "VolMin-B" in text
    rows = list(csv.DictReader(open(out / "comparison.csv")))
    assert [r["filter"] for r in rows] == ["FRad-A", "VolMin-B", "czsmf"]
    assert (out / "comparison.png").exists()
    rc = main(["compare", "--system", "vdp", "--steps", "5", "--filters", "interval",
               "--out", str(out), "--no-figure"])
    assert rc == 0 and "one simulated trajectory" in capsys.readouterr().out


@pytest.mark.parametrize(("argv", "piece"), [
    (["--system", "linear_2d", "--filters", "nope"], "--filters: unknown observer 'nope'"),
    (["--model", "missing.py:f"], "--model"),
    (["--system", "nope"], "--system: unknown system 'nope'"),
    (["--system", "vdp", "--steps", "0"], "--steps: must be >= 1"),
])
def test_cli_compare_user_errors_are_one_line(argv, piece, capsys, tmp_path):
    rc = main(["compare", *argv, "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and piece in err and len(err.strip().splitlines()) == 1
    assert "Traceback" not in err
