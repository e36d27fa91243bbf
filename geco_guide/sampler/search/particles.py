"""A search's particles as the batch of one pipeline call: their rows in a denoiser call, the
denoiser run over sub-batches of particles (and dealt over devices), and the scheduler's
per-particle state carried through a resampling.

A pipeline call with ``K`` particles calls its denoiser on a batch of ``rep x K`` rows: ``rep``
blocks of ``K`` (classifier-free guidance in one call: the unconditional block, then the
conditional one; ``rep = 1`` without CFG or with CFG as two calls). Particle ``k``'s rows are
``k, K + k, ...`` (:func:`particle_rows`), so a sub-batch of particles is a call laid out as the
same call of those particles alone. Every top-level tensor argument whose first dimension is the
batch is cut the same way; other arguments (rotary embeddings, flags) go whole to each call.

Batch size and rounding: a denoiser rounds a row the same wherever it sits in a batch and
whatever the other rows hold (a row swapped with another, or copied, gives the same numbers bit
for bit on CPU), but a batch of another size may sum in another order (CPU kernels pick their
blocking by the batch), so sub-batches of one size give the frames of one batch to float
rounding, and sub-batches of one particle give each particle's frames as a call of that particle
alone, bit for bit. Devices change nothing more: a sub-batch is the same call on any replica.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from ..running.multi_device import dealt_work, module_replicas, to_device

__all__ = ["UNBATCHED_KEYS", "ParticleBatches", "call_rows", "deal_final_decode", "denoiser_places", "hidden_states_of", "output_tensor",
           "particle_batches", "particle_rows", "reorder_scheduler_state", "with_output_tensor"]

#: Keyword arguments of a denoiser that never carry the batch, even where their first dimension
#: happens to equal it (CogVideoX's rotary embeddings: one per token).
UNBATCHED_KEYS = ("image_rotary_emb",)


def particle_batches(particles: int, size: int) -> list[list[int]]:
    """The sub-batches of ``particles`` particles, at most ``size`` each, in order:
    ``[[0, .., size-1], [size, ..], ...]``."""
    if size < 1:
        raise ValueError(f"a particle sub-batch holds at least one particle, got {size}")
    return [list(range(start, min(start + size, particles))) for start in range(0, particles, size)]


def particle_rows(particles: int, batch: int, chosen: Sequence[int]) -> list[int]:
    """The rows of particles ``chosen`` in a denoiser batch of ``batch`` rows made of ``batch /
    particles`` blocks of ``particles`` rows, block by block: ``[r * particles + k for r in blocks
    for k in chosen]``, the layout of the same call of those particles alone.

    Raises:
        ValueError: ``batch`` is no multiple of ``particles``.
    """
    if batch % particles:
        raise ValueError(f"a denoiser batch of {batch} rows is no multiple of the {particles} particles")
    return [block * particles + k for block in range(batch // particles) for k in chosen]


def _batched(key: Any, value: Any, batch: int) -> bool:
    return (isinstance(value, Tensor) and value.ndim > 0 and value.shape[0] == batch
            and key not in UNBATCHED_KEYS)


def call_rows(args: Sequence[Any], kwargs: dict[str, Any], rows: Sequence[int], batch: int,
              device: torch.device | None = None) -> tuple[tuple, dict[str, Any]]:
    """``(args, kwargs)`` of a denoiser call of ``batch`` rows cut to ``rows``: each top-level
    tensor whose first dimension is ``batch`` (but :data:`UNBATCHED_KEYS`) indexed, the others
    as they are; everything moved to ``device`` where one is given."""
    def cut(key: Any, value: Any) -> Any:
        if _batched(key, value, batch):
            value = value[torch.as_tensor(rows, device=value.device)]
        return to_device(value, device) if device is not None else value

    return (tuple(cut(k, v) for k, v in enumerate(args)), {key: cut(key, value) for key, value in kwargs.items()})


def hidden_states_of(args: Sequence[Any], kwargs: dict[str, Any]) -> Tensor:
    """The latents a denoiser call is given: its ``hidden_states`` keyword, else its first
    positional tensor; ValueError for a call that has neither."""
    if "hidden_states" in kwargs:
        return kwargs["hidden_states"]
    if args and isinstance(args[0], Tensor):
        return args[0]
    raise ValueError("could not find the denoiser's hidden_states argument")


def output_tensor(output: Any) -> Tensor:
    """The model output of a denoiser's return value: the tensor, the first of a tuple, or ``.sample``."""
    if isinstance(output, Tensor):
        return output
    if isinstance(output, (tuple, list)):
        return output[0]
    return output.sample


def with_output_tensor(output: Any, tensor: Tensor) -> Any:
    """``output`` (as :func:`output_tensor` reads it) with its model output replaced by ``tensor``."""
    if isinstance(output, Tensor):
        return tensor
    if isinstance(output, (tuple, list)):
        return type(output)([tensor, *output[1:]])
    output.sample = tensor
    return output


