"""``python -m training`` is ``python -m training.tune`` (same one-line user errors)."""

import sys

from diffsmf.cli import run_command

raise SystemExit(run_command("tune", sys.argv[1:], prog="python -m training"))
