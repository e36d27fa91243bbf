"""Reliability: non-finite and absurd values end in a finite result or one clear
ValueError, never a crash (grid_sample's backward segfaults on a NaN grid) and never a silent
0.0 score; config and CLI mistakes are one line, found before any model loads."""

from __future__ import annotations

import errno
import functools
import json
import math
import os
import sys
from dataclasses import dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

import geco_guide.estimators as estimators_package
from geco_guide import generation
from geco_guide.bench.synthetic import inject_deformation, rigid_clip
from geco_guide.cli.evaluate import main as evaluate_main
from geco_guide.cli.generate import main
from geco_guide.config import load_config
from geco_guide.estimators import Estimators
from geco_guide.estimators.loading import fetch_checkpoint_file
from geco_guide.estimators.oracle import OracleFlow, OracleGeometry
from geco_guide.geometry import inside_image, sample_bilinear
from geco_guide.io.files import WriteError, remove_temp_files, write_json_atomic
from geco_guide.io.video import write_video
from geco_guide.loss.geco import (
    GeCoLoss,
    GeCoLossConfig,
    frame_pairs,
    geco_from_geometry,
)
from geco_guide.metric.evaluate import evaluate_video
from geco_guide.sampler.pipelines.loading import load_video_pipeline
from geco_guide.tiny import tiny_estimators
from geco_guide.types import (
    Correspondences,
    NonFiniteFramesError,
    SceneGeometry,
    check_frame_values,
    non_finite_fields,
)

BAD_VALUES = (math.nan, math.inf, -math.inf, 1e30, -1e30)


@pytest.fixture(scope="module")
def clip():
    return inject_deformation(rigid_clip(num_frames=3, height=12, width=16), amplitude=2.0)


# --------------------------------------------------------------------------------------------
# 1. crashes: no non-finite grid reaches grid_sample, the loss stays finite forward and backward


def test_sample_bilinear_with_non_finite_coordinates_is_finite_forward_and_backward():
    image = torch.rand(1, 2, 6, 8, dtype=torch.float64, requires_grad=True)
    points = [[2.5, 3.0], [math.nan, 1.0], [math.inf, 2.0], [1.0, -math.inf], [1e30, 2.0], [3.4e38, -3.4e38]]
    uv = torch.tensor([points], dtype=torch.float64, requires_grad=True)
    samples = sample_bilinear(image, uv)  # segfaulted in backward before (NaN grid, border padding)
    samples.sum().backward()
    assert torch.isfinite(samples).all() and torch.isfinite(image.grad).all() and torch.isfinite(uv.grad).all()
    assert inside_image(uv.detach(), 6, 8).tolist() == [[True, False, False, False, False, False]]
    expected = image.detach()[0, :, 3, 2:4].mean(-1)  # (2.5, 3.0): halfway between two pixel centres
    torch.testing.assert_close(samples.detach()[0, :, 0], expected)
    assert uv.grad[0, 0].abs().sum() > 0 and (uv.grad[0, 1:4] == 0).all()  # no gradient through NaN/inf


def _leaf_inputs(clip, pairs):
    geometry, corr = clip.geometry(torch.float32), clip.pair_correspondences(pairs, torch.float32)
    confidence = torch.rand(geometry.depth.shape, generator=torch.Generator().manual_seed(0)) + 0.1
    return {
        "depth": geometry.depth, "intrinsics": geometry.intrinsics, "extrinsics": geometry.extrinsics,
        "confidence": confidence, "flow": corr.flow, "covisibility": corr.covisibility,
    }


