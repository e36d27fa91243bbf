"""diffusers' private attributes are read in one module (geco_guide.sampler.diffusers_private),
and each of its readers still finds its attribute on the installed diffusers' real objects (tiny
random models): a release that renames one fails here, naming it."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest
import torch

import geco_guide
from geco_guide import tiny as T
from geco_guide.sampler import diffusers_private as private
from geco_guide.sampler.running.module_hooks import hooked

PACKAGE = Path(geco_guide.__file__).parent
READER = PACKAGE / "sampler" / "diffusers_private.py"


def private_names_read_by_the_reader() -> set[str]:
    """The private attribute names the module touches: ``x._name`` and ``getattr(x, "_name")``."""
    return set(re.findall(r"\._([a-z][a-z_0-9]*)\b|\"_([a-z][a-z_0-9]*)\"", READER.read_text())) - {("", "")}


def private_reads(path: Path, names: set[str]) -> list[str]:
    """``obj._name`` and ``getattr/hasattr(obj, "_name")`` of ``names`` in ``path``, ``self`` and
    ``cls`` excepted (a class' own state)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        name = base = None
        if isinstance(node, ast.Attribute):
            name, base = node.attr, node.value
        elif (isinstance(node, ast.Call) and getattr(node.func, "id", None) in ("getattr", "hasattr", "setattr")
              and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant)):
            name, base = node.args[1].value, node.args[0]
        if isinstance(name, str) and name.lstrip("_") in names and name.startswith("_") \
                and getattr(base, "id", None) not in ("self", "cls"):
            found.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno}: {name}")
    return found


def test_no_other_module_reads_the_private_attributes_the_reader_wraps():
    names = {a or b for a, b in private_names_read_by_the_reader()}
    assert {"execution_device", "cp_plan", "diffusers_hook", "all_hooks"} <= names
    reads = [hit for path in sorted(PACKAGE.rglob("*.py")) if path != READER for hit in private_reads(path, names)]
    assert reads == []


def test_the_readers_find_their_attributes_on_a_tiny_wan():
    from diffusers.hooks import ModelHook

    pipe = T.tiny_wan_pipeline(0)
    transformer = pipe.transformer
    assert private.execution_device(pipe) == torch.device("cpu") and not private.offloads_models(pipe)
    assert private.context_parallel_plan(transformer) is not None and private.parallel_config(transformer) is None
    assert private.supports_gradient_checkpointing(transformer) and not private.supports_gradient_checkpointing(pipe)
    assert "norm" in " ".join(private.keeps_in_fp32(transformer))
    assert private.cache_config(transformer) is None and private.hook_registry(transformer) is None
    with hooked(transformer, ModelHook(), "probe"):
        assert type(private.hook_registry(transformer)).__name__ == "HookRegistry"
    assert private.hook_registry(transformer) is None  # the registry GeCo made is gone again
    alpha, sigma = private.sigma_to_alpha_sigma_t(pipe.scheduler, torch.tensor(0.6))
    assert float(alpha) == pytest.approx(0.4) and float(sigma) == pytest.approx(0.6)
    assert private.active_attention_backend() in private.context_parallel_backends()
    assert private.dtype_keyword() in ("dtype", "torch_dtype")


def test_a_denoiser_cache_is_seen():
    from diffusers import FasterCacheConfig

    transformer = T.tiny_cogvideox_pipeline(0).transformer
    transformer.enable_cache(FasterCacheConfig(
        spatial_attention_block_skip_range=2, spatial_attention_timestep_skip_range=(-1, 901),
        current_timestep_callback=lambda: 0, is_guidance_distilled=True))
    assert type(private.cache_config(transformer)).__name__ == "FasterCacheConfig"
