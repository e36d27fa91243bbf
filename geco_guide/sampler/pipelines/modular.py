"""GeCo guidance as Modular Diffusers sub-blocks of the Wan denoise loops.

diffusers' Modular Wan pipelines (``WanModularPipeline``, ``Wan22ModularPipeline``) denoise in a
loop block whose every iteration runs its sub-blocks in order: ``before_denoiser`` (the latent
model input), ``denoiser`` (the denoiser under the pipeline's guider, e.g. CFG: ``noise_pred``)
and ``after_denoiser`` (``scheduler.step``). :class:`GeCoWanDenoiseStep` and
:class:`GeCoWan22DenoiseStep` are those loops (``WanDenoiseStep``, ``Wan22DenoiseStep``, their
loop and sub-blocks unchanged) with two sub-blocks inserted:

- ``geco_start`` (:class:`GeCoStartStep`), first: at the first step, the call's checks (the
  pipeline holds the loop's denoisers; the guidance, estimators and run options are sound) and
  its guidance set up, before any denoiser runs;
- ``geco_guidance`` (:class:`GeCoGuidanceStep`), before ``after_denoiser``: at a step with
  ``R_t > 0`` the shared guidance (:func:`~.stock_call.guide_stock_step`, over
  :meth:`GuidanceContext.guide <geco_guide.sampler.running.context.GuidanceContext.guide>`) moves the
  latents the scheduler is about to step, and the scheduler step gets the guided latents and the
  model output there.

Its prediction at new latents is the loop's own: the sub-blocks between the two run again on a
copy of the loop's state. diffusers runs each of them under ``torch.no_grad``; where faithful mode
differentiates the prediction, a hook in each denoiser's registry (:class:`DifferentiableDenoiser`)
runs its forward with gradients, on the latents being differentiated, and keeps its outputs; the
guider's combination of them is rebuilt with weights fitted to its output (as the hooks rebuild
a stock pipeline's), so the prediction keeps the guider's value and gains its gradient.

It takes, like the pipeline's other per-call inputs:

- ``geco_guidance``: a :class:`~.config.GuidanceConfig` (or a dict of its fields); ``None`` (the
  default) or ``enabled=False`` samples as the stock loop, bit for bit;
- ``geco_estimators``: the :class:`~geco_guide.estimators.bundle.Estimators` of the loss;
- ``geco_run_options``: how it runs (:class:`~.run_options.RunOptions` or a dict);
- ``geco_observer``: a :class:`~.context.GuidanceObserver` watching the updates, as the
  pipeline's ``observer=`` and the hooks' ``handle.observer``;

and leaves in the pipeline state what the call decided: ``geco_report``, the
:class:`~.context.GuidanceReport` the other front doors return (the log, the memory plan, the
devices, the decoder, the masks). The layout, de-normalisation and decode of the latents are
:class:`~.adapters.WanAdapter`'s, as under ``attach_geco_guidance(WanPipeline)``.

Shared as diffusers shares custom blocks: :func:`save_geco_block` writes ``modular_config.json``
and the code file its ``auto_map`` names, and
``ModularPipelineBlocks.from_pretrained(folder_or_repo, trust_remote_code=True)`` loads it.
"""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch
from diffusers.hooks import ModelHook
from diffusers.modular_pipelines import BlockState, ModularPipelineBlocks
from diffusers.modular_pipelines.modular_pipeline_utils import InputParam, OutputParam
from diffusers.modular_pipelines.wan.denoise import Wan22DenoiseStep, WanDenoiseStep
from torch import Tensor, nn

from ...estimators.bundle import Estimators
from ...io.files import write_texts_atomic
from ...types import check_estimator_bundle
from ..algorithm.config import GuidanceConfig
from ..algorithm.slicing import check_latents
from ..algorithm.step import LatentsWatch
from ..running.context import GuidanceContext, GuidanceObserver, GuidanceReport
from ..running.module_hooks import hooked
from ..running.run_options import RunOptions, resolve_call_options
from ..search.particles import hidden_states_of, output_tensor
from .adapters import PipelineAdapter, WanAdapter, fit_combination
from .stock_call import guide_stock_step, stock_call

__all__ = ["DifferentiableDenoiser", "GeCoGuidanceStep", "GeCoStartStep", "GeCoWan22DenoiseStep",
           "GeCoWanDenoiseStep", "save_geco_block"]

