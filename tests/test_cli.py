"""The ``diffsmf`` command: --version, defaults in --help, one-line user errors (exit 2)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

import diffsmf
from diffsmf import cli
from diffsmf.cli import main


def _one_line_error(capsys, argv: list[str], *pieces: str) -> str:
    rc = main(argv)
    captured = capsys.readouterr()
    assert rc == 2, captured
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith(f"diffsmf {argv[0]}: error: "), lines[0]
    assert "Traceback" not in captured.err
    for piece in pieces:
        assert piece in lines[0], lines[0]
    return lines[0]


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"diffsmf {diffsmf.__version__}"


def test_top_level_help_lists_every_command(capsys):
    assert main([]) == 0
    out = capsys.readouterr().out
    for name in cli.COMMANDS:
        assert name in out


def test_unknown_command_is_one_line(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["fliter"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "invalid choice: 'fliter'" in err[0]


@pytest.mark.parametrize(
    "name, default",
    [
        ("demo", "(default: filters,sets,pwl)"),
        ("filter", "(default: hsnsmf)"),
        ("audit", "(default: 1000)"),
        ("tune", "(default: 200)"),
        ("fit-pwl", "default"),
        ("design-observer", "default"),
    ],
)
def test_every_subcommand_help_shows_defaults(capsys, name, default):
    assert main([name, "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: diffsmf {name}")
    assert default in " ".join(out.split())  # help text is wrapped
    assert "(default: None)" not in out


def test_randomness_has_a_seed_option(capsys):
    for name in ("demo", "audit", "tune"):
        assert main([name, "--help"]) == 0
        assert "--seed" in capsys.readouterr().out, name


@pytest.mark.parametrize(
    "argv, pieces",
    [
        (["audit", "--system", "nope", "--filter", "hsnsmf"], ["--system", "'nope'",
                                                               "spring_damper"]),
        (["audit", "--system", "bilinear", "--filter", "kalman"], ["--filter", "'kalman'",
                                                                   "hsnsmf"]),
        (["audit", "--system", "bilinear", "--filter", "hsnsmf", "--trials", "0"],
         ["--trials", "must be >= 1"]),
        (["audit", "--system", "bilinear"], ["--filter", "required"]),
        (["audit", "--system", "oscillator_chain:x", "--filter", "hsnsmf"],
         ["--system", "NAME:N", "'oscillator_chain:x'"]),
        (["audit", "--system", "oscillator_chain:0", "--filter", "hsnsmf"],
         ["--system", "N >= 1"]),
        (["audit", "--system", "vdp:4", "--filter", "hsnsmf"], ["--system", "'vdp'",
                                                               "no size argument"]),
        (["tune", "--system", "vdp:4"], ["--system", "no size argument"]),
        (["tune", "--system", "nope"], ["--system", "'nope'"]),
        (["tune", "--filter", "nope"], ["--filter", "'nope'"]),
        (["tune", "--epochs", "0"], ["--epochs", "must be >= 1"]),
        (["tune", "--trajectories", "0"], ["--trajectories", "must be >= 1"]),
        (["tune", "--lr", "-1"], ["--lr", "> 0"]),
        (["tune", "--epochs", "two"], ["--epochs", "invalid int value"]),
        (["demo", "--parts", "filters,movies"], ["--parts", "movies"]),
    ],
)
def test_user_errors_are_one_line(capsys, tmp_path, argv, pieces):
    _one_line_error(capsys, [*argv, *(["--out", str(tmp_path)] if argv[0] == "tune" else [])],
                    *pieces)


def test_tune_config_and_out_errors(capsys, tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("epochs = [\n")
    _one_line_error(capsys, ["tune", "--config", str(bad)], "config", "not valid TOML",
                    "bad.toml")
    typed = tmp_path / "typed.toml"
    typed.write_text('epochs = "five"\n')
    _one_line_error(capsys, ["tune", "--config", str(typed)], "config", "epochs",
                    "must be an integer")
    unknown = tmp_path / "unknown.toml"
    unknown.write_text("nonsense = 1\n")
    _one_line_error(capsys, ["tune", "--config", str(unknown)], "config", "unknown keys",
                    "nonsense")
    _one_line_error(capsys, ["tune", "--config", str(tmp_path / "none.toml")], "config",
                    "no such file")
    _one_line_error(capsys, ["tune", "--config", str(tmp_path)], "config", "is a folder")
    if Path("/dev/null").exists():
        _one_line_error(capsys, ["tune", "--config", "/dev/null"], "config",
                        "not a regular file")
    weights = tmp_path / "weights.toml"
    weights.write_text("weights = {volum = 1.0}\n")
    _one_line_error(capsys, ["tune", "--config", str(weights), "--out", str(tmp_path / "w")],
                    "config: weights", "volum", "volume")
    kwargs = tmp_path / "kwargs.toml"
    kwargs.write_text("filter_kwargs = {stirling = 0.1}\nsteps = 2\ntrajectories = 2\n"
                      "val_trajectories = 0\ntest_trajectories = 0\n")
    _one_line_error(capsys, ["tune", "--config", str(kwargs), "--out", str(tmp_path / "k"),
                             "--quiet"], "config: filter_kwargs", "stirling")
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    _one_line_error(capsys, ["tune", "--out", str(a_file)], "--out", "not a folder")
    _one_line_error(capsys, ["tune", "--out", str(a_file / "sub")], "--out", "cannot create")


def test_demo_creates_a_missing_out_folder_and_names_a_file(capsys, tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    _one_line_error(capsys, ["demo", "--parts", "sets", "--out", str(a_file)], "--out")
    out = tmp_path / "new" / "deeper"
    assert main(["demo", "--parts", "sets", "--out", str(out)]) == 0
    assert (out / "sets.png").stat().st_size > 0


def test_systemexit_message_of_a_subcommand_becomes_one_line(capsys, monkeypatch):
    import diffsmf.cli.demo as demo

    def boom(args):
        raise SystemExit("demo: --thing: bad value")

    monkeypatch.setattr(demo, "main", boom)
    line = _one_line_error(capsys, ["demo"])
    assert line == "diffsmf demo: error: --thing: bad value"


def test_a_bug_keeps_its_traceback(monkeypatch):
    import diffsmf.cli.demo as demo

    def bug(args):
        raise RuntimeError("internal")

    monkeypatch.setattr(demo, "main", bug)
    with pytest.raises(RuntimeError, match="internal"):
        main(["demo"])


def test_traceback_on_request(monkeypatch):
    monkeypatch.setenv("DIFFSMF_TRACEBACK", "1")
    with pytest.raises(ValueError, match="--system"):
        main(["audit", "--system", "nope", "--filter", "hsnsmf"])


def test_console_process_exit_code_and_stderr():
    """The real process: exit status 2, one line on stderr, nothing on stdout."""
    proc = subprocess.run(
        [sys.executable, "-m", "diffsmf.cli", "audit", "--system", "nope", "--filter", "hsnsmf"],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert proc.stderr.strip().splitlines() == [
        "diffsmf audit: error: --system: unknown system 'nope'; choose from "
        + str(sorted(diffsmf.systems.names()))
    ]


def test_python_dash_m_diffsmf_is_the_command():
    proc = subprocess.run([sys.executable, "-m", "diffsmf", "--version"],
                          capture_output=True, text=True, timeout=120)
    assert (proc.returncode, proc.stdout.strip()) == (0, f"diffsmf {diffsmf.__version__}")


def test_audit_sized_system_and_czsmf(capsys):
    """``--system NAME:N`` audits the sized built-in; CZSMF counts as a guaranteed filter."""
    argv = ["audit", "--system", "oscillator_chain:4", "--trials", "2", "--steps", "3",
            "--noise", "vertex", "--quiet"]
    assert main([*argv, "--filter", "hsnsmf", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out.strip())
    assert (rep["system"], rep["filter"], rep["pairs"]) == ("oscillator_chain(n=4)", "HSNSMF", 8)
    assert main([*argv, "--filter", "czsmf"]) == 0
    out = capsys.readouterr().out
    assert "CZSMF on oscillator_chain(n=4)" in out
    assert "guaranteed filters (cdsmf, czsmf, esmf, eso, hsnsmf, interval, mszm, zbsmf)" in out
