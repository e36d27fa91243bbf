"""One structured config (omegaconf) for a GeCo generation run.

Sections, each the dataclass of the code that uses it: ``model`` (:class:`ModelConfig`: a model of
the registry :mod:`geco_guide.families` and its weights), ``estimators`` (:class:`EstimatorsConfig`:
geometry + flow backbones, segmenter, tiny decoder), ``sampling`` (:class:`SamplingConfig`: steps,
CFG, size; null values are the model's defaults), ``guidance`` (:class:`GuidanceConfig`, what
guidance computes: anchors, schedule, step size, time travel, and ``guidance.loss``, which *is*
:class:`GeCoLossConfig`), ``search`` (:class:`SearchConfig`: particle search with GeCo as the
verifier, off by default), ``run`` (:class:`RunOptions`, how this machine runs it: memory plan,
decode layout, devices), ``output``, ``evaluation`` (:class:`EvaluationConfig`: how ``python -m
geco_guide evaluate`` samples a video, with the metric's own ``evaluation.loss``) and ``seed``.
Defaults are the GeCo paper's CogVideoX-5b setting; the presets are the checkout's
``configs/<name>.yaml``, installed as the package data ``geco_guide/configs`` (so ``--preset``
works after a plain ``pip install``). Earlier spellings of keys (``guidance.eta``,
``guidance.memory_plan``, ``guidance.movers``, ...) are refused in one line naming the new key.

``load_config(path, preset, overrides)`` merges schema <- YAML <- ``key=value`` overrides and
validates: an unknown key or an invalid value raises a ValueError naming the key.
The special id ``"tiny-random"`` (for the model and each estimator) builds the tiny, randomly
initialised offline models of :mod:`geco_guide.tiny` instead of loading weights.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import Any, Optional

import yaml
from omegaconf import DictConfig, ListConfig, OmegaConf, StringNode
from omegaconf.errors import (
    ConfigAttributeError,
    ConfigKeyError,
    OmegaConfBaseException,
)

from .estimators import TINY_RANDOM, EstimatorsConfig
from .families import (MODELS, default_anchors, did_you_mean, frames_problem, generating_model, model_named,
                       video_models)
from .metric.protocol import EvaluationConfig
from .sampler.algorithm.config import GuidanceConfig, paper_guidance_config
from .sampler.pipelines.loading import CHECKPOINT_SCHEDULER, SCHEDULERS, ModelConfig
from .sampler.pipelines.sampling import SamplingConfig, fit_to_model, sampling_problem, with_model_defaults
from .sampler.running.run_options import RunOptions, check_run_for_guidance
from .sampler.search.particle_search import SearchConfig
from .types import OptionError, non_finite_fields, renamed_option

__all__ = ["CONFIG_DIR", "DTYPES", "SEED_RANGE", "GeCoConfig", "ModelConfig", "OutputConfig", "SamplingConfig",
           "SearchConfig",
           "config_to_dict", "config_to_yaml", "load_config", "model_preset", "movers_as_first_spelt", "nested",
           "preset_path", "to_config", "validate_config"]

DTYPES = ("float32", "float16", "bfloat16")
# CFG scales in use are 1-20 (CogVideoX: 6); absurd ones only overflow the latents to NaN/inf
# after minutes of sampling (a black video), so they are refused at once (guidance.step_size likewise,
# in GuidanceConfig).
MAX_GUIDANCE_SCALE = 100.0
# torch.Generator.manual_seed takes 64-bit seeds, signed or unsigned.
SEED_RANGE = (-(2**63), 2**64 - 1)
# Installed: the package data geco_guide/configs; in a checkout (also an editable install): the
# top-level configs/ that the wheel copies it from.
CONFIG_DIR = next((d for d in (Path(__file__).resolve().parent / "configs", Path(__file__).resolve().parents[1] / "configs")
                   if d.is_dir()), Path(__file__).resolve().parent / "configs")


@dataclass
class OutputConfig:
    """Where results go: ``<dir>/<name>.mp4`` and ``<dir>/<name>.json``."""

    dir: str = "outputs"
    name: Optional[str] = None  # default: prompt slug + seed
    score_anchors: bool = True  # GeCo scores of the final video's anchor frames in the sidecar


@dataclass
class GeCoConfig:
    model: ModelConfig = field(default_factory=ModelConfig)
    estimators: EstimatorsConfig = field(default_factory=EstimatorsConfig)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    guidance: GuidanceConfig = field(default_factory=paper_guidance_config)  # the paper's experiment (motion cue)
    search: SearchConfig = field(default_factory=SearchConfig)  # off: particles null
    run: RunOptions = field(default_factory=RunOptions)
    output: OutputConfig = field(default_factory=OutputConfig)
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)
    seed: int = 0


def preset_path(name: str) -> Path:
    """``<name>.yaml`` of :data:`CONFIG_DIR`; ValueError listing the presets if there is none."""
    path = CONFIG_DIR / f"{name}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))
        raise ValueError(f"unknown preset {name!r}; known presets: {known}")
    return path


def _key_error(err: OmegaConfBaseException, source: str) -> ValueError:
    """The one line of a merge's key error: an unknown key, the new spelling of a renamed one
    (its section's ``RENAMED``, e.g. :attr:`GuidanceConfig.RENAMED`), or a value its field cannot take."""
    key = getattr(err, "full_key", None) or getattr(err, "key", None) or "?"
    if isinstance(err, (ConfigKeyError, ConfigAttributeError)):
        section, _, leaf = str(key).partition(".")
        renamed = renamed_option(type(getattr(GeCoConfig(), section, None)), leaf, section)
        return ValueError(f"{renamed or f'unknown config key {key!r}{_close_keys(str(key))}'} ({source})")
    msg = str(err).split("\n")[0]
    return ValueError(f"invalid value for config key {key!r} ({source}): {msg}")


def _close_keys(key: str) -> str:
    """The keys of ``key``'s section close to its misspelt last name, as :func:`did_you_mean` says them."""
    section, _, leaf = key.rpartition(".")
    node: Any = GeCoConfig()
    for name in filter(None, section.split(".")):
        node = getattr(node, name, None)
    if not is_dataclass(node):
        return ""
    return did_you_mean(leaf, [f.name for f in fields(node)], f"{section}." if section else "")


def _merge(base: DictConfig, other: Any, source: str) -> DictConfig:
    try:
        return OmegaConf.merge(base, other)
    except (OmegaConfBaseException, TypeError) as err:  # TypeError: a mapping merged into a list
        mismatch = _container_mismatch(base, other)
        if mismatch is not None:  # omegaconf's merge error names no key for these
            key, expected, value = mismatch
            raise ValueError(f"{key} must be {expected}, got {value!r} ({source})") from None
        if isinstance(err, TypeError):
            raise ValueError(f"cannot merge the config of {source}: {err}") from None
        raise _key_error(err, source) from None


def _container_mismatch(base: DictConfig, other: Any, prefix: str = "") -> tuple[str, str, Any] | None:
    """The first ``(dotted key, what it must be, value)`` of ``other`` that gives a plain value
    or a list where ``base`` has a section (``sampling: 5``), or a mapping or a plain value where
    ``base`` has a list (``guidance.anchors: {a: 1}``, ``guidance.anchors: "4,8"``); None if there
    is none."""
    if not isinstance(other, (DictConfig, Mapping)):
        return None
    for key, value in other.items():
        node = base._get_node(key) if key in base else None  # a None list is a ListConfig node, its value None
        is_mapping = isinstance(value, (DictConfig, Mapping))
        if isinstance(node, DictConfig):
            if not is_mapping:
                expected = "a mapping" if OmegaConf.get_type(node) is dict else "a mapping of options"
                return f"{prefix}{key}", expected, value
            found = _container_mismatch(node, value, f"{prefix}{key}.")
            if found is not None:
                return found
        elif isinstance(node, ListConfig) and value is not None and (
                isinstance(value, str) or not isinstance(value, Sequence)):
            return f"{prefix}{key}", "a list", value
    return None


def model_preset(name: str) -> str | None:
    """The preset of configs/ named for the model ``name`` (``--model NAME``), or ``None``; ValueError
    (one line listing the models) for a name the registry does not know."""
    generating_model(name)
    return name if (CONFIG_DIR / f"{name}.yaml").is_file() else None


def load_config(
    path: str | Path | None = None,
    preset: str | None = None,
    overrides: Sequence[str] = (),
    *,
    changes: Mapping[str, Any] | None = None,
    model_preset: str | None = None,
) -> GeCoConfig:
    """Schema defaults <- the model's preset <- preset <- YAML file <- ``key=value`` overrides <-
    ``changes`` (``{dotted key: Python value}``, what command flags set), validated. With the
    tiny random stand-in (``model.id=tiny-random``) the presets' sizes are fitted to the model
    (``_fit_tiny_call``): the tiny preset runs every model.

    Raises:
        ValueError: unknown key, wrong type or invalid value, naming the key; ``path`` is a
            folder or not a YAML mapping.
        FileNotFoundError: ``path`` does not exist.
    """
    cfg = OmegaConf.structured(GeCoConfig)
    user_keys: set[str] = set()
    if model_preset is not None:
        p = preset_path(model_preset)
        cfg = _merge(cfg, _load_yaml(p), str(p))
    if preset is not None:
        p = preset_path(preset)
        cfg = _merge(cfg, _load_yaml(p), str(p))
    if path is not None:
        p = Path(path)
        if p.is_dir():
            raise ValueError(f"config file {str(p)!r} is a folder, not a config file")
        if not p.is_file():
            raise FileNotFoundError(f"config file {str(p)!r} does not exist")
        layer = _load_yaml(p)
        cfg = _merge(cfg, layer, str(p))
        user_keys |= _dotted_keys(layer)
    if overrides:
        bad = [o for o in overrides if "=" not in o]
        if bad:
            raise ValueError(f"overrides must be key=value, got {bad}")
        for item in overrides:
            layer = _parse_override(cfg, item)
            cfg = _merge(cfg, layer, "command line")
            user_keys |= _dotted_keys(layer)
    for key, value in (changes or {}).items():
        cfg = _merge(cfg, nested({key: value}), "command line")
        user_keys.add(key)
    return to_config(_fit_tiny_call(cfg, user_keys))


def _fit_tiny_call(cfg: DictConfig, kept: set[str]) -> DictConfig:
    """``cfg`` whose call is fitted to its model (:func:`~geco_guide.sampler.pipelines.sampling.fit_to_model`:
    the size multiple, the text length) where it runs the tiny random stand-in, which the tiny
    preset's 32x48 call, made for every model, drives; the keys of ``kept`` (what the user set
    in a file, an override or a flag) are left as set, and refused if they do not fit."""
    name = cfg.model.name
    if cfg.model.id != TINY_RANDOM or name not in MODELS or not MODELS[name].generates:
        return cfg
    s = cfg.sampling
    fitted = fit_to_model(SamplingConfig(height=s.height, width=s.width, max_sequence_length=s.max_sequence_length),
                          MODELS[name])
    changes = {key: getattr(fitted, key) for key in ("height", "width", "max_sequence_length")
               if f"sampling.{key}" not in kept and getattr(fitted, key) != s[key]}
    return _merge(cfg, {"sampling": changes}, "the tiny call fitted to the model") if changes else cfg


def _dotted_keys(layer: DictConfig | dict, prefix: str = "") -> set[str]:
    """Every dotted key a config layer sets (``sampling.width``), its sections' too."""
    keys: set[str] = set()
    for key, value in layer.items():
        keys.add(f"{prefix}{key}")
        if isinstance(value, (DictConfig, dict)):
            keys |= _dotted_keys(value, f"{prefix}{key}.")
    return keys


def _load_yaml(path: Path) -> DictConfig:
    """A config file's sections; ValueError naming the file (and the YAML error's line and column)
    if it is not UTF-8 or not YAML holding a mapping."""
    try:
        loaded = OmegaConf.load(path)
    except UnicodeDecodeError as err:
        raise ValueError(f"config file {str(path)!r} is not UTF-8 text (byte {err.start}: {err.reason})") from None
    except yaml.YAMLError as err:
        raise ValueError(f"config file {str(path)!r} is not valid YAML: {_yaml_reason(err)}") from None
    if not isinstance(loaded, DictConfig):
        raise ValueError(f"config file {str(path)!r} must hold a mapping of sections (model:, sampling:, ...)")
    return loaded


def _yaml_reason(err: yaml.YAMLError) -> str:
    """``line L, column C: problem`` (1-based, as editors count) of a YAML error, on one line."""
    mark = getattr(err, "problem_mark", None)
    problem = getattr(err, "problem", None) or " ".join(str(err).split())
    return f"line {mark.line + 1}, column {mark.column + 1}: {problem}" if mark is not None else problem


def _parse_override(cfg: DictConfig, item: str) -> DictConfig:
    """``key=value`` -> a DictConfig to merge. Values are YAML, except for string fields, which
    take the text as is (YAML would read ``guidance.repeats=0x2`` as the hex number 2)."""
    key, _, raw = item.partition("=")
    key = key.strip()
    parent_key, _, leaf = key.rpartition(".")
    try:
        parent = OmegaConf.select(cfg, parent_key) if parent_key else cfg
        node = parent._get_node(leaf) if isinstance(parent, DictConfig) else None
    except OmegaConfBaseException:
        node = None
    if isinstance(node, StringNode) and raw.strip().lower() not in ("null", "~"):
        return OmegaConf.create(nested({key: raw}))
    try:
        return OmegaConf.from_dotlist([f"{key}={raw}"])
    except OmegaConfBaseException as err:
        raise ValueError(f"cannot parse override {item!r}: {err}") from None


def movers_as_first_spelt(guidance: dict[str, Any], masked: bool) -> dict[str, Any]:
    """A config dict's ``guidance`` section (``masked``: its masks act) with movers where the video
    key of the first videos with movers held it, so that the video of a sidecar of either spelling
    keeps its name (:func:`geco_guide.generation.video_key`): an acting ``loss.movers`` (off its
    default ``drop``, with masks) as the earlier ``guidance.movers``, which is left out where it
    does not act, and ``loss.movers`` left out at ``drop``."""
    kept = dict(guidance)
    loss = kept.get("loss")
    if isinstance(loss, dict) and masked and loss.get("movers", "drop") != "drop":
        kept["movers"], kept["loss"] = loss["movers"], {**loss, "movers": "drop"}
    if kept.get("movers") == "drop" or not masked:
        kept.pop("movers", None)
    loss = kept.get("loss")
    if isinstance(loss, dict) and loss.get("movers") == "drop":
        kept["loss"] = {key: value for key, value in loss.items() if key != "movers"}
    return kept


def nested(changes: Mapping[str, Any]) -> dict[str, Any]:
    """Dotted keys as sections: ``{"guidance.loss.movers": v}`` -> ``{"guidance": {"loss": {"movers": v}}}``."""
    tree: dict[str, Any] = {}
    for key, value in changes.items():
        *sections, name = key.split(".")
        node = tree
        for section in sections:
            node = node.setdefault(section, {})
        node[name] = value
    return tree


def to_config(cfg: DictConfig | dict | GeCoConfig) -> GeCoConfig:
    """A validated :class:`GeCoConfig` from a DictConfig / plain dict / GeCoConfig."""
    if isinstance(cfg, GeCoConfig):
        cfg = OmegaConf.structured(cfg)
    elif not isinstance(cfg, DictConfig) or OmegaConf.get_type(cfg) is not GeCoConfig:
        cfg = _merge(OmegaConf.structured(GeCoConfig), cfg, "config")
    try:
        obj = OmegaConf.to_object(cfg)
    except OmegaConfBaseException as err:
        raise _key_error(err, "config") from None
    except OptionError as err:  # a dataclass's own value check (__post_init__)
        raise ValueError(f"invalid value for config key '{_section_of(cfg)}.{err.key}': {err}") from None
    if obj.model.name not in MODELS or not MODELS[obj.model.name].generates:
        raise ValueError(f"invalid value for config key 'model.name': must be one of {', '.join(video_models())}, "
                         f"got {obj.model.name!r}{did_you_mean(obj.model.name, video_models())}")
    model = model_named(obj.model.name)
    # the registry fills what the config leaves null: the weights' hub id, the call, the anchors
    obj = replace(obj, model=replace(obj.model, id=obj.model.source), sampling=with_model_defaults(obj.sampling, model))
    if obj.guidance.anchors is None and frames_problem(obj.sampling.num_frames, model.temporal_compression) is None:
        anchors = default_anchors(obj.sampling.num_frames, model.temporal_compression)
        obj = replace(obj, guidance=replace(obj.guidance, anchors=anchors))
    validate_config(obj)
    return obj


def _section_of(cfg: DictConfig) -> str:
    """Which checked section of ``cfg`` fails its dataclass's checks: built one by one, innermost
    first, since the same dataclass (GeCoLossConfig) sits in two places."""
    for section in ("guidance.loss", "guidance", "search", "run", "evaluation.loss", "evaluation"):
        try:
            OmegaConf.to_object(OmegaConf.select(cfg, section))
        except OptionError:
            return section
    raise AssertionError("no section fails its checks")  # to_object of the whole config did


def _require(cond: bool, key: str, message: str) -> None:
    if not cond:
        raise ValueError(f"invalid value for config key {key!r}: {message}")


def validate_config(cfg: GeCoConfig) -> None:
    """Semantic checks beyond types; ValueError naming the key."""
    for key, value in non_finite_fields(cfg):  # every float option of every section; first one
        raise ValueError(f"invalid value for config key {key!r}: must be a finite number, got {value}")
    _require(SEED_RANGE[0] <= cfg.seed <= SEED_RANGE[1], "seed", f"must be a 64-bit integer, got {cfg.seed}")
    _require(cfg.model.id is None or bool(cfg.model.id.strip()), "model.id",
             "must be a hub id, a local folder, 'tiny-random', or null (the registry's hub id of model.name)")
    _require(cfg.model.dtype in DTYPES, "model.dtype", f"must be one of {DTYPES}, got {cfg.model.dtype!r}")
    _require(cfg.estimators.dtype in DTYPES, "estimators.dtype", f"must be one of {DTYPES}, got {cfg.estimators.dtype!r}")
    _require(bool(cfg.estimators.geometry), "estimators.geometry", "must not be empty")
    _require(bool(cfg.estimators.flow), "estimators.flow", "must not be empty")
    device = cfg.model.device
    _require(
        device in ("auto", "cpu", "mps") or device.startswith("cuda"),
        "model.device",
        f"must be auto, cpu, mps or cuda[:N], got {device!r}",
    )
    s, model = cfg.sampling, model_named(cfg.model.name)
    _require(s.num_inference_steps >= 1, "sampling.num_inference_steps", f"must be >= 1, got {s.num_inference_steps}")
    for key in ("guidance_scale", "guidance_scale_2"):
        value = getattr(s, key)
        _require(value is None or 0 <= value <= MAX_GUIDANCE_SCALE, f"sampling.{key}",
                 f"must be in [0, {MAX_GUIDANCE_SCALE:g}], got {value}")
    _require(s.fps >= 1, "sampling.fps", f"must be >= 1, got {s.fps}")
    _require(s.max_sequence_length is None or s.max_sequence_length >= 1, "sampling.max_sequence_length",
             f"must be >= 1, got {s.max_sequence_length}")
    problem = sampling_problem(s, model)
    if problem is not None:
        raise ValueError(f"invalid value for config key 'sampling.{problem[0]}': {problem[1]}")
    _require(s.scheduler in (None, CHECKPOINT_SCHEDULER, *SCHEDULERS), "sampling.scheduler",
             f"must be ddim, dpm, checkpoint or null, got {s.scheduler!r}")
    _require(s.scheduler in (None, CHECKPOINT_SCHEDULER) or s.scheduler in model.schedulers, "sampling.scheduler",
             f"ddim and dpm are CogVideoX's schedulers; {model.name} samples with its own (checkpoint or null), "
             f"got {s.scheduler!r}")
    g = cfg.guidance
    # GuidanceConfig's own checks against this run, each error named by its key
    for check, key in ((g.check_loss, "guidance.loss.geometry_grad"),
                       (lambda: g.schedule(s.num_inference_steps), "guidance.repeats / guidance.time_travel"),
                       (lambda: g.anchor_chunks(s.num_frames, model.temporal_compression), "guidance.anchors")):
        try:
            check()
        except ValueError as err:
            raise ValueError(f"invalid value for config key {key!r}: {err}") from None
    try:
        check_run_for_guidance(cfg.run, g.decoder)
    except OptionError as err:
        raise ValueError(f"invalid value for config key 'run.{err.key}': {err}") from None
    if cfg.search.enabled:
        try:
            cfg.search.steps(s.num_inference_steps)
        except ValueError as err:
            raise ValueError(f"invalid value for config key 'search.resample_steps': {err}") from None
        _require(not cfg.run.split_cfg, "run.split_cfg", "splits one video's CFG batch over two devices; a search "
                                                         "deals its particles over run.devices instead: use false")
    _require(bool(cfg.output.dir), "output.dir", "must not be empty")
    name = cfg.output.name
    _require(
        name is None or not re.search(r"[/\\]", name),
        "output.name",
        f"must be a file name without folders (the files go to output.dir), got {name!r}",
    )


def config_to_dict(cfg: GeCoConfig) -> dict[str, Any]:
    """Plain, JSON-serialisable dict of a config (for sidecars)."""
    return OmegaConf.to_container(OmegaConf.structured(cfg), resolve=True)


def config_to_yaml(cfg: GeCoConfig) -> str:
    return OmegaConf.to_yaml(OmegaConf.structured(cfg))