#: The sub-block of a Wan denoise loop that steps the scheduler: guidance runs just before it.
SCHEDULER_STEP = "after_denoiser"
#: The names of GeCo's sub-blocks in a denoise loop.
START, GUIDANCE = "geco_start", "geco_guidance"
#: The denoisers a Wan pipeline may hold: Wan 2.1 the first, Wan 2.2 both (its two experts).
EXPERTS = ("transformer", "transformer_2")
#: The name of :class:`DifferentiableDenoiser` in a denoiser's hook registry.
DIFFERENTIABLE_HOOK = "geco_differentiable_denoiser"
#: The Wan layout and decode every GeCo sub-block guides with.
ADAPTER: PipelineAdapter = WanAdapter()


class _GuidedCall:
    """What one guided call of the loop keeps between its steps."""

    def __init__(self, context: GuidanceContext, watch: LatentsWatch):
        self.context, self.watch = context, watch


class GeCoStartStep(ModularPipelineBlocks):
    """The first sub-block of a GeCo denoise loop: at step 0, before any denoiser runs, the
    pipeline checked for the loop's denoisers, the call's guidance checked and set up
    (``None`` unguided), ``geco_report`` started.

    Args:
        loop: the name of the loop it starts (for its errors), ``version`` its Wan version and
            ``experts`` the denoisers its sub-blocks call.
    """

    model_name = "wan"

    def __init__(self, loop: str = "GeCoWanDenoiseStep", version: str = "2.1", experts: tuple[str, ...] = EXPERTS[:1]):
        super().__init__()
        self.loop, self.version, self.experts = loop, version, tuple(experts)

    @property
    def description(self) -> str:
        return ("GeCo guidance (geco_guide): at the first step, the pipeline and the call's guidance checked and the "
                "guidance set up, before any denoiser runs")

    @property
    def inputs(self) -> list[InputParam]:
        return [
            InputParam("geco_guidance", type_hint=GuidanceConfig | dict | None,
                       description="GeCo guidance (a geco_guide GuidanceConfig or a dict of its fields); "
                                   "None: no guidance"),
            InputParam("geco_estimators", type_hint=Estimators,
                       description="the GeCo loss' models (geco_guide Estimators: geometry, flow, and the segmenter "
                                   "and tiny decoder where the guidance uses them)"),
            InputParam("geco_run_options", type_hint=RunOptions | dict | None,
                       description="how GeCo guidance runs (a geco_guide RunOptions or a dict of its fields)"),
            InputParam("geco_observer", type_hint=GuidanceObserver | None,
                       description="watches the GeCo updates (a geco_guide GuidanceObserver), or None"),
            InputParam("generator", description="the call's generator: the source of the time-travel noise"),
        ]

    @property
    def intermediate_outputs(self) -> list[OutputParam]:
        return [OutputParam("geco_report", type_hint=GuidanceReport,
                            description="what the call decided: the GeCo log (one dict per update), the memory plan, "
                                        "the devices, the decoder, the masks (geco_guide GuidanceReport)")]

    def __call__(self, components: Any, block_state: BlockState, i: int, t: Tensor) -> tuple[Any, BlockState]:
        if i == 0:
            self._check_pipeline(components)
            block_state.geco_report = GuidanceReport(scheduler=type(components.scheduler).__name__)
            block_state.geco_call = self._start(components, block_state)
        return components, block_state

    def _check_pipeline(self, components: Any) -> None:
        """ValueError (one line, before the first step) for a pipeline that lacks a denoiser the
        loop calls: Wan 2.2's loop in a Wan 2.1 pipeline, which has no ``transformer_2`` (diffusers'
        loop would fail on ``None.forward`` after the text encoding and the latents)."""
        present = tuple(name for name in EXPERTS if getattr(components, name, None) is not None)
        missing = [name for name in self.experts if name not in present]
        if not missing:
            return
        other = next((loop for loop in (GeCoWanDenoiseStep, GeCoWan22DenoiseStep) if loop.experts == present), None)
        fix = f"insert {other.__name__} (Wan {other.version}'s loop) instead" if other else "load its weights"
        raise ValueError(f"{self.loop} is Wan {self.version}'s denoise loop, calling {' and '.join(self.experts)}; "
                         f"the pipeline it is in has no {' and no '.join(missing)}: {fix}")

    @staticmethod
    def _start(components: Any, block_state: BlockState) -> _GuidedCall | None:
        """The call's guidance, checked before its first step; ``None`` unguided."""
        if block_state.geco_guidance is None:
            return None
        config, run = resolve_call_options(None, block_state.geco_guidance, None, block_state.geco_run_options)
        if not config.enabled:
            return None
        estimators = check_estimator_bundle(block_state.geco_estimators, "the GeCo block", argument="geco_estimators")
        latents = block_state.latents
        check_latents(latents, None, "this call")
        geometry = ADAPTER.call_geometry(components, {}, latents)
        call = stock_call(components, ADAPTER, geometry, config, run, estimators)
        num_steps = len(block_state.timesteps)
        context = call.context(num_steps, block_state.generator, observer=block_state.geco_observer)
        return _GuidedCall(context, LatentsWatch(num_steps))


