"""GeCo guidance as a Modular Diffusers block: the Wan denoise loops with a guided step.

diffusers' Modular Wan pipelines (``WanModularPipeline``, ``Wan22ModularPipeline``) denoise in a
loop block whose every iteration runs three sub-blocks: ``before_denoiser`` (the latent model
input), ``denoiser`` (the denoiser under the pipeline's guider, e.g. CFG: ``noise_pred``) and
``after_denoiser`` (``scheduler.step``). :class:`GeCoWanDenoiseStep` and
:class:`GeCoWan22DenoiseStep` are those loops (``WanDenoiseStep``, ``Wan22DenoiseStep``, the same
sub-blocks) with GeCo guidance between the denoiser and the scheduler step. At a step with
``R_t > 0`` it runs the shared guidance (:func:`~.stock_call.guide_stock_step`, over
:meth:`GuidanceContext.guide <geco_guide.sampler.context.GuidanceContext.guide>`) on the latents
the scheduler is about to step, and hands the scheduler step the guided latents and the model
output there. Its prediction at new latents is the loop's own: the sub-blocks before the
scheduler step, run again on a copy of the loop's state (with gradients in faithful mode).

It takes, like the pipeline's other per-call inputs:

- ``geco_guidance``: a :class:`~.config.GuidanceConfig` (or a dict of its fields); ``None`` (the
  default) or ``enabled=False`` samples as the stock loop, bit for bit;
- ``geco_estimators``: the :class:`~geco_guide.estimators.bundle.Estimators` of the loss;
- ``geco_run_options``: how it runs (:class:`~.run_options.RunOptions` or a dict).

and leaves in the pipeline state what the call decided: ``geco_report``, the
:class:`~.context.GuidanceReport` the other front doors return (the log, the memory plan, the
devices, the decoder, the masks). The layout, de-normalisation and decode of the latents are
:class:`~.adapters.WanAdapter`'s, as under ``attach_geco_guidance(WanPipeline)``.

Shared as diffusers shares custom blocks: :func:`save_geco_block` writes ``modular_config.json``
and the code file its ``auto_map`` names, and
``ModularPipelineBlocks.from_pretrained(folder_or_repo, trust_remote_code=True)`` loads it.
"""

from __future__ import annotations

import inspect
import tempfile
from pathlib import Path
from typing import Any

import torch
from diffusers.modular_pipelines import BlockState, ModularPipelineBlocks
from diffusers.modular_pipelines.modular_pipeline_utils import InputParam, OutputParam
from diffusers.modular_pipelines.wan.denoise import Wan22DenoiseStep, WanDenoiseStep
from torch import Tensor

from ..estimators.bundle import Estimators
from ..io.files import write_texts_atomic
from ..types import check_estimator_bundle
from .adapters import PipelineAdapter, WanAdapter
from .config import GuidanceConfig
from .context import GuidanceContext, GuidanceReport
from .run_options import RunOptions, resolve_call_options
from .slicing import check_latents
from .step import LatentsWatch
from .stock_call import guide_stock_step, stock_call

__all__ = ["GeCoWan22DenoiseStep", "GeCoWanDenoiseStep", "save_geco_block"]

#: The sub-block of a Wan denoise loop that steps the scheduler: guidance runs just before it.
SCHEDULER_STEP = "after_denoiser"
#: The denoisers a Wan pipeline may hold: Wan 2.1 the first, Wan 2.2 both (its two experts).
EXPERTS = ("transformer", "transformer_2")


class _GuidedCall:
    """What one guided call of the loop keeps between its steps."""

    def __init__(self, context: GuidanceContext, watch: LatentsWatch):
        self.context, self.watch = context, watch


