"""Mask files (:mod:`geco_guide.io.masks`): every bad one is one sentence about the mask file."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from geco_guide.io.masks import MaskReadError, read_masks
from geco_guide.io.video import write_video

GOOD = np.zeros((5, 12, 16), dtype=bool)
GOOD[:, 3:6, 4:9] = True


def _npz(array, **more):
    return lambda path: np.savez(path, masks=array, **more)


def _bytes(data: bytes):
    return lambda path: path.write_bytes(data)


def _png_folder(numbers):
    def make(path: Path):
        path.mkdir()
        for k in numbers:
            Image.fromarray(GOOD[k % 5].astype(np.uint8) * 255).save(path / f"mask_{k:03d}.png")
    return make


def _nan(path):
    values = GOOD.astype(np.float32)
    values[2, 0, 0] = np.nan
    np.savez(path, masks=values)


BAD_FILES = [
    ("flat.npz", _npz(GOOD[0]), "must have shape [S, H, W] (a mask per frame), got [12, 16]"),
    ("batched.npz", _npz(GOOD[None]), "must have shape [S, H, W] (a mask per frame), got [1, 5, 12, 16]"),
    ("no-frames.npz", _npz(GOOD[:0]), "must hold at least one mask"),
    ("nan.npz", _nan, "must be binary (0/1), got NaN or inf values"),
    ("complex.npz", _npz(GOOD.astype(np.complex64)), "must be binary (0/1), got complex values (complex64)"),
    ("grey.npz", _npz(np.full((2, 4, 4), 0.5)), "must be binary (0/1 or 0/255), got values 0.5"),
    ("text.npz", _npz(np.array(["a", "b"])), "holds <U1 values, not numbers"),
    ("objects.npz", _npz(np.array([{}, 1], dtype=object)), "holds Python objects, not numbers"),
    ("two.npz", lambda path: np.savez(path, a=GOOD, b=GOOD), "holds the arrays ['a', 'b']; store one array"),
    ("none.npz", lambda path: np.savez(path), "holds no array; store one array"),
    ("empty.npz", _bytes(b""), "is empty"),
    ("random.npz", _bytes(os.urandom(2000)), "is not an .npz archive (damaged, or another kind of file)"),
    ("masks.npy", lambda path: np.save(path, GOOD), "is a .npy array; mask files are an .npz archive"),
    ("frame.png", lambda path: Image.fromarray(GOOD[0].astype(np.uint8) * 255).save(path),
     "is a single image; masks are one per video frame"),
    ("notes.txt", lambda path: path.write_text("masks"), "is not a mask file; give an .npz archive"),
    ("random.mp4", _bytes(os.urandom(2000)), "is not a readable video ("),
    ("rgb.mp4", lambda path: write_video(path, torch.rand(3, 3, 32, 32), fps=8),
     "is not binary: 7"),  # about 70 % grey pixels
    ("empty", lambda path: path.mkdir(), "holds no .png/.jpg/.jpeg frames"),
    ("gap", _png_folder([0, 1, 2, 4, 5]), "lacks frame(s) 3: its frames are numbered 0 to 5"),
    ("missing.npz", lambda path: None, "does not exist (no such file or folder)"),
]


@pytest.mark.parametrize("name, make, message", BAD_FILES, ids=[case[0] for case in BAD_FILES])
def test_a_bad_mask_file_is_one_sentence_about_it(tmp_path: Path, name, make, message):
    path = tmp_path / name
    make(path)
    with pytest.raises(MaskReadError) as err:
        read_masks(path)
    text = str(err.value)
    kind = "mask folder" if path.is_dir() else "mask file"
    assert text.startswith(f"{kind} {str(path)!r} ") and message in text and "\n" not in text, text


def test_good_mask_files_read_back(tmp_path: Path):
    np.savez(tmp_path / "m.npz", masks=GOOD)
    _png_folder(range(5))(tmp_path / "pngs")
    write_video(tmp_path / "m.gif", torch.from_numpy(GOOD)[:, None].float().expand(-1, 3, -1, -1), fps=8)
    for name in ("m.npz", "pngs", "m.gif"):  # the GIF's five identical frames are five frames
        masks, count = read_masks(tmp_path / name)
        assert count == 5 and torch.equal(masks, torch.from_numpy(GOOD)), name
    with pytest.raises(MaskReadError, match=r"^mask file '.*m\.npz' holds 5 frame\(s\); frames up to 7 are needed$"):
        read_masks(tmp_path / "m.npz", select=[0, 7])
