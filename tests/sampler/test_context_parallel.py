"""``run.context_parallel``: the guided call split over two processes with diffusers' context
parallelism gives one process's video and gradients.

Two processes on the ``gloo`` backend (CPU), spawned here, run the same tiny call as one process:
the paper's pipeline (CogVideoX: our plan and attention processor), the hooks on a stock
``WanPipeline`` (diffusers' own ``_cp_plan``; Wan 2.1, and Wan 2.2 with both experts) and on a stock ``HunyuanVideoPipeline`` (our plan
and the text mask cut to each process's tokens; the denoiser check pads the two prompts to 6
and 10 of 16 tokens, so the mask matters); a CogVideoX denoiser call whose 45 video and 15
text tokens do not split evenly, padded to equal shards; and the hooks on stock ``LTXPipeline``,
``LTX2Pipeline`` (its audio stream whole on every process) and ``HunyuanVideo15Pipeline`` (our
plans; their text whole on every process; the denoiser check pads the prompts). Compared with
one process:

- the denoiser's output and the gradient of a fixed linear read-out of it with respect to the
  latents (a CFG batch of two): the gradient faithful guidance takes through the denoiser;
- a faithful guided call: the norms of its updates' gradients (through the GeCo loss, the anchor
  decode, dealt over the processes, and the denoiser) and its video;
- the anchor decode dealt over the processes alone, on a toy causal decode: each process decodes
  its two spans of four (forward, and again in the backward where the chunks are checkpointed),
  or none, and every process gets one process's frames and gradient with respect to the latents
  (the gradient is counted once, not once per process).

The split changes the order of sums only: the attention of the split sequence (CogVideoX's joint
text-video sequence comes out of the all-to-all in another order), matrix products over fewer
rows per process, the decode's gradient summed over the processes, and a process's chunks
decoded in a smaller batch. So the gradients and the denoiser's output agree to float32 rounding,
checked at 1e-5 relative to their largest entry (measured: at most 1.6e-7). The updates' gradient
norms are checked at 1e-4 relative. The first's measured at most 9.3e-7 on one CPU, 2.5e-5 for
HunyuanVideo on another, whose loss amplifies a rounding-sized change of the denoiser's output
about 50 times; the later updates start from latents the first moved (measured: at most 2.9e-5,
CogVideoX's; with the
denoiser split and the decode not dealt, the latents after the first update differ from one
process's by 1.1e-6 relative, and the second update's gradient by 9.5e-5 of its largest entry). The toy decode's frames and gradient are one
process's to the last bit (checked at 1e-6 absolute and 1e-5 relative). The video is checked at
5e-4 absolute (measured: 9.4e-5 for CogVideoX, 1.4e-5 for Wan, 1.3e-5 for HunyuanVideo): a
guided update is normalised, so its direction carries the rounding into the latents, and a
guided call amplifies it; the call here guides the first step only (two updates; one for
HunyuanVideo, see ``UPDATES``), since the tiny
models' full schedule turns a 1e-6 change of the initial latents into 0.18 of a frame in one
process alone.

The collectives are diffusers' own (its functional all-to-all and all-gather) on gloo; the one
line of diffusers replaced on a CPU is the choice of the rank's accelerator
(``_resolve_parallel_config``, see ``geco_guide.sampler.running.context_parallel``). Not covered on a CPU:
ring attention (the native backend returns no log-sum-exp, which ring attention merges with),
NCCL and the GPU attention kernels (flash, cuDNN); ``scripts/check_context_parallel.py`` checks a
GPU run against one GPU.
"""

from __future__ import annotations

import os
import socket

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

import geco_guide.tiny as T
from geco_guide.estimators import tiny_estimators
from geco_guide.sampler.pipelines.hooks import attach_geco_guidance
from geco_guide.sampler.running.run_options import RunOptions

