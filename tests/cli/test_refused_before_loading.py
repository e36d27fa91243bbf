"""Values geco generate cannot act on are one line before any model loads, and options that cannot
act on the run say so in one warning line (tiny preset, CPU; the models never load here)."""

from __future__ import annotations

import pytest

from geco_guide.cli.generate import main

TINY = ["--preset", "tiny", "--prompt", "a marble bust"]


def _one_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    assert err.startswith("error: "), err
    return err


@pytest.mark.parametrize("argv, expected", [
    (["--dynamic", "5"], "got the number '5'"),
    (["--dynamic", "AUTO"], "write auto in lower case"),
    (["--dynamic", "{mask}"], "which names a file: guidance computes its masks on the anchor frames"),
    (["--devices", "meta"], "device 'meta' cannot run the models"),
    (["--devices", "cpu]"], "invalid device 'cpu]' (run.devices)"),
    (["--seed", "18446744073709551615", "--best-of", "2"], "over the 64-bit limit 18446744073709551615"),
    (["--best-of", "100000000"], "--best-of must be a whole number in [1, 1000], got 100000000"),
    (["guidance.repeats=3"], "guidance repeats schedule '3' covers 1 steps but the sampler runs 4 steps"),
    (["--out", ""], "--out must name a video file (.mp4 or .gif) or a folder, got an empty string"),
    (["--model", "wan2.1-t2v-1.3b", "run.split_cfg=true"],
     "run.split_cfg splits the denoiser calls of GeCoCogVideoXPipeline; wan2.1-t2v-1.3b is guided by the hooks"),
])
def test_a_value_generate_cannot_act_on_is_one_line_before_loading(argv, expected, tmp_path, capsys, no_loading):
    mask = tmp_path / "masks.npz"
    mask.write_bytes(b"")
    argv = [value.format(mask=mask) for value in argv]
    if "--out" not in argv:
        argv += ["--out", str(tmp_path / "out")]
    with _returns() as result:
        result.code = main([*TINY, *argv])
    assert result.code == 2
    assert expected in _one_error(capsys)
    assert not (tmp_path / "out").exists()


def test_a_number_of_repeats_in_python_is_one_line_naming_the_form():
    from geco_guide.sampler.algorithm.config import GuidanceConfig
    from geco_guide.types import OptionError

    with pytest.raises(OptionError, match=r"repeats must be runs 'RxN,...' .* got 3"):
        GuidanceConfig(repeats=3)


class _returns:
    """A context that holds a return code (the commands return 2; argparse exits 2)."""

    code: int | None = None

    def __enter__(self) -> "_returns":
        return self

    def __exit__(self, kind, value, traceback) -> bool:
        if kind is SystemExit:
            self.code = value.code
            return True
        return False


@pytest.mark.parametrize("argv, idle, warning", [
    (["--no-guidance"], ["--dynamic", "auto"], "guidance.dynamic='auto' does nothing without guidance"),
    (["--no-guidance"], ["run.split_cfg=true"], "run.split_cfg does nothing without guidance"),
    (["sampling.guidance_scale=1.0"], ["run.split_cfg=true"], "run.split_cfg does nothing without CFG"),
    (["--no-guidance"], ["run.particle_batch=2"], "run.particle_batch=2 does nothing without a search"),
])
@pytest.mark.slow
def test_an_option_that_cannot_act_is_one_warning_and_renames_nothing(argv, idle, warning, tmp_path, capsys):
    common = [*TINY, *argv, "sampling.num_inference_steps=2"]
    assert main([*common, "--out", str(tmp_path / "plain")]) == 0
    assert warning not in capsys.readouterr().err
    assert main([*common, *idle, "--out", str(tmp_path / "idle")]) == 0
    err = capsys.readouterr().err
    assert sum(warning in line for line in err.splitlines()) == 1, err
    names = [sorted(path.name for path in (tmp_path / run).glob("*.mp4")) for run in ("plain", "idle")]
    assert names[0] == names[1] and len(names[0]) == 1
