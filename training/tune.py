"""``python -m training.tune`` / ``python training/tune.py``: the ``diffsmf tune`` command.

    python -m training.tune --system spring_damper --filter hsnsmf --epochs 200 --out runs/sd
    python -m training.tune --config training/spring_damper.toml
    torchrun --nproc_per_node 2 -m training.tune ...      # data-parallel (gloo / NCCL)

Options, outputs and one-line user errors as ``diffsmf tune --help`` (`diffsmf.cli.tune`).
"""

import sys

from diffsmf.cli import run_command

if __name__ == "__main__":
    raise SystemExit(run_command("tune", sys.argv[1:], prog="python -m training.tune"))