@pytest.mark.parametrize("value", BAD_VALUES)
@pytest.mark.parametrize("name", ["depth", "intrinsics", "extrinsics", "confidence", "flow", "covisibility"])
def test_geco_from_geometry_is_finite_forward_and_backward_for_any_input_value(clip, name, value):
    """Property: a NaN/inf/huge entry anywhere in the estimators' outputs (a few random entries
    of one input) gives finite scores and finite gradients for every input, or a ValueError."""
    pairs = frame_pairs(clip.num_frames, "all")
    for seed in range(3):
        inputs = {k: v.clone() for k, v in _leaf_inputs(clip, pairs).items()}
        flat = inputs[name].view(-1)
        positions = torch.randint(flat.numel(), (1 + seed,), generator=torch.Generator().manual_seed(seed))
        flat[positions] = value
        leaves = {k: v.requires_grad_(k != "covisibility") for k, v in inputs.items()}
        geometry = SceneGeometry(leaves["depth"], leaves["intrinsics"], leaves["extrinsics"], leaves["confidence"])
        try:
            result = geco_from_geometry(geometry, Correspondences(leaves["flow"], leaves["covisibility"]), pairs)
        except ValueError:
            continue
        scalars = torch.stack([result.loss, result.motion, result.structure, result.fused])
        assert torch.isfinite(scalars).all(), (name, value, seed, scalars)
        assert all(torch.isfinite(m).all() for m in (result.pair_maps.fused, result.frame_maps.fused))
        scalars.sum().backward()
        for key, leaf in leaves.items():
            assert leaf.grad is None or torch.isfinite(leaf.grad).all(), (name, value, seed, key)


def test_a_non_finite_camera_invalidates_its_pairs_only(clip):
    pairs = frame_pairs(clip.num_frames, "adjacent")  # (0, 1), (1, 2)
    geometry = clip.geometry(torch.float32)
    extrinsics = geometry.extrinsics.clone()
    extrinsics[0, 2, 0, 3] = math.nan
    result = geco_from_geometry(replace(geometry, extrinsics=extrinsics), clip.pair_correspondences(pairs), pairs)
    assert result.pair_maps.fused_valid[0, 0].any() and not result.pair_maps.fused_valid[0, 1].any()


# --------------------------------------------------------------------------------------------
# 2. silent lies: non-finite or out-of-range frames are refused where frames enter


@pytest.fixture(scope="module")
def tiny_loss():
    return GeCoLoss(tiny_estimators(0), GeCoLossConfig(flow_downscale=0.5))


@pytest.mark.parametrize("value", BAD_VALUES + (255.0, -0.5))
def test_geco_loss_refuses_bad_frames_forward_and_backward(clip, tiny_loss, value):
    frames = clip.frames[None].float().clone()
    frames[0, 1, 2, 3, 4] = value
    frames.requires_grad_(True)
    expected = NonFiniteFramesError if not math.isfinite(value) else ValueError
    with pytest.raises(expected, match=r"frame\(s\) \[1\]"):
        tiny_loss(frames).loss.backward()


def test_geco_loss_on_good_frames_is_finite_forward_and_backward(clip, tiny_loss):
    frames = clip.frames[None].float().clone().requires_grad_(True)
    result = tiny_loss(frames)
    result.loss.backward()
    assert all(math.isfinite(v) for v in result.scalars().values()) and torch.isfinite(frames.grad).all()


def test_sampler_mode_gives_nan_scalars_and_no_update_for_nan_frames(clip, tiny_loss):
    """The samplers' loss (check_values=False: no host sync per update) never scores a NaN decode
    as consistent, and its gradient moves nothing (guided_step drops a non-finite one)."""
    sampler_loss = GeCoLoss(Estimators(tiny_loss.geometry_estimator, tiny_loss.flow_estimator), tiny_loss.config,
                            check_values=False)
    frames = clip.frames[None].float().clone()
    frames[0, 1, :, :4] = math.nan
    frames.requires_grad_(True)
    result = sampler_loss(frames)
    assert all(math.isnan(v) for v in result.scalars().values())
    (grad,) = torch.autograd.grad(result.loss, frames, allow_unused=True)
    assert grad is None or (grad == 0).all() or not torch.isfinite(grad).all()


def test_frame_check_names_frames_and_ranges():
    frames = torch.rand(2, 4, 3, 5, 6)
    check_frame_values(frames)
    check_frame_values(frames.clamp(0, 1) + 5e-4)  # float rounding is tolerated
    bad = frames.clone()
    bad[1, 2, 0, 0, 0] = math.nan
    with pytest.raises(NonFiniteFramesError, match=r"clip must be finite: frame\(s\) \[2\]"):
        check_frame_values(bad, "clip")
    with pytest.raises(ValueError, match=r"in \[0, 1\]: frame\(s\) \[0, 1, 2, 3\].*255"):
        check_frame_values(frames * 255)
    with pytest.raises(ValueError, match=r"frame\(s\) \[10, 30\]"):  # reported as source-video indices
        check_frame_values(torch.full((2, 3, 4, 4), -1.0), indices=[10, 30])


