"""The ``diffsmf`` command. Each sub-command lives in its own module, imported only when used.

A sub-command module exposes ``add_arguments(parser)`` and ``main(args) -> int``.
"""

from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("diffsmf.demo", "run the built-in demo (filters on spring_damper, sets, PWL fit)"),
    "audit": ("diffsmf.audit", "containment audit of a filter on a built-in system"),
    "fit-pwl": ("diffsmf.pwl.cli", "fit an SCPLNN piecewise-linear model to a CSV file"),
    "design-observer": ("diffsmf.observers.cli", "PWL model + LMI observer design pipeline"),
    "tune": ("training.tune", "tune filter hyperparameters by gradient descent on set volume"),
}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="diffsmf",
        description="Differentiable set-membership filters, PWL models and LMI observers.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="commands:\n"
        + "\n".join(f"  {name:<16} {help_}" for name, (_, help_) in COMMANDS.items())
        + "\n\nRun 'diffsmf COMMAND --help' for the options of a command.",
    )
    p.add_argument("command", choices=sorted(COMMANDS), metavar="COMMAND")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser()
    if not argv or argv[0] in ("-h", "--help"):
        parser.print_help()
        return 0
    if argv[0] not in COMMANDS:
        parser.parse_args(argv[:1])  # prints the error and exits 2
    name = argv[0]
    module = importlib.import_module(COMMANDS[name][0])
    sub = argparse.ArgumentParser(prog=f"diffsmf {name}", description=COMMANDS[name][1])
    module.add_arguments(sub)
    args = sub.parse_args(argv[1:])
    return int(module.main(args) or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
