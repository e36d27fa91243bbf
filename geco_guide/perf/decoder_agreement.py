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

import contextlib
from collections.abc import Iterator

from ..config import GeCoConfig, config_to_dict
from ..estimators import TINY_RANDOM
from ..generation import Models, check_generation, load_models, sample
from ..sampler.algorithm.objective import AnchorObjective
from ..sampler.algorithm.step import GuidanceRecord, loss_terms
from ..sampler.pipelines.adapters import adapter_for
from ..sampler.running.anchor_decode import anchor_decoder, plan_anchor_decode
from ..sampler.running.context import GuidanceObserver, decoder_note
from ..sampler.running.memory_plan import MemoryPlan
from .measure import environment_info

__all__ = ["DecoderAgreement", "agreement_record", "agreement_rows", "agreement_summary", "agreement_table",
           "check_agreement_config", "decoder_agreement", "gradient_cosine", "psnr_db"]

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


class DecoderAgreement(GuidanceObserver):
    """Both decoders at every update of one guided call, watched through the guidance's observer
    seam: the updates' objective (the guiding decoder's, with the other decoder's loss and
    gradient beside it on a detached copy) and one row per update in ``rows``, taken when the
    update is recorded (after its backward: the guiding gradient is there).

    Args:
        pipe: the guided pipeline (its VAE, its family's decode).
        models: its estimators, the tiny decoder among them.
        cfg: the call's config (which decoder guides; the anchors and their chunks).
        rows: the list the rows are appended to.
    """

    def __init__(self, pipe: Any, models: Models, cfg: GeCoConfig, rows: list[dict[str, Any]]):
        self.guided_by, self.rows = cfg.guidance.decoder, rows
        self.observer = "vae" if self.guided_by == "tiny" else "tiny"
        self.pending: dict[str, Any] = {}
        self.at: tuple[int, int] = (0, 0)  # (step, t) of the updates under way
        observed = replace(cfg.guidance, decoder=self.observer)
        # the observer decodes in the stock layout: channels-last is for the VAE that guides
        run = replace(cfg.run, decode_layout="default")
        decode = partial(adapter_for(pipe).decode, pipe)
        self._decode = anchor_decoder(observed, run, lambda vae: decode, models.estimators.tiny_decoder, pipe.vae)
        self._chunks = observed.anchor_chunks(cfg.sampling.num_frames, models.video.model.temporal_compression)

    def objective(self, anchor_objective: AnchorObjective, plan: MemoryPlan) -> Callable[[Tensor], Any]:
        """``x0 -> (loss, terms)``: the guiding decoder's anchor decode and loss (without dynamic
        masks), the update unchanged; the other decoder's chunks decoded as the plan decodes the
        guide's, on one device, and measured beside."""
        guide, observer_decode = anchor_objective, plan_anchor_decode(plan, self._decode, self._chunks)

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

    @contextlib.contextmanager
    def step(self, step: int, t: int) -> Iterator[None]:
        self.at = (step, t)
        yield

    def on_update(self, record: GuidanceRecord) -> None:
        """The update's row."""
        p, guide = self.pending, self.guided_by
        step, t = self.at
        self.rows.append({
            "update": len(self.rows), "step": step, "t": t, "guided_by": guide,
            f"loss_{guide}": float(p["guide_loss"]), f"loss_{self.observer}": float(p["observed_loss"]),
            "cosine": gradient_cosine(p.get("guide_grad"), p["observed_grad"]),
            "psnr_db": psnr_db(p["tiny_frames"], p["vae_frames"]),
        })


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


def check_agreement_config(cfg: GeCoConfig, prompt: str) -> GeCoConfig:
    """ValueError (one line) for a config that cannot measure the agreement, and what
    ``generate`` refuses (the tiny decoder's weights among them: where to download them and the
    key to set); before any model loads. Returns the config with the tiny decoder loaded beside
    the guiding decoder."""
    if not cfg.guidance.enabled:
        raise ValueError("decoder-agreement compares the decoders inside guidance: guidance.enabled must be true")
    return check_generation(replace(cfg, guidance=replace(cfg.guidance, decoder="tiny")), prompt)


def agreement_rows(models: Models, cfg: GeCoConfig, prompt: str) -> list[dict[str, Any]]:
    """The per-update rows of one guided call of ``models`` (whose estimators hold the tiny
    decoder, e.g. the models of an A/B run that guides with it) with ``cfg``'s sampling and
    guidance, seeded with ``cfg.seed``: the generation path's own call, watched by a
    :class:`DecoderAgreement`."""
    rows: list[dict[str, Any]] = []
    sample(models, cfg, prompt, observer=DecoderAgreement(models.pipe, models, cfg, rows), progress=False)
    return rows


def agreement_record(models: Models, cfg: GeCoConfig, prompt: str) -> dict[str, Any]:
    """:func:`agreement_rows` of one guided call and their :func:`agreement_summary`, as an A/B run
    records them: ``{"summary": ..., "updates": rows}``."""
    rows = agreement_rows(models, cfg, prompt)
    return {"summary": agreement_summary(rows), "updates": rows}


def decoder_agreement(cfg: GeCoConfig, prompt: str, argv: Sequence[str] = ()) -> dict[str, Any]:
    """One guided generation call of ``cfg`` (``model.id=tiny-random``: the tiny random models)
    with both decoders at every update; the report: per-update rows (:func:`agreement_rows`) and
    :func:`agreement_summary`.

    Raises:
        ValueError / WeightsNotFoundError: one line, before any model loads, for guidance that is
            off or a tiny decoder that is not there (:func:`check_agreement_config`).
    """
    checked = check_agreement_config(cfg, prompt)
    models = load_models(checked)  # with the tiny decoder
    rows = agreement_rows(models, replace(checked, guidance=cfg.guidance), prompt)
    tiny_random = TINY_RANDOM in (cfg.model.source, cfg.estimators.tiny_decoder)
    return {
        "subcommand": "decoder-agreement",
        "argv": list(argv),
        "prompt": prompt,
        "guided_by": cfg.guidance.decoder,
        "tiny_decoder": decoder_note("tiny", models.estimators),
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