@pytest.mark.parametrize("value, message", [(math.nan, "must be finite"), (255.0, r"in \[0, 1\]")])
def test_evaluate_video_refuses_bad_frames_naming_the_frame(clip, value, message):
    frames = clip.frames.float().clone()
    frames[2, 0, 1, 1] = value
    with pytest.raises(ValueError, match=rf"{message}.*frame\(s\) \[2\]"):
        evaluate_video(frames, Estimators(OracleGeometry(clip), OracleFlow(clip)), fps=8)


def test_generate_refuses_a_diverged_video_and_writes_nothing(tmp_path: Path, monkeypatch):
    from geco_guide.sampler.running.context import GuidanceReport

    cfg = load_config(preset="tiny", overrides=[f"output.dir={tmp_path}", "output.score_anchors=false"])
    models = generation.load_models(cfg, estimators=False)
    frames = torch.rand(1, 17, 3, 32, 48)
    frames[0, 5:] = math.nan
    call = type(models.pipe).__call__
    monkeypatch.setattr(type(models.pipe), "__call__", functools.wraps(call)(lambda self, **kwargs: SimpleNamespace(
        frames=frames, report=GuidanceReport())))
    with pytest.raises(ValueError, match=r"sampling diverged, nothing was written.*frame\(s\) \[5, 6,"):
        generation.generate(cfg, "a cat", models=models)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------------
# config: every float option refuses NaN/inf naming its key; absurd magnitudes are refused


def _float_keys(obj, prefix=""):
    for f in fields(obj):
        value = getattr(obj, f.name)
        if is_dataclass(value):
            yield from _float_keys(value, f"{prefix}{f.name}.")
        elif isinstance(value, float):
            yield f"{prefix}{f.name}"


@pytest.mark.slow
def test_every_float_option_refuses_nan_and_inf_naming_the_key():
    keys = list(_float_keys(load_config(preset="tiny")))
    expected = {"guidance.step_size", "sampling.guidance_scale", "guidance.loss.occlusion_tau", "evaluation.window_seconds"}
    assert expected <= set(keys)
    for key in keys:
        for value in ("nan", "inf", "-inf"):
            with pytest.raises(ValueError, match=key.replace(".", r"\.")):
                load_config(preset="tiny", overrides=[f"{key}={value}"])


def test_non_finite_fields_walks_nested_dataclasses_lists_and_dicts():
    @dataclass
    class Inner:
        rates: dict = field(default_factory=lambda: {"a": 1.0, "b": math.inf})

    @dataclass
    class Outer:
        x: float = math.nan
        xs: list = field(default_factory=lambda: [1, -math.inf])
        inner: Inner = field(default_factory=Inner)
        name: str = "nan"

    found = non_finite_fields(Outer(), "cfg.")
    assert [key for key, _ in found] == ["cfg.x", "cfg.xs[1]", "cfg.inner.rates.b"]


def test_loss_config_refuses_non_finite_values():
    with pytest.raises(ValueError, match="occlusion_tau must be a finite number"):
        GeCoLossConfig(occlusion_tau=math.inf)
    with pytest.raises(ValueError, match="depth_edge_tau must be a finite number"):
        GeCoLossConfig(depth_edge_tau=math.nan)


@pytest.mark.parametrize(
    "override, key",
    [
        ("guidance.step_size=1e30", "guidance.step_size"),
        ("sampling.guidance_scale=1e30", "sampling.guidance_scale"),
        ("seed=18446744073709551616", "seed"),  # 2**64: torch.Generator would overflow after loading
        ("output.name=../../x", "output.name"),
    ],
)
def test_absurd_values_are_refused_naming_the_key(override, key):
    with pytest.raises(ValueError, match=rf"'{key}'"):
        load_config(preset="tiny", overrides=[override])


# --------------------------------------------------------------------------------------------
# CLI: one line, before any model loads


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err and "Traceback" not in err, err
    return err


@pytest.mark.parametrize("overrides", [["sampling.guidance_scale=1e30", "--no-guidance"], ["guidance.step_size=inf"]])
def test_cli_absurd_values_are_one_line_and_write_nothing(tmp_path: Path, capsys, no_loading, overrides):
    rc = main(["--preset", "tiny", "--prompt", "a cat", f"output.dir={tmp_path}", *overrides])
    assert rc == 2 and list(tmp_path.iterdir()) == []
    assert overrides[0].split("=")[0] in _one_error_line(capsys)


