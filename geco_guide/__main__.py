"""``geco <command> ...`` (installed) or ``python -m geco_guide <command> ...``: every command of the
package under one name, as ``accelerate`` gathers its own.

Each command is a module of :mod:`geco_guide.cli` with ``SUMMARY`` (its line in ``geco --help``),
``DESCRIPTION``, ``register_subcommand(parser)`` (its options) and ``run(args)`` (the work, whose
heavy imports happen inside it), so that ``geco --help``, ``geco <command> --help`` and a mistyped
option answer at once, without torch.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from importlib import import_module

from . import __version__
from .cli.command_line import parse_command
from .cli.kit import Parser

__all__ = ["COMMANDS", "build_parser", "main"]

#: command -> its module in geco_guide.cli, in the order ``geco --help`` lists them
COMMANDS = {
    "generate": "generate",
    "evaluate": "evaluate",
    "geco-eval": "geco_eval",
    "compare": "compare",
    "ab": "ab",
    "detection": "detection",
    "benchmarks": "benchmarks",
    "validate": "validate",
    "robustness": "robustness",
    "bench": "bench",
}


def build_parser() -> tuple[Parser, dict[str, argparse.ArgumentParser]]:
    """``(the geco parser, {command: its parser})``."""
    parser = Parser(prog="geco", description="GeCo: geometric-consistency guidance and evaluation of video diffusion "
                                             "models.", epilog="geco <command> --help shows a command's options.")
    parser.add_argument("--version", action="version", version=f"geco_guide {__version__}")
    commands = parser.add_subparsers(title="commands", metavar="<command>", parser_class=Parser)
    parsers = {}
    for name, module_name in COMMANDS.items():
        module = import_module(f"geco_guide.cli.{module_name}")
        command = commands.add_parser(name, help=module.SUMMARY, description=module.DESCRIPTION,
                                      formatter_class=argparse.RawDescriptionHelpFormatter)
        module.register_subcommand(command)
        command.set_defaults(run=module.run)
        parsers[name] = command
    return parser, parsers


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser, parsers = build_parser()
    if not argv:
        parser.print_help(sys.stderr)
        return 2
    if argv[0] not in parsers:
        if argv and not argv[0].startswith("-"):
            parser.error(f"unknown command {argv[0]!r}; one of {', '.join(parsers)}")
        parser.parse_args(argv)  # --help, --version, or an option geco itself lacks
        return 2
    args = parse_command(parsers[argv[0]], argv[1:])
    return args.run(args)


if __name__ == "__main__":
    sys.exit(main())