PROCESSES = 2
FAMILIES = ("cogvideox", "cogvideox-padded", "wan", "wan2.2", "hunyuan", "ltx", "ltx2", "hunyuan1.5")
#: the families whose guided call is compared too; the padded CogVideoX call's denoiser only: at
#: 48x48 the tiny models' guided call is far more sensitive to rounding (in one process, a 1e-7
#: relative change of its initial latents moves its frames by 2.7e-3, against 4e-5 at 32x48)
GUIDED = ("cogvideox", "wan", "wan2.2", "hunyuan", "ltx", "ltx2", "hunyuan1.5")
#: the guided call's updates: two at the first step, none after (see the module's docstring); Wan
#: 2.2 one at the first step and one at the last, so that both experts are differentiated;
#: HunyuanVideo one: its tiny call's second update amplifies rounding past the frames' tolerance
#: (in one process, a 1e-7 relative change of the first denoiser output moves the second update's
#: gradient norm by 2.7e-4 and the frames by 2.2e-3; with one update, by at most 7.2e-5)
UPDATES = {"wan2.2": "1x1,0x2,1x1", "hunyuan": "1x1,0x3"}
GRADIENT_TOLERANCE = 1e-5  # relative to the largest entry (of the gradient; of the denoiser's output)
#: relative, the updates' gradient norms: the loss amplifies the denoiser's rounding (in one
#: process, a 1e-7 to 3e-7 relative change of HunyuanVideo's first denoiser output moves the
#: first norm by up to 1.7e-5; split, on an AMD EPYC, 2.5e-5), and the later updates start from
#: latents the first moved, by a direction that carries the rounding (see the module's docstring)
NORM_TOLERANCE = 1e-4
FRAME_TOLERANCE = 5e-4  # absolute, frames in [0, 1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


#: a CogVideoX call whose tokens do not split evenly over two processes: 48x48 pixels (5 latent
#: frames of 3x3 tokens: 45) and 15 text tokens, padded to 46 and 16
PADDED = dict(height=48, width=48, max_sequence_length=15)


def _pipeline(family: str):
    if family.startswith("cogvideox"):
        return T.tiny_pipeline(0)
    if family == "hunyuan":
        return T.tiny_hunyuan_pipeline(0)
    if family in LTX_FAMILIES:
        return LTX_FAMILIES[family](0)
    if family == "hunyuan1.5":
        return T.tiny_hunyuan15_pipeline(0)
    return T.tiny_wan_pipeline(0, scheduler="euler", version="2.2" if family == "wan2.2" else "2.1")


def _denoiser_inputs(pipe, family: str, g: torch.Generator) -> tuple[torch.Tensor, dict]:
    """Random latents (requiring gradients) and the denoiser's inputs for a CFG batch of 2 of them."""
    if family in LTX_FAMILIES:
        return _ltx_inputs(pipe, family, g)
    if family == "hunyuan1.5":
        return _hunyuan15_inputs(pipe, g)
    padded = family == "cogvideox-padded"
    shape = (1, 5, 4, *((6, 6) if padded else (4, 6))) if family.startswith("cogvideox") else (1, 4, 5, 4, 6)
    z = torch.randn(shape, generator=g).requires_grad_(True)
    width = 16 if family != "hunyuan" else pipe.transformer.config.text_embed_dim
    text = torch.randn(2, 15 if padded else 16, width, generator=g)
    inputs = dict(hidden_states=torch.cat([z, z]), encoder_hidden_states=text, timestep=torch.tensor([500, 500]),
                  return_dict=False)
    if family.startswith("cogvideox"):
        size = (48, 48) if padded else (T.TINY_HEIGHT, T.TINY_WIDTH)
        inputs["image_rotary_emb"] = pipe._prepare_rotary_positional_embeddings(*size, 5, "cpu")
    if family == "hunyuan":  # the text padding the mask hides: 6 and 10 tokens of 16
        mask = torch.arange(16) < torch.tensor([[6], [10]])
        inputs.update(encoder_attention_mask=mask.long(), guidance=torch.tensor([6000.0, 6000.0]),
                      pooled_projections=torch.randn(2, pipe.transformer.config.pooled_projection_dim, generator=g))
    return z, inputs


#: LTX-Video and LTX-2: the denoiser check on packed tokens of 3 latent frames of 4x6, with text
#: masks of 6 and 10 of 16 tokens (so that the mask matters); LTX-2's audio stream (5 tokens) stays
#: whole on every process
LTX_FAMILIES = {"ltx": T.tiny_ltx_pipeline, "ltx2": T.tiny_ltx2_pipeline}