@pytest.mark.parametrize("content", [b"sampling: [1, 2\n", b"model:\n  id: \xff\xfe\n", b"- a list\n"])
def test_cli_bad_config_file_is_one_line_naming_the_file(tmp_path: Path, capsys, no_loading, content):
    path = tmp_path / "bad.yaml"
    path.write_bytes(content)
    assert main(["--config", str(path), "--prompt", "a cat"]) == 2
    assert str(path) in _one_error_line(capsys)


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cli_cuda_without_cuda_is_one_line_before_loading(tmp_path: Path, capsys, no_loading):
    assert main(["--preset", "tiny", "--prompt", "a cat", f"output.dir={tmp_path}", "model.device=cuda"]) == 2
    assert "'cuda' is not available" in _one_error_line(capsys)


def test_cli_out_under_a_file_is_one_line_before_loading(tmp_path: Path, capsys, no_loading):
    (tmp_path / "file").write_text("x")
    assert main(["--preset", "tiny", "--prompt", "a cat", "--out", str(tmp_path / "file" / "run.mp4")]) == 2
    assert "is a file, not a folder" in _one_error_line(capsys)


def test_offline_errors_name_the_hf_command(monkeypatch, tmp_path: Path):
    import diffusers.utils.constants
    import huggingface_hub.constants

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    # both libraries read the variable once, at import: without these no request is refused and
    # each one waits for its network timeout
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(diffusers.utils.constants, "HF_HUB_OFFLINE", True, raising=False)
    with pytest.raises(FileNotFoundError, match="`hf download geco-test-missing/VGGT-nothing`"):
        fetch_checkpoint_file("geco-test-missing/VGGT-nothing", ["model.safetensors"], model_name="VGGT",
                              cache_dir=tmp_path)
    cfg = load_config(preset="tiny", overrides=["model.id=geco-test-missing/CogVideoX-nothing"])
    with pytest.raises(FileNotFoundError, match="`hf download geco-test-missing/CogVideoX-nothing`"):
        load_video_pipeline(cfg.model)


# --------------------------------------------------------------------------------------------
# 3. atomic writes under a full disk: one line naming the file, nothing truncated, no temporaries


@pytest.mark.skipif(sys.platform != "linux", reason="RLIMIT_FSIZE semantics of Linux")
def test_ffmpeg_failing_on_a_full_disk_is_caught_before_the_rename(tmp_path: Path):
    """A real failure: a file size limit kills ffmpeg mid-file (as a full disk makes it fail on the
    trailer); imageio's writer returns normally, and the truncated file must not take the name."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    target = tmp_path / "v.mp4"
    resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, hard))  # ffmpeg inherits it; noise frames are ~300 kB
    try:
        with pytest.raises(WriteError, match=rf"^cannot write '{target}': the written file is not a readable video"):
            write_video(target, torch.rand(20, 3, 64, 96), fps=8)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_while_writing_a_file_is_one_line_naming_it(tmp_path: Path, monkeypatch):
    target = write_json_atomic(tmp_path / "result.json", {"ok": True})

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(WriteError, match=rf"^cannot write '{target}': \[Errno 28\] No space left on device$"):
        write_json_atomic(target, {"ok": False})
    assert json.loads(target.read_text()) == {"ok": True} and [p.name for p in tmp_path.iterdir()] == ["result.json"]


def test_the_next_write_removes_the_temporaries_a_killed_write_left(tmp_path: Path):
    stale = [tmp_path / ".v.k2j4_x9a.tmp.mp4", tmp_path / ".v.abcdefgh.tmp.mp4"]  # kill -9 during write_video
    others = [tmp_path / ".v.b.abcdefgh.tmp.mp4", tmp_path / ".v.abcdefgh.tmp.json", tmp_path / ".vv.abcdefgh.tmp.mp4"]
    for path in stale + others:  # temporaries of v.b.mp4, v.json, vv.mp4: another file's, maybe being written
        path.write_bytes(b"")
    write_video(tmp_path / "v.mp4", torch.rand(2, 3, 8, 8), fps=8)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["v.mp4", *(p.name for p in others)])
    remove_temp_files(tmp_path, ["v"])  # what the A/B script and GeCo-Eval do for a unit's files
    assert sorted(p.name for p in tmp_path.iterdir()) == [".v.b.abcdefgh.tmp.mp4", ".vv.abcdefgh.tmp.mp4", "v.mp4"]


@pytest.fixture
def truncating_writer(monkeypatch):
    """imageio's writer, made to leave a truncated file without raising: ffmpeg on a full disk."""
    import imageio.v2 as imageio

    real_get_writer = imageio.get_writer

    class Writer:
        def __init__(self, path, **kwargs):
            self.path, self.inner = Path(path), real_get_writer(path, **kwargs)

        def append_data(self, frame):
            self.inner.append_data(frame)

        def close(self):
            self.inner.close()
            self.path.write_bytes(self.path.read_bytes()[:100])

    monkeypatch.setattr(imageio, "get_writer", Writer)


