r"""``diffsmf filter``: run a set-membership filter on your own model and logged data.

    diffsmf filter --model my_model.py:make_system --data log.csv \
        --outputs y1 [--inputs u1,u2] --filter hsnsmf --out run/

make_system() (any name; no arguments) returns a diffsmf.System. The data file has one row per
step: row i holds the input u_i that drives x_i -> x_{i+1} and the measurement y_{i+1} of the
state it produced (the convention of System.simulate: traj.u[:, i], traj.y[:, i]); the state
x_0 lies in the system's x0_set. Columns not named by --outputs / --inputs are ignored.

Data formats: CSV with a header row; .npz (each named array of shape [N] or [N, k] is a column
or a group of k columns, selected by its name); .npy (one [N, C] array, columns named 0..C-1).

Writes to --out: bounds.csv (or bounds.npz with --format npz) with columns step, lower_NAME..,
upper_NAME.., consistent (1/0), bounded (1/0), one row per step and a row for the initial set
at step 0 (NAME: the --state-names, default 0, 1, ...); bounds.png, the bounds of every state
over time, labelled with the same names; summary.json (filter, settings, inconsistent steps,
where the guarantee was lost, numerical events, time). Bounds are written with 17 significant
digits, so rounding never cuts into a guaranteed set. Where the set became unbounded
(bounded = 0) the bounds are -inf / +inf, never a finite placeholder, and the figure shades
those steps.

Exit status: 0 every step bounded and consistent; 1 some measurement was inconsistent with
the predicted set (the model, the noise bounds or the data were violated; the steps are in
summary.json); 2 a user error (one line on stderr); 3 the guarantee was lost: a set became
unbounded (bounds -inf / +inf from that step on, see summary.json); 4 a numerical failure the
filter could not flag (one line naming the step; not an error in your input, please report
it). Files are written for statuses 0, 1 and 3.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

import diffsmf as ds
from diffsmf.filters import names as filter_names
from diffsmf.filters.events import describe_events
from diffsmf.filters.presets import filter_name
from diffsmf.plot import bounds_figure
from diffsmf.systems import System
from diffsmf.tuning.bounds import bound_sets, read_bounds
from diffsmf.utils import load_object  # the shared FILE.py:FUNC loader (re-exported)

#: Exit statuses of ``diffsmf filter`` (see the module docstring).
EXIT_OK, EXIT_INCONSISTENT, EXIT_USER, EXIT_UNBOUNDED, EXIT_NUMERICAL = 0, 1, 2, 3, 4

__all__ = [
    "EXIT_INCONSISTENT",
    "EXIT_NUMERICAL",
    "EXIT_OK",
    "EXIT_UNBOUNDED",
    "EXIT_USER",
    "FilterRun",
    "NumericalFailure",
    "add_arguments",
    "load_model",
    "load_object",
    "main",
    "read_log",
    "read_table",
    "run_filter",
    "select_columns",
    "write_bounds",
]

# ------------------------------------------------------------------ model
def load_model(spec: str, what: str = "--model"):
    """``"path/to/file.py:FUNCTION"`` -> the `System` that ``FUNCTION()`` returns.

    As `load_object`, and a ``ValueError`` naming ``what`` when the result is not a System.
    """
    system = load_object(spec, what)
    if not isinstance(system, System):
        func = spec.rpartition(":")[2]
        raise ValueError(f"{what}: {func}() must return a diffsmf.System, got "
                         f"{type(system).__name__}")
    return system


# ------------------------------------------------------------------ data
def _csv_table(path: Path) -> tuple[list[str], list[list[str]]]:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise ValueError(f"--data: {str(path)!r} is not a text (CSV) file") from None
    rows = [r for r in csv.reader(text.splitlines()) if any(c.strip() for c in r)]
    if not rows:
        raise ValueError(f"--data: {str(path)!r} is empty (expected a header row and data rows)")
    header = [h.strip() for h in rows[0]]
    if any(not h for h in header):
        raise ValueError(f"--data: {str(path)!r}: the header row has an empty column name "
                         f"({rows[0]})")
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise ValueError(f"--data: {str(path)!r}: duplicate column names {dup}")
    if len(rows) == 1:
        raise ValueError(f"--data: {str(path)!r} has a header but no data rows")
    return header, rows[1:]


def read_table(path: str | Path) -> dict[str, np.ndarray | list[str]]:
    """Columns of a data file: ``{name: values}``.

    CSV (header row): every column as a list of strings (converted by `select_columns`,
    so unused columns may hold text such as time stamps). ``.npz``: each array ``[N]`` or
    ``[N, k]`` under its name. ``.npy``: one array ``[N, C]`` (or ``[N]``), columns ``"0"``,
    ``"1"``, ...
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(2, "--data: no such file", str(p))
    if p.is_dir():
        raise ValueError(f"--data: {str(p)!r} is a folder, not a data file")
    suffix = p.suffix.lower()
    if suffix in (".npz", ".npy"):
        try:
            loaded = np.load(p, allow_pickle=False)
        except Exception as exc:
            raise ValueError(f"--data: cannot read {str(p)!r} as {suffix} "
                             f"({type(exc).__name__}: {exc})") from None
        if suffix == ".npz":
            cols = {k: np.asarray(loaded[k]) for k in loaded.files}
            if not cols:
                raise ValueError(f"--data: {str(p)!r} holds no arrays")
            return cols
        arr = np.asarray(loaded)
        if arr.ndim == 1:
            arr = arr[:, None]
        if arr.ndim != 2:
            raise ValueError(f"--data: {str(p)!r} must hold a 2-D array [steps, columns], got "
                             f"shape {arr.shape}")
        return {str(j): arr[:, j] for j in range(arr.shape[1])}
    header, rows = _csv_table(p)
    for i, r in enumerate(rows):
        if len(r) != len(header):
            raise ValueError(f"--data: {str(p)!r} line {i + 2} has {len(r)} cells, the header "
                             f"has {len(header)}")
    return {h: [r[j].strip() for r in rows] for j, h in enumerate(header)}