class GeCoGuidanceStep(ModularPipelineBlocks):
    """The sub-block of a GeCo denoise loop before its scheduler step: the ``R_t`` updates of a
    guided step, the model output at new latents predicted by the loop's sub-blocks between
    ``geco_start`` and this one (``loop_blocks``: the loop's, read at each prediction).

    Args:
        loop_blocks: the sub-blocks of the loop it is in, by name.
    """

    model_name = "wan"

    def __init__(self, loop_blocks: Mapping[str, ModularPipelineBlocks] | None = None):
        super().__init__()
        self.loop_blocks = loop_blocks if loop_blocks is not None else {}

    @property
    def description(self) -> str:
        return ("GeCo guidance (geco_guide) before the scheduler step: the latents move towards a geometrically "
                "consistent video at the steps of geco_guidance's R_t schedule")

    @property
    def inputs(self) -> list[InputParam]:
        return [InputParam("latents", required=True, type_hint=Tensor),
                InputParam("noise_pred", type_hint=Tensor, description="the loop's model output at the latents")]

    def __call__(self, components: Any, block_state: BlockState, i: int, t: Tensor) -> tuple[Any, BlockState]:
        call = block_state.geco_call
        if call is not None:
            self._guide(components, block_state, call, i, t)
            if i == call.watch.num_steps - 1:
                block_state.geco_report = call.context.report(components.scheduler)
        return components, block_state

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
            call.context, components, ADAPTER, ADAPTER.denoisers(components), i, t, sample, model_output, predict)

    def _prediction_blocks(self) -> list[ModularPipelineBlocks]:
        """The loop's sub-blocks between ``geco_start`` and this one: what predicts ``noise_pred``."""
        names = list(self.loop_blocks)
        first = names.index(START) + 1 if START in names else 0
        return [self.loop_blocks[name] for name in names[first: names.index(GUIDANCE)]]

    def _predictor(self, components: Any, block_state: BlockState, i: int, t: Tensor, start: Tensor,
                   model_output: Tensor) -> Callable[[Tensor, bool], Tensor]:
        """``(z, differentiate) -> model output at z`` (both ``[B, C, F, h, w]``; ``start``: the
        latents of ``model_output``, the loop's own prediction): the prediction sub-blocks run
        again on a copy of the loop's state whose latents are ``z``; differentiated through
        :class:`DifferentiableDenoiser` hooks on the denoisers."""
        blocks = self._prediction_blocks()

        def predict(z: Tensor, differentiate: bool) -> Tensor:
            if not differentiate and torch.equal(z, start):
                return model_output.float()  # the loop's own prediction at this very sample
            state = BlockState(**block_state.as_dict())
            state.latents = z.detach()
            if not (differentiate and torch.is_grad_enabled()):
                return _run(blocks, components, state, i, t).noise_pred
            hooks = [DifferentiableDenoiser(z) for _ in ADAPTER.denoisers(components)]
            with contextlib.ExitStack() as stack:
                for denoiser, hook in zip(ADAPTER.denoisers(components), hooks):
                    stack.enter_context(hooked(denoiser, hook, DIFFERENTIABLE_HOOK))
                output = _run(blocks, components, state, i, t).noise_pred
            return _with_gradient(output, [part for hook in hooks for part in hook.parts], blocks)

        return predict


def _run(blocks: list[ModularPipelineBlocks], components: Any, state: BlockState, i: int, t: Tensor) -> BlockState:
    for block in blocks:
        components, state = block(components, state, i=i, t=t)
    return state