class _GeCoLoop:
    """GeCo guidance in a diffusers Wan denoise loop (a ``WanDenoiseLoopWrapper``): mixed in
    before the stock loop class, whose sub-blocks and loop it keeps."""

    adapter: PipelineAdapter = WanAdapter()
    #: the Wan version whose loop this is, and the denoisers (experts) its sub-blocks call
    version: str
    experts: tuple[str, ...]

    @property
    def description(self) -> str:
        return (super().description + "\nWith GeCo guidance (geco_guide) before the scheduler step: the latents "
                "move towards a geometrically consistent video at the steps of geco_guidance's R_t schedule.")

    @property
    def loop_inputs(self) -> list[InputParam]:
        return [
            *super().loop_inputs,
            InputParam("geco_guidance", type_hint=GuidanceConfig | dict | None,
                       description="GeCo guidance (a geco_guide GuidanceConfig or a dict of its fields); "
                                   "None: no guidance"),
            InputParam("geco_estimators", type_hint=Estimators,
                       description="the GeCo loss' models (geco_guide Estimators: geometry, flow, and the segmenter "
                                   "and tiny decoder where the guidance uses them)"),
            InputParam("geco_run_options", type_hint=RunOptions | dict | None,
                       description="how GeCo guidance runs (a geco_guide RunOptions or a dict of its fields)"),
            InputParam("generator", description="the call's generator: the source of the time-travel noise"),
        ]

    @property
    def loop_intermediate_outputs(self) -> list[OutputParam]:
        return [
            *super().loop_intermediate_outputs,
            OutputParam("geco_report", type_hint=GuidanceReport,
                        description="what the call decided: the GeCo log (one dict per update), the memory plan, the "
                                    "devices, the decoder, the masks (geco_guide GuidanceReport)"),
        ]

    def loop_step(self, components: Any, block_state: BlockState, i: int, t: Tensor) -> tuple[Any, BlockState]:
        if i == 0:
            self._check_pipeline(components)
            block_state.geco_call = self._start(components, block_state)
        call = block_state.geco_call
        for name, block in self.sub_blocks.items():
            if name == SCHEDULER_STEP and call is not None:
                self._guide(components, block_state, call, i, t)
            components, block_state = block(components, block_state, i=i, t=t)
        if call is not None and i == call.watch.num_steps - 1:
            block_state.geco_report = call.context.report(components.scheduler)
        return components, block_state

    def _check_pipeline(self, components: Any) -> None:
        """ValueError (one line, before the first step) for a pipeline that lacks a denoiser this
        loop calls: Wan 2.2's loop in a Wan 2.1 pipeline, which has no ``transformer_2`` (diffusers'
        loop would fail on ``None.forward`` after the text encoding and the latents)."""
        present = tuple(name for name in EXPERTS if getattr(components, name, None) is not None)
        missing = [name for name in self.experts if name not in present]
        if not missing:
            return
        other = next((loop for loop in (GeCoWanDenoiseStep, GeCoWan22DenoiseStep) if loop.experts == present), None)
        fix = f"insert {other.__name__} (Wan {other.version}'s loop) instead" if other else "load its weights"
        raise ValueError(f"{type(self).__name__} is Wan {self.version}'s denoise loop, calling "
                         f"{' and '.join(self.experts)}; the pipeline it is in has no {' and no '.join(missing)}: {fix}")

    def _start(self, components: Any, block_state: BlockState) -> _GuidedCall | None:
        """The call's guidance, checked before its first step (``None`` unguided), and its outputs."""
        block_state.geco_report = GuidanceReport(scheduler=type(components.scheduler).__name__)
        if block_state.geco_guidance is None:
            return None
        if SCHEDULER_STEP not in self.sub_blocks:
            raise ValueError(f"GeCo guidance runs before the {SCHEDULER_STEP!r} sub-block of the denoise loop, and "
                             f"{type(self).__name__} has none (sub-blocks: {', '.join(self.sub_blocks)})")
        config, run = resolve_call_options(None, block_state.geco_guidance, None, block_state.geco_run_options)
        if not config.enabled:
            return None
        estimators = check_estimator_bundle(block_state.geco_estimators, "the GeCo block", argument="geco_estimators")
        latents = block_state.latents
        check_latents(latents, None, "this call")
        geometry = self.adapter.call_geometry(components, {}, latents)
        call = stock_call(components, self.adapter, geometry, config, run, estimators)
        num_steps = len(block_state.timesteps)
        context = call.context(num_steps, block_state.generator)
        return _GuidedCall(context, LatentsWatch(num_steps))

    def _guide(self, components: Any, block_state: BlockState, call: _GuidedCall, i: int, t: Tensor) -> None:
        """Step ``i``'s updates: ``block_state.latents`` and ``noise_pred`` (both ``[B, C, F, h, w]``)
        become the guided latents and the model output there."""
        sample = block_state.latents
        # NaN latents are refused at a guided step, whose log waits for the device anyway
        call.watch.see(sample, i)
        if call.context.schedule.repeats_at(i) == 0:
            return
        call.watch.check()
        model_output = block_state.noise_pred
        predict = self._predictor(components, block_state, i, t, sample.detach().float(), model_output)
        block_state.latents, block_state.noise_pred = guide_stock_step(
            call.context, components, self.adapter, self.adapter.denoisers(components), i, t, sample, model_output,
            predict)

    def _predictor(self, components: Any, block_state: BlockState, i: int, t: Tensor, start: Tensor,
                   model_output: Tensor):
        """``(z, differentiate) -> model output at z`` (both ``[B, C, F, h, w]``; ``start``: the
        latents of ``model_output``, the loop's own prediction): the loop's sub-blocks before the scheduler
        step (the latent model input, the denoiser under the pipeline's guider) run again on a copy
        of the loop's state whose latents are ``z``. diffusers runs each block under
        ``torch.no_grad``; faithful mode needs the gradient through them, so the blocks' undecorated
        ``__call__`` runs here."""
        names = list(self.sub_blocks)
        blocks = [self.sub_blocks[name] for name in names[: names.index(SCHEDULER_STEP)]]

        def predict(z: Tensor, differentiate: bool) -> Tensor:
            if not differentiate and torch.equal(z, start):
                return model_output.float()  # the loop's own prediction at this very sample
            state = BlockState(**block_state.as_dict())
            state.latents = z
            with torch.set_grad_enabled(differentiate and torch.is_grad_enabled()):
                for block in blocks:
                    _, state = inspect.unwrap(type(block).__call__)(block, components, state, i=i, t=t)
            if differentiate and torch.is_grad_enabled() and not state.noise_pred.requires_grad:
                raise RuntimeError(f"GeCo guidance got no gradient through the loop's sub-blocks "
                                   f"({', '.join(type(b).__name__ for b in blocks)}): one of them runs without "
                                   "autograd; use fast mode (guidance.denoiser_grad=false)")
            return state.noise_pred

        return predict


