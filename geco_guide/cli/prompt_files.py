"""Prompt files (what ``geco ab --prompts`` reads): one prompt per line, or JSON
lines ``{"id": ..., "prompt": ..., "subjects": ...}``, or a GeCo-Eval suite by name
(``geco-eval[:SCENARIO][:CAMERA]``, the paper's; ``dynamic[...]``, ours with moving subjects).

A prompt's id (its slug when not given) names output folders, so ids must be unique and
filesystem-safe. ``subjects`` names what moves on its own (``"a dog, a ball"``): it is masked in
the scores and the guidance. Anything wrong is one :class:`PromptFileError` line naming the file
and line.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

from ..bench.geco_eval import PROMPT_FILES, select_prompts
from ..estimators.segmenters import subjects_of
from ..generation import slugify

__all__ = ["Prompt", "read_prompts"]

SAFE_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")


class PromptFileError(ValueError):
    """A prompt file (or suite name) that cannot be read, in one line naming the file and line."""


@dataclass(frozen=True)
class Prompt:
    id: str
    text: str
    subjects: str | None = None  # what moves on its own, masked in scores and guidance


def parse_prompt_line(line: str, where: str) -> Prompt:
    """One non-empty line: plain text, or a JSON object with ``prompt`` and optional ``id`` and
    ``subjects``."""
    if not line.startswith("{"):
        return Prompt(slugify(line), line)
    try:
        item = json.loads(line)
    except json.JSONDecodeError as err:
        raise PromptFileError(f"{where}: not valid JSON ({err.msg})") from None
    text = item.get("prompt") if isinstance(item, dict) else None
    if not isinstance(text, str) or not text.strip():
        raise PromptFileError(f"{where}: a JSON line needs a non-empty string 'prompt'")
    subjects = item.get("subjects")
    try:
        subjects is None or subjects_of(subjects)
    except ValueError as err:
        raise PromptFileError(f"{where}: 'subjects' {err}") from None
    if item.get("id") is None:
        return Prompt(slugify(text), text.strip(), subjects)
    prompt_id = str(item["id"])
    if not SAFE_ID.fullmatch(prompt_id):
        raise PromptFileError(
            f"{where}: id {prompt_id!r} is not filesystem-safe (1-64 letters, digits, '.', '_', '-', "
            f"not starting with '.', '_' or '-'), e.g. {slugify(prompt_id)!r}"
        )
    return Prompt(prompt_id, text.strip(), subjects)


def read_prompts(path: str | os.PathLike) -> list[Prompt]:
    """The prompts of a file, or of a GeCo-Eval suite (``geco-eval[:SCENARIO][:CAMERA]``, ids
    a1..d20; ``dynamic[...]``, ours, ids m1..m24 with their subjects); PromptFileError naming the
    file and line for anything wrong."""
    if str(path).split(":")[0] in PROMPT_FILES and not Path(path).exists():
        try:
            return [Prompt(p["id"], p["prompt"], p.get("subjects")) for p in select_prompts(str(path))]
        except ValueError as err:
            raise PromptFileError(str(err)) from None
    path = Path(path)
    if path.is_dir():
        raise PromptFileError(f"prompts file {str(path)!r} is a folder, not a prompt file")
    if not path.is_file():
        raise PromptFileError(f"prompts file {str(path)!r} does not exist")
    prompts: list[Prompt] = []
    first_line: dict[str, int] = {}
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise PromptFileError(f"prompts file {str(path)!r} is not UTF-8 text (byte {err.start}: {err.reason})") from None
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        prompt = parse_prompt_line(line, f"{path}:{number}")
        if prompt.id in first_line:
            raise PromptFileError(
                f"{path}:{number}: prompt id {prompt.id!r} already used on line {first_line[prompt.id]}; "
                'give distinct ids with JSON lines {"id": ..., "prompt": ...}'
            )
        first_line[prompt.id] = number
        prompts.append(prompt)
    if not prompts:
        raise PromptFileError(f"prompts file {str(path)!r} holds no prompts")
    return prompts
