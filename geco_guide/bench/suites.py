"""GeCo-Eval's prompt suites and the labels that select prompts within them. Imports nothing, so
that the commands' parsers offer them without loading torch (:mod:`geco_guide.bench.geco_eval`
reads the suites)."""

__all__ = ["CAMERAS", "DYNAMIC_SUITE", "PROMPT_FILES", "SCENARIOS", "SUITE"]

SCENARIOS = ("object-centric", "indoor", "outdoor", "appearance-complex")
CAMERAS = ("slow", "fast")
#: The paper's 80 prompts.
SUITE = "geco-eval"
#: Our own prompts with moving subjects (not the paper's): scored and guided with their masks.
DYNAMIC_SUITE = "dynamic"
#: suite -> its JSON-lines file, package data of :mod:`geco_guide.bench`
PROMPT_FILES = {SUITE: "data/geco_eval_prompts.jsonl", DYNAMIC_SUITE: "data/geco_eval_dynamic_prompts.jsonl"}
