"""Text segmenters: the pixels of named subjects in every frame of a clip, as GeCo dynamic masks.

``text_segmenter("a dog, a person")`` returns a :class:`~geco_guide.types.DynamicMaskSource`: the
frames of one clip ``[S, 3, H, W]`` in ``[0, 1]`` go in, a boolean ``[S, H, W]`` mask comes out,
true on every subject (the union of the comma-separated subjects), computed without gradients.
Two open-vocabulary video segmenters of transformers stand behind it:

- ``sam3`` (default): SAM 3 video (``Sam3VideoModel``, hub ``facebook/sam3``). It finds every
  instance of each phrase on every frame and tracks them through the clip. Its weights are gated
  on the hub: accept the licence on the model's page, then ``hf auth login``, or pass a folder.
- ``grounding-sam2``: Grounding DINO boxes of the subjects on the first frame
  (``GroundingDinoForObjectDetection``, hub ``IDEA-Research/grounding-dino-tiny``) handed to
  SAM 2 video (``Sam2VideoModel``, hub ``facebook/sam2.1-hiera-tiny``), which propagates each
  box's mask through the clip. Not gated; a subject that enters after the first frame is missed.

The frames are resized and normalised here (what the models' processors do: a resize to the
model's input size, then the checkpoint's mean and standard deviation), because transformers'
video processors need torchvision, which GeCo does not otherwise use; the tokenizers are the
checkpoints' own.

A subject the segmenter does not find gives no mask on that frame, with one warning per clip:
a generated video may well lack the subject its prompt names (the model did not draw the dog),
and failing then would end a guided run in the middle; GeCo simply scores those pixels as it
would without a mask. Empty text is a ValueError.

A folder of weights is checked before it is used: its ``config.json`` must describe a model of
the segmenter's family, and every weight must fit (a missing key would stay random, an
unexpected one go unused: another model's weights). What does not fit, or cannot be read (a
truncated file), is one line naming ``estimators.segmenter``, without transformers' load report.

``source="tiny-random"`` builds tiny randomly initialised instances of the same classes (CPU,
seconds, offline), as the other estimators' ``tiny-random``: their masks are noise-like, only the
mechanics are real.
"""

from __future__ import annotations

import contextlib
import json
import logging
import pickle
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from ..types import Correspondences, DynamicMaskSource, SceneGeometry
from .loading import (
    CheckpointMismatchError,
    UnreadableCheckpointError,
    WeightsSource,
    pretrained_or_one_line,
    short_reason,
)

__all__ = ["GROUNDING_DINO_WEIGHTS", "SAM3_WEIGHTS", "GroundedSam2Segmenter", "Sam3Segmenter",
           "SegmenterFactory", "detector_and_tracker", "model_pixels", "segmenter_from_spec",
           "segmenter_weight_sources", "segmenters_from_spec", "subjects_of", "text_segmenter", "tiny_grounded_sam2",
           "tiny_sam3", "union_mask"]

logger = logging.getLogger(__name__)

SEGMENTER_MODELS = ("sam3", "grounding-sam2")
SAM3_WEIGHTS = "facebook/sam3"
GROUNDING_DINO_WEIGHTS = "IDEA-Research/grounding-dino-tiny"
SAM2_VIDEO_WEIGHTS = "facebook/sam2.1-hiera-tiny"
TINY_RANDOM = "tiny-random"
#: The config key naming a segmenter's weights (see :func:`segmenter_from_spec`).
CONFIG_KEY = "estimators.segmenter"

# The published checkpoints' processor settings: SAM 3 normalises pixels to [-1, 1]; SAM 2 and
# Grounding DINO use the ImageNet statistics.
SAM3_MEAN_STD = ((0.5, 0.5, 0.5), (0.5, 0.5, 0.5))
IMAGENET_MEAN_STD = ((0.485, 0.456, 0.406), (0.229, 0.224, 0.225))
#: SAM 3 pads every phrase to this many tokens (its text encoder's positions).
SAM3_TEXT_TOKENS = 32
#: Grounding DINO keeps a box whose best phrase token scores above this (its model card's value).
BOX_THRESHOLD = 0.35
#: Grounding DINO's shorter image side (its processor's default).
GROUNDING_SHORT_SIDE = 800


