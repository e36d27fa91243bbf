"""``geco <command> ...`` (installed) or ``python -m geco_guide <command> ...``: every command of the
package under one name, as ``accelerate`` and ``huggingface-cli`` gather theirs.

``geco generate --prompt "..."`` is ``python -m geco_guide.generate --prompt "..."`` (still the
documented entry), and so on for each command below. Listing the commands imports none of them,
so ``geco --help`` answers at once.
"""

from __future__ import annotations

import sys
from importlib import import_module

from . import __version__

__all__ = ["COMMANDS", "main"]

#: command -> (its module in geco_guide.cli, what it does)
COMMANDS = {
    "generate": ("generate", "generate a video with GeCo guidance (or without: --no-guidance)"),
    "evaluate": ("evaluate", "score videos with the GeCo protocol"),
    "geco-eval": ("geco_eval", "run the GeCo-Eval benchmark: generate its prompts with video models and score them"),
    "detection": ("detection", "per-frame detection maps: where a video breaks, frame by frame"),
    "benchmarks": ("benchmarks", "build WarpBench/OccluBench-style clips with ground truth"),
    "validate": ("validate", "score those clips on the paper's three detection tasks"),
    "robustness": ("robustness", "the metric against noisy depth and flow"),
    "ab": ("ab", "A/B test of guidance on your prompts: unguided vs guided (vs best-of-N), same noise"),
}


def usage() -> str:
    width = max(map(len, COMMANDS))
    rows = "\n".join(f"  {name:<{width}}  {summary}" for name, (_, summary) in COMMANDS.items())
    return (f"usage: geco <command> [options]   (also: python -m geco_guide <command>)\n\ncommands:\n{rows}\n\n"
            "geco <command> --help shows a command's options.")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(usage(), file=sys.stdout if argv else sys.stderr)
        return 0 if argv else 2
    if argv[0] == "--version":
        print(f"geco_guide {__version__}")
        return 0
    if argv[0] not in COMMANDS:
        print(f"geco: error: unknown command {argv[0]!r}; one of {', '.join(COMMANDS)} (geco --help)", file=sys.stderr)
        return 2
    module = import_module(f"geco_guide.cli.{COMMANDS[argv[0]][0]}")
    return module.main(argv[1:])


if __name__ == "__main__":
    sys.exit(main())
