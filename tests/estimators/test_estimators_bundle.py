"""One estimator bundle: ``load_estimators`` returns an :class:`Estimators` (geometry, flow and an
optional text segmenter) that the metric, the hooks, the pipeline and the loaders take as one
object; the old ``geometry, flow = load_estimators(...)`` still unpacks it for one release, with a
FutureWarning (tiny models, CPU)."""

from __future__ import annotations

import json
import warnings

import pytest

import geco_guide
from geco_guide import tiny as T
from geco_guide.bench.synthetic import rigid_clip
from geco_guide.config import load_config
from geco_guide.estimators import Estimators, EstimatorsConfig, estimator_ids, load_estimators, load_segmenter
from geco_guide.estimators.oracle import OracleFlow, OracleGeometry
from geco_guide.metric.evaluate import evaluate_video

TINY = EstimatorsConfig(geometry="tiny-random", flow="tiny-random", segmenter="tiny-random", dtype="float32")


@pytest.fixture(scope="module")
def loaded() -> Estimators:
    return load_estimators(TINY, "cpu", segmenter=True)


@pytest.fixture(scope="module")
def clip():
    return rigid_clip(num_frames=4, height=28, width=42)


def test_load_estimators_returns_one_named_bundle(loaded):
    assert isinstance(loaded, Estimators) and geco_guide.Estimators is Estimators
    assert type(loaded.geometry).__name__ == "VGGT" and type(loaded.flow).__name__ == "UFM"
    ids = {"geometry": "tiny-random(seed=0)", "flow": "tiny-random(seed=0)", "segmenter": "tiny-random(seed=0)"}
    assert loaded.ids() == ids == estimator_ids(TINY, segmenter=True)  # a report without the models says the same
    assert repr(loaded) == ("Estimators(geometry=tiny-random(seed=0), flow=tiny-random(seed=0), "
                            "segmenter=tiny-random(seed=0))")
    bare = load_estimators(TINY, "cpu")
    assert bare.segmenter is None and set(bare.ids()) == {"geometry", "flow"} and "segmenter" not in repr(bare)


def test_unpacking_the_old_pair_warns_and_still_works(loaded):
    with pytest.warns(FutureWarning, match=r"estimators\.geometry and estimators\.flow") as caught:
        geometry, flow = loaded
    assert geometry is loaded.geometry and flow is loaded.flow
    assert caught[0].filename == __file__  # the warning points at the caller's line
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the attributes never warn
        assert loaded.geometry is geometry and loaded.with_segmenter(None).segmenter is None


def test_the_segmenter_makes_the_mask_source_of_any_subjects(loaded):
    assert loaded.masks_for(None) is None
    assert loaded.masks_for("a dog").source_name == "sam3: a dog"
    assert loaded.masks_for("a dog, a person").source_name == "sam3: a dog, a person"
    with pytest.raises(ValueError, match="need a segmenter, and none was loaded"):
        loaded.with_segmenter(None).masks_for("a dog")
    one_text = loaded.with_segmenter(loaded.masks_for("a dog"))
    assert one_text.masks_for("a dog") is one_text.segmenter
    assert one_text.ids()["segmenter"] == "sam3: a dog"
    with pytest.raises(ValueError, match="masks a dog, not 'a cat'"):
        one_text.masks_for("a cat")


def test_load_segmenter_alone_names_itself(clip):
    segment = load_segmenter(TINY, "cpu")
    assert segment("a dog").source_name == "sam3: a dog"
    assert Estimators(OracleGeometry(clip), OracleFlow(clip), segment).ids()["segmenter"] == "tiny-random(seed=0)"


def test_evaluate_video_takes_the_bundle(clip):
    oracles = Estimators(OracleGeometry(clip), OracleFlow(clip))
    by_bundle = evaluate_video(clip.frames, fps=8, estimators=oracles)
    by_name = evaluate_video(clip.frames, fps=8, geometry_estimator=OracleGeometry(clip), flow_estimator=OracleFlow(clip))
    assert by_bundle.fused == by_name.fused and by_bundle.motion == by_name.motion
    assert by_bundle.estimators == {"geometry": "OracleGeometry", "flow": "OracleFlow"}
    with pytest.raises(ValueError, match="not both"):
        evaluate_video(clip.frames, fps=8, estimators=oracles, geometry_estimator=OracleGeometry(clip))


def test_evaluate_video_masks_text_subjects_with_the_bundles_segmenter(loaded, clip):
    result = evaluate_video(clip.frames, fps=8, estimators=loaded, dynamic_masks="a dog")
    assert result.dynamic_masks["source"] == "sam3: a dog"
    assert result.estimators == {"geometry": "tiny-random(seed=0)", "flow": "tiny-random(seed=0)"}


def test_attach_geco_guidance_takes_the_bundle(loaded):
    from geco_guide.sampler.hooks import attach_geco_guidance

    pipe = T.tiny_wan_pipeline(0)
    with attach_geco_guidance(pipe, T.tiny_guidance_config(), estimators=loaded) as handle:
        assert handle.geometry_estimator is loaded.geometry and handle.flow_estimator is loaded.flow
    with pytest.raises(ValueError, match="not both"):
        attach_geco_guidance(pipe, T.tiny_guidance_config(), estimators=loaded, flow_estimator=loaded.flow)


def test_the_pipeline_shows_its_components_as_a_bundle():
    from geco_guide.sampler.loading import build_pipeline

    cfg = load_config(preset="tiny")
    pipe = build_pipeline(cfg, components=T.tiny_cogvideox_components(0))
    estimators = pipe.estimators
    assert estimators.geometry is pipe.geometry_estimator and estimators.flow is pipe.flow_estimator
    assert estimators.ids() == estimator_ids(cfg.estimators) and estimators.segmenter is None
    with pytest.raises(AttributeError):
        pipe.estimators = estimators  # read-only: the components are what the pipeline saves and moves
    assert "estimators" not in pipe.components


def test_evaluate_command_loads_the_segmenter_with_the_estimators(tmp_path, capsys):
    from geco_guide.cli.evaluate import main as evaluate_main
    from geco_guide.io.video import write_video

    clip = rigid_clip(3, 24, 32)
    write_video(tmp_path / "a.mp4", clip.frames.float(), fps=8)
    write_video(tmp_path / "b.mp4", clip.frames.float(), fps=8)
    out = tmp_path / "out"
    code = evaluate_main([str(tmp_path / "a.mp4"), str(tmp_path / "b.mp4"), "--preset", "tiny", "--pairs", "adjacent",
                          "--out", str(out), "--dynamic-masks", "a dog", "estimators.segmenter=tiny-random"])
    assert code == 0
    assert "loading segmenter: tiny-random for 'a dog' ..." in capsys.readouterr().err
    for name in ("a", "b"):
        assert json.loads((out / f"{name}.geco.json").read_text())["dynamic_masks"]["source"] == "sam3: a dog"
    assert json.loads((out / "geco_summary.json").read_text())["estimators"] == {
        "geometry": "tiny-random(seed=0)", "flow": "tiny-random(seed=0)", "segmenter": "tiny-random(seed=0)"}
    code = evaluate_main([str(tmp_path / "a.mp4"), "--preset", "tiny", "--out", str(tmp_path / "none"),
                          "--dynamic-masks", " , "])
    assert code == 2 and "names no subject" in capsys.readouterr().err  # before any model loads
