"""A/B test of GeCo guidance on your prompts: unguided vs guided video from the same noise, and
with ``--best-of`` a third arm, selection among unguided seeds (``geco ab``; the docs: docs/geco_eval.md).

    python scripts/ab_compare.py --prompts prompts.txt --seeds 0 1 2 --out ab/ --preset tiny
    python scripts/ab_compare.py --prompts prompts.jsonl --seeds 0 --out ab/ --config my.yaml guidance.step_size=2.0
    accelerate launch scripts/ab_compare.py --prompts prompts.txt --seeds 0 1 --out ab/ --preset cogvideox-5b

Everything it does is :mod:`geco_guide.cli.ab`'s; this file keeps the command that ``accelerate
launch`` (which starts a script) and existing notes call.
"""

from __future__ import annotations

import sys

from geco_guide.cli import ab

PROG = "scripts/ab_compare.py"


def build_parser():
    return ab.build_parser(PROG)


main = ab.command(PROG)


if __name__ == "__main__":
    sys.exit(main())
