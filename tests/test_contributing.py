"""CONTRIBUTING.md names real files: every repository path it quotes exists (``NAME`` stands for a
model's name), and every name of the package it quotes as code is defined where it says."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "CONTRIBUTING.md"


def quoted_paths() -> list[str]:
    """The quoted repository paths: a folder of the repository, then a file or folder inside it."""
    quoted = re.findall(r"`([^`\s]+)`", GUIDE.read_text())
    return [q for q in quoted if re.match(r"(geco_guide|tests|configs|docs|\.ci)/", q) or q == "README.md"]


def test_every_path_the_guide_names_exists():
    paths = quoted_paths()
    assert len(paths) >= 15, paths
    missing = [p for p in paths if "NAME" not in p and not (ROOT / p).exists()]
    assert not missing, f"CONTRIBUTING.md names paths that do not exist: {missing}"


def test_the_adapter_methods_and_registries_it_names_exist():
    from geco_guide.families import FAMILIES, MODELS, TINY_DECODERS, VideoModel  # noqa: F401
    from geco_guide.families.published import LEFT_OUT  # noqa: F401
    from geco_guide.sampler.pipelines import adapters  # noqa: F401
    from geco_guide.sampler import register_adapter  # noqa: F401
    from geco_guide.sampler.pipelines.sampling import fit_to_model  # noqa: F401
    from geco_guide.tiny import tiny_call_kwargs  # noqa: F401

    for method in ("frames_first", "denormalize", "denoisers", "combine", "traced_prediction"):
        assert callable(getattr(adapters.PipelineAdapter, method))
    for name in ("WanAdapter", "LTXAdapter", "HunyuanVideo15Adapter", "LTX2Adapter"):
        assert adapters.ADAPTERS[name].__name__ == name
    for field in ("text_length", "image_to_video", "size_multiple", "frame_multiple", "tiny", "tiny_decoder",
                  "adapter", "schedulers", "tiny_call"):
        assert field in VideoModel.__dataclass_fields__
