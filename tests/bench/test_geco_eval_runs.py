"""GeCo-Eval runs that survive bad inputs and resume truthfully: failed videos are recorded and
the others scored, incomplete results are redone, another config is refused naming the key,
``--overwrite``, progress lines, Ctrl-C (tiny estimators on small random videos, CPU)."""

from __future__ import annotations

import csv
import errno
import json
import os
import re
import tempfile
from pathlib import Path

import pytest
import torch

from geco_guide.bench import geco_eval, runs
from geco_guide.bench.runs import check_output_folder, config_fingerprint, read_finished
from geco_guide.cli.geco_eval import main
from geco_guide.config import config_to_dict, load_config
from geco_guide.estimators.loading import WeightsNotFoundError
from geco_guide.io.video import write_video

INTERRUPTED = "interrupted: finished videos and scores are kept; rerun the same command to resume\n"


def _videos(folder: Path, frames: dict[str, int], garbage: tuple[str, ...] = ()) -> Path:
    """``folder/<name>.mp4`` of ``frames[name]`` random frames at 16 fps, and files of junk bytes."""
    folder.mkdir(parents=True, exist_ok=True)
    generator = torch.Generator().manual_seed(0)
    for name, count in frames.items():
        write_video(folder / f"{name}.mp4", torch.rand(count, 3, 32, 48, generator=generator), fps=16)
    for name in garbage:
        (folder / f"{name}.mp4").write_bytes(b"not a video" * 50)
    return folder


def _score(videos: Path, out: Path, *extra: str) -> int:
    return main(["--preset", "tiny", "--videos", f"sora-2={videos}", "--out", str(out), *extra])


def _one_line(text: str) -> str:
    assert text.count("\n") == 1, text
    return text


@pytest.mark.slow
def test_bad_videos_are_recorded_as_failed_and_the_others_scored(tmp_path: Path, capsys):
    videos = _videos(tmp_path / "in", {"a1-s0": 17, "a2-s0": 1}, garbage=("a3-s0",))
    out = tmp_path / "out"
    assert _score(videos, out, "--limit", "3") == 1  # some failed
    captured = capsys.readouterr()
    assert captured.out.strip() == f"1 video scored (2 failed, 0 missing); report: {out / 'report.md'}"
    assert "[1/3] sora-2 a1 seed 0: " in captured.err and "failed: cannot use video" in captured.err
    rows = {row["prompt_id"]: row for row in csv.DictReader((out / "results.csv").open())}
    assert rows["a1"]["error"] == "" and float(rows["a1"]["fused"]) >= 0
    assert "at least 2" in rows["a2"]["error"] and rows["a2"]["fused"] == ""
    assert rows["a3"]["error"].startswith("cannot read video")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["videos"] == 1 and [f["job"] for f in summary["failed"]] == ["sora-2/a2-s0", "sora-2/a3-s0"]
    report = (out / "report.md").read_text()
    assert "**Failed videos**" in report and "- sora-2/a3-s0: cannot read video" in report
    assert "existing videos (--videos)" in report and "tiny random models" in report  # what it ran with
    # a rerun tries the failed ones again: a fixed file is scored and its failure record goes
    _videos(videos, {"a3-s0": 17})
    assert _score(videos, out, "--limit", "3") == 1
    captured = capsys.readouterr()
    assert "1 of 3 videos already done; 2 that failed before are tried again" in captured.err
    assert "2 videos scored (1 failed, 0 missing)" in captured.out
    assert not (out / "videos" / "sora-2" / "a3-s0.failed.json").exists()
    assert (out / "videos" / "sora-2" / "a2-s0.failed.json").is_file()


def test_an_fps_that_leaves_one_frame_per_window_still_scores_the_video(tmp_path: Path, capsys):
    # a window left with one frame keeps the one before it (the protocol), so a slow clip scores
    videos = _videos(tmp_path / "in", {"a1-s0": 2})
    assert _score(videos, tmp_path / "out", "--limit", "1", "--fps", "0.01") == 0
    assert "1 video scored (0 failed, 0 missing)" in capsys.readouterr().out


