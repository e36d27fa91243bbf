"""The top-level names: the pipeline and its config import from ``geco_guide`` lazily, so that
importing the package and scoring a video load no diffusion code, and ``dir(geco_guide)`` lists
the public names, not the module's helpers. Every module says what its public names are
(``__all__``): names that exist, none of them a private ``_name``."""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys

import pytest

import geco_guide

MODULES = sorted(info.name for info in pkgutil.walk_packages(geco_guide.__path__, "geco_guide."))


def test_the_pipeline_and_its_config_are_top_level_names():
    from geco_guide import GeCoCogVideoXPipeline, GuidanceConfig
    from geco_guide.sampler.algorithm.config import GuidanceConfig as config_class
    from geco_guide.sampler.pipelines.pipeline_cogvideox import GeCoCogVideoXPipeline as pipeline_class

    assert GeCoCogVideoXPipeline is pipeline_class and GuidanceConfig is config_class
    assert {"GeCoCogVideoXPipeline", "GuidanceConfig"} <= set(geco_guide.__all__)
    assert all(getattr(geco_guide, name) is not None for name in geco_guide.__all__)


def test_dir_lists_the_public_names_only():
    names = dir(geco_guide)
    assert set(geco_guide.__all__) <= set(names) and "__version__" in names
    assert not {"TYPE_CHECKING", "import_module", "_import_module", "_EXPORTS"} & set(names)


@pytest.mark.slow
def test_importing_the_package_and_scoring_a_video_load_no_diffusion_code():
    probe = """
import sys
import geco_guide
from geco_guide import GuidanceConfig
from geco_guide.bench.synthetic import rigid_clip
from geco_guide.estimators.oracle import OracleFlow, OracleGeometry
clip = rigid_clip(num_frames=4, height=24, width=32)
result = geco_guide.evaluate_video(clip.frames, geco_guide.Estimators(OracleGeometry(clip), OracleFlow(clip)), fps=8)
assert result.fused == result.fused  # a score, not NaN
print(sorted(m for m in ("diffusers", "transformers", "accelerate") if m in sys.modules))
"""
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize("name", ["geco_guide", *MODULES])
def test_every_module_lists_its_public_names(name):
    module = importlib.import_module(name)
    assert isinstance(getattr(module, "__all__", None), (list, tuple)), f"{name} has no __all__"
    public = list(module.__all__)
    assert len(public) == len(set(public)), f"{name}.__all__ lists a name twice"
    assert not [n for n in public if n.startswith("_")], f"{name}.__all__ lists private names"
    assert not [n for n in public if not hasattr(module, n)], f"{name}.__all__ lists names it lacks"


def test_an_entry_point_refuses_its_earlier_keywords_in_one_line_and_keeps_its_signature():
    import inspect

    from geco_guide.types import refuses_earlier_keywords

    @refuses_earlier_keywords("fixed", masks="the masks are config.dynamic")
    def fixed(video, estimators=None):
        return video

    @refuses_earlier_keywords("open", masks="the masks are config.dynamic")
    def open_ended(video, **options):
        return options

    assert list(inspect.signature(fixed).parameters) == ["video", "estimators"] and fixed(1, estimators=2) == 1
    assert open_ended(1, fps=8) == {"fps": 8}  # a function that takes any keyword keeps taking them
    for function, where in ((fixed, "fixed"), (open_ended, "open")):
        with pytest.raises(TypeError, match=rf"^{where}\(masks=\.\.\.\) is the earlier spelling: the masks are"):
            function(1, masks=None)
        with pytest.raises(TypeError, match=rf"^{where}\(geometry=\.\.\.\) is the earlier spelling: pass the models as one"):
            function(1, geometry=None)
    with pytest.raises(TypeError, match=r"^fixed\(\) got an unexpected keyword argument 'fps'$"):
        fixed(1, fps=8)