def _ltx_inputs(pipe, family: str, g: torch.Generator) -> tuple[torch.Tensor, dict]:
    denoiser = pipe.transformer
    z = torch.randn(1, 3 * 4 * 6, denoiser.config.in_channels, generator=g).requires_grad_(True)
    mask = (torch.arange(16) < torch.tensor([[6], [10]])).long()
    inputs = dict(hidden_states=torch.cat([z, z]), encoder_hidden_states=torch.randn(2, 16, 16, generator=g),
                  encoder_attention_mask=mask, timestep=torch.tensor([500.0, 500.0]), num_frames=3, height=4, width=6,
                  return_dict=False)
    if family == "ltx":
        inputs["rope_interpolation_scale"] = (8 / 25, 8, 8)
    else:
        audio = torch.randn(2, 5, denoiser.audio_proj_in.in_features, generator=g)
        inputs.update(audio_hidden_states=audio, audio_encoder_hidden_states=torch.randn(2, 16, 16, generator=g),
                      audio_encoder_attention_mask=mask, sigma=torch.tensor([0.5, 0.5]), audio_num_frames=5)
    return z, inputs


def _hunyuan15_inputs(pipe, g: torch.Generator) -> tuple[torch.Tensor, dict]:
    """HunyuanVideo 1.5's denoiser: 3 latent frames of 4x6 (text-to-video: the condition channels
    zero), its two texts padded (6 and 10 of 16 tokens; 3 and 5 of 8), the image tokens zero (and
    masked, as the pipeline's text-to-video call)."""
    config = pipe.transformer.config
    z = torch.randn(1, config.out_channels, 3, 4, 6, generator=g).requires_grad_(True)
    condition = torch.zeros(1, config.in_channels - config.out_channels, 3, 4, 6)
    inputs = dict(hidden_states=torch.cat([z, condition], dim=1).expand(2, -1, -1, -1, -1),
                  timestep=torch.tensor([500.0, 500.0]), return_dict=False,
                  encoder_hidden_states=torch.randn(2, 16, config.text_embed_dim, generator=g),
                  encoder_attention_mask=(torch.arange(16) < torch.tensor([[6], [10]])).long(),
                  encoder_hidden_states_2=torch.randn(2, 8, config.text_embed_2_dim, generator=g),
                  encoder_attention_mask_2=(torch.arange(8) < torch.tensor([[3], [5]])).long(),
                  image_embeds=torch.zeros(2, pipe.vision_num_semantic_tokens, config.image_embed_dim))
    return z, inputs


def _denoiser_gradient(pipe, family: str) -> tuple[torch.Tensor, torch.Tensor]:
    """The denoiser's output at random latents (a CFG batch of 2) and the gradient of a fixed
    linear read-out of it with respect to the latents."""
    g = torch.Generator().manual_seed(1)
    z, inputs = _denoiser_inputs(pipe, family, g)
    out = pipe.transformer(**inputs)[0]
    weights = torch.randn(out.shape, generator=g)
    (grad,) = torch.autograd.grad((out * weights).sum(), z)
    return out.detach(), grad


def _guided_call(pipe, family: str, run: RunOptions) -> tuple[torch.Tensor, torch.Tensor]:
    """A faithful guided call: its frames and its updates' gradient norms."""
    estimators = tiny_estimators(0)
    config = T.tiny_guidance_config(denoiser_grad=True, repeats=UPDATES.get(family, "2x1,0x3"), time_travel=None)
    kwargs = T.tiny_call_kwargs(pipe, prompt="a marble bust", output_type="pt",
                                generator=torch.Generator().manual_seed(0), **(PADDED if "padded" in family else {}))
    if family.startswith("cogvideox"):
        out = pipe(**kwargs, guidance=config, estimators=estimators, run_options=run)
        log = out.report.log
    else:
        with attach_geco_guidance(pipe, config, estimators, run_options=run) as handle:
            out = pipe(**kwargs)
            log = handle.last.log
    norms = torch.tensor([record["grad_norm"] for record in log])
    return out.frames.float(), norms


