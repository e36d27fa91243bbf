"""The guided update's parts: the anchor decode strategies (the frames and gradients of the
slicing functions they stand for), the objective (decode, then score: the numbers of the decode
and loss called by hand), and the context's public seam, its observer (each update's record, the
objective made per memory plan, again after a fallback)."""

from __future__ import annotations

from dataclasses import replace
from functools import partial

import pytest
import torch

from geco_guide.loss.geco import GeCoLoss
from geco_guide.sampler.running.anchor_decode import (
    AcrossDevicesDecode,
    BatchedDecode,
    ChunkedDecode,
    anchor_decoder,
    plan_anchor_decode,
)
from geco_guide.sampler.running.context import GuidanceContext, GuidanceObserver
from geco_guide.sampler.running.memory_plan import PLANS, PlanChoice, explicit_plan, plan_named
from geco_guide.sampler.algorithm.objective import AnchorObjective
from geco_guide.sampler.running.run_options import RunOptions
from geco_guide.sampler.algorithm.slicing import anchor_latent_chunks, decode_anchor_frames, decode_anchor_frames_across, decode_chunk
from geco_guide.sampler.algorithm.step import loss_terms
from geco_guide.tiny import (
    TINY_CALL_KWARGS,
    TINY_NUM_FRAMES,
    tiny_estimators,
    tiny_guidance_config,
    tiny_pipeline,
    tiny_run_options,
)

CHUNKS = anchor_latent_chunks([4, 8, 12, 16], 17, 4, 3)
EXPLICIT_BATCHED = explicit_plan(RunOptions(vae_checkpointing=False))
ESTIMATORS = tiny_estimators(0)


@pytest.fixture(scope="module")
def pipe():
    return tiny_pipeline(0)


def vae_decoder(pipe):
    return anchor_decoder(tiny_guidance_config(), RunOptions(),
                          lambda vae: partial(decode_chunk, vae, scaling_factor=pipe.vae_scaling_factor_image),
                          None, pipe.vae)


def latents(pipe, seed=0):
    channels = pipe.transformer.config.in_channels
    return torch.randn(1, 5, channels, 4, 6, generator=torch.Generator().manual_seed(seed))


def frames_and_grad(decode, z):
    z = z.clone().requires_grad_(True)
    frames = decode(z)
    (grad,) = torch.autograd.grad(frames.square().sum(), z)
    return frames.detach(), grad


# ---- the anchor decode strategies ---------------------------------------------------------------


def test_each_plan_picks_its_strategy_once():
    decode = object()
    assert isinstance(plan_anchor_decode(EXPLICIT_BATCHED, decode, CHUNKS), BatchedDecode)
    for plan in PLANS:
        strategy = plan_anchor_decode(plan, decode, CHUNKS)
        assert isinstance(strategy, ChunkedDecode) and strategy.checkpointed is plan.chunk_checkpointing
    checkpointed_explicit = explicit_plan(RunOptions(vae_checkpointing=True))
    assert plan_anchor_decode(checkpointed_explicit, decode, CHUNKS) == ChunkedDecode(decode, CHUNKS, True)
    across = plan_anchor_decode(plan_named("chunked"), decode, CHUNKS, [torch.device("cpu")] * 2)
    assert isinstance(across, AcrossDevicesDecode) and across.checkpointed
    assert isinstance(plan_anchor_decode(plan_named("chunked"), decode, CHUNKS, []), ChunkedDecode)


@pytest.mark.slow
def test_the_strategies_give_the_frames_and_gradients_of_the_slicing_functions(pipe):
    decode, z = vae_decoder(pipe), latents(pipe)
    cases = [
        (BatchedDecode(decode, CHUNKS), partial(decode_anchor_frames, decode, chunks=CHUNKS)),
        (ChunkedDecode(decode, CHUNKS, False), partial(decode_anchor_frames, decode, chunks=CHUNKS, batch_chunks=False)),
        (ChunkedDecode(decode, CHUNKS, True), partial(decode_anchor_frames, decode, chunks=CHUNKS,
                                                      checkpoint_chunks=True)),
    ]
    for strategy, function in cases:
        (frames, grad), (expected, expected_grad) = frames_and_grad(strategy, z), frames_and_grad(function, z)
        assert torch.equal(frames, expected) and torch.equal(grad, expected_grad), strategy
    # one call per chunk: the checkpointed regions' numbers to the last bit
    assert all(torch.equal(a, b) for a, b in zip(frames_and_grad(cases[1][0], z), frames_and_grad(cases[2][0], z)))


@pytest.mark.slow
def test_across_devices_copies_the_replicas_once_and_gives_the_frames_of_the_function(pipe):
    decode, z, devices = vae_decoder(pipe), latents(pipe), [torch.device("cpu"), torch.device("cpu")]
    copied = []
    counting = type(decode)(decode.module, lambda module: copied.append(module) or decode.decode_with(module))
    strategy = AcrossDevicesDecode(counting, devices, CHUNKS, checkpointed=True)
    assert copied == [pipe.vae]  # the home decode only, until the first call
    frames, grad = frames_and_grad(strategy, z)
    frames_and_grad(strategy, z)
    assert len(copied) == 3 and copied[1] is pipe.vae and copied[2] is not pipe.vae  # the replicas, made once
    placed = [(device, decode.on(module)) for device, module in zip(devices, copied[1:])]
    expected, expected_grad = frames_and_grad(partial(decode_anchor_frames_across, placed, chunks=CHUNKS,
                                                      checkpoint_chunks=True), z)
    assert torch.equal(frames, expected) and torch.equal(grad, expected_grad)