class GeCoWanDenoiseStep(_GeCoLoop, WanDenoiseStep):
    """Wan 2.1's text-to-video denoise loop (``WanDenoiseStep``) with GeCo guidance before each
    scheduler step: the ``denoise`` loop of ``WanModularPipeline`` (see the module docstring)."""

    version, experts = "2.1", ("transformer",)


class GeCoWan22DenoiseStep(_GeCoLoop, Wan22DenoiseStep):
    """Wan 2.2's text-to-video denoise loop (``Wan22DenoiseStep``: two experts, two guiders)
    with GeCo guidance before each scheduler step: the ``denoise`` loop of
    ``Wan22ModularPipeline`` (see the module docstring)."""

    version, experts = "2.2", EXPERTS


_BLOCK_CODE = '''"""GeCo guidance in diffusers' Modular Wan denoise loops. The blocks' code is the geco_guide
package, which must be installed; load with ModularPipelineBlocks.from_pretrained(..., trust_remote_code=True)."""

from geco_guide.sampler.modular import GeCoWan22DenoiseStep, GeCoWanDenoiseStep  # noqa: F401
'''


def save_geco_block(block: ModularPipelineBlocks, folder: str | Path) -> Path:
    """Save a GeCo block as diffusers shares custom blocks, to a folder (or a Hub repository's
    files): ``modular_config.json`` (its ``auto_map`` names the block's class in ``modular.py``)
    and ``modular.py``, which imports the block from the installed geco_guide. Both files are
    written at once or not at all.

    Load it with ``ModularPipelineBlocks.from_pretrained(folder_or_repo, trust_remote_code=True)``.

    Returns:
        the ``modular_config.json`` written.

    Raises:
        TypeError: ``block`` is not a GeCo block of this module.
        WriteError: the folder cannot be written (one line naming it).
    """
    if not isinstance(block, _GeCoLoop):
        raise TypeError(f"save_geco_block saves GeCoWanDenoiseStep or GeCoWan22DenoiseStep, got {type(block).__name__}")
    code_file = f"{type(block).__module__.rsplit('.', 1)[-1]}.py"  # what diffusers' auto_map will name
    with tempfile.TemporaryDirectory() as staging:
        block.save_pretrained(staging)
        config = (Path(staging) / block.config_name).read_text()
    folder = Path(folder)
    written = write_texts_atomic({folder / block.config_name: config, folder / code_file: _BLOCK_CODE})
    return written[0]
