"""Full containment audit: every guaranteed filter on every bounded built-in system.

For each (system, filter, noise in {vertex, uniform}) one batch of ``--trials`` trajectories
runs over the system's horizon (``system.horizon``: the papers' horizons), and the table lists
the (trajectory, step) pairs outside the set (tolerance 1e-9 on the normalised distance, see
`diffsmf.audit`), the worst normalised distance outside, the mean volume and the wall
time. ``--trials-for fermenter=100`` lowers the count for a slow system (stated in the table).
Output: a markdown table on stdout (pasted into docs/filters.md). ``--compile inductor``
audits the compiled step (``filt.compile()``; ``--compile eager``: the traced step run by
torch's eager backend, without Inductor's compile time).

    python benchmarks/filters_audit.py --trials 1000 --trials-for fermenter=100

A long audit can be split into runs and resumed: ``--log FILE`` appends one JSON line per
chunk of 100 trajectories (with a fingerprint of the package's source), ``--first N`` /
``--count M`` audit only some of the ``--trials`` trajectories (the same ones as in the whole
audit), and ``--merge FILE`` prints the table from a log, each row the union of its chunks
and how many of the trajectories it covers. A row only merges chunks whose filter gave
bit-identical sets on a probe (2 trajectories x 10 steps, the ``sets`` fingerprint; the
package's source hash is logged too): run with ``OMP_NUM_THREADS=1`` so that the probe does
not depend on the thread count. The probe is short: it sees the first 10 steps only, so it
misses a change that acts later (CZSMF's default caps are reached after 34 steps on fermenter;
a change to the reduction at the caps keeps the fingerprint). Merge the chunks of one code
version with ``--source HASH`` whenever the code changed between runs.

    python benchmarks/filters_audit.py --filters czsmf --systems fermenter --noises vertex \
        --log audit.jsonl --first 300          # resumes after 3 logged chunks
    python benchmarks/filters_audit.py --filters czsmf --systems fermenter --noises vertex \
        --log audit.jsonl --resume             # the same, found in the log
    python benchmarks/filters_audit.py --merge audit.jsonl
    python benchmarks/filters_audit.py --merge audit.jsonl --source 15ff9b4e0824  # one source

``--resume`` audits the first stretch of the requested trajectories (``--first`` /
``--count``) that has no logged chunk of the same row (system, filter, noise, trials, steps,
seed and sets fingerprint) logged by the same package source, up to the next such chunk, so
that a stopped run continues where its log ends without overlapping chunks; run it again to
fill a later gap. One process per row: two processes resuming the same row would audit the
same trajectories.

A system with a size argument is given as ``NAME:N`` (``oscillator_chain:16`` is
``systems.get("oscillator_chain", n=16)``; its rows are named the same way).

Filters are built with their defaults; ``--filter-kwargs JSON`` passes keyword arguments to
every audited filter (e.g. CZSMF's caps), and the filter column names them:

    python benchmarks/filters_audit.py --filters czsmf --systems bilinear \
        --filter-kwargs '{"max_generators": 30, "max_constraints": 5, "elimination": "propagation"}'
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import pathlib
import sys

import torch

import diffsmf
from diffsmf import filters, systems
from diffsmf.audit import containment, paper_steps

HEADER = (
    "| system | filter | noise | trajectories x steps | outside / pairs | worst dist. "
    "| mean volume | inconsistent | unbounded | time [s] |\n"
    "|---|---|---|---|---:|---:|---:|---:|---:|---:|"
)


def _unbounded(r: dict) -> int | None:
    """Unbounded pairs of a logged chunk. Chunks logged before the audit counted them have no
    such entry: 0 when their volume sum is finite (an unbounded set has infinite volume),
    else unknown (``None``)."""
    if "unbounded" in r:
        return int(r["unbounded"])
    return 0 if math.isfinite(r["volume_sum"]) else None


def source_fingerprint() -> str:
    """sha256 (first 12 hex digits) of the package's Python sources: chunks logged with the
    same fingerprint were filtered by the same code."""
    h = hashlib.sha256()
    root = pathlib.Path(diffsmf.__file__).parent
    for f in sorted(root.rglob("*.py")):
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


def sets_fingerprint(fname: str, system, noise: str, seed: int, kw: dict | None = None) -> str:
    """sha256 (first 12 hex digits) of the bounds that the filter gives on a probe (2
    trajectories x 10 steps of this noise and seed): a code change that leaves the sets bit
    for bit the same keeps it, so chunks logged before and after such a change merge."""
    tr = system.simulate(steps=min(10, paper_steps(system)), batch=2, seed=seed, noise=noise)
    with torch.no_grad():
        res = filters.by_name(fname)(system, **(kw or {}))(tr.y, u=tr.u)
    h = hashlib.sha256(res.lower.numpy().tobytes())
    h.update(res.upper.numpy().tobytes())
    return h.hexdigest()[:12]


ROW_KEYS = ("system", "filter", "noise", "trials", "steps", "seed", "sets")


def _log_rows(path: str) -> list[dict]:
    """The chunk records of a ``--log`` file, one per non-blank line."""
    lines = pathlib.Path(path).read_text().splitlines()
    return [json.loads(line) for line in lines if line.strip()]


def logged_chunks(path: str, meta: dict) -> list[tuple[int, int]]:
    """``(start, stop)`` of the chunks of ``meta``'s row (`ROW_KEYS`) logged in ``path``
    by the same package source (none if the file does not exist), sorted. A chunk of other
    code counts as not done even when its sets are the same: the containment check itself
    lives in the package (e.g. the reference LPs' tolerance), so a re-run must redo it."""
    if not pathlib.Path(path).exists():
        return []
    keys = (*ROW_KEYS, "source")
    key = tuple(meta[k] for k in keys)
    mine = (r for r in _log_rows(path) if tuple(r.get(k) for k in keys) == key)
    return sorted({(r["start"], r["stop"]) for r in mine})


def resume_range(first: int, count: int, chunks: list[tuple[int, int]]) -> tuple[int, int]:
    """``(first, count)`` of the first stretch of ``first .. first + count - 1`` that no
    chunk covers, up to the next chunk; ``count = 0`` when every trajectory is covered."""
    start, end = first, first + count
    for a, b in chunks:  # sorted by start
        if a <= start < b:
            start = b
    if start >= end:
        return start, 0
    nxt = min((a for a, _ in chunks if a > start), default=end)
    return start, min(nxt, end) - start


def merge(path: str, sources: list[str] | None = None) -> int:
    """Print the table of a ``--log`` file: one row per (system, filter, noise, trials, steps,
    seed, sets fingerprint), the union of its chunks; a chunk logged twice (same first
    trajectory) counts once, the later entry; overlapping chunks are an error. ``sources``:
    only the chunks logged by these package sources (e.g. a row re-run after a change of the
    containment check, whose earlier chunks have the same sets and overlap the new ones)."""
    groups: dict[tuple, dict[int, dict]] = {}
    for r in _log_rows(path):
        if sources and r.get("source") not in sources:
            continue
        groups.setdefault(tuple(r[k] for k in ROW_KEYS), {})[r["start"]] = r
    print(HEADER)
    bad = 0
    for (sname, fname, noise, trials, steps, seed, fp), parts in groups.items():
        rs = sorted(parts.values(), key=lambda r: r["start"])
        for a, b in zip(rs, rs[1:]):
            if b["start"] < a["stop"]:
                print(f"{path}: overlapping chunks {a['start']}-{a['stop']} and "
                      f"{b['start']}-{b['stop']} ({sname}, {fname}, {noise})", file=sys.stderr)
                return 2
        done = sum(r["stop"] - r["start"] for r in rs)
        counts = [_unbounded(r) for r in rs]
        unb = "?" if None in counts else sum(counts)
        viol = sum(r["violations"] for r in rs)
        bad += viol
        print(
            f"| {sname} | {fname} | {noise} | {done} x {steps} "
            f"({'all' if done == trials else f'{done} of'} {trials}, seed {seed}, sets {fp}) | "
            f"{viol} / {sum(r['pairs'] for r in rs)} | "
            f"{max(r['worst_distance'] for r in rs):.1e} | "
            f"{sum(r['volume_sum'] for r in rs) / (done * steps):.3e} | "
            f"{sum(r['inconsistent'] for r in rs)} | {unb} | "
            f"{sum(r['seconds'] for r in rs):.0f} |"
        )
    return 1 if bad else 0


def _system(spec: str):
    """``NAME`` or ``NAME:N`` (the system's size argument ``n``) -> the built-in system."""
    systems.check_name(spec, option="--systems")
    return systems.get(spec)


def _filter_kwargs(text: str | None) -> dict:
    """``--filter-kwargs`` (a JSON object) -> dict; a one-line ``ValueError`` otherwise."""
    if text is None:
        return {}
    try:
        kw = json.loads(text)
    except json.JSONDecodeError as e:
        raise ValueError(f"--filter-kwargs: not JSON ({e.msg}): {text!r}") from None
    if not isinstance(kw, dict):
        raise ValueError(f"--filter-kwargs: expected a JSON object, got {text!r}")
    return kw


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=1000)
    ap.add_argument("--trials-for", nargs="*", default=[], help="NAME=COUNT overrides")
    ap.add_argument("--steps", type=int, default=None, help="override every horizon")
    ap.add_argument("--systems", nargs="*", default=None,
                    help="built-in names; NAME:N for a sized system (oscillator_chain:16)")
    ap.add_argument("--filters", nargs="*", default=["hsnsmf", "mszm", "cdsmf", "esmf"])
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--compile", default=None, metavar="BACKEND",
                    help="audit the compiled step: filt.compile(backend=BACKEND), e.g. "
                         "'inductor' or 'eager' (the traced step without Inductor)")
    ap.add_argument("--filter-kwargs", default=None, metavar="JSON",
                    help='keyword arguments for every audited filter, e.g. \'{"max_generators": '
                    '30, "max_constraints": 5, "elimination": "propagation"}\' (CZSMF caps); '
                    "the filter column and the log name them")
    ap.add_argument("--noises", nargs="+", default=["vertex", "uniform"],
                    choices=["vertex", "uniform"], help="noise kinds (default both)")
    ap.add_argument(
        "--progress", action="store_true",
        help="progress bars on stderr; filters each batch in chunks of 100 trajectories "
        "(same trajectories; CZSMF runs faster in chunks: its LP batches then fit in cache)",
    )
    ap.add_argument("--first", type=int, default=0,
                    help="audit the trajectories from this index on (of --trials)")
    ap.add_argument("--count", type=int, default=None,
                    help="audit this many trajectories (default: up to --trials)")
    ap.add_argument("--log", default=None,
                    help="append one JSON line per chunk of 100 trajectories to this file")
    ap.add_argument("--resume", action="store_true",
                    help="with --log: audit the first stretch of the requested trajectories "
                    "that has no logged chunk of the same row (see above)")
    ap.add_argument("--merge", default=None, metavar="LOG",
                    help="print the table of a --log file and exit")
    ap.add_argument("--source", nargs="+", default=None, metavar="HASH",
                    help="with --merge: only the chunks logged by these package sources")
    args = ap.parse_args()
    if args.source and not args.merge:
        raise ValueError("--source: only with --merge (which chunks to merge)")
    if args.merge:
        return merge(args.merge, args.source)
    if args.resume and not args.log:
        raise ValueError("--resume: needs --log (the log to resume from)")
    torch.set_default_dtype(torch.float64)
    source = source_fingerprint() if args.log else None
    override = {k: int(v) for k, v in (s.split("=") for s in args.trials_for)}
    kw = _filter_kwargs(args.filter_kwargs)
    names = args.systems or systems.names()
    print(HEADER)
    bad = 0
    for sname in names:
        system = _system(sname)
        if system.process_cov is not None or system.measurement_cov is not None:
            print(f"| {sname} | - | - | - | skipped: Gaussian noise, no guaranteed bound | | | | |")
            continue
        trials = override.get(sname, args.trials)
        for fname in args.filters:
            for noise in args.noises:
                filt = filters.by_name(fname)(system, **kw)
                label = type(filt).__name__ + (f" {json.dumps(kw, sort_keys=True)}" if kw else "")
                if args.compile:
                    filt.compile(backend=args.compile)
                    label += f" (compiled, {args.compile})"
                on_chunk = None
                if args.log:
                    meta = {
                        "system": sname, "filter": label, "noise": noise,
                        "trials": trials, "steps": args.steps or paper_steps(system),
                        "seed": args.seed, "source": source,
                        "sets": sets_fingerprint(fname, system, noise, args.seed, kw),
                    }

                    def on_chunk(part: dict, meta: dict = meta) -> None:
                        with open(args.log, "a") as fh:
                            fh.write(json.dumps({**meta, **part}) + "\n")

                first, count = args.first, args.count
                todo = trials - first if count is None else count
                if args.resume and 0 <= first < trials and 1 <= todo <= trials - first:
                    # (bad --first / --count: left to containment's one-line errors)
                    first, count = resume_range(first, todo, logged_chunks(args.log, meta))
                    if count == 0:
                        print(f"| {sname} | {label} | {noise} | all requested trajectories "
                              f"logged in {args.log} | | | | | | |", flush=True)
                        continue
                rep = containment(
                    filt, system, trials, args.steps, noise, args.seed,
                    progress=args.progress, first=first, count=count, on_chunk=on_chunk,
                )
                bad += rep.violations
                print(
                    f"| {sname} | {label} | {noise} | {rep.trials} x {rep.steps} | "
                    f"{rep.violations} / {rep.pairs} | {rep.worst_distance:.1e} | "
                    f"{rep.mean_volume:.3e} | {rep.inconsistent} | {rep.unbounded} | "
                    f"{rep.seconds:.0f} |",
                    flush=True,
                )
    return 1 if bad else 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except (ValueError, KeyError, OSError, TypeError) as e:  # a bad option, log file or line
        print(f"filters_audit.py: {type(e).__name__}: {e}", file=sys.stderr)
        sys.exit(2)