@pytest.mark.slow
def test_videos_covering_part_of_the_selection_count_the_rest_missing(tmp_path: Path, capsys):
    videos = _videos(tmp_path / "in", {"a1-s0": 17, "a2-s0": 17})
    out = tmp_path / "out"
    assert _score(videos, out, "--limit", "5") == 1
    assert "2 videos scored (0 failed, 3 missing)" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["no_video"] == ["sora-2/a3", "sora-2/a4", "sora-2/a5"] and summary["missing"] == []
    assert "**No video** in the --videos folder for: sora-2/a3, sora-2/a4, sora-2/a5" in (out / "report.md").read_text()


@pytest.mark.slow
def test_resume_redoes_results_that_lack_fields_or_point_at_another_video(tmp_path: Path, capsys):
    videos = _videos(tmp_path / "in", {"a1-s0": 17, "a2-s0": 17})
    out = tmp_path / "out"
    assert _score(videos, out, "--limit", "2") == 0
    first, second = (out / "videos" / "sora-2" / f"{name}.json" for name in ("a1-s0", "a2-s0"))
    truncated = json.loads(first.read_text())
    scored = truncated.pop("fused")
    first.write_text(json.dumps(truncated))
    elsewhere = json.loads(second.read_text())
    second.write_text(json.dumps({**elsewhere, "video": str(tmp_path / "other.mp4")}))
    capsys.readouterr()
    assert _score(videos, out, "--limit", "2") == 0
    err = capsys.readouterr().err
    assert f"warning: {first} lacks 'fused'; job sora-2/a1-s0 is redone" in err
    assert f"warning: {second} scores {str(tmp_path / 'other.mp4')!r}" in err and "0 of 2 videos already done" in err
    assert json.loads(first.read_text())["fused"] == pytest.approx(scored)  # scored again, the same
    assert json.loads(second.read_text())["video"] == str(videos / "a2-s0.mp4")


def test_read_finished_checks_required_fields_and_readable_outputs(tmp_path: Path, capsys):
    result, video = tmp_path / "r.json", tmp_path / "v.mp4"
    result.write_text(json.dumps({"fused": 0.1}))
    video.write_bytes(b"")
    assert read_finished(result, [], "unit u", required=("fused",)) == {"fused": 0.1}
    assert read_finished(result, [], "unit u", required=("fused", "video")) is None
    assert read_finished(result, [video], "unit u") is None
    video.write_bytes(b"x")
    assert read_finished(result, [video], "unit u") == {"fused": 0.1}
    err = capsys.readouterr().err.splitlines()
    assert err == [f"warning: {result} lacks 'video'; unit u is redone", f"warning: {video} is empty; unit u is redone"]


def _pinned_folder(out: Path, overrides: list[str]) -> None:
    cfg = load_config(preset="tiny", overrides=overrides)
    out.mkdir(parents=True)
    (out / "run.json").write_text(json.dumps({"config_sha": config_fingerprint(cfg), "config": config_to_dict(cfg)}))


def test_another_config_is_refused_naming_the_keys_it_changed(tmp_path: Path):
    out = tmp_path / "out"
    _pinned_folder(out, ["evaluation.max_fps=8"])
    check_output_folder(out, load_config(preset="tiny", overrides=["evaluation.max_fps=8"]))
    other = load_config(preset="tiny", overrides=["evaluation.max_fps=4", "evaluation.loss.pairs=center"])
    with pytest.raises(ValueError) as err:
        check_output_folder(out, other, overwrite=False)
    message = str(err.value)
    assert "\n" not in message and "evaluation.max_fps: 8.0 -> 4.0" in message
    assert 'evaluation.loss.pairs: "all" -> "center"' in message and "--overwrite" in message
    with pytest.raises(ValueError, match="use a new --out folder or the same config$"):
        check_output_folder(out, other)  # a command without --overwrite does not offer it
    check_output_folder(out, other, overwrite=True)  # the caller starts afresh