def _numeric(name: str, values, source: str, allow_blank: bool) -> np.ndarray:
    """One column as float64 ``[N, k]``; blank / non-numeric cells raise naming row and column."""
    if isinstance(values, list):
        out = np.empty(len(values))
        for i, cell in enumerate(values):
            if cell == "":
                if allow_blank:
                    out[i] = np.nan
                    continue
                raise ValueError(f"--data: {source} line {i + 2}, column {name!r} is blank (a "
                                 "missing measurement? --skip-missing skips those updates)")
            try:
                out[i] = float(cell)
            except ValueError:
                raise ValueError(f"--data: {source} line {i + 2}, column {name!r}: {cell!r} is "
                                 "not a number") from None
        arr = out[:, None]
    else:
        arr = np.asarray(values)
        if arr.dtype.kind not in "biuf":
            raise ValueError(f"--data: {source} array {name!r} is not numeric (dtype {arr.dtype})")
        arr = arr.astype(np.float64)
        if arr.ndim == 1:
            arr = arr[:, None]
        if arr.ndim != 2:
            raise ValueError(f"--data: {source} array {name!r} must have shape [steps] or "
                             f"[steps, k], got {arr.shape}")
    bad = ~np.isfinite(arr)
    if allow_blank:
        bad &= ~np.isnan(arr)
    if bad.any():
        i = int(np.argwhere(bad)[0, 0])
        where = f"line {i + 2}" if isinstance(values, list) else f"row {i}"
        raise ValueError(f"--data: {source} {where}, column {name!r} is {arr[i].tolist()}: "
                         "values must be finite")
    return arr


def select_columns(
    table: dict, names: list[str], what: str, source: str, allow_blank: bool = False
) -> np.ndarray:
    """Named columns of `read_table`'s result as float64 ``[N, sum of widths]``."""
    missing = [c for c in names if c not in table]
    if missing:
        raise ValueError(f"{what}: no column {missing[0]!r} in {source}; columns there: "
                         f"{list(table)}")
    cols = [_numeric(c, table[c], source, allow_blank) for c in names]
    lengths = {c.shape[0] for c in cols}
    if len(lengths) > 1:
        raise ValueError(f"{what}: the columns {names} of {source} have different lengths "
                         f"{sorted(lengths)}")
    if cols[0].shape[0] == 0:
        raise ValueError(f"--data: {source} has no data rows")
    return np.concatenate(cols, axis=1)


def _names(text: str | None) -> list[str]:
    return [] if not text else [c.strip() for c in text.split(",") if c.strip()]


