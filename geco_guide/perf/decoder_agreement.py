"""How faithful the tiny decoder's guidance is: both decoders at every update of one guided call.

``guidance.decoder=tiny`` replaces the VAE in the loss' anchor decode by the TAEHV tiny decoder,
an approximation. :func:`decoder_agreement` measures what it changes on a real guided generation:
at every guidance update the anchor frames are decoded by both decoders from the same clean
latents, and each update's row holds

* ``cosine``: the cosine between the two gradients of the GeCo loss with respect to those latents
  (through the VAE and through the tiny decoder; the guiding one is the gradient the update
  used, the other is computed beside it on a detached copy),
* ``loss_vae`` / ``loss_tiny``: the two losses,
* ``psnr_db``: the PSNR of the tiny decoder's anchor frames against the VAE's (``[0, 1]`` frames;
  the MSE floored at 1e-10, so identical frames read 100 dB).

The trajectory is the guiding decoder's (``guidance.decoder``, the VAE by default): the other
decoder only observes. A gradient that is zero or not finite gives a NaN cosine (counted in
the summary, never read as agreement).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable, Sequence
from dataclasses import replace
from functools import partial
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from ..config import GeCoConfig, config_to_dict
from ..estimators import TINY_RANDOM
from ..sampler import loading
from ..sampler.anchor_decode import anchor_decoder, plan_anchor_decode
from ..sampler.context import GuidanceContext
from ..sampler.memory_plan import MemoryPlan
from ..sampler.objective import AnchorObjective
from ..sampler.run_options import RunOptions
from ..sampler.slicing import decode_chunk
from ..sampler.step import loss_terms, read_scalars
from .measure import environment_info

__all__ = ["DecoderAgreement", "agreement_rows", "agreement_summary", "agreement_table", "check_agreement_config",
           "decoder_agreement", "gradient_cosine", "psnr_db"]

#: The PSNR's MSE floor: identical frames read 10 * log10(1 / 1e-10) = 100 dB.
MSE_FLOOR = 1e-10


def gradient_cosine(a: Tensor | None, b: Tensor | None) -> float:
    """Cosine between two gradients (float64); NaN when either is missing, zero or not finite."""
    if a is None or b is None:
        return math.nan
    a, b = a.detach().flatten().double(), b.detach().flatten().double()
    norms = a.norm() * b.norm()
    if not torch.isfinite(norms) or norms == 0:
        return math.nan
    return float((a @ b / norms).clamp(-1, 1))


def psnr_db(frames: Tensor, reference: Tensor) -> float:
    """PSNR (dB) of ``frames`` against ``reference``, both ``[..., 3, H, W]`` in ``[0, 1]``."""
    mse = F.mse_loss(frames.detach().float(), reference.detach().float())
    return float(10 * torch.log10(1 / mse.clamp_min(MSE_FLOOR)))


class DecoderAgreement:
    """Both decoders at every update of one guided call: the updates' objective (the guiding
    decoder's, with the other decoder's loss and gradient beside it on a detached copy) and one
    row per update in ``rows``, taken where the guidance log reads the update's numbers (after
    its backward: the guiding gradient is there).

    Args:
        guided_by: the guiding decoder (``guidance.decoder``: ``"vae"`` or ``"tiny"``).
        rows: the list the rows are appended to.
    """

    def __init__(self, guided_by: str, rows: list[dict[str, Any]]):
        self.guided_by, self.rows = guided_by, rows
        self.observer = "vae" if guided_by == "tiny" else "tiny"
        self.pending: dict[str, Any] = {}
        self.at: tuple[int, int] = (0, 0)  # (step, t) of the updates under way

    def objective(self, guide: AnchorObjective,
                  observer_decode: Callable[[Tensor], Tensor]) -> Callable[[Tensor], tuple[Tensor, dict[str, Tensor]]]:
        """``x0 -> (loss, terms)``: ``guide``'s anchor decode and loss (without dynamic masks), the
        update unchanged; ``observer_decode`` (the other decoder's anchor decode) measured beside."""

        def objective(x0: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
            latents = guide.latent_frames(x0)
            # the observer: its own graph on a detached copy, differentiated here
            observed_in = latents.detach().requires_grad_(True)
            observed_frames = observer_decode(observed_in)
            observed_loss, _ = loss_terms(guide.loss_fn(observed_frames))
            (observed_grad,) = torch.autograd.grad(observed_loss, observed_in, allow_unused=True)
            # the guide: the update's own graph; its gradient at the latents is caught on the way back
            pending = {"observed_grad": observed_grad, "observed_loss": observed_loss.detach()}
            if latents.requires_grad:
                latents.register_hook(lambda grad: pending.__setitem__("guide_grad", grad.detach()))
            frames = guide.decode(latents)
            loss, terms = loss_terms(guide.loss_fn(frames))
            tiny, vae = (frames, observed_frames) if self.observer == "vae" else (observed_frames, frames)
            pending.update(guide_loss=loss.detach(), tiny_frames=tiny.detach(), vae_frames=vae.detach())
            self.pending = pending
            return loss, terms

        return objective

    def read_scalars(self, values: dict[str, Tensor], device: torch.device) -> dict[str, float]:
        """The update's numbers (:func:`~geco_guide.sampler.step.read_scalars`), and its row."""
        scalars = read_scalars(values, device)
        p, guide = self.pending, self.guided_by
        step, t = self.at
        self.rows.append({
            "update": len(self.rows), "step": step, "t": t, "guided_by": guide,
            f"loss_{guide}": float(p["guide_loss"]), f"loss_{self.observer}": float(p["observed_loss"]),
            "cosine": gradient_cosine(p.get("guide_grad"), p["observed_grad"]),
            "psnr_db": psnr_db(p["tiny_frames"], p["vae_frames"]),
        })
        return scalars


def agreement_context_class(pipe: Any, num_frames: int, rows: list[dict[str, Any]]) -> type[GuidanceContext]:
    """A :class:`GuidanceContext` for ``pipe`` (which holds both its VAE and a ``guidance_decoder``)
    whose updates are measured by a :class:`DecoderAgreement` appending to ``rows``, through the
    context's ``objective_for`` and ``read_scalars``; the update itself is unchanged."""
    def vae_decode_with(vae: Any) -> Callable[[Tensor], Tensor]:
        return partial(decode_chunk, vae, scaling_factor=pipe.vae_scaling_factor_image)

    class AgreementContext(GuidanceContext):
        def __init__(self, config: Any, *args: Any, **kwargs: Any) -> None:
            measure = DecoderAgreement(config.decoder, rows)
            observer_config = replace(config, decoder=measure.observer)
            # the observer decodes in the stock layout: channels-last is for the VAE that guides
            observer_run = replace(kwargs.get("run") or RunOptions(), decode_layout="default")
            observer_decode = anchor_decoder(observer_config, observer_run, vae_decode_with, pipe.guidance_decoder,
                                             pipe.vae)
            observer_chunks = observer_config.anchor_chunks(num_frames, pipe.vae_scale_factor_temporal)

            def objective_for(guide: AnchorObjective, plan: MemoryPlan) -> Callable[[Tensor], Any]:
                # the observer's chunks decoded as the plan decodes the guide's, on one device
                return measure.objective(guide, plan_anchor_decode(plan, observer_decode, observer_chunks))

            super().__init__(config, *args, read_scalars=measure.read_scalars, objective_for=objective_for, **kwargs)
            self.measure = measure

        def guide(self, z: Tensor, predict: Callable[[Tensor, bool], Tensor], levels: Any, step: int,
                  t: int) -> tuple[Tensor, Tensor]:
            self.measure.at = (step, int(t))
            return super().guide(z, predict, levels, step, t)

    return AgreementContext


def agreement_summary(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Median / min cosine and mean PSNR over the updates with finite values; how many had none."""
    cosines = [r["cosine"] for r in rows if math.isfinite(r["cosine"])]
    psnrs = [r["psnr_db"] for r in rows if math.isfinite(r["psnr_db"])]
    return {
        "updates": len(rows),
        "non_finite_cosines": len(rows) - len(cosines),
        "cosine_median": statistics.median(cosines) if cosines else math.nan,
        "cosine_min": min(cosines) if cosines else math.nan,
        "psnr_mean_db": statistics.fmean(psnrs) if psnrs else math.nan,
    }


def check_agreement_config(cfg: GeCoConfig) -> None:
    """ValueError (one line) for a config that cannot measure the agreement; before any model loads."""
    if not cfg.guidance.enabled:
        raise ValueError("decoder-agreement compares the decoders inside guidance: guidance.enabled must be true")
    loading.check_tiny_decoder_source(cfg)
    loading.check_weights_before_loading(cfg)


def agreement_rows(pipe: Any, cfg: GeCoConfig, prompt: str) -> list[dict[str, Any]]:
    """The per-update rows of one guided call of ``pipe`` (a :class:`GeCoCogVideoXPipeline` with
    its ``guidance_decoder`` attached, e.g. the pipeline of an A/B run that guides with it) with
    ``cfg``'s sampling and guidance, seeded with ``cfg.seed``. The pipeline's own guidance
    context class is restored afterwards."""
    rows: list[dict[str, Any]] = []
    own = pipe.__dict__.get("guidance_context_class")
    pipe.guidance_context_class = agreement_context_class(pipe, cfg.sampling.num_frames, rows)
    s = cfg.sampling
    try:
        pipe(prompt=prompt, negative_prompt=s.negative_prompt, height=s.height, width=s.width,
             num_frames=s.num_frames, num_inference_steps=s.num_inference_steps, guidance_scale=s.guidance_scale,
             use_dynamic_cfg=s.use_dynamic_cfg, generator=torch.Generator(device="cpu").manual_seed(cfg.seed),
             output_type="latent", max_sequence_length=s.max_sequence_length, guidance=cfg.guidance,
             run_options=cfg.run)
    finally:
        if own is None:
            del pipe.guidance_context_class  # the class's again
        else:
            pipe.guidance_context_class = own
    return rows


def decoder_agreement(cfg: GeCoConfig, prompt: str, argv: Sequence[str] = ()) -> dict[str, Any]:
    """One guided generation call of ``cfg`` (``model.id=tiny-random``: the tiny random models)
    with both decoders at every update; the report: per-update rows (:func:`agreement_rows`) and
    :func:`agreement_summary`.

    Raises:
        ValueError / WeightsNotFoundError: one line, before any model loads, for guidance that is
            off or a tiny decoder that is not there (:func:`check_agreement_config`).
    """
    check_agreement_config(cfg)
    from ..tiny import video_components  # the tiny models pull in transformers: only when a run starts

    pipe = loading.build_pipeline(cfg, components=video_components(cfg), tiny_decoder=True)
    pipe.set_progress_bar_config(disable=True)
    rows = agreement_rows(pipe, cfg, prompt)
    tiny_random = TINY_RANDOM in (cfg.model.id, cfg.estimators.tiny_decoder)
    return {
        "subcommand": "decoder-agreement",
        "argv": list(argv),
        "prompt": prompt,
        "guided_by": cfg.guidance.decoder,
        "tiny_decoder": loading.tiny_decoder_note(pipe.guidance_decoder, cfg.estimators.init_seed),
        "summary": agreement_summary(rows),
        "rows": rows,
        "note": ("tiny random models: these numbers exercise the measurement only and say nothing about the "
                 "published decoder's fidelity" if tiny_random else
                 "gradients with respect to the clean latent estimate that both decoders decode"),
        "config": config_to_dict(cfg),
        "environment": environment_info(torch.get_num_threads()),
    }


def agreement_table(report: dict[str, Any]) -> str:
    """Markdown: one row per update, then the summary line."""
    guide = report["guided_by"]
    observer = "vae" if guide == "tiny" else "tiny"
    lines = [f"| update | step | t | loss {guide} (guides) | loss {observer} | gradient cosine | PSNR (dB) |",
             "|---|---|---|---|---|---|---|"]
    for r in report["rows"]:
        lines.append(f"| {r['update']} | {r['step']} | {r['t']} | {r[f'loss_{guide}']:.4g} | "
                     f"{r[f'loss_{observer}']:.4g} | {r['cosine']:.3f} | {r['psnr_db']:.1f} |")
    s = report["summary"]
    summary = (f"{s['updates']} updates: gradient cosine median {s['cosine_median']:.3f}, min {s['cosine_min']:.3f} "
               f"({s['non_finite_cosines']} not finite); anchor-frame PSNR mean {s['psnr_mean_db']:.1f} dB")
    lines += ["", summary, report["note"]]
    return "\n".join(lines)