def subjects_of(text: str) -> list[str]:
    """The subjects of ``"a dog, a person"``: ``["a dog", "a person"]`` (trimmed, empty parts
    dropped); ValueError (one line) when none is left."""
    if not isinstance(text, str):
        raise ValueError(f"subject text must be a string such as 'a dog, a person', got {type(text).__name__}")
    subjects = [part.strip() for part in text.split(",") if part.strip()]
    if not subjects:
        raise ValueError(f"subject text {text!r} names no subject; write e.g. 'a dog' or 'a dog, a person'")
    return subjects


def model_pixels(frames: Tensor, size: tuple[int, int], mean_std: tuple[Sequence[float], Sequence[float]]) -> Tensor:
    """``frames [S, 3, H, W]`` in ``[0, 1]`` resized to ``size`` (bilinear) and normalised: a
    video model's pixel values ``[S, 3, size]`` (float32)."""
    mean, std = (torch.tensor(v, dtype=torch.float32, device=frames.device).view(1, 3, 1, 1) for v in mean_std)
    resized = F.interpolate(frames.float(), size=size, mode="bilinear", align_corners=False, antialias=True)
    return (resized - mean) / std


def union_mask(mask_logits: Sequence[Tensor], size: tuple[int, int], device: torch.device) -> Tensor:
    """The union of object masks given as logits ``[h, w]`` (any size), at ``size``: ``[H, W]`` bool."""
    if not mask_logits:
        return torch.zeros(size, dtype=torch.bool, device=device)
    logits = torch.stack([m.reshape(m.shape[-2:]).float() for m in mask_logits])[:, None]
    return (F.interpolate(logits, size=size, mode="bilinear", align_corners=False)[:, 0] > 0).any(0).to(device)


def _warn_if_empty(masks: Tensor, name: str) -> None:
    if not bool(masks.any()):
        logger.warning("%s: found none of the subjects in the %d frames; nothing is masked", name, masks.shape[0])


class Sam3Segmenter:
    """SAM 3 video, prompted with text: :class:`~geco_guide.types.DynamicMaskSource`.

    Args:
        model: a ``Sam3VideoModel`` (frozen, on its device, in its dtype).
        tokenizer: its tokenizer (the checkpoint's CLIP tokenizer).
        subjects: the phrases to segment, e.g. ``["a dog", "a person"]``.
    """

    def __init__(self, model: Any, tokenizer: Any, subjects: Sequence[str]):
        self.model, self.tokenizer, self.subjects = model, tokenizer, list(subjects)
        self.source_name = f"sam3: {', '.join(self.subjects)}"

    def dynamic_masks(self, frames: Tensor, geometry: SceneGeometry | None = None, flow: Correspondences | None = None,
                      pairs: Sequence[tuple[int, int]] | None = None) -> Tensor:
        """``frames [S, 3, H, W]`` in ``[0, 1]`` -> ``[S, H, W]`` bool, true on any subject
        (``geometry``, ``flow``, ``pairs`` are not used). No gradient reaches the frames."""
        from transformers.models.sam3_video.modeling_sam3_video import Sam3VideoInferenceSession

        frames = frames.detach()
        num_frames, _, height, width = frames.shape
        size = self.model.config.image_size
        device, dtype = self.model.device, self.model.dtype
        session = Sam3VideoInferenceSession(
            video=model_pixels(frames.to(device), (size, size), SAM3_MEAN_STD), video_height=height, video_width=width,
            inference_device=device, inference_state_device=device, video_storage_device=device, dtype=dtype,
        )
        for subject in self.subjects:
            prompt = session.add_prompt(subject)
            tokens = self.tokenizer(subject, return_tensors="pt", padding="max_length", max_length=SAM3_TEXT_TOKENS,
                                    truncation=True).to(device)
            session.prompt_input_ids[prompt] = tokens.input_ids
            session.prompt_attention_masks[prompt] = tokens.attention_mask
        per_frame: dict[int, Tensor] = {}
        for out in self.model.propagate_in_video_iterator(inference_session=session):
            # The processor's filter: objects suppressed on this frame, or dropped by the
            # tracker's start-up heuristics, are not shown.
            hidden = set(out.suppressed_obj_ids or ()) | set(session.hotstart_removed_obj_ids)
            kept = [mask for obj, mask in out.obj_id_to_mask.items() if obj not in hidden]
            per_frame[out.frame_idx] = union_mask(kept, (height, width), frames.device)
        # Outside inference mode, so the masks can enter a loss that autograd records.
        masks = torch.stack([per_frame[i] for i in range(num_frames)]).clone()
        _warn_if_empty(masks, self.source_name)
        return masks


