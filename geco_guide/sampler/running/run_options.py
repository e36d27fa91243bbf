"""How one machine runs guidance (:class:`RunOptions`), apart from what guidance computes
(:class:`~geco_guide.sampler.algorithm.config.GuidanceConfig`).

A :class:`GuidanceConfig` is the algorithm: it is saved with a pipeline and names the videos it
makes. A :class:`RunOptions` is this machine's way of running it: what the guidance backward
recomputes to fit the memory, the layout and compilation of the anchor decode, the devices it
runs on. It is the config's ``run`` section, is never written by ``save_pretrained`` (a folder
saved on an 80 GB card would otherwise impose that card's budget on a 24 GB one), and stays out
of the video key, except for the options that change frames to float rounding
(:data:`FRAME_ROUNDING_KEYS`).

These options sat in ``guidance`` before; their old keys (``guidance.memory_plan=...`` in a config
file, a ``key=value`` override or a dict) are refused in one line naming the new key
(:attr:`GuidanceConfig.RENAMED <geco_guide.sampler.algorithm.config.GuidanceConfig.RENAMED>`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, Optional

from ...types import OptionError, is_integer, is_number, merge_dataclass, non_finite_fields
from ..algorithm.config import GuidanceConfig, resolve_guidance_config
from .fast_decode import DECODE_LAYOUTS
from .plan_names import PLAN_NAMES

__all__ = ["FRAME_ROUNDING_KEYS", "RUN_KEYS", "RunOptions", "check_call_options", "check_run_for_guidance",
           "resolve_call_options", "resolve_run_options"]


@dataclass
class RunOptions:
    """How guidance runs on this machine (defaults: the memory plan fitted to the device, the
    stock decode, one device). No option here changes what guidance computes; the memory plans
    and devices give the same frames bit for bit, ``decode_layout`` and ``compile`` the same
    frames to float rounding (hence :data:`FRAME_ROUNDING_KEYS`).

    Attributes:
        memory_plan: what the guidance backward recomputes (:mod:`.memory_plan`): ``auto``
            (default: the plan of least predicted time that fits the memory budget),
            ``explicit`` (the three checkpointing flags below as given, the estimators as loaded),
            or a named plan, ``fastest``, ``partial``, ``chunked``, ``checkpointed`` or ``leanest``.
        memory_budget_gb: the memory (GiB) ``auto`` plans for; ``None``: 94 % of the device's
            (a CUDA device's total, a CPU's physical RAM).
        gradient_checkpointing: ``explicit`` plan only: checkpoint the denoiser's blocks while
            differentiating it.
        vae_checkpointing: ``explicit`` plan only: decode the anchor chunks one at a time in
            checkpointed regions (the backward then holds one chunk's decode instead of all of
            them, for one extra forward decode per chunk); ``False`` batches the chunks in one
            decode and keeps everything.
        vae_block_checkpointing: ``explicit`` plan only: the VAE's own block checkpointing while
            guiding (where the VAE supports it); ``None`` follows ``vae_checkpointing``.
        decode_layout: memory layout of the VAE's guidance decode (:mod:`.fast_decode`):
            ``default`` (the stock decode) or ``channels_last`` (the CogVideoX VAE decoder in
            ``torch.channels_last_3d``: the same frames and gradients to float rounding, not
            bitwise, hence off by default; with ``guidance.decoder=vae`` only). The final video
            is decoded as stock.
        compile: ``torch.compile`` the guidance decoder (the VAE decoder, or the tiny decoder),
            forward and backward, once per decoder and input shape; if compiling fails, one
            warning and an eager decode. See docs/guidance.md (Faster anchor decode).
        devices: where the anchor decode runs: ``None`` (default) on the pipeline's device; a
            list of devices (``["cuda:0", "cuda:1"]``, ``["auto"]`` for every visible GPU) deals
            the anchor decode's calls round-robin over them (a chunk per call under the chunked
            plans; under a plan that batches the chunks, a batch of chunks of one length per
            call), each with its own replica of the guidance decoder, decoded forward and
            backward at once; the frames meet on the pipeline's device for the loss. Every call
            is one device's call under the same plan, so the frames are one device's bit for bit
            on devices of one kind (to float rounding across kinds of device). See
            docs/performance.md (Several GPUs).
        split_cfg: run the denoiser's classifier-free-guidance batch of a guided call as two calls,
            unconditional and conditional, on the first two ``devices`` (each with its own replica
            of the denoiser: both halves of faithful mode's backward at once), or one after the
            other on the pipeline's device without ``devices``. The halves are calls of half the
            batch, so the frames equal the one-call frames to float rounding only (hence off by
            default, and in :data:`FRAME_ROUNDING_KEYS`); the same on one device or two.
            ``GeCoCogVideoXPipeline`` only (the hooks leave a pipeline's own denoiser calls as they are).
        particle_batch: the most particles of a search (``search.particles``) one denoiser call,
            guided update, anchor scoring or final decode holds; ``None`` (default): the memory
            plan's choice (:func:`~.search.choose_particle_batch`: all of them where they fit, one
            for a model the estimates do not know). Sub-batches of one size give the frames of one
            batch to float rounding (kernels of another batch size may sum in another order; hence
            in :data:`FRAME_ROUNDING_KEYS`), of one particle each particle's frames as its own
            call, bit for bit. With ``devices`` the sub-batches of the sampling's denoiser calls are
            dealt over them, each device with a replica of the denoiser.
        context_parallel: ``None`` (default: one process) or the number of processes ``N >= 2``
            the call runs over, launched with ``torchrun --nproc-per-node N`` (or ``accelerate
            launch``): every process runs the whole call, and each denoiser's token sequence is
            split over them with diffusers' context parallelism (Ulysses attention), forward and
            backward, and the anchor decode's chunks dealt over them (:mod:`.context_parallel`,
            docs/context_parallel.md). The attention of the
            split sequence sums in another order, so the frames equal one process's to float
            rounding (hence in :data:`FRAME_ROUNDING_KEYS`).
    """

    memory_plan: str = "auto"
    memory_budget_gb: Optional[float] = None
    gradient_checkpointing: bool = True
    vae_checkpointing: bool = True
    vae_block_checkpointing: Optional[bool] = None
    decode_layout: str = "default"
    compile: bool = False
    devices: Optional[list[str]] = None
    split_cfg: bool = False
    particle_batch: Optional[int] = None
    context_parallel: Optional[int] = None

    def __post_init__(self) -> None:
        for key in ("gradient_checkpointing", "vae_checkpointing", "compile", "split_cfg"):
            if not isinstance(getattr(self, key), bool):
                raise OptionError(key, f"must be true or false, got {getattr(self, key)!r}")
        if self.vae_block_checkpointing is not None and not isinstance(self.vae_block_checkpointing, bool):
            raise OptionError("vae_block_checkpointing", f"must be true, false or null, got {self.vae_block_checkpointing!r}")
        if self.memory_budget_gb is not None and not is_number(self.memory_budget_gb):
            raise OptionError("memory_budget_gb", f"must be a number of GiB (or null: the device's memory), "
                                                  f"got {self.memory_budget_gb!r}")
        for key, value in non_finite_fields(self):  # the first one
            raise OptionError(key, f"must be a finite number, got {value}")
        if self.memory_budget_gb is not None and not self.memory_budget_gb > 0:
            raise OptionError("memory_budget_gb", f"must be a positive number of GiB (or null: the device's memory), "
                                                  f"got {self.memory_budget_gb}")
        if self.memory_plan not in PLAN_NAMES:
            raise OptionError("memory_plan", f"must be one of {', '.join(PLAN_NAMES)}, got {self.memory_plan!r}")
        if self.particle_batch is not None and (not is_integer(self.particle_batch) or self.particle_batch < 1):
            raise OptionError("particle_batch", f"must be a whole number of particles >= 1 (or null: the memory plan's "
                                                f"choice), got {self.particle_batch!r}")
        if self.context_parallel is not None and (not is_integer(self.context_parallel) or self.context_parallel < 2):
            raise OptionError("context_parallel", f"must be a whole number of processes >= 2 (or null: one process), "
                                                  f"got {self.context_parallel!r}")
        if self.decode_layout not in DECODE_LAYOUTS:
            raise OptionError("decode_layout", f"must be one of {', '.join(DECODE_LAYOUTS)}, got {self.decode_layout!r}")
        if self.devices is not None and (not isinstance(self.devices, (list, tuple)) or not self.devices
                                         or not all(isinstance(d, str) and d.strip() for d in self.devices)):
            raise OptionError("devices", f"must be null or a list of devices (e.g. [cuda:0, cuda:1], or [auto]), "
                                         f"got {self.devices!r}")


#: The options of :class:`RunOptions`.
RUN_KEYS = tuple(f.name for f in fields(RunOptions))
#: The run options that can change the frames to float rounding, and so stay in the video key
#: (the memory plans and devices give the same frames bit for bit on one kind of device).
FRAME_ROUNDING_KEYS = ("decode_layout", "compile", "split_cfg", "particle_batch", "context_parallel")


def resolve_run_options(base: RunOptions | None, override: RunOptions | Mapping[str, Any] | None) -> RunOptions:
    """The run options of one call: ``override`` (options, or a dict of changes) over ``base``
    (default :class:`RunOptions`); ValueError naming an unknown key."""
    base = base if base is not None else RunOptions()
    if override is None:
        return base
    if isinstance(override, RunOptions):
        return override
    if hasattr(override, "keys"):  # dict or omegaconf DictConfig
        return merge_dataclass(base, override, "run")
    raise ValueError(f"run options must be a RunOptions or a dict, got {type(override).__name__}")


def check_run_for_guidance(run: RunOptions, decoder: str) -> None:
    """OptionError (one line naming the key) for run options the guidance of ``decoder``
    (``guidance.decoder``) cannot use."""
    if run.decode_layout != "default" and decoder != "vae":
        raise OptionError("decode_layout", f"{run.decode_layout} lays out the VAE's decode, but guidance.decoder="
                                           f"{decoder!r}: use run.decode_layout=default with the tiny decoder")


def check_call_options(config: GuidanceConfig, run: RunOptions) -> None:
    """ValueError (one line naming the ``run`` key) for run options ``config`` cannot use
    (:func:`check_run_for_guidance`)."""
    try:
        check_run_for_guidance(run, config.decoder)
    except OptionError as err:
        raise ValueError(f"run.{err}") from None


def resolve_call_options(
    base: GuidanceConfig | None,
    override: GuidanceConfig | Mapping[str, Any] | bool | None,
    run_base: RunOptions | None = None,
    run_override: RunOptions | Mapping[str, Any] | None = None,
) -> tuple[GuidanceConfig, RunOptions]:
    """What one call's guidance computes and how it runs:
    :func:`~.config.resolve_guidance_config` and :func:`resolve_run_options`.

    Raises:
        ValueError: (one line naming the key) an unknown key or an earlier spelling of one, or run
            options this guidance cannot use (``run.decode_layout=channels_last`` with the tiny
            decoder).
    """
    config = resolve_guidance_config(base, override)
    run = resolve_run_options(run_base, run_override)
    check_call_options(config, run)
    return config, run