def _run(family: str, run: RunOptions) -> dict[str, torch.Tensor]:
    pipe = _pipeline(family)
    if run.context_parallel:  # the split as the guided call makes it, before the gradient check
        from geco_guide.sampler.pipelines.adapters import adapter_for
        from geco_guide.sampler.running.context_parallel import start_context_parallel

        start_context_parallel(pipe, adapter_for(pipe), run, differentiates=True)
    out, grad = _denoiser_gradient(pipe, family)
    if family not in GUIDED:
        return {"out": out, "grad": grad}
    frames, norms = _guided_call(pipe, family, run)
    return {"out": out, "grad": grad, "frames": frames, "norms": norms}


def _uneven_message() -> str:
    """What a split Wan denoiser says to a sequence of 9 tokens (after one of 18, which splits)."""
    from geco_guide.sampler.pipelines.adapters import adapter_for
    from geco_guide.sampler.running.context_parallel import start_context_parallel

    pipe = T.tiny_wan_pipeline(0)
    start_context_parallel(pipe, adapter_for(pipe), T.tiny_run_options(context_parallel=PROCESSES), differentiates=True)

    def denoise(latents: torch.Tensor) -> None:
        pipe.transformer(hidden_states=latents, encoder_hidden_states=torch.randn(1, 16, 16),
                         timestep=torch.tensor([500]), return_dict=False)

    denoise(torch.randn(1, 4, 3, 4, 6))  # 3 latent frames of 2x3 tokens: 18 tokens, 9 each
    try:
        denoise(torch.randn(1, 4, 3, 2, 6))  # 9 tokens: no equal shards
    except ValueError as err:
        return str(err)
    return "no error"


#: the anchors of the decode check, on a 17-frame video (5 latents): four spans, one of two latents
#: and three of three, so that each of two processes decodes two, of one length or of two
DECODE_ANCHORS = (4, 8, 12, 16)
#: two anchors of one span: the second process decodes nothing, yet takes part in the gather and
#: in the backward's all-reduce
ONE_SPAN_ANCHORS = (5, 6)


def _toy_decode(latents: torch.Tensor) -> torch.Tensor:
    """A causal decode ``[N, F, C, h, w] -> [N, 1 + 4(F-1), 3, h, w]`` that mixes each latent with
    the one before (so a frame depends on two latents) through a square, in ``[0, 1]``."""
    mixed = latents + 0.5 * torch.cat([latents[:, :1], latents[:, :-1]], dim=1)
    frames = torch.sigmoid(mixed[:, :, :3] ** 2)  # [N, F, 3, h, w]
    return torch.cat([frames[:, :1], frames[:, 1:].repeat_interleave(4, dim=1)], dim=1)


def _dealt_decode(processes: int, checkpointed: bool, anchors=DECODE_ANCHORS) -> dict[str, torch.Tensor]:
    """The anchor frames of random latents, decoded as ``processes`` processes deal them (one:
    the plan's own decode), the gradient of a loss of them with respect to the latents (every
    process computes the same loss, as guidance does), and how many spans this process decoded."""
    from geco_guide.sampler.running.anchor_decode import plan_anchor_decode
    from geco_guide.sampler.running.memory_plan import MemoryPlan
    from geco_guide.sampler.algorithm.slicing import anchor_latent_chunks

    calls = []

    def decode(latents: torch.Tensor) -> torch.Tensor:
        calls.append(latents.shape[0] // 2)  # the spans in this call (a batch of 2 videos each)
        return _toy_decode(latents)

    g = torch.Generator().manual_seed(3)
    latents = torch.randn(2, 5, 4, 3, 5, generator=g).requires_grad_(True)
    weights = torch.randn(2, len(anchors), 3, 3, 5, generator=g)
    plan = MemoryPlan("explicit", chunk_checkpointing=checkpointed, vae_block_checkpointing=False,
                      denoiser_checkpointing=False, estimator_checkpointing=None, batch_chunks=not checkpointed)
    chunks = anchor_latent_chunks(anchors, 17)
    frames = plan_anchor_decode(plan, decode, chunks, processes=processes)(latents)
    (grad,) = torch.autograd.grad((frames * weights).square().sum(), latents)
    return {"frames": frames.detach(), "grad": grad, "decodes": torch.tensor(sum(calls))}


def _worker(rank: int, port: int, folder: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), OMP_NUM_THREADS="1")
    torch.set_num_threads(1)
    dist.init_process_group("gloo", rank=rank, world_size=PROCESSES)
    try:
        run = T.tiny_run_options(context_parallel=PROCESSES)
        results = {family: _run(family, run) for family in FAMILIES}
        results["decode"] = {checkpointed: _dealt_decode(PROCESSES, checkpointed) for checkpointed in (False, True)}
        results["one span"] = _dealt_decode(PROCESSES, True, ONE_SPAN_ANCHORS)
        results["uneven"] = _uneven_message()
        torch.save(results, os.path.join(folder, f"rank{rank}.pt"))
    finally:
        dist.destroy_process_group()