class GroundedSam2Segmenter:
    """Grounding DINO boxes on the first frame, propagated by SAM 2 video:
    :class:`~geco_guide.types.DynamicMaskSource`.

    Args:
        detector: a ``GroundingDinoForObjectDetection``; ``detector_tokenizer`` its tokenizer.
        tracker: a ``Sam2VideoModel``.
        subjects: the phrases to find, e.g. ``["a dog", "a person"]``.
        box_threshold: the lowest phrase score of a kept box.
        short_side: the detector's input size: the frame's shorter side is resized to it.
    """

    def __init__(self, detector: Any, detector_tokenizer: Any, tracker: Any, subjects: Sequence[str],
                 box_threshold: float = BOX_THRESHOLD, short_side: int = GROUNDING_SHORT_SIDE):
        self.detector, self.detector_tokenizer, self.tracker = detector, detector_tokenizer, tracker
        self.subjects, self.box_threshold, self.short_side = list(subjects), box_threshold, short_side
        self.source_name = f"grounding-sam2: {', '.join(self.subjects)}"

    def boxes(self, frame: Tensor) -> Tensor:
        """The subjects' boxes ``[N, 4]`` (x0, y0, x1, y1 in pixels of ``frame [3, H, W]``)."""
        height, width = frame.shape[-2:]
        scale = self.short_side / min(height, width)
        device = self.detector.device
        pixels = model_pixels(frame[None].to(device), (round(height * scale), round(width * scale)), IMAGENET_MEAN_STD)
        # The processor's text form: lower-case phrases, each ending with a full stop.
        tokens = self.detector_tokenizer(" ".join(f"{s.lower()} ." for s in self.subjects), return_tensors="pt").to(device)
        out = self.detector(pixel_values=pixels.to(self.detector.dtype), input_ids=tokens.input_ids,
                            attention_mask=tokens.attention_mask, token_type_ids=tokens.get("token_type_ids"))
        keep = out.logits[0].float().sigmoid().amax(-1) > self.box_threshold  # [queries]
        cx, cy, w, h = out.pred_boxes[0][keep].float().unbind(-1)  # centre and size, in fractions of the frame
        return torch.stack([(cx - w / 2) * width, (cy - h / 2) * height, (cx + w / 2) * width, (cy + h / 2) * height], -1)

    def dynamic_masks(self, frames: Tensor, geometry: SceneGeometry | None = None, flow: Correspondences | None = None,
                      pairs: Sequence[tuple[int, int]] | None = None) -> Tensor:
        """``frames [S, 3, H, W]`` in ``[0, 1]`` -> ``[S, H, W]`` bool, true on any subject found
        on the first frame and tracked from there (``geometry``, ``flow``, ``pairs`` are not
        used). No gradient reaches the frames."""
        from transformers.models.sam2_video.modeling_sam2_video import Sam2VideoInferenceSession

        frames = frames.detach()
        num_frames, _, height, width = frames.shape
        with torch.inference_mode():
            boxes = self.boxes(frames[0])
        per_frame: dict[int, Tensor] = {}
        if boxes.shape[0]:
            size = self.tracker.config.image_size
            device = self.tracker.device
            session = Sam2VideoInferenceSession(
                video=model_pixels(frames.to(device), (size, size), IMAGENET_MEAN_STD), video_height=height,
                video_width=width, inference_device=device, inference_state_device=device,
                video_storage_device=device, dtype=self.tracker.dtype,
            )
            # Each box is one object, prompted on the first frame as SAM 2 takes boxes: its two
            # corners as points labelled 2 and 3, in the model's input pixels.
            corners = boxes.to(device).view(-1, 2, 2) * torch.tensor([size / width, size / height], device=device)
            labels = torch.tensor([[[2, 3]]], dtype=torch.int32, device=device)
            for obj, points in enumerate(corners):
                session.add_point_inputs(session.obj_id_to_idx(obj), 0, {"point_coords": points[None, None],
                                                                         "point_labels": labels})
            session.obj_with_new_inputs = list(range(len(corners)))
            with torch.inference_mode():
                self.tracker(inference_session=session, frame_idx=0)
                for out in self.tracker.propagate_in_video_iterator(session, start_frame_idx=0):
                    per_frame[out.frame_idx] = union_mask(list(out.pred_masks[:, 0]), (height, width), frames.device)
        empty = torch.zeros(height, width, dtype=torch.bool, device=frames.device)
        # Outside inference mode, so the masks can enter a loss that autograd records.
        masks = torch.stack([per_frame.get(i, empty) for i in range(num_frames)]).clone()
        _warn_if_empty(masks, self.source_name)
        return masks