def test_out_folders_that_cannot_be_written_are_one_line(tmp_path: Path, monkeypatch):
    cfg = load_config(preset="tiny")
    with pytest.raises(ValueError, match="cannot write to --out .*: a file name in it is too long$"):
        check_output_folder(tmp_path / ("x" * 300), cfg)
    (tmp_path / "file").write_text("")
    with pytest.raises(ValueError, match="exists and is not a folder"):
        check_output_folder(tmp_path / "file", cfg)
    with pytest.raises(ValueError, match=r"cannot be made: a file is in the way \(.*file'\)"):
        check_output_folder(tmp_path / "file" / "sub", cfg)
    assert not (tmp_path / "new").exists()
    check_output_folder(tmp_path / "new" / "deeper", cfg)
    assert not (tmp_path / "new").exists()  # checked, not created

    def read_only(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(tempfile, "mkstemp", read_only)  # root writes into a chmod 555 folder anyway
    with pytest.raises(ValueError, match="cannot write to --out .*: Permission denied$"):
        check_output_folder(tmp_path, cfg)


def test_missing_weights_leave_no_run_json(tmp_path: Path, monkeypatch, capsys):
    def missing(cfg, estimators=True):
        raise WeightsNotFoundError(f"{cfg.model.name}: weights not found")

    monkeypatch.setattr(geco_eval, "load_models", missing)
    out = tmp_path / "out"
    assert main(["--preset", "tiny", "--models", "cogvideox-5b", "--seeds", "0", "--limit", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[-1] == "error: cogvideox-5b: weights not found" and "Traceback" not in "".join(err)
    assert not (out / "run.json").exists() and not (out / "videos").exists()


def test_a_generation_that_fails_is_recorded_and_the_run_pinned_once_the_model_loaded(tmp_path: Path, monkeypatch,
                                                                                        capsys):
    def diverged(models, cfg, prompt, **kwargs):
        raise ValueError(f"{cfg.model.name}: sampling produced non-finite frames; nothing was written")

    monkeypatch.setattr(geco_eval, "sample", diverged)
    out = tmp_path / "out"
    assert main(["--preset", "tiny", "--models", "cogvideox-5b", "--seeds", "0", "--limit", "1", "--out", str(out)]) == 1
    captured = capsys.readouterr()
    assert "loading models: cogvideox-5b (tiny-random (cogvideox family" in captured.err
    assert "0 videos scored (1 failed, 0 missing)" in captured.out and (out / "run.json").is_file()
    failure = json.loads((out / "videos" / "cogvideox-5b" / "a1-s0.failed.json").read_text())
    assert failure["error"].endswith("non-finite frames; nothing was written") and failure["seed"] == 0


@pytest.mark.slow
def test_overwrite_starts_afresh_removing_only_the_runs_files(tmp_path: Path, capsys):
    videos = _videos(tmp_path / "in", {"a1-s0": 17})
    out = tmp_path / "out"
    assert _score(videos, out, "--limit", "1") == 0
    (out / "notes.txt").write_text("mine")
    (out / "videos" / "sora-2" / "keep.txt").write_text("mine")
    before = json.loads((out / "run.json").read_text())["config_sha"]
    capsys.readouterr()
    assert _score(videos, out, "--limit", "1", "evaluation.loss.pairs=center") == 2
    assert 'evaluation.loss.pairs: "all" -> "center"' in _one_line(capsys.readouterr().err)
    assert _score(videos, out, "--limit", "1", "evaluation.loss.pairs=center", "--overwrite") == 0
    assert "0 of 1 video already done" in capsys.readouterr().err
    assert json.loads((out / "run.json").read_text())["config_sha"] != before
    assert (out / "notes.txt").read_text() == "mine" and (out / "videos" / "sora-2" / "keep.txt").is_file()
    assert (out / "videos" / "sora-2" / "a1-s0.json").is_file()


@pytest.mark.slow
def test_progress_names_each_job_and_the_models_loading(tmp_path: Path, capsys):
    videos = _videos(tmp_path / "in", {"a1-s0": 17, "a2-s0": 17})
    assert _score(videos, tmp_path / "out", "--limit", "2") == 0
    lines = capsys.readouterr().err.splitlines()
    assert lines[:2] == ["0 of 2 videos already done", "loading models: geometry tiny-random, flow tiny-random"]
    assert [line.split(":")[0] for line in lines[2:]] == ["[1/2] sora-2 a1 seed 0", "[2/2] sora-2 a2 seed 0"]
    assert all(": scored in " in line and " s, fused " in line and line.endswith(" %") for line in lines[2:])


def test_ctrl_c_is_one_line_and_exit_code_130(tmp_path: Path, monkeypatch, capsys):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(geco_eval, "run_jobs", interrupted)
    videos = _videos(tmp_path / "in", {"a1-s0": 17})
    assert _score(videos, tmp_path / "out", "--limit", "1") == 130
    assert capsys.readouterr().err == INTERRUPTED


def test_a_second_run_in_one_folder_is_refused_while_the_first_holds_the_lock(tmp_path: Path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / runs.LOCK_NAME).write_text(f"{os.getppid()}\n")  # a live process
    assert _score(_videos(tmp_path / "in", {"a1-s0": 17}), out, "--limit", "1") == 2
    err = _one_line(capsys.readouterr().err)
    assert err == f"error: another GeCo-Eval run (pid {os.getppid()}) is writing to {out}; wait for it to end or use another --out folder\n"


@pytest.mark.slow
def test_the_lock_is_released_when_the_run_ends(tmp_path: Path, capsys):
    out = tmp_path / "out"
    assert _score(_videos(tmp_path / "in", {"a1-s0": 17}), out, "--limit", "1") == 0
    assert not (out / runs.LOCK_NAME).exists()


def test_a_lock_of_an_impossible_pid_is_taken_over_and_a_folder_in_its_place_is_one_line(tmp_path: Path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    videos = _videos(tmp_path / "in", {"a1-s0": 17})
    (out / runs.LOCK_NAME).write_text("99999999999999\n")  # beyond any pid: no process holds it
    assert _score(videos, out, "--limit", "1") == 0
    assert not (out / runs.LOCK_NAME).exists()
    capsys.readouterr()
    (out / runs.LOCK_NAME).mkdir()
    assert _score(videos, out, "--limit", "1", "--overwrite") == 2
    assert _one_line(capsys.readouterr().err) == (f"error: {out / runs.LOCK_NAME} is a folder, not a run lock; remove it "
                                                  "(or use another --out folder)\n")
    assert (out / "videos" / "sora-2" / "a1-s0.json").is_file()  # refused before --overwrite removed anything



def _generate(out: Path, *extra: str) -> int:
    return main(["--preset", "tiny", "--seeds", "0", "--limit", "1", "--out", str(out), *extra])


@pytest.mark.parametrize("models, overrides, message", [
    (["ltx-video"], ["run.decode_layout=channels_last"],
     "ltx-video guided: run.decode_layout=channels_last is written for the CogVideoX VAE, not ltx-video's"),
    (["cogvideox-5b", "ltx-video"], ["guidance.decoder=tiny"],
     "ltx-video guided: guidance.decoder=tiny: there is no tiny decoder for ltx-video's latents"),
    (["wan2.1-t2v-1.3b"], ["guidance.decoder=tiny", "estimators.tiny_decoder=null"],
     "wan2.1-t2v-1.3b guided: guidance.decoder=tiny needs the tiny decoder's weights"),
    (["cogvideox-5b"], ["run.memory_plan=auto", "run.memory_budget_gb=0.001"],
     "cogvideox-5b guided: no memory plan fits 0.0 GiB"),
])
def test_guided_options_a_model_refuses_are_one_line_before_the_run_starts(tmp_path: Path, monkeypatch, capsys,
                                                                            models, overrides, message):
    monkeypatch.setattr(runs, "process_state", lambda cfg: pytest.fail("the run started"))
    out = tmp_path / "out"
    assert _generate(out, "--models", *models, "--guided", *overrides) == 2
    assert _one_line(capsys.readouterr().err).startswith(f"error: {message}")
    assert not out.exists()


def test_a_named_tiny_decoder_of_another_family_is_refused_before_the_run_starts(tmp_path: Path, monkeypatch, capsys):
    from geco_guide.estimators import tiny_random_decoder

    torch.save(tiny_random_decoder("wan2.1").state_dict(), tmp_path / "taew2_1.pth")
    monkeypatch.setattr(runs, "process_state", lambda cfg: pytest.fail("the run started"))
    assert _generate(tmp_path / "out", "--models", "cogvideox-5b", "--guided", "guidance.decoder=tiny",
                     f"estimators.tiny_decoder={tmp_path / 'taew2_1.pth'}") == 2
    assert "is the tiny decoder of Wan 2.1, Wan 2.2 14B; cogvideox-5b needs taecvx.pth" in _one_line(capsys.readouterr().err)


@pytest.mark.slow
def test_guidance_by_the_tiny_decoder_loads_the_one_each_family_needs(tmp_path: Path, capsys):
    out = tmp_path / "out"
    assert _generate(out, "--models", "cogvideox-5b", "wan2.1-t2v-1.3b", "--guided", "guidance.decoder=tiny",
                     "sampling.num_inference_steps=2", "guidance.repeats=1x2", "guidance.time_travel=[]") == 0
    assert "4 videos scored (0 failed, 0 missing)" in capsys.readouterr().out
    for arm in ("cogvideox-5b-guided", "wan2.1-t2v-1.3b-guided"):
        assert json.loads((out / "videos" / arm / "a1-s0.json").read_text())["guidance_updates"] > 0


@pytest.mark.slow
def test_a_guided_call_that_fails_on_an_option_is_recorded_and_the_run_goes_on(tmp_path: Path, monkeypatch, capsys):
    original = geco_eval.sample

    def refused(models, cfg, prompt, **kwargs):
        if cfg.guidance.enabled:  # what a pipeline raises for an option it cannot take
            raise TypeError(f"{cfg.model.name}: this pipeline cannot take that option")
        return original(models, cfg, prompt, **kwargs)

    monkeypatch.setattr(geco_eval, "sample", refused)
    out = tmp_path / "out"
    assert _generate(out, "--models", "cogvideox-5b", "--guided", "sampling.num_inference_steps=2",
                     "guidance.repeats=1x2", "guidance.time_travel=[]") == 1
    assert re.search(r"^1 videos? scored \(1 failed, 0 missing\)", capsys.readouterr().out)
    failure = json.loads((out / "videos" / "cogvideox-5b-guided" / "a1-s0.failed.json").read_text())
    assert failure["error"] == "cogvideox-5b: this pipeline cannot take that option"
    assert (out / "videos" / "cogvideox-5b" / "a1-s0.json").is_file()


def test_the_weights_of_every_model_are_checked_before_the_run_starts(tmp_path: Path, monkeypatch, capsys):
    monkeypatch.setattr(runs, "process_state", lambda cfg: pytest.fail("the run started"))
    out = tmp_path / "out"
    rc = main(["--preset", "cogvideox-5b", "--models", "wan2.1-t2v-1.3b", "cogvideox-5b", "--seeds", "0",
               "--limit", "1", "--weights", f"wan2.1-t2v-1.3b={tmp_path / 'nowhere'}", "--out", str(out)])
    assert rc == 2
    err = _one_line(capsys.readouterr().err)
    # the video models first, then the estimators the preset names (not in this machine's cache either)
    assert err.startswith(f"error: 4 models lack their weights: (1) wan2.1-t2v-1.3b: local path '{tmp_path / 'nowhere'}' "
                          "does not exist")
    assert "(--weights wan2.1-t2v-1.3b=/path/to/Wan2.1-T2V-1.3B-Diffusers); (2) cogvideox-5b" in err
    assert err.rstrip().endswith("(config: estimators.flow=/path/to/UFM-Base)")
    assert not out.exists()


@pytest.mark.slow
def test_ltx2_videos_keep_their_sound_where_it_was_made_for_the_written_rate(tmp_path: Path, caplog):
    # the tiny preset samples at 8 fps: written at the protocol's 24 fps the sound would outlast
    # the video, so it is left out (and said); at a protocol rate of 8 fps it is muxed in
    from geco_guide.io.video import audio_stream

    video = Path("videos") / "ltx-2" / "a1-s0.mp4"
    with caplog.at_level("INFO", logger="geco_guide.bench.geco_eval"):
        assert _generate(tmp_path / "native", "--models", "ltx-2") == 0
    assert audio_stream(tmp_path / "native" / video) is None
    assert "the sound was made for 8 fps, the video is written at the protocol's 24 fps" in caplog.text
    assert _generate(tmp_path / "eight", "evaluation.model_fps.ltx-2=8", "--models", "ltx-2") == 0
    assert audio_stream(tmp_path / "eight" / video) == {"codec": "aac", "sample_rate": 16000, "channels": "stereo"}