def read_log(
    system: System, path: str | Path, outputs: list[str], inputs: list[str],
    allow_blank: bool = False,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """One logged trajectory of ``system`` from a data file (`read_table`):
    ``y [T, m]`` from the ``outputs`` columns (in the order of ``h``) and ``u [T, p]`` from
    the ``inputs`` columns, the system's ``inputs`` schedule, or None.

    Raises:
        ValueError: naming ``--outputs``, ``--inputs`` or ``--data``: a missing or
            non-numeric column, a width that does not match ``h`` or ``n_inputs``.
    """
    source = repr(str(path))
    table = read_table(path)
    if not outputs:
        raise ValueError("--outputs: name at least one measurement column")
    Y = select_columns(table, outputs, "--outputs", source, allow_blank=allow_blank)
    if Y.shape[1] != system.m:
        raise ValueError(f"--outputs: {outputs} give {Y.shape[1]} measurement(s) per step, "
                         f"the model's h(x) has {system.m}")
    T = Y.shape[0]
    y = torch.as_tensor(Y, dtype=system.x0_set.dtype)
    if inputs:
        if system.n_inputs == 0:
            raise ValueError(f"--inputs: the model {system.name!r} has no inputs "
                             "(build it with System(..., n_inputs=p))")
        U = select_columns(table, inputs, "--inputs", source)
        if U.shape[1] != system.n_inputs:
            raise ValueError(f"--inputs: {inputs} give {U.shape[1]} input(s) per step, the "
                             f"model has n_inputs={system.n_inputs}")
        return y, system.check_input(torch.as_tensor(U), (T,))
    if system.n_inputs > 0 and system.inputs is not None:
        return y, torch.cat([system.input_at(k, 1) for k in range(T)], 0)  # the schedule
    if system.n_inputs > 0:
        raise ValueError(f"--inputs: the model {system.name!r} has n_inputs="
                         f"{system.n_inputs} and no inputs schedule; name the input columns")
    return y, None


def _floats(text: str | None, what: str, dim: int) -> torch.Tensor | None:
    if text is None:
        return None
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"{what}: expected comma-separated numbers, got {text!r}") from None
    if len(vals) not in (1, dim):
        raise ValueError(f"{what}: expected 1 or {dim} numbers, got {len(vals)}")
    if not all(np.isfinite(v) and v > 0 for v in vals):
        raise ValueError(f"{what}: half-widths must be finite and > 0, got {vals}")
    return torch.tensor(vals, dtype=torch.float64).expand(dim).clone()


# ------------------------------------------------------------------ filtering
class NumericalFailure(RuntimeError):
    """A filter step raised for a numerical reason the filter could not flag (not a user
    error: ``diffsmf filter`` reports it in one line with exit status 4)."""


@dataclass
class FilterRun:
    """Result of `run_filter` for one logged trajectory.

    lower, upper: ``[T+1, n]`` interval hull of the guaranteed set at each step (row 0 =
    initial set); -inf / +inf where it is unbounded; consistent: ``[T+1]`` bool (False where
    the measurement did not meet the predicted set; True where the set is unbounded);
    bounded: ``[T+1]`` bool (False from the step where the set stopped being finite);
    events: ``[T+1]`` int64 ``FilterEvent`` bits met at or before each step; seconds: wall
    time of the filter loop.
    """

    lower: np.ndarray
    upper: np.ndarray
    consistent: np.ndarray
    bounded: np.ndarray
    seconds: float
    events: np.ndarray | None = None


def run_filter(filt, y: torch.Tensor, u: torch.Tensor | None, progress: bool = True) -> FilterRun:
    """Drive ``filt`` online over one trajectory: ``y [T, m]``, ``u [T, p]`` or None.

    ``state = filt.initial_state(batch=1)``; then, for each step, ``predict(state, u_k)`` and
    ``update(state, y_{k+1})`` (the loop ``forward`` runs), with a progress bar over steps.
    The bounds are those of ``state.guaranteed_set`` (+-inf where the set is unbounded).
    A model error (``JetError``: an operation the interval engine does not support) raises a
    ``ValueError`` naming the step; an arithmetic, runtime (e.g. a linear-algebra failure)
    or value error of a step raises `NumericalFailure` naming the step (other
    exceptions, bugs, propagate).
    """
    from tqdm.auto import tqdm

    from diffsmf.linearize import JetError

    T = y.shape[0]
    state = filt.initial_state(batch=1)
    rows = [_row(state)]
    t0 = time.perf_counter()
    with torch.no_grad():
        for k in tqdm(range(T), desc="filter", unit="step", disable=not progress, leave=False):
            try:
                state = filt.predict(state, None if u is None else u[k : k + 1])
                state = filt.update(state, y[k : k + 1])
            except JetError as exc:
                raise ValueError(f"--model: step {k + 1}: {exc}") from exc
            except (ArithmeticError, RuntimeError, ValueError) as exc:  # e.g. LinAlgError
                raise NumericalFailure(
                    f"step {k + 1}: {type(exc).__name__}: {exc}"
                ) from exc
            rows.append(_row(state))
    seconds = time.perf_counter() - t0
    lows, ups, cons, bnds, evs = zip(*rows)
    return FilterRun(
        lower=np.stack(lows), upper=np.stack(ups), consistent=np.array(cons, dtype=bool),
        bounded=np.array(bnds, dtype=bool), seconds=seconds,
        events=np.array(evs, dtype=np.int64),
    )