# ---- loading ---------------------------------------------------------------------------------


def _from_pretrained(cls: Any, source: str, what: str, folder: str, gated: bool = False) -> Any:
    """``cls.from_pretrained(source)`` of a hub id or a local folder; one-line
    :class:`WeightsNotFoundError` naming the id, :data:`CONFIG_KEY` and how to pass a folder
    (``folder``: the example value). A model (not a tokenizer) is loaded checked
    (:func:`_checked_model`)."""
    load = cls.from_pretrained
    if hasattr(cls, "config_class"):
        def load(path: str) -> Any:
            return _checked_model(cls, path, what, source, folder)
    return pretrained_or_one_line(load, source, model_name=what, folder_hint=f"{CONFIG_KEY}={folder}", gated=gated)


@contextlib.contextmanager
def _quiet_transformers() -> Iterator[None]:
    """transformers' load report (hundreds of lines for weights that do not fit) and its progress
    bars off: what is wrong is said in one line instead (:func:`_checked_model`)."""
    from transformers.utils import logging as transformers_logging

    level, bars = transformers_logging.get_verbosity(), transformers_logging.is_progress_bar_enabled()
    transformers_logging.set_verbosity_error()
    transformers_logging.disable_progress_bar()
    try:
        yield
    finally:
        transformers_logging.set_verbosity(level)
        if bars:
            transformers_logging.enable_progress_bar()


def _check_model_type(cls: Any, path: str, what: str, source: str, folder: str) -> None:
    """A local folder's ``config.json`` must describe a model of ``cls``'s family (``sam3_video``
    for SAM 3 video, ``sam2*`` for SAM 2, ``grounding-dino``), checked before anything loads: a
    VGGT folder would otherwise build a full-size random SAM 3 first. Hub repos are what they are."""
    config = Path(path) / "config.json"
    if not Path(path).is_dir():
        return
    where = f"{CONFIG_KEY}={source!r}"
    if not config.is_file():
        raise CheckpointMismatchError(f"{where}: the folder holds no config.json, so it is no {what} model "
                                      f"(save_pretrained writes config.json beside the weights; {CONFIG_KEY}={folder})")
    try:
        model_type = json.loads(config.read_text(encoding="utf-8")).get("model_type")
    except (OSError, ValueError, AttributeError) as err:
        raise CheckpointMismatchError(f"{where}: {str(config)!r} is not a readable config.json "
                                      f"({type(err).__name__})") from None
    family = cls.config_class.model_type.split("_")[0]
    if not (isinstance(model_type, str) and model_type.startswith(family)):
        named = f"a {model_type!r} model" if isinstance(model_type, str) else "no transformers model (no model_type)"
        raise CheckpointMismatchError(f"{where}: the folder's config.json describes {named}, not {what} "
                                      f"({cls.config_class.model_type!r}); pass a {what} folder ({CONFIG_KEY}={folder})")


