"""The inputs of a scoring run (``geco evaluate``): command-line paths made videos (files, frame
folders, folders of videos) with unique output names, what each writes and the checks made before
any model loads (nothing scorable, outputs already there, ``--dynamic-masks`` read and fitted to
each input, ``--detection`` with masks it cannot use). Each check is one ValueError line."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..io.files import unique_names

if TYPE_CHECKING:
    from .protocol import EvaluationConfig

__all__ = ["VideoInput", "check_detection_masks", "check_inputs_and_outputs", "check_masks_fit", "check_scorable",
           "dynamic_mask_option", "expand_inputs", "holds_frames", "needs_segmenter", "output_files", "run_outputs"]


@dataclass
class VideoInput:
    """One video to score (a file or a frame folder), or an input that already failed."""

    path: Path
    name: str
    error: str | None = None


def holds_frames(folder: Path) -> bool:
    """Whether ``folder`` holds png/jpg frames (one video)."""
    from ..io.video import frame_files

    return bool(frame_files(folder))


def expand_inputs(paths: list[str]) -> list[VideoInput]:
    """Command-line inputs -> videos. A folder with png/jpg frames is one video; any other
    folder stands for its video files and frame sub-folders (one level), and is an error when it
    holds none. Names (output stems) are made unique with ``-2``, ``-3``, ..."""
    from ..io.video import IMAGE_SUFFIXES, VIDEO_SUFFIXES, input_stem

    items: list[VideoInput] = []
    for arg in paths:
        path = Path(arg)
        if path.is_dir() and not holds_frames(path):
            entries = sorted(p for p in path.iterdir() if not p.name.startswith("."))
            videos = [p for p in entries if (p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES) or (p.is_dir() and holds_frames(p))]
            if not videos:
                kinds = "/".join(s.lstrip(".") for s in VIDEO_SUFFIXES + IMAGE_SUFFIXES)
                items.append(VideoInput(path, input_stem(path), f"folder {str(path)!r} holds no video ({kinds})"))
            items.extend(VideoInput(p, input_stem(p)) for p in videos)
        elif not path.exists():
            items.append(VideoInput(path, input_stem(path), "no such file or folder"))
        else:
            items.append(VideoInput(path, input_stem(path)))
    for item, name in zip(items, unique_names(item.name for item in items)):
        item.name = name
    return items


def output_files(out: Path, name: str, maps: bool, detection: bool) -> list[Path]:
    """What scoring the input ``name`` writes into ``out``."""
    return [out / f"{name}.geco.json", *([out / f"{name}.maps.mp4"] if maps else []),
            *([out / f"{name}.detection.mp4"] if detection else [])]


def check_scorable(items: list[VideoInput]) -> None:
    """ValueError (one line naming each input and why), before any model loads, when no input
    can be scored (all missing, or folders without a video)."""
    if all(item.error is not None for item in items):
        raise ValueError("; ".join(f"{item.path}: {item.error}" for item in items))


def check_inputs_and_outputs(items: list[VideoInput], out: Path, overwrite: bool, maps: bool,
                             detection: bool) -> None:
    """ValueError (one line), before any model loads, when no input can be scored
    (:func:`check_scorable`), or when an output is already there without ``--overwrite``
    (another input's score of the same name, perhaps: ``b/g17.gif`` would replace the score of
    ``a/g17.gif``)."""
    check_scorable(items)
    if overwrite:
        return
    for item in items:
        taken = [p for p in output_files(out, item.name, maps, detection) if p.exists()]
        if item.error is None and taken:
            raise ValueError(f"{str(taken[0])!r} already exists (the score of an earlier run); pass --overwrite to "
                             "replace it, or choose another --out folder")


def run_outputs(items: list[VideoInput], out: Path, maps: bool, detection: bool, table: bool) -> list[Path]:
    """Every file this run may write into ``out``: what it holds the output locks of."""
    paths = [p for item in items if item.error is None for p in output_files(out, item.name, maps, detection)]
    return paths + ([out / "geco_scores.csv", out / "geco_summary.json"] if table else [])


def dynamic_mask_option(spec: str | None, device: Any) -> Any:
    """``--dynamic-masks``: a mask path is read and checked now, once, before any model loads (a
    :class:`~geco_guide.estimators.dynamic_masks.GivenMasks` of the whole file, which each video
    cuts to the frames its protocol picks); ``auto`` becomes one mask source for every input; text
    stays text, after checking that it names subjects: the segmenter of ``estimators.segmenter``,
    loaded once with the estimators (:func:`needs_segmenter`), masks them.

    Raises:
        MaskReadError: one sentence about the mask file (unreadable, not binary, wrong shape ...).
    """
    from ..estimators.dynamic_masks import AUTO, GivenMasks, looks_like_path, mask_source

    if spec is None:
        return None
    if looks_like_path(spec):
        return GivenMasks.from_path(spec)
    if spec.strip() == AUTO:
        return mask_source(AUTO, device=device)
    from ..estimators.segmenters import subjects_of

    subjects_of(spec)
    return spec


def needs_segmenter(dynamic: Any) -> bool:
    """Whether the ``--dynamic-masks`` of :func:`dynamic_mask_option` is text for the segmenter."""
    return isinstance(dynamic, str)


def check_masks_fit(items: list[VideoInput], masks: Any, evaluation: EvaluationConfig) -> None:
    """Given masks against each input, before any model loads: an input whose frame count or
    aspect ratio the masks do not fit (:func:`~geco_guide.metric.evaluate.clip_mask_source`, with
    ``evaluation.max_frames``) gets that one line as its error, as does one that cannot be read."""
    from ..estimators.dynamic_masks import GivenMasks
    from ..io.video import read_frames
    from .evaluate import clip_mask_source

    if not isinstance(masks, GivenMasks):
        return
    limit = evaluation.max_frames
    for item in items:
        if item.error is not None:
            continue
        try:  # the first frame only is kept: its size, and the count
            probe = read_frames(item.path, default_fps=evaluation.default_fps, select=lambda count, fps: [0])
            clip = replace(probe, num_frames=min(probe.num_frames, limit or probe.num_frames))
            clip_mask_source(masks, clip, probe.num_frames)
        except ValueError as err:  # MaskReadError and VideoReadError are ValueErrors
            item.error = str(err)


def check_detection_masks(detection: bool, masks: Any) -> None:
    """ValueError (one line) for ``--detection`` with automatic or text ``--dynamic-masks``: the
    detection maps judge each frame against a window of its own, which those masks are not made
    for (given masks of the video are applied to them)."""
    from ..estimators.dynamic_masks import GivenMasks

    if detection and masks is not None and not isinstance(masks, GivenMasks):
        raise ValueError("--detection draws its maps with given masks only (a mask file of the video); with "
                         "--dynamic-masks auto or subject text, score without --detection or write the masks to a "
                         "file first")
