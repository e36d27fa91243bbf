"""Dynamic masks from files and tensors: :func:`read_masks` and :func:`check_masks`.

A dynamic mask is a boolean ``[S, H, W]`` tensor, true where content may move on its own (GeCo
leaves those pixels out). It comes as a mask video (any format :func:`~.video.read_frames` reads),
a folder of PNG frames, an ``.npz`` holding one ``[S, H, W]`` array, or a tensor. Values must be
binary: ``0/1`` (bool, integer or float) or ``0/255`` (uint8 images). Lossy codecs (mp4 and other
videos, JPEG frames) blur a mask's edges, so such masks are thresholded at one half, and only refused when more than
:data:`LOSSY_GREY_FRACTION` of their pixels are grey (an RGB video passed by mistake). Every problem
is one :class:`MaskReadError` line naming the input, raised before any model loads.

:func:`fit_masks` checks the frame count against the video and resizes (nearest) to the frames;
:func:`connected_regions` splits a mask into its 8-connected regions.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .video import VideoReadError, frame_files, read_frames

__all__ = ["MASK_SUFFIXES", "MaskReadError", "check_masks", "connected_regions", "fit_masks", "read_masks"]

#: Largest fraction of a lossy mask video's pixels allowed between 1/4 and 3/4 (codec blur at
#: edges); more means the file is not a mask.
LOSSY_GREY_FRACTION = 0.05

MASK_SUFFIXES = (".npz",)


class MaskReadError(ValueError):
    """A dynamic-mask input is unreadable, not binary or of the wrong shape; one line."""


def _binary(array: Tensor, name: str) -> Tensor:
    """``array`` (bool, integer or float) -> bool, refusing values other than 0/1 (or 0/255)."""
    if array.dtype == torch.bool:
        return array
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
    if masks.ndim not in ((3, 4) if batched else (3,)) or masks.numel() == 0:
        raise MaskReadError(f"{name} must have shape {shapes}, got {list(masks.shape)}")
    return _binary(masks, name)


def _read_npz(path: Path) -> Tensor:
    try:
        with np.load(path) as data:
            names = list(data.keys())
            key = "masks" if "masks" in names else (names[0] if len(names) == 1 else None)
            if key is None:
                raise MaskReadError(f"cannot read masks {str(path)!r}: it holds {names}; store one array or one named 'masks'")
            array = data[key]
    except MaskReadError:
        raise
    except Exception as err:  # numpy raises several types for a corrupt archive
        raise MaskReadError(f"cannot read masks {str(path)!r}: {type(err).__name__}: {err}".splitlines()[0]) from err
    if array.dtype == object or not (np.issubdtype(array.dtype, np.number) or array.dtype == np.bool_):
        raise MaskReadError(f"cannot read masks {str(path)!r}: array dtype {array.dtype} is not numeric")
    return check_masks(torch.from_numpy(np.ascontiguousarray(array)), f"masks {str(path)!r}")


def _read_images(path: Path, select: Sequence[int] | None, lossy: bool) -> tuple[Tensor, int]:
    """A mask video or PNG folder -> ``[N, H, W]`` bool of the selected frames and the count."""
    def pick(count: int, fps: float) -> list[int]:
        if select is None:
            return list(range(count))
        return [i for i in select if 0 <= i < count]

    try:
        clip = read_frames(path, select=pick)
    except VideoReadError as err:
        raise MaskReadError(str(err).replace("video", "mask video", 1)) from None
    count = clip.num_frames
    if select is not None and list(clip.indices) != sorted(set(select)):
        raise MaskReadError(f"masks {str(path)!r} hold {count} frame(s); frames {max(select)} and earlier are needed")
    grey = clip.frames.amax(dim=1)  # any channel: a coloured mask counts as set
    if lossy:
        ambiguous = ((grey > 0.25) & (grey < 0.75)).float().mean()
        if float(ambiguous) > LOSSY_GREY_FRACTION:
            raise MaskReadError(
                f"masks {str(path)!r} are not binary: {float(ambiguous):.0%} of the pixels are grey "
                f"(at most {LOSSY_GREY_FRACTION:.0%} allowed for a lossy mask video)"
            )
        return grey > 0.5, count
    return _binary((grey * 255).round().to(torch.uint8), f"masks {str(path)!r}"), count


def read_masks(path: str | os.PathLike, select: Sequence[int] | None = None) -> tuple[Tensor, int]:
    """Dynamic masks stored in a file or folder.

    Args:
        path: a mask video, a folder of PNG frames (natural order, as video frames are read), or an
            ``.npz`` with one ``[S, H, W]`` array (or one named ``masks``).
        select: source frame indices to keep (the protocol's, see ``evaluate_video``); ``None``
            keeps all.

    Returns:
        ``(masks [N, H, W] bool, S)``: the selected frames and the number of frames stored.

    Raises:
        MaskReadError: missing, unreadable, wrong shape, non-binary, or too few frames for
            ``select``.
    """
    path = Path(path)
    if not path.exists():
        raise MaskReadError(f"cannot read masks {str(path)!r}: no such file or folder")
    if path.is_file() and path.suffix.lower() in MASK_SUFFIXES:
        masks = _read_npz(path)
        count = masks.shape[0]
        if select is not None:
            if max(select, default=0) >= count:
                raise MaskReadError(f"masks {str(path)!r} hold {count} frame(s); frames up to {max(select)} are needed")
            masks = masks[list(select)]
        return masks, count
    if path.is_dir():  # JPEG frames blur edges as a lossy video does
        lossy = any(f.suffix.lower() in (".jpg", ".jpeg") for f in frame_files(path))
    else:
        lossy = path.suffix.lower() not in (".png", ".gif")
    return _read_images(path, select, lossy)


def fit_masks(masks: Tensor, num_frames: int, size: tuple[int, int], name: str = "dynamic_masks") -> Tensor:
    """Check the frame count of ``masks [..., S, h, w]`` and resize them (nearest) to ``size``.

    Raises:
        MaskReadError: ``S != num_frames``, or the aspect ratio differs from the frames' by more
            than 2 % (masks drawn for another video).
    """
    if masks.shape[-3] != num_frames:
        raise MaskReadError(f"{name} hold {masks.shape[-3]} frame(s), the video {num_frames}")
    height, width = masks.shape[-2:]
    if tuple(masks.shape[-2:]) == tuple(size):
        return masks
    if abs((width / height) / (size[1] / size[0]) - 1.0) > 0.02:
        raise MaskReadError(f"{name} are {height}x{width}, the frames {size[0]}x{size[1]}: a different aspect ratio")
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