def _checked_model(cls: Any, path: str, what: str, source: str, folder: str) -> Any:
    """``cls.from_pretrained(path)`` without transformers' load report, refusing weights that do not
    fit (a missing key would stay random, an unexpected one unused: another model's weights) or
    cannot be read (truncated), in one line naming :data:`CONFIG_KEY`."""
    _check_model_type(cls, path, what, source, folder)
    where = f"{CONFIG_KEY}={source!r}"
    with _quiet_transformers():
        try:
            model, info = cls.from_pretrained(path, output_loading_info=True)
        except (RuntimeError, EOFError, pickle.UnpicklingError) as err:  # size mismatches, damaged torch files
            raise UnreadableCheckpointError(f"{where}: the {what} weights cannot be loaded ({short_reason(err)}); "
                                            "they may be truncated or of another model: download them again") from None
        except Exception as err:
            if type(err).__name__ != "SafetensorError":  # safetensors' own error type, for a truncated file
                raise
            raise UnreadableCheckpointError(f"{where}: the {what} weights cannot be read ({short_reason(err)}); "
                                            "they may be truncated: download them again") from None
    wrong = {kind: sorted(info.get(f"{kind}_keys") or []) for kind in ("missing", "unexpected", "mismatched")}
    if any(wrong.values()):
        found = "; ".join(f"{len(keys)} {kind} key(s), e.g. {str(keys[0])!r}" for kind, keys in wrong.items() if keys)
        raise CheckpointMismatchError(f"{where}: the weights do not fit {what} ({found}): another model's weights, "
                                      f"or damaged ones; pass a {what} folder or hub id ({CONFIG_KEY}={folder})")
    return model


#: Makes the mask source of a subject text (``"a dog, a person"``) with models loaded once.
SegmenterFactory = Callable[[str], DynamicMaskSource]


def load_text_segmenters(*, model: str = "sam3", source: str | Sequence[str] | None = None,
                         device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32,
                         seed: int = 0) -> SegmenterFactory:
    """Load a segmenter's models once; the returned function makes the
    :class:`~geco_guide.types.DynamicMaskSource` of any subject text with them (a suite of prompts,
    each naming its own subjects, loads the models once).

    Args:
        model: ``"sam3"`` (SAM 3 video) or ``"grounding-sam2"`` (Grounding DINO + SAM 2 video).
        source: where the weights are: ``None`` (the published ones on the hub), a hub id or a
            local folder (``sam3``: a ``Sam3VideoModel`` saved with its tokenizer), a
            ``(detector, tracker)`` pair of them or ``"DETECTOR,TRACKER"`` (``grounding-sam2``),
            or ``"tiny-random"`` (tiny random instances seeded with ``seed``).
        device, dtype: where the models run, in which dtype.

    Raises:
        ValueError: an unknown ``model`` (before anything loads); the returned function, text
            that names no subject.
        WeightsNotFoundError: one line naming the repo id, :data:`CONFIG_KEY` and how to pass a
            local folder, when the weights cannot be had.
    """
    if model not in SEGMENTER_MODELS:
        raise ValueError(f"segmenter model must be one of {list(SEGMENTER_MODELS)}, got {model!r}")
    if model == "sam3":
        if source == TINY_RANDOM:
            sam3, tokenizer = tiny_sam3(seed)
        else:
            from transformers import AutoTokenizer, Sam3VideoModel

            weights = source or SAM3_WEIGHTS
            sam3 = _from_pretrained(Sam3VideoModel, weights, "SAM 3 video", "/path/to/sam3", gated=True)
            tokenizer = _from_pretrained(AutoTokenizer, weights, "SAM 3 video tokenizer", "/path/to/sam3")
        sam3 = _frozen(sam3, device, dtype)
        return lambda text: Sam3Segmenter(sam3, tokenizer, subjects_of(text))
    options = {}
    if source == TINY_RANDOM:
        detector, detector_tokenizer, tracker = tiny_grounded_sam2(seed)
        options["short_side"] = TINY_IMAGE_SIZE
    else:
        from transformers import AutoTokenizer, GroundingDinoForObjectDetection, Sam2VideoModel

        detector_source, tracker_source = detector_and_tracker(source)
        folders = "/path/to/grounding-dino-tiny,/path/to/sam2.1-hiera-tiny"
        detector = _from_pretrained(GroundingDinoForObjectDetection, detector_source, "Grounding DINO", folders)
        detector_tokenizer = _from_pretrained(AutoTokenizer, detector_source, "Grounding DINO tokenizer", folders)
        tracker = _from_pretrained(Sam2VideoModel, tracker_source, "SAM 2 video", folders)
    detector, tracker = _frozen(detector, device, dtype), _frozen(tracker, device, dtype)
    return lambda text: GroundedSam2Segmenter(detector, detector_tokenizer, tracker, subjects_of(text), **options)