def _with_gradient(output: Tensor, parts: list[Tensor], blocks: list[ModularPipelineBlocks]) -> Tensor:
    """``output`` (the guider's, without gradient) with the gradient of the denoiser outputs
    ``parts`` combined as the guider combined them (weights fitted to ``output``): its value
    unchanged, bit for bit.

    Raises:
        RuntimeError: no denoiser ran (a sub-block predicted without one), or the guider's
            combination is not linear in the denoiser outputs (nothing to differentiate through).
    """
    names = ", ".join(type(block).__name__ for block in blocks)
    if not parts:
        raise RuntimeError(f"GeCo guidance got no gradient through the loop's sub-blocks ({names}): none of them ran "
                           "a denoiser of the pipeline; use fast mode (guidance.denoiser_grad=false)")
    weights, residual = fit_combination(parts, output)
    if residual > (1e-4 if output.dtype in (torch.float32, torch.float64) else 3e-2):
        raise RuntimeError(f"GeCo guidance cannot differentiate the loop's sub-blocks ({names}): their guider combines "
                           f"the denoiser's outputs in a way that is not linear (relative residual {residual:.2e}); "
                           "use fast mode (guidance.denoiser_grad=false)")
    combined = sum(weight.to(part.device) * part.float() for weight, part in zip(weights, parts))
    # the guider's output may be a denoiser output itself (no CFG), with its gradient already
    return output.detach() + (combined - combined.detach()).to(output.dtype)


class DifferentiableDenoiser(ModelHook):
    """While a prediction is differentiated: the denoiser's forward with gradients (the loop's
    sub-blocks run under ``torch.no_grad``), on ``z``, the latents being differentiated, in place
    of its detached copy (``[B, C, F, h, w]``; repeated where the call batches the guider's
    branches); each output kept in :attr:`parts`, one per video batch."""

    def __init__(self, z: Tensor):
        super().__init__()
        self.z = z
        self.parts: list[Tensor] = []

    def new_forward(self, module: nn.Module, *args: Any, **kwargs: Any) -> Any:
        hidden = hidden_states_of(args, kwargs)
        batch = self.z.shape[0]
        with torch.enable_grad():
            z_in = self.z.to(device=hidden.device, dtype=hidden.dtype)
            z_in = torch.cat([z_in] * (hidden.shape[0] // batch)) if hidden.shape[0] > batch else z_in
            if z_in.shape != hidden.shape or not torch.equal(z_in.detach(), hidden):
                raise ValueError("the denoiser's input is not the loop's latents (a transformed model input?): GeCo "
                                 "guidance cannot differentiate it; use fast mode (guidance.denoiser_grad=false)")
            if "hidden_states" in kwargs:
                kwargs["hidden_states"] = z_in
            else:
                args = (z_in, *args[1:])
            output = self.fn_ref.original_forward(*args, **kwargs)
            self.parts.extend(output_tensor(output).split(batch))  # views made with grad on, or untracked
        return output


class _GeCoLoop:
    """A diffusers Wan denoise loop (a ``WanDenoiseLoopWrapper``) with GeCo's sub-blocks
    inserted: :class:`GeCoStartStep` first, :class:`GeCoGuidanceStep` before the scheduler step.
    Mixed in before the stock loop class, whose loop and sub-blocks it keeps."""

    #: the Wan version whose loop this is, and the denoisers (experts) its sub-blocks call
    version: str
    experts: tuple[str, ...]

    def __init__(self):
        super().__init__()
        blocks = self.sub_blocks
        blocks.insert(GUIDANCE, GeCoGuidanceStep(blocks), list(blocks).index(SCHEDULER_STEP))
        blocks.insert(START, GeCoStartStep(type(self).__name__, self.version, self.experts), 0)

    @property
    def description(self) -> str:
        return (super().description + "\nWith GeCo guidance (geco_guide) before the scheduler step: the latents "
                "move towards a geometrically consistent video at the steps of geco_guidance's R_t schedule.")


class GeCoWanDenoiseStep(_GeCoLoop, WanDenoiseStep):
    """Wan 2.1's text-to-video denoise loop (``WanDenoiseStep``) with GeCo's sub-blocks: the
    ``denoise`` loop of ``WanModularPipeline`` (see the module docstring)."""

    version, experts = "2.1", ("transformer",)


class GeCoWan22DenoiseStep(_GeCoLoop, Wan22DenoiseStep):
    """Wan 2.2's text-to-video denoise loop (``Wan22DenoiseStep``: two experts, two guiders)
    with GeCo's sub-blocks: the ``denoise`` loop of ``Wan22ModularPipeline`` (see the module
    docstring)."""

    version, experts = "2.2", EXPERTS


_BLOCK_CODE = '''"""GeCo guidance in diffusers' Modular Wan denoise loops. The blocks' code is the geco_guide
package, which must be installed; load with ModularPipelineBlocks.from_pretrained(..., trust_remote_code=True)."""

from geco_guide.sampler.pipelines.modular import GeCoWan22DenoiseStep, GeCoWanDenoiseStep  # noqa: F401
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
