"""Latents that turn NaN or inf during sampling stop the call with one line naming the step,
in GeCoCogVideoXPipeline (after the last step, before the decode) and under the hooks, instead of
returning NaN frames (tiny models, CPU; the NaN comes from a step-end callback, as a diverging
update or a caller's callback would)."""

from __future__ import annotations

import math

import pytest
import torch

from geco_guide import tiny as T
from geco_guide.sampler.pipelines.hooks import attach_geco_guidance
from geco_guide.sampler.algorithm.step import LatentsWatch, NonFiniteLatentsError

PROMPT = "a marble bust"


def poison_at(step: int):
    """A step-end callback that makes the latents NaN after denoising step ``step``."""
    def callback(pipe, i, t, kwargs):
        if i == step:
            kwargs["latents"] = torch.full_like(kwargs["latents"], math.nan)
        return kwargs
    return callback


def _message(step: int, steps: int) -> str:
    return (f"the latents hold NaN or inf from denoising step {step} on (0-based, of {steps}); the video would be NaN "
            "frames, so the call stops (lower guidance.step_size or the guidance scale, or check latents set by a callback)")


@pytest.mark.parametrize("guidance", [None, False], ids=["guided", "unguided"])
@pytest.mark.parametrize("step", [1, 3])
@pytest.mark.slow
def test_the_pipeline_refuses_latents_that_turn_nan_naming_the_step(guidance, step, estimators):
    pipe = T.tiny_pipeline(0)
    with pytest.raises(NonFiniteLatentsError) as err:
        pipe(prompt=PROMPT, generator=torch.Generator().manual_seed(0), guidance=guidance, estimators=estimators,
             run_options=T.tiny_run_options(), callback_on_step_end=poison_at(step), **T.TINY_CALL_KWARGS)
    assert str(err.value) == _message(step, 4)


@pytest.mark.parametrize("repeats, poisoned, named", [
    ("1x4", 1, 2),  # every step guided: refused where the next guided step starts from them
    ("1x1,0x3", 1, 2),  # no guided step after: refused at the last step, naming the first step that made them
])
@pytest.mark.slow
def test_the_hooks_refuse_latents_that_turn_nan_naming_the_step(repeats, poisoned, named, estimators):
    pipe = T.tiny_wan_pipeline(0)
    config = {"anchors": [4, 8, 12, 16], "repeats": repeats, "time_travel": []}
    with attach_geco_guidance(pipe, config, estimators):
        with pytest.raises(NonFiniteLatentsError) as err:
            pipe(prompt=PROMPT, generator=torch.Generator().manual_seed(0), callback_on_step_end=poison_at(poisoned),
                 **T.tiny_call_kwargs(pipe))
    assert str(err.value) == _message(named, 4)


def test_finite_latents_pass_and_the_watch_names_the_first_bad_step():
    watch = LatentsWatch(5)
    watch.check()  # nothing seen yet
    for step in range(5):
        latents = torch.zeros(2, 3)
        if step >= 2:
            latents[1, step % 3] = math.inf
        watch.see(latents, step)
    with pytest.raises(NonFiniteLatentsError, match=r"from denoising step 2 on \(0-based, of 5\)"):
        watch.check()
    fine = LatentsWatch(2)
    fine.see(torch.ones(3), 0)
    fine.see(torch.ones(3), 1)
    fine.check()