def text_segmenter(text: str, *, model: str = "sam3", source: str | Sequence[str] | None = None,
                   device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32,
                   seed: int = 0) -> DynamicMaskSource:
    """The :class:`~geco_guide.types.DynamicMaskSource` that masks the subjects of ``text``
    (comma-separated: ``"a dog"``, ``"a dog, a person"``); the other arguments as
    :func:`load_text_segmenters`. Text that names no subject is a ValueError before anything loads."""
    subjects_of(text)
    return load_text_segmenters(model=model, source=source, device=device, dtype=dtype, seed=seed)(text)


def _frozen(model: Any, device: torch.device | str, dtype: torch.dtype) -> Any:
    return model.to(device=device, dtype=dtype).eval().requires_grad_(False)


def detector_and_tracker(source: str | Sequence[str] | None) -> tuple[str, str]:
    """The Grounding DINO and SAM 2 video weights of ``source``: ``None`` (the published ones),
    ``"DETECTOR,TRACKER"`` or a pair; ValueError (one line) for anything else."""
    if source is None:
        return GROUNDING_DINO_WEIGHTS, SAM2_VIDEO_WEIGHTS
    parts = [p.strip() for p in source.split(",")] if isinstance(source, str) else list(source)
    if len(parts) != 2 or not all(isinstance(p, str) and p for p in parts):
        raise ValueError(f"grounding-sam2 weights must be 'DETECTOR,TRACKER' (two hub ids or folders), got {source!r}")
    return parts[0], parts[1]


def segmenters_from_spec(spec: str, *, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32,
                         seed: int = 0) -> SegmenterFactory:
    """:func:`load_text_segmenters` of a config's :data:`CONFIG_KEY`: ``grounding-sam2`` (its
    published weights), ``DETECTOR,TRACKER`` (Grounding DINO and SAM 2 video weights: hub ids or
    folders), ``tiny-random`` / ``tiny-random-grounding-sam2`` (tiny random models seeded with
    ``seed``), or a hub id or folder of SAM 3 video weights (the default ``facebook/sam3``)."""
    if not isinstance(spec, str) or not spec.strip():
        raise ValueError(f"{CONFIG_KEY} must name the segmenter's weights (e.g. {SAM3_WEIGHTS}), got {spec!r}")
    if spec == "grounding-sam2":
        return load_text_segmenters(model="grounding-sam2", device=device, dtype=dtype)
    if spec in (TINY_RANDOM, f"{TINY_RANDOM}-grounding-sam2"):
        model = "sam3" if spec == TINY_RANDOM else "grounding-sam2"
        return load_text_segmenters(model=model, source=TINY_RANDOM, device=device, dtype=dtype, seed=seed)
    return load_text_segmenters(model="grounding-sam2" if "," in spec else "sam3", source=spec, device=device,
                                dtype=dtype)


def segmenter_weight_sources(spec: str) -> list[WeightsSource]:
    """The weights :func:`segmenters_from_spec` loads for the config's :data:`CONFIG_KEY`, as
    :func:`~geco_guide.estimators.check_weights` checks them before anything loads
    (none for the tiny random models)."""
    if not isinstance(spec, str) or spec.startswith(TINY_RANDOM):
        return []
    if spec == "grounding-sam2" or "," in spec:
        folders = "/path/to/grounding-dino-tiny,/path/to/sam2.1-hiera-tiny"
        detector, tracker = detector_and_tracker(None if spec == "grounding-sam2" else spec)
        return [WeightsSource(CONFIG_KEY, detector, "Grounding DINO", example=folders),
                WeightsSource(CONFIG_KEY, tracker, "SAM 2 video", example=folders)]
    return [WeightsSource(CONFIG_KEY, spec, "SAM 3 video", example="/path/to/sam3")]


def segmenter_from_spec(text: str, spec: str, *, device: torch.device | str = "cpu",
                        dtype: torch.dtype = torch.float32, seed: int = 0) -> DynamicMaskSource:
    """The mask source of ``text`` from :func:`segmenters_from_spec`; text that names no subject
    is a ValueError before anything loads."""
    subjects_of(text)
    return segmenters_from_spec(spec, device=device, dtype=dtype, seed=seed)(text)


