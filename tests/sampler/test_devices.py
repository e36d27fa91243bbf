"""One guided call over several devices (``run.devices``): the anchor chunks dealt round-robin,
each device with its own replica of the decoder; the same frames as one device, bitwise on CPU."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from geco_guide.sampler.algorithm.config import GuidanceConfig
from geco_guide.io.devices import resolve_devices
from geco_guide.sampler.running.multi_device import module_replicas
from geco_guide.sampler.running.run_options import RunOptions
from geco_guide.sampler.algorithm.slicing import anchor_latent_chunks, decode_anchor_frames, decode_anchor_frames_across
from geco_guide.tiny import TINY_CALL_KWARGS, tiny_estimators, tiny_call_kwargs, tiny_guidance_config, tiny_pipeline, \
    tiny_run_options

ESTIMATORS = tiny_estimators(0)


def test_chunks_are_dealt_round_robin_and_only_anchor_frames_come_back():
    chunks = anchor_latent_chunks([4, 8, 12, 16], 17, 4, 3)
    latents = torch.randn(1, 5, 2, 3, 3, requires_grad=True)
    calls = []

    def decoder(tag):
        def decode(part):
            calls.append((tag, part.shape[1]))
            return part.mean(2, keepdim=True).repeat_interleave(4, dim=1)[:, :1 + 4 * (part.shape[1] - 1)].expand(
                -1, -1, 3, -1, -1)
        return decode

    one = decode_anchor_frames(decoder("home"), latents, chunks, batch_chunks=False)
    calls.clear()
    two = decode_anchor_frames_across([(torch.device("cpu"), decoder("a")), (torch.device("cpu"), decoder("b"))],
                                      latents, chunks, checkpoint_chunks=True)
    assert [tag for tag, _ in calls] == ["a", "b", "a", "b"]  # four spans, alternately
    assert torch.equal(one, two) and two.shape == (1, 4, 3, 3, 3)
    (g1,) = torch.autograd.grad(one.sum(), latents)
    (g2,) = torch.autograd.grad(two.sum(), latents)
    assert torch.equal(g1, g2)


def test_each_extra_device_gets_a_replica_of_its_own():
    module = torch.nn.Linear(2, 2)
    replicas = module_replicas(module, [torch.device("cpu"), torch.device("cpu"), torch.device("cpu")])
    assert replicas[0] is module and replicas[1] is not module and replicas[2] is not replicas[1]
    assert all(torch.equal(r.weight, module.weight) for r in replicas)


def _pipe_frames(config, run):
    pipe = tiny_pipeline(seed=0)
    out = pipe("a marble bust", generator=torch.Generator().manual_seed(0), output_type="pt", guidance=config,
               run_options=run, estimators=ESTIMATORS, **TINY_CALL_KWARGS)
    return out.frames, out.report, pipe


@pytest.mark.parametrize("plan", ["chunked", "explicit"], ids=["a-chunk-per-call", "batched-chunks"])
@pytest.mark.parametrize("denoiser_grad", [False, True], ids=["fast", "faithful"])
@pytest.mark.slow
def test_two_devices_give_the_frames_of_one_in_the_pipeline(denoiser_grad, plan):
    # explicit: the tiny preset's own flags, which batch the chunks of one length in one decode call
    config, run = replace(tiny_guidance_config(), denoiser_grad=denoiser_grad), tiny_run_options(memory_plan=plan)
    one, report_one, _ = _pipe_frames(config, run)
    listed, _, _ = _pipe_frames(config, replace(run, devices=["cpu"]))
    two, report_two, pipe = _pipe_frames(config, replace(run, devices=["cpu", "cpu"]))
    assert torch.equal(one, two) and torch.equal(one, listed)
    assert [r["loss"] for r in report_one.log] == [r["loss"] for r in report_two.log]
    assert report_one.devices is None and report_two.devices == ["cpu", "cpu"]


@pytest.mark.slow
def test_two_devices_give_the_frames_of_one_through_a_hook():
    from geco_guide import attach_geco_guidance
    from geco_guide.tiny import tiny_wan_pipeline

    config = GuidanceConfig(anchors=[4, 8], repeats="0x3,2x1", time_travel=[], step_size=1.0)
    videos = []
    for devices in (None, ["cpu", "cpu"]):
        pipe = tiny_wan_pipeline(0)
        with attach_geco_guidance(pipe, config, ESTIMATORS,
                                  run_options=RunOptions(memory_plan="chunked", devices=devices)) as handle:
            videos.append(pipe("a marble bust", generator=torch.Generator().manual_seed(0), output_type="pt",
                               **tiny_call_kwargs(pipe, num_frames=9)).frames)
            assert handle.last.devices == (None if devices is None else ["cpu", "cpu"]) and handle.last.log
    assert torch.equal(videos[0], videos[1])


@pytest.mark.parametrize("devices, message", [
    (["tpu"], "invalid device 'tpu' (run.devices)"),
    (["cpu", "cuda:7"], "device 'cuda:7' is not available"),
])
def test_a_device_this_machine_lacks_is_one_line(devices, message):
    if torch.cuda.device_count() > 7:
        pytest.skip("this machine has a cuda:7")
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")) as err:
        resolve_devices(devices)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("devices", ["cuda:0", [], [""], [3]])
def test_devices_must_be_a_list_of_names(devices):
    with pytest.raises(ValueError, match="devices must be null or a list of devices"):
        RunOptions(devices=devices)


def test_generate_refuses_unknown_devices_before_loading(tmp_path, capsys, monkeypatch):
    from geco_guide import generation
    from geco_guide.cli import generate as generate_cli

    monkeypatch.setattr(generation, "load_models", lambda *a, **k: pytest.fail("models were loaded"))
    assert generate_cli.main(["--preset", "tiny", "--prompt", "a cat", "--out", str(tmp_path / "o"),
                              "--devices", "cpu", "cuda:7"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: device 'cuda:7' is not available") and "run.devices" in err
    assert not (tmp_path / "o").exists()


def test_devices_do_not_change_the_video_name():
    from geco_guide.generation import default_name
    from geco_guide.config import load_config

    plain = load_config(preset="tiny")
    spread = load_config(preset="tiny", overrides=["run.devices=[cpu,cpu]"])
    assert spread.run.devices == ["cpu", "cpu"] and default_name(plain, "a") == default_name(spread, "a")


def test_one_plan_fits_the_smallest_of_the_devices(monkeypatch):
    from geco_guide.io import devices

    memory = {"cuda:0": 80.0, "cuda:1": 24.0, "cuda:2": None}
    monkeypatch.setattr(devices, "device_memory_gb", lambda device: memory[str(device)])
    assert devices.planning_memory_gb("cuda:0") == 80.0
    assert devices.planning_memory_gb("cuda:0", ["cuda:1", "cuda:2"]) == 24.0  # an unknown one adds nothing
    assert devices.planning_memory_gb("cuda:2") is None


def test_the_pipeline_plans_for_the_devices_it_deals_the_decode_over(monkeypatch):
    from geco_guide.sampler.pipelines import pipeline_cogvideox

    seen = []

    def planning(home, devices=None):
        seen.append((str(home), [str(d) for d in devices] if devices else None))
        return 1000.0

    monkeypatch.setattr(pipeline_cogvideox, "planning_memory_gb", planning)
    _pipe_frames(tiny_guidance_config(repeats="0x3,1x1", time_travel=[]),
                 tiny_run_options(memory_plan="auto", devices=["cpu", "cpu"]))
    assert seen == [("cpu", ["cpu", "cpu"])]


@pytest.mark.parametrize("denoiser_grad", [False, True], ids=["fast", "faithful"])
@pytest.mark.slow
def test_the_cfg_halves_on_two_devices_give_the_frames_of_one(denoiser_grad):
    """run.split_cfg: the unconditional and conditional halves as two calls, on two devices (two
    replicas) or one after the other on one: bitwise the same; the stock one-call batch to float
    rounding only."""
    config = replace(tiny_guidance_config(), denoiser_grad=denoiser_grad)
    run = tiny_run_options(split_cfg=True, memory_plan="chunked")  # the anchor decode as it is across devices
    one, report_one, _ = _pipe_frames(config, run)
    two, report_two, pipe = _pipe_frames(config, replace(run, devices=["cpu", "cpu"]))
    assert torch.equal(one, two) and [r["loss"] for r in report_one.log] == [r["loss"] for r in report_two.log]
    assert pipe._cfg_halves is None  # the replicas are the call's only


#: Units in the last place of the halves' largest output that two batch sizes of the tiny denoiser
#: may differ by: a GEMM blocks its sums by the batch's rows and by the CPU's vector width (AVX2 or
#: AVX-512 lanes, the BLAS's kernels), so each of its few layers may round otherwise; 64 is ample
#: for its two blocks (8 are seen on an AVX2 machine) and far below what a wrong split changes.
HALF_ULPS = 64


def test_the_cfg_halves_are_the_two_half_calls_and_the_one_call_to_float_rounding():
    """One denoiser output, split in two calls or not.

    Exact on any CPU: the split output is, bit for bit, the unconditional and the conditional
    calls made one by one here and guided (the same calls of one batch run the same kernels).

    To float rounding: the stock call of batch 2 against those of batch 1 (see :data:`HALF_ULPS`);
    guidance ``u + s (c - u)`` multiplies a rounding of the halves by up to ``1 + 2 s``. (A whole
    guided run then follows another path, since normalised updates of tiny random models amplify
    it.)"""
    from geco_guide.sampler.running.multi_device import CfgHalves

    pipe = tiny_pipeline(seed=0)
    z = torch.randn(1, 5, 4, 4, 6, generator=torch.Generator().manual_seed(0))
    embeds = torch.randn(2, 16, pipe.transformer.config.text_embed_dim, generator=torch.Generator().manual_seed(1))
    pipe._guidance_scale = 6.0
    pipe.scheduler.set_timesteps(4)
    kwargs = dict(t=pipe.scheduler.timesteps[1], image_rotary_emb=None, attention_kwargs=None)
    stock = pipe.model_output(z, prompt_embeds=embeds, do_classifier_free_guidance=True, **kwargs)
    uncond, text = (pipe.model_output(z, prompt_embeds=half, do_classifier_free_guidance=False, **kwargs)
                    for half in embeds.chunk(2))
    pipe._cfg_halves = CfgHalves(pipe.transformer, [torch.device("cpu"), torch.device("cpu")], torch.device("cpu"))
    split = pipe.model_output(z, prompt_embeds=embeds, do_classifier_free_guidance=True, **kwargs)

    assert torch.equal(split, uncond + pipe.guidance_scale * (text - uncond))
    scale = torch.maximum(uncond.abs().max(), text.abs().max())
    tolerance = (1 + 2 * pipe.guidance_scale) * HALF_ULPS * torch.finfo(torch.float32).eps * scale
    assert (split - stock).abs().max() <= tolerance
    swapped = text + pipe.guidance_scale * (uncond - text)  # what a split that mixed up the halves would give
    assert (swapped - stock).abs().max() > 100 * tolerance


def test_the_cfg_halves_split_every_batched_input_and_share_the_rest():
    from geco_guide.sampler.running.multi_device import CfgHalves

    seen = []

    class Denoiser(torch.nn.Module):
        def forward(self, hidden_states, encoder_hidden_states, timestep, image_rotary_emb=None, return_dict=False):
            seen.append((hidden_states.shape[0], encoder_hidden_states.shape[0], timestep.shape[0],
                         image_rotary_emb[0].shape[0]))
            return (hidden_states * encoder_hidden_states.mean() + timestep.view(-1, 1),)

    halves = CfgHalves(Denoiser(), [torch.device("cpu"), torch.device("cpu")], torch.device("cpu"))
    x, e, t = torch.randn(4, 3), torch.randn(4, 5), torch.arange(4.0)
    out = halves(hidden_states=x, encoder_hidden_states=e, timestep=t, image_rotary_emb=(torch.ones(7, 2),),
                 return_dict=False)
    assert seen == [(2, 2, 2, 7), (2, 2, 2, 7)] and out.shape == (4, 3)
    assert torch.equal(out[:2], x[:2] * e[:2].mean() + t[:2].view(-1, 1))
    assert torch.equal(out[2:], x[2:] * e[2:].mean() + t[2:].view(-1, 1))
    assert halves.replicas[0] is not halves.replicas[1]