def _row(state) -> tuple[np.ndarray, np.ndarray, bool, bool, int]:
    """``(lower [n], upper [n], consistent, bounded, events)`` of a batch-1 state: the hull of
    its guaranteed set (+-inf where unbounded; a state without ``bounded``: a finite hull is
    bounded)."""
    flag = getattr(state, "bounded", None)
    S = getattr(state, "guaranteed_set", state.set)
    hull = S.interval_hull()
    lo, up = hull.lower[0].cpu().numpy(), hull.upper[0].cpu().numpy()
    bounded = bool(flag.reshape(-1)[0]) if flag is not None else bool(
        np.isfinite(lo).all() and np.isfinite(up).all()
    )
    if not bounded:  # never a finite placeholder
        lo, up = np.full_like(lo, -np.inf), np.full_like(up, np.inf)
    ev = getattr(state, "events", None)
    events = 0 if ev is None else int(ev.reshape(-1)[0])
    consistent = bool(state.consistent[0]) or not bounded
    return lo, up, consistent, bounded, events


def write_bounds(
    out: Path, run: FilterRun, fmt: str = "csv", state_names: list[str] | None = None
) -> Path:
    """``out/bounds.csv`` (``step, lower_NAME.., upper_NAME.., consistent, bounded``) or
    ``out/bounds.npz`` (arrays ``step, lower, upper, consistent, bounded, events,
    state_names``). NAME: ``state_names`` (default ``0 .. n-1``). Unbounded steps are written
    as ``-inf`` / ``inf``."""
    n = run.lower.shape[1]
    names = state_names or [str(i) for i in range(n)]
    steps = np.arange(run.lower.shape[0])
    events = run.events if run.events is not None else np.zeros(len(steps), np.int64)
    if fmt == "npz":
        path = out / "bounds.npz"
        np.savez(path, step=steps, lower=run.lower, upper=run.upper, consistent=run.consistent,
                 bounded=run.bounded, events=events, state_names=np.array(names))
        return path
    path = out / "bounds.csv"
    head = ["step", *(f"lower_{c}" for c in names), *(f"upper_{c}" for c in names),
            "consistent", "bounded"]
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(head)
        for k in steps:
            w.writerow([int(k), *(repr(float(v)) for v in run.lower[k]),
                        *(repr(float(v)) for v in run.upper[k]), int(run.consistent[k]),
                        int(run.bounded[k])])
    return path


def _state_names(text: str | None, n: int) -> list[str] | None:
    """``--state-names a,b,c`` -> ``["a", "b", "c"]`` (exactly n distinct, non-empty names of
    letters, digits, ``_``, ``.`` and ``-``), or None."""
    if text is None:
        return None
    names = [c.strip() for c in text.split(",")]
    if len(names) != n:
        raise ValueError(f"--state-names: expected {n} names (one per state), got {len(names)}")
    bad = [c for c in names if not c or not all(ch.isalnum() or ch in "_.-" for ch in c)]
    if bad:
        raise ValueError(f"--state-names: names must be non-empty and use letters, digits, "
                         f"'_', '.', '-' only, got {bad}")
    if len(set(names)) != n:
        raise ValueError(f"--state-names: names must be distinct, got {names}")
    return names