# ---- tiny random instances -------------------------------------------------------------------

#: The tiny models' image size: 8 x 8 patches of 14 pixels.
TINY_IMAGE_SIZE = 112
_TINY_WORDS = ("a an the and of with dog cat person man woman child bird horse car bus train boat bicycle ball "
               "water wave smoke fire flag tree leaves people crowd traffic animal").split()


def tiny_word_tokenizer(start: str, end: str, unknown: str, pad: str | None = None):
    """A word-level fast tokenizer over :data:`_TINY_WORDS` that wraps a text in ``start ... end``
    (with CLIP's or BERT's special tokens; offline: real checkpoints ship their own). ``pad``:
    the padding token, ``end`` by default (as CLIP pads)."""
    from tokenizers import Tokenizer, normalizers, pre_tokenizers, processors
    from tokenizers.models import WordLevel
    from transformers import PreTrainedTokenizerFast

    pad = pad or end
    vocab = {word: i for i, word in enumerate([*dict.fromkeys([start, end, unknown, pad]), *_TINY_WORDS, "."])}
    tok = Tokenizer(WordLevel(vocab=vocab, unk_token=unknown))
    tok.normalizer = normalizers.Lowercase()
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    tok.post_processor = processors.TemplateProcessing(single=f"{start} $A {end}",
                                                       special_tokens=[(start, vocab[start]), (end, vocab[end])])
    return PreTrainedTokenizerFast(tokenizer_object=tok, bos_token=start, eos_token=end, pad_token=pad,
                                   unk_token=unknown)