def test_cli_full_disk_is_one_line_naming_the_video_and_writes_nothing(tmp_path: Path, capsys, stub_generation,
                                                                       truncating_writer):
    stub_generation(torch.rand(1, 9, 3, 32, 48))
    out = tmp_path / "clip.mp4"
    assert main(["--preset", "tiny", "--prompt", "a cat", "--out", str(out), "output.score_anchors=false"]) == 2
    loading, error = capsys.readouterr().err.strip().splitlines()  # the error follows the line of what loaded
    assert loading.startswith("loading models: ") and error.startswith(f"error: cannot write '{out}'")
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------------
# 4. evaluate's CLI: inputs that look like options, devices, before any model loads


@pytest.fixture
def no_estimators(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("estimators were loaded")
    monkeypatch.setattr(estimators_package, "load_estimators", refuse)


def test_evaluate_names_a_missing_input_that_looks_like_an_override(tmp_path: Path, capsys, no_estimators):
    assert evaluate_main(["--preset", "tiny", "a=b.mp4", "--out", str(tmp_path)]) == 2
    err = _one_error_line(capsys)
    assert "'a=b.mp4' is neither an existing file nor a config override ('a' is not a config key)" in err
    # real overrides, free mapping entries included, are still overrides
    assert evaluate_main(["--preset", "tiny", "evaluation.model_fps.mine=12", "evaluation.max_fps=4"]) == 2
    assert "no input video given" in _one_error_line(capsys)


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_evaluate_cuda_without_cuda_is_one_line_before_loading(tmp_path: Path, capsys, no_estimators):
    video = write_video(tmp_path / "v.mp4", torch.rand(3, 3, 16, 16), fps=8)
    assert evaluate_main([str(video), "--preset", "tiny", "evaluation.device=cuda", "--out", str(tmp_path)]) == 2
    err = _one_error_line(capsys)
    assert "'cuda' is not available" in err and "use evaluation.device=cpu or auto" in err


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
@pytest.mark.parametrize("override", ["model.device=cuda", "evaluation.device=cuda"])
def test_geco_eval_cuda_without_cuda_is_one_line_before_loading(tmp_path: Path, capsys, monkeypatch, override):
    from geco_guide.bench import runs
    from geco_guide.cli import geco_eval

    monkeypatch.setattr(runs, "process_state", lambda cfg: pytest.fail("the run started"))
    argv = ["--preset", "tiny", "--models", "cogvideox-5b", "--limit", "1", "--out", str(tmp_path / "x"), override]
    assert geco_eval.main(argv) == 2
    assert f"use {override.split('=')[0]}=cpu or auto" in _one_error_line(capsys)
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("changes, key", [
    ({"step_size": float("inf")}, "step_size"), ({"step_size": 1e30}, "step_size"), ({"step_size": -1.0}, "step_size"),
    ({"grad_eps": float("nan")}, "grad_eps"), ({"grad_eps": 0.0}, "grad_eps"), ({"chunk_latents": 1}, "chunk_latents"),
])
def test_guidance_config_refuses_bad_values_in_the_python_api_and_the_hook(changes, key):
    """The library path (GuidanceConfig, attach_geco_guidance with a dict) checks what the CLI checks."""
    from geco_guide.sampler import GuidanceConfig
    from geco_guide.sampler.pipelines.hooks import attach_geco_guidance
    from geco_guide.tiny import tiny_estimators, tiny_wan_pipeline

    with pytest.raises(ValueError, match=key):
        GuidanceConfig(**changes)
    pipe = tiny_wan_pipeline(0)
    with pytest.raises(ValueError, match=key):
        attach_geco_guidance(pipe, changes, tiny_estimators(0))
