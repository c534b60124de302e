"""The ``diffsmf`` command. Each sub-command lives in its own module, imported only when used.

A sub-command module exposes ``add_arguments(parser)`` and ``main(args) -> int``.

User errors are reported here, once, for every sub-command: a bad option, a missing or
malformed file, an unknown name, or any ``ValueError`` / ``FileNotFoundError`` raised while
running prints **one line** ``diffsmf <command>: error: <what is wrong>`` to stderr and exits
with status 2. Other exceptions are bugs and keep their traceback. Set ``DIFFSMF_TRACEBACK=1``
to see the traceback of a user error too.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from typing import NoReturn

from diffsmf import __version__

COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("diffsmf.cli.demo", "run the built-in demo (filters on spring_damper, sets, PWL fit)"),
    "filter": ("diffsmf.cli.filter", "run a set-membership filter on your model and logged data"),
    "compare": ("diffsmf.cli.compare", "several observers on the same data, side by side"),
    "audit": ("diffsmf.cli.audit", "containment audit of a filter on a built-in system"),
    "fit-pwl": ("diffsmf.cli.pwl", "fit an SCPLNN piecewise-linear model to a CSV file"),
    "design-observer": ("diffsmf.cli.observer", "PWL model + LMI observer design pipeline"),
    "tune": ("diffsmf.cli.tune", "tune filter hyperparameters by gradient descent on set volume"),
}

#: Exceptions that mean "the user gave something wrong" (one-line error, exit 2). Configuration
#: parse errors (``tomllib.TOMLDecodeError``, ``json.JSONDecodeError``) subclass ValueError.
USER_ERRORS: tuple[type[BaseException], ...] = (
    ValueError,
    FileNotFoundError,
    IsADirectoryError,
    NotADirectoryError,
    PermissionError,
    FileExistsError,
)

EXIT_USAGE = 2


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """``--help`` shows every option's default and keeps the description's line breaks.

    Defaults of ``None`` (required options, or "computed": the help says how) and of flags
    (``store_true``) are not printed.
    """

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None or isinstance(action.default, bool):
            return action.help
        return super()._get_help_string(action)


class CommandParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line: ``prog: error: message``."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {_one_line(message)} (see {self.prog} -h)\n")


def _one_line(text: str) -> str:
    return "; ".join(line.strip() for line in str(text).strip().splitlines() if line.strip())


def format_user_error(exc: BaseException) -> str:
    """The one-line text of a user error (``FileNotFoundError`` shows the path)."""
    if isinstance(exc, OSError) and exc.filename is not None:
        return f"{exc.strerror or type(exc).__name__}: {exc.filename}"
    text = _one_line(str(exc))
    return text or type(exc).__name__


def _version() -> str:
    return f"diffsmf {__version__}"


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser (``diffsmf COMMAND ...``; sub-command options are parsed later)."""
    p = CommandParser(
        prog="diffsmf",
        description="Differentiable set-membership filters, PWL models and LMI observers.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="commands:\n"
        + "\n".join(f"  {name:<16} {help_}" for name, (_, help_) in COMMANDS.items())
        + "\n\nRun 'diffsmf COMMAND --help' for the options of a command (with defaults).",
    )
    p.add_argument("--version", action="version", version=_version())
    p.add_argument("command", choices=list(COMMANDS), metavar="COMMAND")
    return p


def build_subparser(name: str, prog: str | None = None) -> tuple[argparse.ArgumentParser, object]:
    """Parser of ``diffsmf NAME`` (or ``prog``) and the module implementing it."""
    module = importlib.import_module(COMMANDS[name][0])
    doc = (module.__doc__ or "").strip().replace("``", "")
    sub = CommandParser(
        prog=prog or f"diffsmf {name}",
        description=doc or COMMANDS[name][1],
        formatter_class=HelpFormatter,
    )
    module.add_arguments(sub)
    return sub, module


def run_command(name: str, argv: list[str], prog: str | None = None) -> int:
    """Parse ``argv`` for sub-command ``name`` and run it; user errors -> one line, status 2.

    ``prog`` names the command in messages (default ``diffsmf NAME``).
    """
    prog = prog or f"diffsmf {name}"
    try:
        sub, module = build_subparser(name, prog)
        args = sub.parse_args(argv)
        return int(module.main(args) or 0)
    except USER_ERRORS as exc:
        if os.environ.get("DIFFSMF_TRACEBACK"):
            raise
        print(f"{prog}: error: {format_user_error(exc)}", file=sys.stderr)
        return EXIT_USAGE
    except SystemExit as exc:  # raise SystemExit("message") in a sub-command = user error
        if isinstance(exc.code, str):
            msg = _one_line(exc.code)
            for prefix in (f"{prog}: ", f"diffsmf {name}: ", f"{name}: "):
                msg = msg.removeprefix(prefix)
            print(f"{prog}: error: {msg}", file=sys.stderr)
            return EXIT_USAGE
        return int(exc.code or 0)  # argparse: --help (0) or a usage error already printed (2)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``diffsmf``; returns the sub-command's exit status (2 for a user error).

    ``--version`` and an unknown command exit through argparse (``SystemExit`` 0 / 2).
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser()
    if not argv or argv[0] in ("-h", "--help"):
        parser.print_help()
        return 0
    if argv[0] not in COMMANDS:
        parser.parse_args(argv[:1])  # --version, or the one-line error: exits (0 or 2)
    return run_command(argv[0], argv[1:])