@pytest.fixture(scope="module")
def split_runs(tmp_path_factory) -> list[dict]:
    """Every process's results of the split runs (one spawn for both families: the imports are
    most of a process's time)."""
    folder = tmp_path_factory.mktemp("context_parallel")
    mp.spawn(_worker, args=(_free_port(), str(folder)), nprocs=PROCESSES)
    return [torch.load(folder / f"rank{rank}.pt") for rank in range(PROCESSES)]


@pytest.mark.slow
@pytest.mark.parametrize("family", FAMILIES)
def test_two_processes_give_one_process_video_and_gradient(family, split_runs):
    torch.set_num_threads(1)
    one = _run(family, T.tiny_run_options())
    for rank, runs in enumerate(split_runs):
        split = runs[family]
        for key in ("out", "grad"):
            error = (split[key] - one[key]).abs().max() / one[key].abs().max()
            assert error <= GRADIENT_TOLERANCE, (rank, key, float(error))
        if family in GUIDED:
            assert (split["frames"] - one["frames"]).abs().max() <= FRAME_TOLERANCE, rank
            torch.testing.assert_close(split["norms"], one["norms"], rtol=NORM_TOLERANCE, atol=0)


@pytest.mark.slow
@pytest.mark.parametrize("checkpointed", [False, True])
def test_the_anchor_decode_dealt_over_processes_gives_one_process_frames_and_gradient(checkpointed, split_runs):
    """Each process decodes its spans only (two of four; checkpointed, again in the backward),
    and gathers the others' frames; the gradient with respect to the latents, its share summed
    over the processes, is one process's: not ``PROCESSES`` times it."""
    one = _dealt_decode(1, checkpointed)
    passes = 2 if checkpointed else 1  # a checkpointed span is decoded again in the backward
    assert one["decodes"] == 4 * passes
    for rank, runs in enumerate(split_runs):
        split = runs["decode"][checkpointed]
        assert split["decodes"] == 2 * passes, rank
        torch.testing.assert_close(split["frames"], one["frames"], rtol=0, atol=1e-6)
        torch.testing.assert_close(split["grad"], one["grad"], rtol=GRADIENT_TOLERANCE, atol=1e-7)


@pytest.mark.slow
def test_a_process_without_a_span_to_decode_gets_the_frames(split_runs):
    one = _dealt_decode(1, True, ONE_SPAN_ANCHORS)
    for rank, runs in enumerate(split_runs):
        split = runs["one span"]
        assert split["decodes"] == (2 if rank == 0 else 0), rank
        torch.testing.assert_close(split["frames"], one["frames"], rtol=0, atol=1e-6)
        torch.testing.assert_close(split["grad"], one["grad"], rtol=GRADIENT_TOLERANCE, atol=1e-7)


# --------------------------------------------------------------------------------------------
# what cannot run split is refused in one line, before anything loads


def _one_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err and err.startswith("error: "), err
    return err


@pytest.mark.parametrize("value", [1, 0, 2.5, True, "2"])
def test_a_number_of_processes_below_two_or_not_whole_is_refused(value):
    from geco_guide.types import OptionError

    with pytest.raises(OptionError, match="context_parallel must be a whole number of processes >= 2"):
        RunOptions(context_parallel=value)


