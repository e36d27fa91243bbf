"""Dynamic masks from files and tensors: :func:`read_masks` and :func:`check_masks`.

A dynamic mask is a boolean ``[S, H, W]`` tensor, true where content may move on its own (GeCo
leaves those pixels out). It comes as a mask video (any format :func:`~.video.read_frames` reads),
a folder of PNG frames, an ``.npz`` holding one ``[S, H, W]`` array, or a tensor. Values must be
binary: ``0/1`` (bool, integer or float) or ``0/255`` (uint8 images). Lossy codecs (mp4 and other
videos, JPEG frames) blur a mask's edges, so such masks are thresholded at one half, and only refused when more than
:data:`LOSSY_GREY_FRACTION` of their pixels are grey (an RGB video passed by mistake). Every problem
is one :class:`MaskReadError` line, a sentence about the mask file (``mask file 'm.npz' ...``, or
``mask folder``), raised before any model loads.

:func:`fit_masks` checks the frame count against the video and resizes (nearest) to the frames;
:func:`connected_regions` splits a mask into its 8-connected regions.
"""

from __future__ import annotations

import os
import re
import zipfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .video import IMAGE_SUFFIXES, VIDEO_SUFFIXES, VideoReadError, frame_files, read_frames

__all__ = ["MASK_KINDS", "MASK_SUFFIXES", "MaskReadError", "check_masks", "connected_regions", "fit_masks",
           "mask_file_name", "read_masks"]

#: Largest fraction of a lossy mask video's pixels allowed between 1/4 and 3/4 (codec blur at
#: edges); more means the file is not a mask.
LOSSY_GREY_FRACTION = 0.05

MASK_SUFFIXES = (".npz",)


class MaskReadError(ValueError):
    """A dynamic-mask input is unreadable, not binary or of the wrong shape; one line."""


def mask_file_name(path: str | os.PathLike) -> str:
    """What messages call a mask input: ``mask folder '...'`` or ``mask file '...'``."""
    return f"{'mask folder' if Path(path).is_dir() else 'mask file'} {os.fspath(path)!r}"


def _binary(array: Tensor, name: str) -> Tensor:
    """``array`` (bool, integer or float) -> bool, refusing values other than 0/1 (or 0/255)."""
    if array.dtype == torch.bool:
        return array
    if array.is_complex():
        raise MaskReadError(f"{name} must be binary (0/1), got complex values ({str(array.dtype).removeprefix('torch.')})")
    values = array.detach()
    if values.is_floating_point() and not bool(torch.isfinite(values).all()):
        raise MaskReadError(f"{name} must be binary (0/1), got NaN or inf values")
    unique = torch.unique(values)
    if unique.numel() > 0 and float(unique.max()) == 255 and set(unique.tolist()) <= {0, 255}:
        return values > 0
    if not set(unique.tolist()) <= {0, 1}:
        shown = ", ".join(f"{v:g}" for v in unique[:5].tolist())
        raise MaskReadError(f"{name} must be binary (0/1 or 0/255), got values {shown}{'...' if unique.numel() > 5 else ''}")
    return values > 0


def check_masks(masks: Tensor, name: str = "dynamic_masks", batched: bool = False) -> Tensor:
    """``masks`` as a bool tensor after checking it.

    Args:
        masks: ``[S, H, W]`` (or ``[B, S, H, W]`` with ``batched``), bool or 0/1 numbers.
        name: what messages call it.
        batched: accept ``[B, S, H, W]`` as well.

    Returns:
        The same shape, ``torch.bool``.

    Raises:
        MaskReadError: not a tensor, wrong number of dimensions, empty, or not binary.
    """
    if not isinstance(masks, Tensor):
        raise MaskReadError(f"{name} must be a tensor, a path or a mask source, got {type(masks).__name__}")
    shapes = "[S, H, W] or [B, S, H, W]" if batched else "[S, H, W]"
    if masks.ndim not in ((3, 4) if batched else (3,)):
        raise MaskReadError(f"{name} must have shape {shapes} (a mask per frame), got {list(masks.shape)}")
    if masks.numel() == 0:
        raise MaskReadError(f"{name} must hold at least one mask of at least one pixel, got shape {list(masks.shape)}")
    return _binary(masks, name)


#: What a mask input may be, for the messages that refuse another kind of file.
MASK_KINDS = "an .npz archive (numpy.savez('masks.npz', masks=array)), a mask video or a folder of PNG frames"