@dataclass
class ParticleBatches:
    """A denoiser call of ``particles`` particles run as calls of at most ``size`` particles each
    (:func:`particle_batches`), sub-batch ``j`` on ``places[j mod N]``; the outputs meet, in the
    call's row order, on the device of the call's latents.

    Attributes:
        particles: ``K``, the particles of the pipeline call.
        size: the most particles one call holds.
        places: ``(device, runner)`` per place: ``runner(*args, **kwargs)`` is the denoiser there
            (the module's own forward on its device; a replica elsewhere); device ``None``: the
            call's own. A call of one place and no more than ``size`` particles runs as it is.
    """

    particles: int
    size: int
    places: Sequence[tuple[torch.device | None, Callable[..., Any]]]

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        """The denoiser's output for a call of all the particles (``rep x K`` rows), as one call
        would return it."""
        hidden = hidden_states_of(args, kwargs)
        batch, home = hidden.shape[0], hidden.device
        if self.particles <= self.size and self.places[0][0] in (None, home):
            return self.places[0][1](*args, **kwargs)
        outputs, order = [], []
        for j, chosen in enumerate(particle_batches(self.particles, self.size)):
            device, runner = self.places[j % len(self.places)]
            rows = particle_rows(self.particles, batch, chosen)
            sub_args, sub_kwargs = call_rows(args, kwargs, rows, batch, None if device in (None, home) else device)
            outputs.append(runner(*sub_args, **sub_kwargs))
            order.extend(rows)
        joined = torch.cat([output_tensor(out).to(home) for out in outputs])
        inverse = torch.empty(batch, dtype=torch.long)
        inverse[torch.as_tensor(order)] = torch.arange(batch)
        return with_output_tensor(outputs[0], joined[inverse.to(home)])


def deal_final_decode(vae: nn.Module, devices: Sequence[torch.device]) -> Callable[[], None]:
    """Deal a search's final decode over ``devices``: ``vae.decode`` of ``K`` videos becomes the
    decode of video ``k`` alone on ``devices[k mod N]`` (the VAE itself where it lives, a replica
    elsewhere; the call's other batched arguments, e.g. LTX's decode timestep, cut the same way),
    the devices decoding at once (:func:`~.multi_device.dealt_work`); the frames meet, in the
    videos' order, on the device of the latents. Each video is its own decode as on one device
    (the VAE's ``use_slicing``), so the frames are the same. Returns the function that puts the
    VAE's own ``decode`` back. Install it after the denoising loop: the anchor decodes of the
    loop call ``vae.decode`` too."""
    replicas = module_replicas(vae, devices)
    previous = vae.__dict__.get("decode")
    decodes = [replica.decode for replica in replicas]

    def decode(latents: Tensor, *args: Any, **kwargs: Any) -> Any:
        batch, home = latents.shape[0], latents.device

        def one_video(k: int, place: int) -> Any:
            target = None if devices[place] == home else devices[place]
            video_args, video_kwargs = call_rows((latents, *args), kwargs, [k], batch, target)
            return decodes[place](*video_args, **video_kwargs)

        outputs = list(dealt_work(batch, len(devices), one_video))
        return with_output_tensor(outputs[0], torch.cat([output_tensor(out).to(home) for out in outputs]))

    vae.decode = decode

    def restore() -> None:
        if previous is None:
            vae.__dict__.pop("decode", None)
        else:
            vae.decode = previous

    return restore


def _is_state(value: Any, shape: torch.Size) -> bool:
    return isinstance(value, Tensor) and value.shape == shape


def reorder_scheduler_state(scheduler: Any, ancestors: Tensor, shape: torch.Size) -> list[str]:
    """Carry a scheduler's per-particle state through a resampling: every attribute of
    ``scheduler`` that is a tensor of the latents' ``shape`` ``[K, ...]`` (UniPC's
    ``last_sample``, DPM-Solver single-step's ``sample``, Heun's ``prev_derivative``), or a list
    or tuple holding such tensors (the multistep histories, ``model_outputs``), is indexed by
    ``ancestors [K]``: slot ``k`` gets particle ``ancestors[k]``'s. Other attributes (timesteps,
    sigmas, step counters) are the same for every particle and stay. Returns the names carried.
    """
    carried = []
    for name, value in list(vars(scheduler).items()):
        if _is_state(value, shape):
            setattr(scheduler, name, value[ancestors.to(value.device)])
            carried.append(name)
        elif isinstance(value, (list, tuple)) and any(_is_state(item, shape) for item in value):
            setattr(scheduler, name, type(value)(item[ancestors.to(item.device)] if _is_state(item, shape) else item
                                                 for item in value))
            carried.append(name)
    return carried


def denoiser_places(denoiser: nn.Module, devices: Sequence[torch.device] | None,
                    home_runner: Callable[..., Any]) -> list[tuple[torch.device, Callable[..., Any]]]:
    """The places of :class:`ParticleBatches` for ``denoiser``: ``home_runner`` on its own device,
    and a replica (:func:`~.multi_device.module_replicas`) on each other device of ``devices``."""
    first = next(denoiser.parameters(), None)
    home = first.device if first is not None else torch.device("cpu")
    if not devices:
        return [(home, home_runner)]
    replicas = module_replicas(denoiser, devices)
    return [(device, home_runner if replica is denoiser else replica) for device, replica in zip(devices, replicas)]