def tiny_sam3(seed: int = 0) -> tuple[Any, Any]:
    """A tiny random ``Sam3VideoModel`` and a word-level tokenizer (seeded; CPU, seconds).

    Its sizes keep the constraints of the real model: the tracker's memory attention takes
    64-channel memories and splits the object pointers into them, so the feature width is a
    multiple of 64 above it (128)."""
    from transformers import Sam3VideoConfig, Sam3VideoModel
    from transformers.models.sam3.configuration_sam3 import (
        Sam3Config,
        Sam3DETRDecoderConfig,
        Sam3DETREncoderConfig,
        Sam3GeometryEncoderConfig,
        Sam3MaskDecoderConfig,
        Sam3VisionConfig,
        Sam3ViTConfig,
    )
    from transformers.models.sam3_tracker_video.configuration_sam3_tracker_video import Sam3TrackerVideoConfig

    size, patch, width, small = TINY_IMAGE_SIZE, 14, 128, dict(num_attention_heads=4, intermediate_size=64)
    grid = size // patch
    tokenizer = tiny_word_tokenizer("<|startoftext|>", "<|endoftext|>", "<unk>")
    vision = Sam3VisionConfig(
        backbone_config=Sam3ViTConfig(hidden_size=32, num_hidden_layers=2, image_size=size, patch_size=patch,
                                      window_size=grid // 2, global_attn_indexes=[1], pretrain_image_size=size, **small),
        fpn_hidden_size=width, backbone_feature_sizes=[[4 * grid] * 2, [2 * grid] * 2, [grid] * 2],
    )
    text = dict(vocab_size=len(tokenizer), hidden_size=32, intermediate_size=64, projection_dim=32, num_hidden_layers=1,
                num_attention_heads=4, max_position_embeddings=SAM3_TEXT_TOKENS, bos_token_id=tokenizer.bos_token_id,
                eos_token_id=tokenizer.eos_token_id, pad_token_id=tokenizer.pad_token_id)
    detector = Sam3Config(
        vision_config=vision, text_config=text,
        geometry_encoder_config=Sam3GeometryEncoderConfig(hidden_size=width, num_layers=1, **small),
        detr_encoder_config=Sam3DETREncoderConfig(hidden_size=width, num_layers=1, **small),
        detr_decoder_config=Sam3DETRDecoderConfig(hidden_size=width, num_layers=1, num_queries=5, **small),
        mask_decoder_config=Sam3MaskDecoderConfig(hidden_size=width, num_upsampling_stages=2, num_attention_heads=4),
    )
    tracker = Sam3TrackerVideoConfig(
        vision_config=vision.to_dict(), prompt_encoder_config=dict(hidden_size=width, image_size=size, patch_size=patch),
        mask_decoder_config=dict(hidden_size=width, mlp_dim=64, num_attention_heads=4, iou_head_hidden_dim=32),
        memory_attention_hidden_size=width, memory_attention_num_layers=1, memory_attention_feed_forward_hidden_size=64,
        memory_encoder_hidden_size=width, memory_encoder_output_channels=64, mask_downsampler_embed_dim=width,
        memory_fuser_embed_dim=width, memory_fuser_intermediate_dim=64, memory_fuser_num_layers=1, image_size=size,
    )
    # No start-up delay: the tiny clips are shorter than the real model's 15-frame hold-back; and
    # no score threshold: a random detector's scores sit near 0.25, so it would find nothing.
    config = Sam3VideoConfig(detector_config=detector, tracker_config=tracker, low_res_mask_size=4 * grid,
                             hotstart_delay=0, score_threshold_detection=0.0, new_det_thresh=0.0)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = Sam3VideoModel(config)
    return model.eval(), tokenizer


def tiny_grounded_sam2(seed: int = 0) -> tuple[Any, Any, Any]:
    """A tiny random ``GroundingDinoForObjectDetection`` with a word-level tokenizer, and a tiny
    random ``Sam2VideoModel`` (seeded; CPU, seconds). The tracker keeps the real model's
    constraints (64-channel memories, features a multiple of 64 wider)."""
    from transformers import GroundingDinoConfig, GroundingDinoForObjectDetection, Sam2VideoConfig, Sam2VideoModel, SwinConfig
    from transformers.models.sam2.configuration_sam2 import Sam2HieraDetConfig, Sam2VisionConfig

    tokenizer = tiny_word_tokenizer("[CLS]", "[SEP]", "[UNK]", "[PAD]")
    swin = SwinConfig(window_size=7, embed_dim=8, depths=[1, 1, 1, 1], num_heads=[1, 1, 1, 1], image_size=TINY_IMAGE_SIZE,
                      out_features=["stage2", "stage3", "stage4"], out_indices=[2, 3, 4])
    text = dict(model_type="bert", vocab_size=len(tokenizer), hidden_size=8, num_hidden_layers=1, num_attention_heads=2,
                intermediate_size=8, max_position_embeddings=32)
    # Two decoder layers: the box heads of the layers after the first are tied to it.
    detector_config = GroundingDinoConfig(
        d_model=32, encoder_layers=1, decoder_layers=2, encoder_attention_heads=4, decoder_attention_heads=4,
        encoder_ffn_dim=8, decoder_ffn_dim=8, num_queries=4, encoder_n_points=2, decoder_n_points=2,
        use_timm_backbone=False, backbone_config=swin, max_text_len=16, text_config=text,
    )
    size, width = 128, 128
    vision = Sam2VisionConfig(
        backbone_config=Sam2HieraDetConfig(hidden_size=12, embed_dim_per_stage=[12, 24, 48, 96],
                                           num_attention_heads_per_stage=[1, 2, 4, 8], blocks_per_stage=[1, 1, 1, 1],
                                           image_size=[size, size], patch_kernel_size=[7, 7], patch_stride=[4, 4],
                                           patch_padding=[3, 3]),
        backbone_channel_list=[96, 48, 24, 12], backbone_feature_sizes=[[32, 32], [16, 16], [8, 8]], fpn_hidden_size=width,
    )
    tracker_config = Sam2VideoConfig(
        vision_config=vision, image_size=size,
        prompt_encoder_config=dict(hidden_size=width, image_size=size, patch_size=16),
        mask_decoder_config=dict(hidden_size=width, mlp_dim=64, num_attention_heads=4, iou_head_hidden_dim=32),
        memory_attention_hidden_size=width, memory_attention_num_layers=1, memory_attention_feed_forward_hidden_size=64,
        memory_attention_rope_feat_sizes=[8, 8], memory_encoder_hidden_size=width, memory_encoder_output_channels=64,
        mask_downsampler_embed_dim=width, memory_fuser_embed_dim=width, memory_fuser_intermediate_dim=64,
        memory_fuser_num_layers=1,
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        detector = GroundingDinoForObjectDetection(detector_config)
        tracker = Sam2VideoModel(tracker_config)
    return detector.eval(), tokenizer, tracker.eval()
