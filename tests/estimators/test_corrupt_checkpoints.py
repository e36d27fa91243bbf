"""Checkpoint files that cannot be read (random bytes, empty, truncated) are one line naming the
file, through the Python API and through every command that loads them: generate, geco ab,
GeCo-Eval and geco bench (tiny models, CPU; nothing here reaches the network)."""

from __future__ import annotations

import json
import random
from pathlib import Path

import pytest
import torch

from geco_guide.cli import ab
from geco_guide.cli.generate import main as generate_main
from geco_guide.config import load_config
from geco_guide.estimators import load_estimators
from geco_guide.estimators.loading import CheckpointMismatchError, UnreadableCheckpointError, load_weights
from geco_guide.estimators.tiny_decoder import TinyDecoder
from geco_guide.estimators.ufm import UFM, UFMConfig
from geco_guide.estimators.vggt import VGGT, VGGTConfig





def _truncated(path: Path) -> Path:
    torch.save({"weight": torch.zeros(64, 64)}, path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def _noise(size: int = 700) -> bytes:
    """Random bytes, the same every run (some draws read as another reader error)."""
    return random.Random(0).randbytes(size)


#: How each kind of damage is made, and what the line says about it.
DAMAGE = {
    "random.pth": (lambda p: p.write_bytes(_noise()), "UnpicklingError"),
    "random.safetensors": (lambda p: p.write_bytes(_noise()), "SafetensorError"),
    "empty.pth": (lambda p: p.write_bytes(b""), "the file is empty"),
    "empty.safetensors": (lambda p: p.write_bytes(b""), "the file is empty"),
    "truncated.pth": (_truncated, "Error: "),  # a zip error or an OSError, by where the cut falls
}


def _one_line(text: str) -> str:
    text = text.strip()
    assert "\n" not in text and "Traceback" not in text, text
    return text


@pytest.mark.parametrize("name", sorted(DAMAGE))
def test_load_weights_names_a_file_it_cannot_read(tmp_path: Path, name: str):
    make, reason = DAMAGE[name]
    path = tmp_path / name
    make(path)
    with pytest.raises(UnreadableCheckpointError) as err:
        load_weights(path)
    message = _one_line(str(err.value))
    assert message.startswith(f"{str(path)!r} is not a readable checkpoint (") and reason in message
    assert isinstance(err.value, ValueError)  # what every command catches


def test_a_torch_file_of_other_things_than_tensors_is_a_mismatch(tmp_path: Path):
    torch.save({"weight": 3, "step": "x"}, tmp_path / "odd.pth")
    with pytest.raises(CheckpointMismatchError, match="odd.pth does not hold a state dict of tensors: step, weight are not tensors"):
        load_weights(tmp_path / "odd.pth")


@pytest.mark.parametrize("name", ["taecvx.pth", "taecvx.safetensors"])
def test_the_tiny_decoder_refuses_a_damaged_file_naming_it(tmp_path: Path, name: str):
    path = tmp_path / name
    path.write_bytes(_noise(500))
    with pytest.raises(UnreadableCheckpointError, match=f"'{path}' is not a readable checkpoint"):
        TinyDecoder.from_pretrained(path)
    folder = tmp_path / "folder"
    folder.mkdir()
    (folder / "taecvx.pth").write_bytes(b"")
    with pytest.raises(UnreadableCheckpointError, match="taecvx.pth' is not a readable checkpoint .the file is empty"):
        TinyDecoder.from_pretrained(folder, "cogvideox")


def _estimator_folder(tmp_path: Path, estimator: type, weights: bytes) -> Path:
    """A folder with a tiny architecture's config.json and damaged weights."""
    folder = tmp_path / estimator.model_name
    folder.mkdir()
    config = (VGGTConfig if estimator is VGGT else UFMConfig).tiny()
    (folder / "config.json").write_text(json.dumps(config.to_dict()))
    (folder / "model.safetensors").write_bytes(weights)
    return folder


@pytest.mark.parametrize("estimator", [VGGT, UFM])
@pytest.mark.parametrize("weights", [b"", b"\x00garbage" * 40])
def test_vggt_and_ufm_folders_with_damaged_weights_are_one_line(tmp_path: Path, estimator: type, weights: bytes):
    folder = _estimator_folder(tmp_path, estimator, weights)
    with pytest.raises(UnreadableCheckpointError) as err:
        estimator.from_pretrained(folder)
    assert _one_line(str(err.value)).startswith(f"'{folder / 'model.safetensors'}' is not a readable checkpoint")
    cfg = load_config(preset="tiny", overrides=[f"estimators.{'geometry' if estimator is VGGT else 'flow'}={folder}"])
    with pytest.raises(UnreadableCheckpointError):
        load_estimators(cfg.estimators, "cpu")


# ---- through the commands: one "error:" line, exit code 2 ----------------------------------------


def _damaged(tmp_path: Path) -> dict[str, str]:
    """Overrides pointing each loader at a damaged file: the tiny decoder and VGGT."""
    decoder = tmp_path / "taecvx.pth"
    decoder.write_bytes(_noise(600))
    return {
        "tiny decoder": f"estimators.tiny_decoder={decoder}",
        "vggt": f"estimators.geometry={_estimator_folder(tmp_path, VGGT, b'')}",
    }


@pytest.mark.parametrize("which", ["tiny decoder", "vggt"])
def test_generate_prints_one_line_for_a_damaged_checkpoint(tmp_path: Path, capsys, which: str):
    override = _damaged(tmp_path)[which]
    out = tmp_path / "out"
    rc = generate_main(["--preset", "tiny", "--prompt", "a cat", "--out", str(out / "v.mp4"), "guidance.decoder=tiny",
                        override])
    assert rc == 2
    err = capsys.readouterr().err
    assert err.startswith("loading models: ") and "Traceback" not in err  # the line says what loads, then one error
    assert _one_line(err.split("\n", 1)[1]).startswith("error: '") and "is not a readable checkpoint" in err
    assert not (out / "v.mp4").exists() and not (out / "v.json").exists()


@pytest.mark.parametrize("which", ["tiny decoder", "vggt"])
def test_the_ab_script_prints_one_line_and_pins_nothing(tmp_path: Path, capsys, which: str):
    override = _damaged(tmp_path)[which]
    (tmp_path / "p.txt").write_text("a cat\n")
    out = tmp_path / "out"
    rc = ab.main(["--prompts", str(tmp_path / "p.txt"), "--seeds", "0", "--out", str(out), "--preset", "tiny",
                  "guidance.decoder=tiny", override])
    assert rc == 2
    err = capsys.readouterr().err
    assert err.startswith("loading models: ") and "Traceback" not in err
    assert _one_line(err.split("\n", 1)[1]).startswith("error: '") and "is not a readable checkpoint" in err
    assert not (out / "run.json").exists() and not (out / "pairs").exists()


@pytest.mark.parametrize("which", ["tiny decoder", "vggt"])
def test_benchmark_decoder_agreement_prints_one_line(tmp_path: Path, capsys, which: str):
    from geco_guide.cli import bench

    override = _damaged(tmp_path)[which]
    assert bench.main(["decoder-agreement", "--preset", "tiny", override]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith("error: '") and "is not a readable checkpoint" in err


def test_geco_eval_prints_one_line_and_pins_nothing(tmp_path: Path, capsys):
    from geco_guide.cli.geco_eval import main as geco_eval_main
    from geco_guide.io.video import write_video

    videos = tmp_path / "in"
    write_video(videos / "a1-s0.mp4", torch.rand(17, 3, 32, 48), fps=16)
    out = tmp_path / "out"
    rc = geco_eval_main(["--preset", "tiny", "--videos", f"sora-2={videos}", "--limit", "1", "--out", str(out),
                         _damaged(tmp_path)["vggt"]])
    assert rc == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.splitlines()[-1].startswith("error: '")
    assert "is not a readable checkpoint" in err.splitlines()[-1]
    assert not (out / "run.json").exists() and not (out / ".run.lock").exists()
