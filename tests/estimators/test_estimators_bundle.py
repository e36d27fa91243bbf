"""One estimator bundle: ``load_estimators`` returns an :class:`Estimators` (geometry, flow and an
optional text segmenter) that the metric, the hooks, the pipeline's call and the loaders take as
one object; the old ``geometry, flow = load_estimators(...)`` and the old keywords of the pair are
refused in one line naming the bundle (tiny models, CPU)."""

from __future__ import annotations

import json
import warnings

import pytest

import geco_guide
from geco_guide import tiny as T
from geco_guide.bench.synthetic import rigid_clip
from geco_guide.config import load_config
from geco_guide.estimators import (
    Estimators,
    EstimatorsConfig,
    estimator_ids,
    load_estimators,
    load_segmenter,
    segmenter_id,
)
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


def test_unpacking_the_old_pair_is_refused_naming_the_attributes(loaded):
    with pytest.raises(TypeError, match=r"^Estimators is not a \(geometry, flow\) pair: use estimators\.geometry and "
                                        r"estimators\.flow$"):
        geometry, flow = loaded
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the attributes never warn
        geometry = loaded.geometry
        assert type(geometry).__name__ == "VGGT" and loaded.with_segmenter(None).segmenter is None


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


def test_the_bundle_keeps_the_ids_its_models_were_loaded_from(clip, loaded):
    segment = load_segmenter(TINY, "cpu")
    assert segment("a dog").source_name == "sam3: a dog" and not hasattr(segment, "geco_estimator_id")
    oracles = Estimators(OracleGeometry(clip), OracleFlow(clip))
    with_segment = oracles.with_segmenter(segment, segmenter_id(TINY))
    assert with_segment.ids() == {"geometry": "OracleGeometry", "flow": "OracleFlow", "segmenter": "tiny-random(seed=0)"}
    assert with_segment.ids("flow", "segmenter") == {"flow": "OracleFlow", "segmenter": "tiny-random(seed=0)"}
    # a model replaced or removed takes its id along; one given without an id is named by itself
    assert with_segment.with_segmenter(None).sources == {} and with_segment.sources == {"segmenter": "tiny-random(seed=0)"}
    assert "segmenter" not in loaded.with_segmenter(None).ids() and loaded.with_segmenter(None).sources.keys() == {
        "geometry", "flow"}
    assert oracles.with_segmenter(segment).ids()["segmenter"] == "function"
    assert not any(hasattr(model, "geco_estimator_id") for model in loaded.modules())


def test_evaluate_video_takes_the_bundle(clip):
    oracles = Estimators(OracleGeometry(clip), OracleFlow(clip))
    by_keyword = evaluate_video(clip.frames, fps=8, estimators=oracles)
    by_position = evaluate_video(clip.frames, oracles, fps=8)
    assert by_keyword.fused == by_position.fused and by_keyword.motion == by_position.motion
    assert by_keyword.estimators == {"geometry": "OracleGeometry", "flow": "OracleFlow"}
    with pytest.raises(TypeError, match=r"^evaluate_video\(geometry_estimator=...\) is the earlier spelling: pass the "
                                        r"models as one estimators=Estimators\(geometry, flow\)"):
        evaluate_video(clip.frames, fps=8, estimators=oracles, geometry_estimator=OracleGeometry(clip))


def test_evaluate_video_masks_text_subjects_with_the_bundles_segmenter(loaded, clip):
    result = evaluate_video(clip.frames, fps=8, estimators=loaded, dynamic_masks="a dog")
    assert result.dynamic_masks["source"] == "sam3: a dog"
    assert result.estimators == {"geometry": "tiny-random(seed=0)", "flow": "tiny-random(seed=0)"}


def test_attach_geco_guidance_takes_the_bundle(loaded):
    from geco_guide.sampler.pipelines.hooks import attach_geco_guidance

    pipe = T.tiny_wan_pipeline(0)
    with attach_geco_guidance(pipe, T.tiny_guidance_config(), estimators=loaded) as handle:
        assert handle.estimators is loaded
        assert not hasattr(handle, "geometry_estimator") and not hasattr(handle, "flow_estimator")
    with pytest.raises(TypeError, match=r"^attach_geco_guidance\(flow_estimator=...\) is the earlier spelling: pass the "
                                        r"models as one estimators=Estimators\(geometry, flow\)"):
        attach_geco_guidance(pipe, T.tiny_guidance_config(), estimators=loaded, flow_estimator=loaded.flow)
    with pytest.raises(TypeError, match=r"^attach_geco_guidance takes the estimators as one Estimators"):
        attach_geco_guidance(pipe, T.tiny_guidance_config(), (loaded.geometry, loaded.flow))


def test_a_run_loads_the_bundle_beside_the_pipeline_which_has_no_estimator_components():
    from geco_guide.generation import load_models

    cfg = load_config(preset="tiny")
    models = load_models(cfg)
    estimators, pipe = models.estimators, models.pipe
    assert isinstance(estimators, Estimators)
    assert estimators.ids() == estimator_ids(cfg.estimators) and estimators.segmenter is None
    assert estimators.tiny_decoder is None  # guidance.decoder=vae: none loaded
    # the pipeline saves and moves its own models only: the bundle enters at each call (estimators=)
    assert set(pipe.components) == {"tokenizer", "text_encoder", "vae", "transformer", "scheduler"}
    assert not any(hasattr(pipe, name) for name in ("estimators", "geometry_estimator", "flow_estimator",
                                                     "guidance_decoder"))


@pytest.mark.slow
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
