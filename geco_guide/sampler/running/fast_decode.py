"""Faster anchor decode, exact: a channels-last-3d layout for the CogVideoX VAE, and ``torch.compile``.

Both act only on the guidance decode: :func:`guidance_decode` patches instances of the pipeline's
modules for the duration of :meth:`~.context.GuidanceContext.models` and restores them on exit,
even on error, so the final video decode stays the stock one. The patches are instance
``forward``s, not hooks in diffusers' ``HookRegistry`` (:mod:`.module_hooks`): a compiled decode
needs the same forward objects at every call, and a deep copy of the patched VAE (a replica of
``run.devices``) needs forwards that call the copy (docs/architecture.md, How we patch
third-party code).

``run.decode_layout=channels_last`` runs the VAE decoder with its activations in
``torch.channels_last_3d`` (``N T H W C`` in memory, the layout cuDNN's 3-D convolutions work in
natively) instead of ``N C T H W``. Two things of the stock decode would give the layout up: the
causal time padding (``torch.cat`` of copies of the first frame makes a contiguous tensor when
the batch is 1, since a one-frame slice of a one-video batch has no recognisable layout), and
``GroupNorm`` on CUDA (its kernel copies the input to contiguous). Here both keep the layout;
the values are the same to float rounding, not bitwise (other kernels, other summation orders).

``run.compile=true`` wraps the guidance decoder (the VAE decoder's ``forward``, or the tiny
decoder's ``decode``) in ``torch.compile``, forward and backward. One compiled wrapper per function
for the process (:func:`compiled`): dynamo compiles it for each new module, input shape or layout
and reuses it on every later step and call. If compiling fails (no C++ compiler for the CPU
backend, no Triton for CUDA, an unsupported Python), one warning says so and the decode runs
eagerly from then on.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import warnings
from collections.abc import Callable, Iterator
from typing import Any

import torch
from torch import Tensor, nn

__all__ = ["CHANNELS_LAST", "DECODE_LAYOUTS", "CompileFallbackWarning", "causal_time_pad",
           "channels_last_decode", "channels_last_group_norm", "check_channels_last_vae", "guidance_decode"]

DECODE_LAYOUTS = ("default", "channels_last")
CHANNELS_LAST = "channels_last"


class CompileFallbackWarning(UserWarning):
    """``run.compile`` could not compile the guidance decode; it runs eagerly."""


# ---- layout-preserving pieces ---------------------------------------------------------------------


def causal_time_pad(inputs: Tensor, pad: int, cache: Tensor | None = None) -> Tensor:
    """``inputs [N, C, T, H, W]`` with ``pad`` frames in front, channels-last-3d: ``cache
    [N, C, pad, H, W]`` (the previous frame batch's last frames), else ``pad`` copies of the first
    frame. The values of the stock padding (``torch.cat``), written into a channels-last buffer
    because ``cat`` gives a contiguous one for a batch of one video."""
    head = cache if cache is not None else inputs[:, :, :1].expand(-1, -1, pad, -1, -1)
    n, c, t, h, w = inputs.shape
    padded = torch.empty((n, c, pad + t, h, w), dtype=inputs.dtype, device=inputs.device,
                         memory_format=torch.channels_last_3d)
    padded[:, :, :pad] = head
    padded[:, :, pad:] = inputs
    return padded


def channels_last_group_norm(x: Tensor, num_groups: int, weight: Tensor | None, bias: Tensor | None,
                             eps: float) -> Tensor:
    """``F.group_norm`` of ``x [N, C, *S]`` computed in channels-last order, so that a
    channels-last ``x`` gives a channels-last result without a copy (the CUDA kernel makes ``x``
    contiguous first). The statistics are taken over ``[N, prod(S), G, C/G]``, a view of a
    channels-last ``x``; normalisation, scale and shift are one ``addcmul`` with per-(video, channel)
    factors, computed and applied in at least float32 (for bf16 and fp16 ``x`` the mean is a second,
    float32 reduction, the variance is rounded to ``x``'s dtype)."""
    n, c = x.shape[:2]
    grouped = x.movedim(1, -1).reshape(n, -1, num_groups, c // num_groups)  # [N, L, G, C/G]
    var, mean = torch.var_mean(grouped, dim=(1, 3), correction=0, keepdim=True)  # [N, 1, G, 1]
    factor_dtype = torch.promote_types(x.dtype, torch.float32)
    if mean.dtype != factor_dtype:  # bf16/fp16: a rounded mean would shift every value of its group
        mean = grouped.mean(dim=(1, 3), keepdim=True, dtype=factor_dtype)
    scale = torch.rsqrt(var.to(factor_dtype) + eps)
    if weight is not None:
        scale = scale * weight.to(factor_dtype).view(1, 1, num_groups, -1)  # [N, 1, G, C/G]
    shift = -mean.to(factor_dtype) * scale
    if bias is not None:
        shift = shift + bias.to(factor_dtype).view(1, 1, num_groups, -1)
    # in the factors' precision, rounded once (bf16 factors lose the shift's cancellation)
    out = torch.addcmul(shift, grouped, scale).to(x.dtype)  # [N, L, G, C/G]
    return out.reshape(n, *x.shape[2:], c).movedim(-1, 1)


def _group_norm_forward(norm: nn.GroupNorm, x: Tensor) -> Tensor:
    return channels_last_group_norm(x, norm.num_groups, norm.weight, norm.bias, norm.eps)


def _causal_conv_forward(conv: nn.Module, inputs: Tensor, conv_cache: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """``CogVideoXCausalConv3d.forward`` (constant time padding, kernel longer than one frame) with
    the padding of :func:`causal_time_pad`: the padded input and the next cache as the stock ones."""
    pad = conv.time_kernel_size - 1
    padded = causal_time_pad(inputs, pad, conv_cache)
    return conv.conv(padded), padded[:, :, -pad:].clone()


def _channels_last_decoder_forward(decoder: nn.Module, sample: Tensor, *args: Any, **kwargs: Any):
    """The decoder's own ``forward`` on a channels-last-3d ``sample``; its frames come back
    contiguous (the stock layout, for everything after the decode)."""
    frames, conv_cache = type(decoder).forward(decoder, sample.contiguous(memory_format=torch.channels_last_3d),
                                               *args, **kwargs)
    return frames.contiguous(), conv_cache


def _stock_decoder_forward(decoder: nn.Module, *args: Any, **kwargs: Any):
    return type(decoder).forward(decoder, *args, **kwargs)


# ---- patching instances -------------------------------------------------------------------------


def bound(module: nn.Module, function: Callable) -> functools.partial:
    """``function`` bound to ``module``, the same object on every call: a compiled decode guards on
    the identity of its modules' ``forward``, so a new one at each step would recompile it."""
    cache = module.__dict__.setdefault("_geco_bound", {})
    if function not in cache:
        cache[function] = functools.partial(function, module)
    return cache[function]


@contextlib.contextmanager
def patched(module: nn.Module, name: str, function: Callable) -> Iterator[None]:
    """``module.<name>`` is ``function`` bound to ``module`` (:func:`bound`) for the duration, an
    instance attribute over the class's method; the previous attribute, or none, on exit."""
    had, previous = name in module.__dict__, module.__dict__.get(name)
    object.__setattr__(module, name, bound(module, function))
    try:
        yield
    finally:
        if had:
            object.__setattr__(module, name, previous)
        else:
            object.__delattr__(module, name)


@contextlib.contextmanager
def channels_last_weights(root: nn.Module) -> Iterator[None]:
    """The contiguous 5-D (Conv3d) and 4-D (Conv2d) weights under ``root`` in channels-last-3d /
    channels-last memory for the duration, contiguous again on exit (the same values)."""
    formats = {5: torch.channels_last_3d, 4: torch.channels_last}
    params = [p for m in root.modules() if isinstance(m, (nn.Conv3d, nn.Conv2d)) for p in m.parameters(recurse=False)
              if p.dim() in formats and p.is_contiguous()]
    try:
        for p in params:
            p.data = p.data.contiguous(memory_format=formats[p.dim()])
        yield
    finally:
        for p in params:
            p.data = p.data.contiguous()


def check_channels_last_vae(vae: Any) -> None:
    """TypeError (one line) unless ``vae`` is a CogVideoX VAE, the one the layout is written for."""
    from diffusers import AutoencoderKLCogVideoX

    if not isinstance(vae, AutoencoderKLCogVideoX):
        raise TypeError(
            f"run.decode_layout=channels_last is written for the CogVideoX VAE (AutoencoderKLCogVideoX), "
            f"not {type(vae).__name__}: use run.decode_layout=default"
        )


@contextlib.contextmanager
def channels_last_decode(vae: Any) -> Iterator[None]:
    """The CogVideoX ``vae``'s decoder in channels-last-3d for the duration (weights, input, causal
    padding, group norms); all restored on exit."""
    from diffusers.models.autoencoders.autoencoder_kl_cogvideox import CogVideoXCausalConv3d

    check_channels_last_vae(vae)
    decoder = vae.decoder
    replaced = {}
    for name, module in decoder.named_modules():
        if isinstance(module, nn.GroupNorm):
            replaced[name] = (module, _group_norm_forward)
        elif isinstance(module, CogVideoXCausalConv3d) and module.pad_mode != "replicate" and module.time_kernel_size > 1:
            replaced[name] = (module, _causal_conv_forward)
    # The layout's forwards of these modules and of the decoder itself would bypass a forward they
    # already have (e.g. accelerate's sequential CPU offload); the other modules' hooks still run.
    taken = [name or "decoder" for name, module in decoder.named_modules()
             if "forward" in module.__dict__ and (module is decoder or name in replaced)]
    if taken:
        raise ValueError(f"run.decode_layout=channels_last cannot lay out this VAE decoder: {len(taken)} of the modules "
                         "whose forward it replaces (the decoder, its group norms and causal convolutions) already "
                         f"have their own forward (e.g. {taken[0]}: an offload hook?): use run.decode_layout=default")
    with contextlib.ExitStack() as stack:
        stack.enter_context(channels_last_weights(decoder))
        for module, function in replaced.values():
            stack.enter_context(patched(module, "forward", function))
        yield


# ---- torch.compile --------------------------------------------------------------------------------

_COMPILED: dict[Callable, CompiledOrEager] = {}
logger = logging.getLogger(__name__)


class CompiledOrEager:
    """``function`` through ``torch.compile``, or ``function`` itself from the first failure to
    compile on (one :class:`CompileFallbackWarning`). Errors of the computation itself are
    raised as they are."""

    def __init__(self, function: Callable):
        self.function, self.compiled, self.announced = function, None, False
        try:
            self.compiled = torch.compile(function)
        except RuntimeError as error:  # torch.compile refuses this Python or platform
            self._fall_back(error)

    def _fall_back(self, error: BaseException) -> None:
        self.compiled = None
        first_line = next((line for line in str(error).splitlines() if line.strip()), "")
        warnings.warn(f"run.compile: torch.compile failed ({type(error).__name__}: {first_line[:300]}); "
                      "the guidance decode runs eagerly", CompileFallbackWarning, stacklevel=3)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        if self.compiled is not None:
            if not self.announced:  # the first call compiles: minutes of silence otherwise
                logger.warning("run.compile: compiling the guidance decode; the first guided update waits for "
                               "it (minutes on a CPU, longer when the machine is busy)")
                self.announced = True
            try:
                return self.compiled(*args, **kwargs)
            except (torch._dynamo.exc.BackendCompilerFailed, torch._dynamo.exc.InternalTorchDynamoError) as error:
                self._fall_back(error)
        return self.function(*args, **kwargs)


def compiled(function: Callable) -> CompiledOrEager:
    """The process's one :class:`CompiledOrEager` of ``function`` (made on first use)."""
    if function not in _COMPILED:
        _COMPILED[function] = CompiledOrEager(function)
    return _COMPILED[function]


def _tiny_decode(decoder: nn.Module, latents: Tensor) -> Tensor:
    return type(decoder).decode(decoder, latents)


# ---- the guidance decode --------------------------------------------------------------------------


@contextlib.contextmanager
def guidance_decode(run: Any, decoder: str, vae: Any, guidance_decoder: Any = None) -> Iterator[None]:
    """The guidance decode of ``run`` (a :class:`~.run_options.RunOptions`) for the duration: with
    ``decode_layout=channels_last`` the VAE decoder in channels-last-3d (:func:`channels_last_decode`),
    with ``compile`` the decoder that ``decoder`` (``guidance.decoder``: ``vae`` or ``tiny``) names
    compiled (the VAE decoder's ``forward``, the tiny ``guidance_decoder``'s ``decode``). Nothing is
    patched with the defaults."""
    layout, compile_vae = run.decode_layout == CHANNELS_LAST, run.compile and decoder == "vae"
    if compile_vae and not isinstance(getattr(vae, "decoder", None), nn.Module):
        raise TypeError(f"run.compile compiles the VAE's decoder module, and {type(vae).__name__} has none: "
                        "use run.compile=false")
    with contextlib.ExitStack() as stack:
        if layout:
            stack.enter_context(channels_last_decode(vae))
        if layout or compile_vae:
            forward = _channels_last_decoder_forward if layout else _stock_decoder_forward
            stack.enter_context(patched(vae.decoder, "forward", compiled(forward) if compile_vae else forward))
        if run.compile and decoder == "tiny" and guidance_decoder is not None:
            stack.enter_context(patched(guidance_decoder, "decode", compiled(_tiny_decode)))
        yield