# ------------------------------------------------------------------ command line
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``diffsmf filter``."""
    a = parser.add_argument
    a("--model", required=True, metavar="FILE.py:FUNC",
      help="Python file and the function in it that returns your diffsmf.System")
    a("--data", required=True, type=Path, metavar="FILE",
      help="measurements (and inputs): .csv with a header row, .npz or .npy")
    a("--outputs", required=True, metavar="COLS",
      help="comma-separated measurement columns, in the order of h(x)")
    a("--inputs", default=None, metavar="COLS",
      help="comma-separated input columns, in the order of u (default: none, or the model's "
           "own inputs schedule)")
    a("--filter", default="hsnsmf", help=f"filter: {' | '.join(filter_names(presets=True))}")
    a("--out", default="diffsmf-run", type=Path, help="output folder (created when missing)")
    a("--format", default="csv", choices=["csv", "npz"], help="file format of the bounds")
    a("--process-noise", default=None, metavar="W",
      help="process-noise half-widths, one number or one per state (default: the model's W)")
    a("--measurement-noise", default=None, metavar="V",
      help="measurement-noise half-widths, one number or one per output (default: the "
           "model's V)")
    a("--bounds", default=None, type=Path, metavar="FILE",
      help="noise half-widths from the bounds.json that diffsmf tune writes (--process-noise "
           "and --measurement-noise, when given, win)")
    a("--skip-missing", action="store_true",
      help="blank / NaN measurement cells skip that update (default: they are an error)")
    a("--no-figure", dest="figure", action="store_false", help="do not write bounds.png")
    a("--state-names", default=None, metavar="NAMES",
      help="comma-separated names of the states, one per state, used in the CSV columns "
           "(lower_NAME, upper_NAME) and the figure (default: 0, 1, ...)")
    a("--quiet", action="store_true",
      help="no progress bar and no summary on stdout (warnings about inconsistent steps and "
           "a lost guarantee still go to stderr)")


def main(args: argparse.Namespace) -> int:
    """Run ``diffsmf filter``; the exit status (module docstring): 0 bounded and consistent,
    1 inconsistent steps, 3 the guarantee was lost (unbounded), 4 a numerical failure."""
    try:
        cls = ds.filters.by_name(args.filter)
    except ValueError:
        raise ValueError(f"--filter: unknown filter {args.filter!r}; choose from "
                         f"{ds.filters.names(presets=True)}") from None
    system = load_model(args.model)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out: {str(out)!r} exists and is not a folder")
    outs, ins = _names(args.outputs), _names(args.inputs)
    y, u = read_log(system, args.data, outs, ins, allow_blank=args.skip_missing)
    Y = y.numpy()
    T = Y.shape[0]
    filt = _build_filter(cls, system, args)
    if getattr(args, "bounds", None) is not None:
        _check_bounds_centres(args.bounds, filt)
    state_names = _state_names(getattr(args, "state_names", None), system.n)
    try:
        run = run_filter(filt, y, u, progress=not args.quiet)
    except NumericalFailure as exc:
        print(f"diffsmf filter: numerical failure at {exc} (not an error in your input; "
              "please report it)", file=sys.stderr)
        return EXIT_NUMERICAL
    out.mkdir(parents=True, exist_ok=True)
    bounds_path = write_bounds(out, run, args.format, state_names)
    files = {"bounds": bounds_path.name}
    name = filter_name(filt)
    guaranteed = ds.filters.is_guaranteed(filt)
    skipped = [int(k) + 1 for k in np.flatnonzero(np.isnan(Y).any(1))]
    if args.figure:
        title = f"{name} on {system.name}: {T} steps of {Path(args.data).name}"
        names = state_names or [str(i) for i in range(system.n)]
        bounds_figure(run.lower, run.upper, out / "bounds.png", consistent=run.consistent,
                      title=title, guaranteed=guaranteed,
                      state_names=names if state_names else [f"state {c}" for c in names],
                      bounded=run.bounded, skipped=skipped)
        files["figure"] = "bounds.png"
    inconsistent = [int(k) for k in np.flatnonzero(~run.consistent)]
    lost = int(np.flatnonzero(~run.bounded)[0]) if not run.bounded.all() else None
    status = EXIT_UNBOUNDED if lost is not None else (
        EXIT_INCONSISTENT if inconsistent else EXIT_OK
    )
    summary = {
        "filter": name,
        "guaranteed": guaranteed,
        "model": args.model,
        "system": system.name,
        "data": str(args.data),
        "outputs": outs,
        "inputs": ins if ins else ("schedule" if u is not None else []),
        "steps": T,
        "state_dim": system.n,
        "settings": {
            "process_noise": filt.process_half_widths.detach().tolist()
            if hasattr(filt, "process_half_widths") else None,
            "measurement_noise": filt.measurement_half_widths.detach().tolist()
            if hasattr(filt, "measurement_half_widths") else None,
            "bounds_file": None if getattr(args, "bounds", None) is None else str(args.bounds),
            "skip_missing": bool(args.skip_missing),
            "format": args.format,
        },
        "state_names": state_names or [str(i) for i in range(system.n)],
        "inconsistent_steps": inconsistent,
        "skipped_updates": skipped,
        "bounded": bool(run.bounded.all()),
        "guarantee_lost_at_step": lost,
        "unbounded_steps": [int(k) for k in np.flatnonzero(~run.bounded)],
        "events": describe_events(run.events)[:100] if run.events is not None else [],
        "seconds": run.seconds,
        "exit_status": status,
        "files": {**files, "summary": "summary.json"},
        "diffsmf_version": ds.__version__,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    _report(args, run, out, files, name, system.name, T, inconsistent, lost, guaranteed)
    return status


def _build_filter(cls: type, system: Any, args: argparse.Namespace) -> Any:
    """The filter ``cls`` on ``system`` with the noise bounds of ``--process-noise``,
    ``--measurement-noise`` and ``--bounds`` (explicit values win) and ``--skip-missing``."""
    kw = {}
    wn = _floats(args.process_noise, "--process-noise", system.n)
    vn = _floats(args.measurement_noise, "--measurement-noise", system.m)
    if getattr(args, "bounds", None) is not None:  # explicit --*-noise values win
        tuned = read_bounds(args.bounds, system.n, system.m, what="--bounds")
        wn = tuned["process_noise"] if wn is None else wn
        vn = tuned["measurement_noise"] if vn is None else vn
    if wn is not None:
        kw["process_half_widths"] = wn
    if vn is not None:
        kw["measurement_half_widths"] = vn
    if args.skip_missing:
        kw["skip_nan"] = True
    try:
        return cls(system, **kw)
    except TypeError as exc:  # a filter without that option (e.g. CombinedFilter's own bounds)
        flags = {"process_half_widths": "--process-noise",
                 "measurement_half_widths": "--measurement-noise"}
        opts = ", ".join(flags[k] for k in kw if k in flags)
        if not opts or "unexpected keyword" not in str(exc):
            raise
        raise ValueError(f"{opts}: the {cls.__name__} filter does not take this option "
                         "(it has its own noise parameters)") from None


def _report(args: argparse.Namespace, run: FilterRun, out: Path, files: dict, name: str,
            system: str, T: int, inconsistent: list[int], lost: int | None,
            guaranteed: bool) -> None:
    """The warnings (stderr, also with ``--quiet``: they say the bounds cannot be used as they
    are) and, without ``--quiet``, the summary lines of a run."""
    if inconsistent:
        print(f"diffsmf filter: warning: {len(inconsistent)} inconsistent step(s) (measurement "
              f"outside the predicted set: the model, the noise bounds or the data were "
              f"violated), first at step {inconsistent[0]}; see {out / 'summary.json'}",
              file=sys.stderr)
    if lost is not None:
        print(f"diffsmf filter: warning: the guarantee was lost at step {lost}: "
              f"{_event_reason(run)}; see {out / 'summary.json'}", file=sys.stderr)
    if args.quiet:
        return
    width = run.upper[-1] - run.lower[-1]
    print(f"{name} on {system}: {T} steps in {run.seconds:.2f} s; final bound widths "
          f"{np.array2string(width, precision=3)}")
    if not inconsistent:
        print("  every measurement was consistent with the model and the noise bounds")
    if not guaranteed:
        print(f"  note: {name} is not a guaranteed filter; its bounds are not guaranteed")
    print(f"  wrote {out / files['bounds']}, " +
          (f"{out / 'bounds.png'}, " if args.figure else "") + f"{out / 'summary.json'}")


def _check_bounds_centres(path: Path, filt) -> None:
    """The centres of a bounds file must be those of the model's noise sets (the file was
    tuned for this model: tuning moves half-widths, never centres)."""
    for name, S in bound_sets(path, what="--bounds").items():
        have = getattr(filt, f"{name}_center", None)
        if have is not None and not torch.allclose(S.center, have, rtol=1e-12, atol=1e-15):
            raise ValueError(f"--bounds: the {name} centre {S.center.tolist()} in "
                             f"{str(path)!r} is not the model's ({have.tolist()}): the file "
                             "was tuned for another model")


def _event_reason(run: FilterRun) -> str:
    """The reason of the event that lost the bound, as text."""
    from diffsmf.filters.events import LOSES_BOUND, event_text

    code = 0 if run.events is None else int(run.events[-1]) & LOSES_BOUND
    return event_text(code) if code else "the set became unbounded; bounds are -inf/+inf from here"
