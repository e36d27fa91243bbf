"""Text segmenters (SAM 3 video; Grounding DINO + SAM 2 video) as dynamic-mask sources: tiny
random instances of the real transformers classes, their loading (saved folders, missing
weights), subjects and empty finds."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
import torch

from geco_guide.estimators.loading import WeightsNotFoundError
from geco_guide.estimators.segmenters import (
    GROUNDING_DINO_WEIGHTS,
    SAM3_WEIGHTS,
    GroundedSam2Segmenter,
    Sam3Segmenter,
    detector_and_tracker,
    model_pixels,
    segmenter_from_spec,
    subjects_of,
    text_segmenter,
    tiny_grounded_sam2,
    tiny_sam3,
    union_mask,
)
from geco_guide.types import DynamicMaskSource


@pytest.fixture(scope="module")
def tiny_model():
    return tiny_sam3(seed=0)


@pytest.fixture(scope="module")
def tiny_grounded():
    return tiny_grounded_sam2(seed=0)


def clip(num_frames: int = 3, height: int = 24, width: int = 32) -> torch.Tensor:
    return torch.rand(num_frames, 3, height, width, generator=torch.Generator().manual_seed(0))


def test_subjects_are_the_comma_separated_phrases():
    assert subjects_of("a dog") == ["a dog"]
    assert subjects_of(" a dog ,a person, ") == ["a dog", "a person"]
    for text in ("", " , ,"):
        with pytest.raises(ValueError, match="names no subject"):
            subjects_of(text)
    with pytest.raises(ValueError, match="must be a string"):
        subjects_of(None)


def test_union_mask_is_the_union_of_the_objects_at_the_frame_size():
    left = torch.full((4, 4), -1.0)
    left[:, :2] = 1.0
    top = torch.full((4, 4), -1.0)
    top[:2] = 1.0
    mask = union_mask([left[None], top[None]], (8, 8), torch.device("cpu"))
    assert mask.shape == (8, 8) and mask.dtype == torch.bool
    assert mask[:, :3].all() and mask[:3].all() and not mask[5:, 5:].any()
    assert not union_mask([], (8, 8), torch.device("cpu")).any()  # no object: nothing masked


def test_model_pixels_resize_and_normalise():
    frames = torch.ones(2, 3, 10, 20)
    pixels = model_pixels(frames, (8, 8), ((0.5, 0.5, 0.5), (0.5, 0.5, 0.5)))
    assert pixels.shape == (2, 3, 8, 8) and torch.allclose(pixels, torch.ones(()))


@pytest.mark.slow
def test_tiny_sam3_segments_a_clip_without_gradients(tiny_model):
    model, tokenizer = tiny_model
    segmenter = Sam3Segmenter(model, tokenizer, subjects_of("a dog, a person"))
    assert isinstance(segmenter, DynamicMaskSource)
    assert segmenter.source_name == "sam3: a dog, a person"
    frames = clip().requires_grad_(True)
    masks = segmenter.dynamic_masks(frames)
    assert masks.shape == (3, 24, 32) and masks.dtype == torch.bool and not masks.requires_grad
    assert masks.any()  # the tiny detector keeps every query (no score threshold)
    # Usable in a loss that autograd records (no inference tensor escapes).
    (frames.mean(1) * masks).sum().backward()
    assert frames.grad is not None
    one = Sam3Segmenter(model, tokenizer, ["a dog"]).dynamic_masks(frames)
    other = Sam3Segmenter(model, tokenizer, ["a person"]).dynamic_masks(frames)
    assert torch.equal(masks, one | other)


def test_a_subject_not_found_masks_nothing_with_one_warning(tiny_model, caplog):
    model, tokenizer = tiny_model
    before = model.score_threshold_detection
    model.score_threshold_detection = 1.1  # no detection can pass
    try:
        with caplog.at_level(logging.WARNING, logger="geco_guide.estimators.segmenters"):
            masks = Sam3Segmenter(model, tokenizer, ["a unicorn"]).dynamic_masks(clip())
    finally:
        model.score_threshold_detection = before
    assert not masks.any() and masks.shape == (3, 24, 32)
    warnings = [r.getMessage() for r in caplog.records]
    assert warnings == ["sam3: a unicorn: found none of the subjects in the 3 frames; nothing is masked"]


@pytest.mark.slow
def test_text_segmenter_loads_a_saved_folder(tiny_model, tmp_path: Path):
    model, tokenizer = tiny_model
    model.save_pretrained(tmp_path)
    tokenizer.save_pretrained(tmp_path)
    loaded = text_segmenter("a dog", source=str(tmp_path))
    assert not any(p.requires_grad for p in loaded.model.parameters()) and not loaded.model.training
    frames = clip()
    assert torch.equal(loaded.dynamic_masks(frames), Sam3Segmenter(model, tokenizer, ["a dog"]).dynamic_masks(frames))
    tiny = text_segmenter("a dog", source="tiny-random")
    assert torch.equal(tiny.dynamic_masks(frames), loaded.dynamic_masks(frames))  # the same seed, the same model


@pytest.mark.slow
def test_segmenter_folders_that_hold_other_weights_are_one_line_naming_the_key(tiny_model, tmp_path: Path, capfd):
    import shutil

    from geco_guide.estimators.loading import CheckpointMismatchError, UnreadableCheckpointError
    from geco_guide.estimators.vggt import VGGT, VGGTConfig

    model, tokenizer = tiny_model
    good = tmp_path / "sam3"
    model.save_pretrained(good)
    tokenizer.save_pretrained(good)
    vggt = VGGT.random(VGGTConfig.tiny()).save_pretrained(tmp_path / "vggt")
    other = shutil.copytree(good, tmp_path / "other")  # a SAM 3 folder holding VGGT's weights
    shutil.copy(vggt / "model.safetensors", other / "model.safetensors")
    truncated = shutil.copytree(good, tmp_path / "truncated")
    weights = (good / "model.safetensors").read_bytes()
    (truncated / "model.safetensors").write_bytes(weights[: len(weights) // 2])
    (other_config := shutil.copytree(good, tmp_path / "sam2-config")).joinpath("config.json").write_text(
        '{"model_type": "sam2_video"}')
    capfd.readouterr()
    cases = [(other, CheckpointMismatchError, "unexpected key(s), e.g. 'aggregator."),
             (vggt, CheckpointMismatchError, "the folder's config.json describes no transformers model"),
             (other_config, CheckpointMismatchError, "describes a 'sam2_video' model, not SAM 3 video"),
             (truncated, UnreadableCheckpointError, "the SAM 3 video weights cannot be read (SafetensorError: ")]
    for folder, error, message in cases:
        with pytest.raises(error) as err:
            segmenter_from_spec("a dog", str(folder))
        text = str(err.value)
        assert text.startswith(f"estimators.segmenter={str(folder)!r}: ") and message in text and "\n" not in text
    # no load report, no progress bars: the one line says it all
    assert capfd.readouterr().err == ""
    assert isinstance(segmenter_from_spec("a dog", str(good)), Sam3Segmenter)


def test_missing_weights_are_one_line(monkeypatch, tmp_path: Path):
    import huggingface_hub.constants

    with pytest.raises(ValueError, match="names no subject"):  # before anything loads
        text_segmenter(" , ", source="geco-guide-tests/no-such-sam3")
    with pytest.raises(WeightsNotFoundError) as err:
        text_segmenter("a dog", source=str(tmp_path / "missing"))
    assert "does not exist" in str(err.value) and "estimators.segmenter=/path/to/sam3" in str(err.value)
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    with pytest.raises(WeightsNotFoundError) as err:
        text_segmenter("a dog")
    message = str(err.value)
    assert "\n" not in message and repr(SAM3_WEIGHTS) in message
    assert "hf auth login" in message and "estimators.segmenter=/path/to/sam3" in message


def test_tiny_grounding_sam2_tracks_the_first_frames_boxes(tiny_grounded):
    detector, tokenizer, tracker = tiny_grounded
    segmenter = GroundedSam2Segmenter(detector, tokenizer, tracker, ["a dog", "a person"], short_side=112)
    assert isinstance(segmenter, DynamicMaskSource) and segmenter.source_name == "grounding-sam2: a dog, a person"
    frames = clip(4, 24, 36).requires_grad_(True)
    boxes = segmenter.boxes(frames[0].detach())
    assert boxes.shape[1] == 4 and boxes.shape[0] > 0  # the random detector scores some queries above 0.35
    assert bool((boxes[:, 2:] >= boxes[:, :2]).all())
    masks = segmenter.dynamic_masks(frames)
    assert masks.shape == (4, 24, 36) and masks.dtype == torch.bool and not masks.requires_grad
    assert masks.any()
    segmenter.box_threshold = 1.1  # nothing found: nothing masked (the warning as SAM 3's)
    assert not segmenter.dynamic_masks(frames).any()


@pytest.mark.slow
def test_grounding_sam2_loads_saved_folders_from_the_config_spec(tiny_grounded, tmp_path: Path):
    detector, tokenizer, tracker = tiny_grounded
    detector.save_pretrained(tmp_path / "detector")
    tokenizer.save_pretrained(tmp_path / "detector")
    tracker.save_pretrained(tmp_path / "tracker")
    loaded = segmenter_from_spec("a dog", f"{tmp_path / 'detector'},{tmp_path / 'tracker'}")
    reference = GroundedSam2Segmenter(detector, tokenizer, tracker, ["a dog"], box_threshold=0.0)
    loaded.box_threshold = 0.0  # every query kept: both find the same boxes
    frames = clip(3, 24, 36)
    assert isinstance(loaded, GroundedSam2Segmenter) and loaded.boxes(frames[0]).shape[0] == 4
    assert torch.equal(loaded.boxes(frames[0]), reference.boxes(frames[0]))
    assert torch.equal(loaded.dynamic_masks(frames), reference.dynamic_masks(frames))
    assert isinstance(segmenter_from_spec("a dog", "tiny-random-grounding-sam2"), GroundedSam2Segmenter)
    assert isinstance(segmenter_from_spec("a dog", "tiny-random"), Sam3Segmenter)


def test_bad_segmenter_choices_are_one_line(monkeypatch, tmp_path: Path):
    import huggingface_hub.constants

    with pytest.raises(ValueError, match="segmenter model must be one of"):
        text_segmenter("a dog", model="sam9")
    with pytest.raises(ValueError, match="must be 'DETECTOR,TRACKER'"):
        segmenter_from_spec("a dog", "a,b,c")
    with pytest.raises(ValueError, match="estimators.segmenter must name the segmenter's weights"):
        segmenter_from_spec("a dog", " ")
    assert detector_and_tracker(" x/det , y/trk ") == ("x/det", "y/trk")
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    with pytest.raises(WeightsNotFoundError) as err:
        segmenter_from_spec("a dog", "grounding-sam2")
    message = str(err.value)
    assert "\n" not in message and repr(GROUNDING_DINO_WEIGHTS) in message and "hf auth login" not in message
    assert "estimators.segmenter=/path/to/grounding-dino-tiny,/path/to/sam2.1-hiera-tiny" in message
