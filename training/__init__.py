"""Tuning entry points and configurations for a source checkout (not installed).

The library is `diffsmf.tuning`; the command is ``diffsmf tune`` (`diffsmf.cli.tune`). From the
repository root, ``python -m training.tune`` (or ``python training/tune.py``) runs the same
command, e.g. ``python -m training.tune --config training/spring_damper.toml``.
"""
