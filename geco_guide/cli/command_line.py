"""A command line parsed as every ``geco`` command parses it: options and positionals in any order,
the ``key=value`` overrides that a list option took given back, and the command as typed kept for
the reports that say how to run it again; and ``main(argv)`` of a command run on its own."""

from __future__ import annotations

import argparse
import shlex
import sys
from collections.abc import Callable, Sequence
from typing import Any

from .kit import Parser, split_overrides

__all__ = ["command_main", "parse_command"]


def parse_command(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> argparse.Namespace:
    """``argv`` parsed by a command's ``parser``, options and positionals in any order
    (``geco evaluate a.mp4 --out scores evaluation.max_frames=9``), except for a command made of
    subcommands, whose options follow its subcommand; ``args.command_line`` is the command as
    typed (``geco <command> ...``), for the reports that say how to run them again."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if any(isinstance(action, argparse._SubParsersAction) for action in parser._actions):
        args = parser.parse_args(argv)
    else:
        args = parser.parse_intermixed_args(argv)
        _return_overrides(parser, args)
    args.command_line = shlex.join([*parser.prog.split(), *argv])
    return args


def _return_overrides(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Give the command's ``key=value`` positionals back what a list option took of them: an
    option of several values (``--devices cuda:0 cuda:1``) takes every word after it, so the
    overrides typed after it would be read as devices (or seeds, or model names)."""
    positional = next((action for action in parser._actions if not action.option_strings
                       and action.nargs in ("*", "+") and "key=value" in str(action.metavar)), None)
    if positional is None:
        return
    for action in parser._actions:
        values = getattr(args, action.dest, None)
        if not action.option_strings or action.nargs not in ("*", "+") or not isinstance(values, list):
            continue
        overrides, kept = split_overrides(value for value in values if isinstance(value, str))
        if overrides:
            if action.nargs == "+" and not kept:
                parser.error(f"argument {action.option_strings[0]}: expected at least one value before "
                             f"{overrides[0]!r}")
            setattr(args, action.dest, [value for value in values if value not in overrides])
            setattr(args, positional.dest, [*(getattr(args, positional.dest) or []), *overrides])


def command_main(prog: str, description: str, register_subcommand: Callable[[argparse.ArgumentParser], Any],
                 run: Callable[[argparse.Namespace], int]) -> Callable[[Sequence[str] | None], int]:
    """``main(argv)`` of a command run on its own (``geco-generate``, ``python -m
    geco_guide.generate``, a test): its options on a parser of its own, then ``run``, as ``geco
    <command>`` runs it."""

    def main(argv: Sequence[str] | None = None) -> int:
        parser = Parser(prog=prog, description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
        register_subcommand(parser)
        return run(parse_command(parser, argv))

    main.__doc__ = f"``{prog}``: the command on its own ({description})"
    return main