def _read_npz(path: Path) -> Tensor:
    name = mask_file_name(path)
    if path.stat().st_size == 0:
        raise MaskReadError(f"{name} is empty")
    if not zipfile.is_zipfile(path):
        raise MaskReadError(f"{name} is not an .npz archive (damaged, or another kind of file); save masks as {MASK_KINDS}")
    try:
        with np.load(path, allow_pickle=False) as data:
            names = list(data.keys())
            key = "masks" if "masks" in names else (names[0] if len(names) == 1 else None)
            if key is None:
                held = f"the arrays {names}" if names else "no array"
                raise MaskReadError(f"{name} holds {held}; store one array, or one named 'masks'")
            array = data[key]
    except MaskReadError:
        raise
    except ValueError as err:  # numpy refuses object arrays without pickle
        if "pickle" in str(err).lower() or "object" in str(err).lower():
            raise MaskReadError(f"{name} holds Python objects, not numbers") from None
        raise MaskReadError(f"{name} is a damaged .npz archive ({type(err).__name__})") from None
    except Exception as err:  # zipfile, zlib and numpy raise several types for a damaged archive
        raise MaskReadError(f"{name} is a damaged .npz archive ({type(err).__name__})") from err
    if not (np.issubdtype(array.dtype, np.number) or array.dtype == np.bool_):
        raise MaskReadError(f"{name} holds {array.dtype} values, not numbers")
    return check_masks(torch.from_numpy(np.ascontiguousarray(array)), name)


def _video_reason(err: VideoReadError, path: Path) -> str:
    """The reason of a :class:`VideoReadError` of ``path``, without its ``cannot read video '...'`` prefix."""
    text = str(err)
    for prefix in (f"cannot read video {str(path)!r}: ", f"cannot use video {str(path)!r}: "):
        if text.startswith(prefix):
            return text[len(prefix):]
    return text


def _frame_numbers(files: Sequence[Path]) -> list[int] | None:
    """The number at the end of each frame file's stem (``mask_007.png`` -> 7), or None when one has none."""
    numbers = [re.search(r"(\d+)$", f.stem) for f in files]
    return None if any(n is None for n in numbers) else [int(n.group(1)) for n in numbers]


def _check_folder(path: Path) -> list[Path]:
    """The frame files of a mask folder, refusing one without frames or with a gap in its
    numbering (a mask missing there would shift every later mask onto the wrong video frame)."""
    name = mask_file_name(path)
    files = frame_files(path)
    if not files:
        raise MaskReadError(f"{name} holds no {'/'.join(IMAGE_SUFFIXES)} frames")
    numbers = _frame_numbers(files)
    if numbers is not None and len(numbers) == len(set(numbers)):
        missing = sorted(set(range(min(numbers), max(numbers) + 1)) - set(numbers))
        if missing:
            shown = ", ".join(map(str, missing[:5])) + (", ..." if len(missing) > 5 else "")
            raise MaskReadError(f"{name} lacks frame(s) {shown}: its frames are numbered {min(numbers)} to "
                                f"{max(numbers)}, and a missing mask would shift the later ones onto other frames")
    return files


def _read_images(path: Path, select: Sequence[int] | None, lossy: bool) -> tuple[Tensor, int]:
    """A mask video or PNG folder -> ``[N, H, W]`` bool of the selected frames and the count."""
    name = mask_file_name(path)

    def pick(count: int, fps: float) -> list[int]:
        if select is None:
            return list(range(count))
        return [i for i in select if 0 <= i < count]

    try:
        clip = read_frames(path, select=pick)
    except VideoReadError as err:
        raise MaskReadError(f"{name} is not a readable {'folder of frames' if path.is_dir() else 'video'} "
                            f"({_video_reason(err, path)})") from None
    count = clip.num_frames
    if select is not None and list(clip.indices) != sorted(set(select)):
        raise MaskReadError(f"{name} holds {count} frame(s); frames up to {max(select)} are needed")
    grey = clip.frames.amax(dim=1)  # any channel: a coloured mask counts as set
    if lossy:
        ambiguous = ((grey > 0.25) & (grey < 0.75)).float().mean()
        if float(ambiguous) > LOSSY_GREY_FRACTION:
            raise MaskReadError(
                f"{name} is not binary: {float(ambiguous):.0%} of its pixels are grey (a lossy mask video may have at most "
                f"{LOSSY_GREY_FRACTION:.0%}); is it the video rather than its masks?"
            )
        return grey > 0.5, count
    return _binary((grey * 255).round().to(torch.uint8), name), count


