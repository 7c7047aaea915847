"""The ``formtwin`` command. Each command group is a module of this package with a
``register(subparsers)`` function; :data:`COMMANDS` lists them in help order."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from formtwin import __version__

COMMANDS: tuple[str, ...] = (
    "spec",
    "plot",
    "doe",
    "metamodel",
    "study",
    "control",
    "demo",
    "serve",
    "replay",
    "export",
    "track",
    "sensors",
)

#: the module of a command whose name is not its module's
MODULE_OF = {"control-study": "control"}


def build_parser(commands: Sequence[str] = COMMANDS) -> argparse.ArgumentParser:
    """The parser with the command groups ``commands`` (default: all, in help order)."""
    parser = argparse.ArgumentParser(
        prog="formtwin",
        description="Hybrid twin for metal-forming mass production (Havinga et al.).")
    parser.add_argument("--version", action="version", version=f"formtwin {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in commands:
        importlib.import_module(f"formtwin.cli.{name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: parse ``argv`` and run the chosen command; returns the exit code.

    Only the chosen command's module is imported (each imports its own stack: ~1-3 s of a
    short command's start otherwise); without a known command, all of them (the help)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    first = next((a for a in argv if not a.startswith("-")), "")
    module = MODULE_OF.get(first, first)
    args = build_parser((module,) if module in COMMANDS else COMMANDS).parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.run(args) or 0)
    except (ValueError, OSError) as exc:
        print(f"formtwin {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
