"""Run configuration of ``diffsmf tune`` (command line and ``--config file.toml``)."""

from __future__ import annotations

import sys
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["TuneConfig", "load_config"]


@dataclass
class TuneConfig:
    """Every option of the tuning command; TOML keys use the same names.

    ``init_scale`` multiplies the system's noise bounds before tuning (5 = start from 5 b*);
    ``loss``: ``auto`` (containment when the true states are used, i.e. ``ground_truth``),
    ``consistency``, ``containment`` or ``both``; ``params``: hyperparameter names to tune
    (``process_noise``, ``measurement_noise``, ``stirling_step``, ``remainder_margin``,
    ``minkowski_scale``; the margin starts from ``filter_kwargs.remainder_margin``, which must
    be > 0 to move; ``minkowski_scale``, CDSMF and ESMF only, from 1 = the Minkowski rule);
    ``tie``: ``noise`` (one shared scale for all noise bounds), ``none``, or ``auto`` (``noise``
    without ground truth, where the split between process and measurement noise is not
    identifiable, else ``none``); ``window``: steps per window of truncated
    back-propagation (``tune(window=...)``, `diffsmf.tuning.windows`), 0 = the whole horizon;
    ``compile``: tune through the compiled step (``tune(compile=True)``: a one-off compile,
    then 5-8x faster epochs, measured).

    Your own model and logs (instead of simulating ``system``): ``model`` is
    ``FILE.py:FUNC`` (a function that returns your ``System``, whose noise sets are the
    starting guess), ``data`` the log files (one run each, all of the same length; the
    formats of ``diffsmf filter``), ``outputs`` / ``inputs`` their comma-separated columns,
    ``val_runs`` how many of the last runs are held out for validation (0: none);
    ``safety`` (>= 1) multiplies the tuned half-widths written to ``bounds.json``.
    """

    system: str = "spring_damper"
    model: str | None = None
    data: list[str] = field(default_factory=list)
    outputs: str | None = None
    inputs: str | None = None
    val_runs: int = 0
    safety: float = 1.25
    filter: str = "hsnsmf"
    filter_kwargs: dict[str, Any] = field(default_factory=dict)
    epochs: int = 200
    batch_size: int = 64
    trajectories: int = 64
    val_trajectories: int = 32
    test_trajectories: int = 200
    steps: int = 100
    noise: str = "vertex"
    init_scale: float = 1.0
    ground_truth: bool = False
    loss: str = "auto"
    params: list[str] = field(
        default_factory=lambda: ["process_noise", "measurement_noise", "stirling_step"]
    )
    tie: str = "auto"
    optimizer: str = "adam"
    lr: float = 0.05
    patience: int = 10
    val_every: int = 5
    checkpoint_every: int = 20
    seed: int = 0
    window: int = 0
    compile: bool = False
    out: str = "runs/tune"
    progress: bool = True
    weights: dict[str, float] = field(default_factory=dict)

    @classmethod
    def keys(cls) -> list[str]:
        return [f.name for f in fields(cls)]


#: keys whose default is None and whose value is a string
_OPTIONAL_STR = ("model", "outputs", "inputs")


def load_config(path: str | Path) -> dict[str, Any]:
    """Read a TOML file of `TuneConfig` keys; unknown keys raise ``ValueError``."""
    p = Path(path)
    if not p.exists():
        raise ValueError(f"config: no such file {str(p)!r}")
    if not p.is_file():
        kind = "a folder" if p.is_dir() else "not a regular file"
        raise ValueError(f"config: {str(p)!r} is {kind}, not a TOML file")
    try:
        with p.open("rb") as fh:
            data = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"config: {str(p)!r} is not valid TOML ({exc})") from None
    except UnicodeDecodeError:
        raise ValueError(f"config: {str(p)!r} is not a UTF-8 text (TOML) file") from None
    unknown = sorted(set(data) - set(TuneConfig.keys()))
    if unknown:
        raise ValueError(f"config: unknown keys {unknown}; allowed: {TuneConfig.keys()}")
    defaults = TuneConfig()
    for key, value in data.items():
        want = str if key in _OPTIONAL_STR else type(getattr(defaults, key))
        ok = isinstance(value, want) or (want is float and isinstance(value, int))
        if not ok or (want is not bool and isinstance(value, bool)):
            kind = {int: "an integer", float: "a number", bool: "true or false", str: "a string",
                    list: "a list", dict: "a table"}.get(want, want.__name__)
            raise ValueError(f"config: {key} = {value!r} in {str(p)!r} must be {kind}")
    return data