def read_masks(path: str | os.PathLike, select: Sequence[int] | None = None) -> tuple[Tensor, int]:
    """Dynamic masks stored in a file or folder.

    Args:
        path: a mask video, a folder of PNG frames (natural order, as video frames are read,
            numbered without gaps), or an ``.npz`` with one ``[S, H, W]`` array (or one named
            ``masks``).
        select: source frame indices to keep (the protocol's, see ``evaluate_video``); ``None``
            keeps all.

    Returns:
        ``(masks [N, H, W] bool, S)``: the selected frames and the number of frames stored.

    Raises:
        MaskReadError: one sentence about the mask file: missing, another kind of file,
            unreadable, wrong shape, non-binary, a gap in a folder's numbering, or too few frames
            for ``select``.
    """
    if not os.fspath(path).strip():  # Path("") is the working folder
        raise MaskReadError("the mask file's path is empty: give a mask file or folder")
    path = Path(path)
    name = mask_file_name(path)
    if not path.exists():
        raise MaskReadError(f"{name} does not exist (no such file or folder)")
    suffix = path.suffix.lower()
    if path.is_file() and suffix in MASK_SUFFIXES:
        masks = _read_npz(path)
        count = masks.shape[0]
        if select is not None:
            if max(select, default=0) >= count:
                raise MaskReadError(f"{name} holds {count} frame(s); frames up to {max(select)} are needed")
            masks = masks[list(select)]
        return masks, count
    if path.is_dir():  # JPEG frames blur edges as a lossy video does
        lossy = any(f.suffix.lower() in (".jpg", ".jpeg") for f in _check_folder(path))
    elif suffix == ".npy":
        raise MaskReadError(f"{name} is a .npy array; mask files are {MASK_KINDS}")
    elif suffix in IMAGE_SUFFIXES:
        raise MaskReadError(f"{name} is a single image; masks are one per video frame: {MASK_KINDS}")
    elif suffix not in VIDEO_SUFFIXES:
        raise MaskReadError(f"{name} is not a mask file; give {MASK_KINDS}")
    else:
        lossy = suffix != ".gif"  # GIF frames are exact; other videos are lossy
    return _read_images(path, select, lossy)


def fit_masks(masks: Tensor, num_frames: int, size: tuple[int, int], name: str = "dynamic_masks") -> Tensor:
    """Check the frame count of ``masks [..., S, h, w]`` and resize them (nearest) to ``size``.

    Raises:
        MaskReadError: ``S != num_frames``, or the aspect ratio differs from the frames' by more
            than 2 % (masks drawn for another video).
    """
    one = name.startswith(("mask file", "mask folder"))  # one file, or masks
    if masks.shape[-3] != num_frames:
        raise MaskReadError(f"{name} {'holds' if one else 'hold'} {masks.shape[-3]} frame(s), the video {num_frames}")
    height, width = masks.shape[-2:]
    if tuple(masks.shape[-2:]) == tuple(size):
        return masks
    if abs((width / height) / (size[1] / size[0]) - 1.0) > 0.02:
        raise MaskReadError(f"{name} {'holds masks of' if one else 'are'} {height}x{width}, the frames "
                            f"{size[0]}x{size[1]}: a different aspect ratio")
    flat = masks.reshape(-1, 1, height, width).float()
    resized = F.interpolate(flat, size=tuple(size), mode="nearest")
    return resized.reshape(*masks.shape[:-2], *size) > 0.5


def connected_regions(mask: Tensor) -> Tensor:
    """8-connected regions of ``mask [H, W]`` bool -> labels ``[H, W]`` int64 (0 outside, each
    region the largest flat index + 1 of its pixels)."""
    height, width = mask.shape
    labels = torch.arange(1, height * width + 1, device=mask.device).reshape(height, width)
    labels = torch.where(mask, labels, torch.zeros_like(labels))
    while True:
        # Each pass spreads the largest label along whole rows and columns of the region, then one
        # pixel in every direction (the diagonal steps); a box-like region settles in a few passes.
        grown = _run_max(_run_max(labels, mask).T, mask.T).T
        pooled = F.max_pool2d(grown[None, None].double(), 3, stride=1, padding=1)[0, 0].long()
        grown = torch.where(mask, pooled, grown)
        if torch.equal(grown, labels):
            return labels
        labels = grown


def _run_max(labels: Tensor, mask: Tensor) -> Tensor:
    """``labels [H, W]`` with every horizontal run of ``mask`` set to the run's largest label."""
    starts = mask.clone()
    starts[:, 1:] &= ~mask[:, :-1]
    run = torch.cumsum(starts.flatten(), 0).reshape(mask.shape)  # a run's id on each of its pixels
    largest = torch.zeros(int(run.max()) + 1, dtype=labels.dtype, device=labels.device)
    largest = largest.scatter_reduce(0, run[mask], labels[mask], reduce="amax")
    return torch.where(mask, largest[run], labels)