# ---- the objective --------------------------------------------------------------------------------


@pytest.mark.slow
def test_the_objective_is_the_decode_then_the_loss_for_every_plan(pipe):
    """On the tiny pipeline's models: the context's objective for each plan gives the loss, terms
    and gradient of the plan's decode and the GeCo loss called by hand, bit for bit."""
    config = tiny_guidance_config()
    decode = vae_decoder(pipe)
    chunks = config.anchor_chunks(TINY_NUM_FRAMES, pipe.vae_scale_factor_temporal)
    loss_fn = GeCoLoss(ESTIMATORS, config.loss, check_values=False)
    x0 = latents(pipe, seed=1)

    def by_hand(plan, x0):
        frames = decode_anchor_frames(decode, x0[:, 0:], chunks, checkpoint_chunks=plan.chunk_checkpointing,
                                      batch_chunks=plan.batch_chunks)
        return loss_terms(loss_fn(frames))

    def loss_and_grad(objective):
        x = x0.clone().requires_grad_(True)
        loss, terms = objective(x)
        (grad,) = torch.autograd.grad(loss, x)
        return loss.detach(), {k: v.detach() for k, v in terms.items()}, grad

    for plan in (EXPLICIT_BATCHED, *PLANS):
        context = GuidanceContext(config, config.schedule(4), chunks, decode, lambda x: x[:, 0:], ESTIMATORS,
                                  memory_plan=PlanChoice(plan, "test"))
        assert isinstance(context.anchor_objective, AnchorObjective)
        assert context.update_objective is context.anchor_objective
        loss, terms, grad = loss_and_grad(context.objective)
        expected_loss, expected_terms, expected_grad = loss_and_grad(partial(by_hand, plan))
        assert torch.equal(loss, expected_loss) and torch.equal(grad, expected_grad), plan.name
        assert terms.keys() == expected_terms.keys() and all(torch.equal(terms[k], expected_terms[k]) for k in terms)


def test_with_decode_keeps_the_loss_and_the_latent_layout():
    objective = AnchorObjective(decode=str, latent_frames=abs, loss_fn=len)
    other = objective.with_decode(repr)
    assert other.decode is repr and other.latent_frames is abs and other.loss_fn is len and objective.decode is str


# ---- the seams ------------------------------------------------------------------------------------


def run(pipe, observer=None, **run_options):
    """A guided call of the tiny pipeline, watched by ``observer``, with ``run_options`` over the tiny ones."""
    return pipe("a marble bust", generator=torch.Generator().manual_seed(3), output_type="pt", estimators=ESTIMATORS,
                run_options=tiny_run_options(**run_options), observer=observer, **TINY_CALL_KWARGS)


@pytest.mark.slow
def test_the_observer_sees_each_update_as_the_log_records_it(pipe):
    seen, steps = [], []

    class Watching(GuidanceObserver):
        def on_update(self, record):
            seen.append(record)

        def step(self, step, t):
            steps.append((step, t))
            return super().step(step, t)

    out = run(pipe, Watching())
    plain = run(pipe)
    assert len(seen) == len(out.report.log) == 5 and [r.to_dict() for r in seen] == out.report.log
    assert all(r.grad_norm > 0 and not r.skipped for r in seen)
    assert steps == sorted({(r["step"], r["t"]) for r in out.report.log}) and len(steps) == 3  # the guided steps
    assert torch.equal(out.frames, plain.frames)  # watching changes nothing


@pytest.mark.slow
def test_the_objective_is_made_for_the_plan_and_again_after_a_fallback(pipe):
    """The observer's ``objective`` sees each plan's anchor objective: the first plan's, then after an
    injected out-of-memory error at the first update the fallback's, whose decode that plan picks."""
    made = []

    class Injected(GuidanceObserver):
        def objective(self, anchor_objective, plan):
            made.append((plan.name, anchor_objective.decode))
            if len(made) == 1:
                def failing(x0):
                    raise torch.cuda.OutOfMemoryError("CUDA out of memory (injected)")
                return failing
            return anchor_objective

    out = run(pipe, Injected(), memory_plan="auto", memory_budget_gb=1000.0)
    (first, first_decode), (second, second_decode) = made
    assert out.report.memory_plan["name"] == second != first and len(out.report.log) == 5
    assert isinstance(first_decode, ChunkedDecode) and not first_decode.checkpointed
    assert second_decode == plan_anchor_decode(plan_named(second), first_decode.decode, first_decode.chunks)
    reference = run(pipe, memory_plan=second)
    assert torch.equal(out.frames, reference.frames)


def test_the_context_keeps_its_public_face(pipe):
    config = replace(tiny_guidance_config(), repeats="0x3,1x1", time_travel=[])
    seen = []
    context = GuidanceContext(config, config.schedule(4), CHUNKS, vae_decoder(pipe), lambda x: x, ESTIMATORS,
                              on_record=seen.append)
    assert context.log == [] and context.memory_plan.plan == explicit_plan(RunOptions())
    context.on_record = None
    assert context.on_record is None and context.guidance_log.on_record is None
    flags = [p.requires_grad for p in pipe.vae.parameters()]
    with context.models([pipe.transformer], pipe.vae):
        assert not any(p.requires_grad for p in pipe.vae.parameters())
    assert [p.requires_grad for p in pipe.vae.parameters()] == flags