@pytest.mark.parametrize("argv, world, expected", [
    (["--context-parallel", "2"], None,
     "run.context_parallel=2 runs the call over 2 processes, but this launch has 1: start it with torchrun "
     "--nproc-per-node 2"),
    (["run.context_parallel=1"], None, "'run.context_parallel': context_parallel must be a whole number of processes >= 2"),
    (["--context-parallel", "2", "--devices", "cpu", "cpu"], "2", "run.devices deals the anchor decode over this "
     "process's GPUs, and under run.context_parallel each process owns one GPU"),
    (["--context-parallel", "2", "--best-of", "2"], "2", "--best-of writes each candidate from one process"),
])
def test_what_cannot_run_split_is_one_line_before_loading(argv, world, expected, monkeypatch, capsys, no_loading):
    from geco_guide.cli.generate import main

    if world is not None:
        monkeypatch.setenv("WORLD_SIZE", world)
    else:
        monkeypatch.delenv("WORLD_SIZE", raising=False)
    assert main(["--preset", "tiny", "--prompt", "a marble bust", *argv]) == 2
    assert expected in _one_error(capsys)


@pytest.mark.parametrize("backend, differentiates, expected", [
    ("sage", True, "the attention backend 'sage' has no backward under context parallelism"),
    ("_native_math", False, "the attention backend '_native_math' has no context parallelism in diffusers"),
])
def test_an_attention_backend_that_cannot_split_or_differentiate_is_refused(backend, differentiates, expected,
                                                                            monkeypatch):
    from diffusers.models.attention_dispatch import AttentionBackendName, _AttentionBackendRegistry

    from geco_guide.sampler.pipelines.adapters import WanAdapter
    from geco_guide.sampler.running.context_parallel import check_context_parallel_before_loading

    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setattr(_AttentionBackendRegistry, "_active_backend", AttentionBackendName(backend))
    with pytest.raises(ValueError, match=expected):
        check_context_parallel_before_loading(RunOptions(context_parallel=2), WanAdapter(),
                                              differentiates=differentiates)
    # a search or fast guidance runs no backward through the denoiser: sage splits it then
    monkeypatch.setattr(_AttentionBackendRegistry, "_active_backend", AttentionBackendName.SAGE)
    check_context_parallel_before_loading(RunOptions(context_parallel=2), WanAdapter(), differentiates=False)


def test_a_family_that_declares_it_cannot_be_split_is_refused(monkeypatch):
    """Every family shipped has a plan; a registered one may say why it cannot be split."""
    from geco_guide.sampler.pipelines.adapters import WanAdapter
    from geco_guide.sampler.running.context_parallel import check_context_parallel_before_loading

    class Unsplittable(WanAdapter):
        name = "Unsplittable"
        context_parallel_refusal = "its attention takes a mask of the whole sequence"

    monkeypatch.setenv("WORLD_SIZE", "2")
    with pytest.raises(ValueError, match="run.context_parallel cannot split Unsplittable: its attention takes a mask"):
        check_context_parallel_before_loading(RunOptions(context_parallel=2), Unsplittable(), differentiates=True)


def test_one_gpu_named_for_every_process_is_refused(monkeypatch):
    from geco_guide.sampler.pipelines.adapters import WanAdapter
    from geco_guide.sampler.running.context_parallel import check_context_parallel_before_loading

    monkeypatch.setenv("WORLD_SIZE", "2")
    with pytest.raises(ValueError, match="model.device=cuda:1 would put every process on one GPU"):
        check_context_parallel_before_loading(RunOptions(context_parallel=2), WanAdapter(), model_device="cuda:1",
                                              differentiates=True)


@pytest.mark.slow
def test_a_sequence_that_does_not_split_evenly_is_one_line(split_runs):
    for runs in split_runs:
        message = runs["uneven"]
        assert message.startswith("run.context_parallel=2: the WanTransformer3DModel's token sequence of this call does "
                                  "not divide into equal shards"), message
        assert "\n" not in message
