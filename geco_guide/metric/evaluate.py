"""Score any video with GeCo: ``python -m geco_guide.evaluate VIDEO [VIDEO ...|DIR]``.

    python -m geco_guide.evaluate clip.mp4 --maps                 # VGGT-1B + UFM-Base from the hub
    python -m geco_guide.evaluate videos/ --vggt /data/VGGT-1B --ufm /data/UFM-Base --out scores
    python -m geco_guide.evaluate --preset tiny clip.mp4 frames/   # tiny random models, CPU, offline
    python -m geco_guide.evaluate clip.mp4 --model cogvideox-5b    # timed at the model's native 16 fps

The GeCo-Eval protocol (:class:`~geco_guide.config.EvaluationConfig`, the paper and its published
evaluation script): the clip, timed at the model's native frame rate (``--model``), ``--fps`` or
the file's, is covered by ``ceil(T / 3 s)`` overlapping windows of 3 s (more than 4 -> exactly 4
equal windows), each sampled on a time grid at ``min(8, fps)`` fps; GeCo runs on each window with
every ordered frame pair. A frame's map is the pixel-wise mean over its pairs, its score the mean
over valid pixels, a window's score the mean over its frames, and the clip's the windows'
frame-weighted mean. Total Motion / Mean Motion come from the flow between consecutive frames of
the whole clip's time grid.

Per video: ``<out>/<stem>.geco.json`` and with ``--maps`` ``<out>/<stem>.maps.mp4`` (source |
motion | structure | fused on the fixed colour scale of :data:`geco_guide.video.MAP_RANGE`, with
a legend). Several inputs (or a folder of videos) add ``<out>/geco_scores.csv`` (one row per
video, failures with an ``error``) and ``<out>/geco_summary.json`` (means over videos). Every
output is written atomically. A bad input is one error line and does not stop the others; the
exit code is non-zero only when every input failed (2 for a bad config or unavailable weights).
"""

from __future__ import annotations

import argparse
import csv
import io
import math
import os
import re
import sys
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Callable

import torch
from omegaconf import DictConfig, OmegaConf
from torch import Tensor

from .. import __version__
from ..config import GeCoConfig, load_config
from ..estimators import EstimatorsConfig, estimator_id, load_estimators
from ..io.devices import check_device
from ..io.files import write_json_atomic, write_text_atomic
from ..io.video import (
    IMAGE_SUFFIXES,
    VIDEO_SUFFIXES,
    VideoFrames,
    frame_files,
    read_frames,
    write_video,
)
from ..loss.geco import (
    CUES,
    PAIR_MODES,
    GeCoLoss,
    GeCoLossConfig,
    GeCoMaps,
    GeCoResult,
    frame_pairs,
    geco_from_geometry,
)
from ..loss.motion_stats import motion_statistics
from ..types import Correspondences, SceneGeometry, check_frame_values
from .protocol import (
    EvaluationConfig,
    Window,
    evaluation_windows,
    motion_grid,
    sampled_rate,
)
from .render import colorbar, colorize, side_by_side, text_scale, text_strip

MAP_PANELS = ("source", "motion", "structure", "fused")
PAPER_NAMES = {
    "motion": "M_motion",
    "structure": "M_struct",
    "fused": "M_geo",
    "total_motion": "Total Motion (%)",
    "mean_motion": "Mean Motion (%/s)",
}


@dataclass
class EvaluationMaps(GeCoMaps):
    """The frame maps of every evaluated frame (``N`` of them, in time order), on the CPU.

    Attributes:
        motion, structure, fused: ``[N, H, W]`` the frame maps (mean over the frame's pairs),
            with their ``*_valid`` masks, as in :class:`~geco_guide.loss.geco.GeCoMaps`.
        frames: ``[N, 3, H, W]`` the evaluated frames.

    ``maps[k]`` is a dict of frame ``k``'s ``frame [3, H, W]`` and maps ``[H, W]``.
    """

    frames: Tensor

    def __len__(self) -> int:
        return self.frames.shape[0]

    def __getitem__(self, k: int) -> dict[str, Tensor]:
        return {"frame": self.frames[k], **{name: getattr(self, name)[k] for name in _MAP_FIELDS}}


_MAP_FIELDS = tuple(f.name for f in fields(GeCoMaps))


@dataclass
class EvaluationResult:
    """GeCo scores of one video.

    Attributes:
        motion, structure, fused: M_motion, M_struct, M_geo: means of the frame scores over
            evaluated frames with valid pixels (frame-weighted over windows); NaN if none.
        total_motion: Total Motion (%): the flow magnitude over the image diagonal, summed over
            consecutive frames of the clip's time grid (:func:`geco_guide.video.motion_grid`).
        mean_motion: Mean Motion (%/s): Total Motion over the clip's duration.
        frame_scores: per evaluated frame and window ``{index, time_s, window, motion, structure,
            fused}`` (source frame index; a score is ``None`` when the frame has no valid pixel;
            overlapping windows score a frame once each).
        windows: per window ``{start_s, length_s, frames, motion, structure, fused}`` (``frames``:
            source indices).
        num_frames: frames in the source video.
        fps: the frame rate the protocol used; fps_source: where it came from (``--fps``,
            ``model <name>``, ``file``, ``default``); sampled_fps: the windows' sampling rate.
        estimators: ``{geometry, flow}`` ids.
        config: the :class:`EvaluationConfig` used, as a dict.
        source: the input path, ``None`` for a tensor.
        maps: :class:`EvaluationMaps` when asked for (``maps=True``).
    """

    motion: float
    structure: float
    fused: float
    total_motion: float
    mean_motion: float
    frame_scores: list[dict[str, Any]]
    windows: list[dict[str, Any]]
    num_frames: int
    fps: float
    fps_source: str
    sampled_fps: float
    estimators: dict[str, str]
    config: dict[str, Any]
    source: str | None = None
    maps: EvaluationMaps | None = field(default=None, repr=False)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (no tensors; NaN scores become ``None``)."""
        data = {name: _number(getattr(self, name)) for name in ("motion", "structure", "fused", "total_motion", "mean_motion")}
        return {
            "source": self.source,
            **data,
            "paper_names": PAPER_NAMES,
            "num_frames": self.num_frames,
            "num_evaluated_frames": len(self.frame_scores),
            "fps": self.fps,
            "fps_source": self.fps_source,
            "duration_s": self.num_frames / self.fps,
            "sampled_fps": self.sampled_fps,
            "windows": self.windows,
            "frame_scores": self.frame_scores,
            "estimators": self.estimators,
            "config": self.config,
        }


def _number(value: float) -> float | None:
    return value if math.isfinite(value) else None


def _mean(values: list[float]) -> float:
    return sum(values) / len(values) if values else math.nan


def estimator_device(*estimators: Any) -> torch.device:
    """Where the estimators' weights live (frames go there); CPU for weightless ones (oracles)."""
    for estimator in estimators:
        if isinstance(estimator, torch.nn.Module):
            for tensor in estimator.parameters():
                return tensor.device
    return torch.device("cpu")


def pair_correspondences(metric: GeCoLoss, frames: Tensor, pairs: list[tuple[int, int]], batch_size: int, device: torch.device) -> Correspondences:
    """Flow + covisibility of ``pairs`` of ``frames [S, 3, H, W]``, ``batch_size`` pairs per
    estimator call; only the frames a batch uses are moved to ``device``.
    Returns flow ``[P, 2, H, W]`` and covisibility ``[P, H, W]`` on ``device``."""
    flows, covis = [], []
    for start in range(0, len(pairs), batch_size):
        chunk = pairs[start : start + batch_size]
        used = sorted({k for pair in chunk for k in pair})
        local = {k: n for n, k in enumerate(used)}
        subset = frames[used][None].to(device)
        result = metric.estimate_correspondences(subset, [(local[i], local[j]) for i, j in chunk])
        flows.append(result.flow)
        covis.append(result.covisibility)
    return Correspondences(flow=torch.cat(flows), covisibility=torch.cat(covis))


@torch.no_grad()
def score_frames(frames: Tensor, geometry: Any, flow: Any, config: GeCoLossConfig,
                 pairs: list[tuple[int, int]] | None = None, flow_batch_size: int = 16) -> tuple[SceneGeometry, GeCoResult]:
    """GeCo of one clip ``frames [S, 3, H, W]`` in ``[0, 1]`` (a batch of 1) over ``pairs``
    (default: ``config.pairs``): one geometry call, the flow ``flow_batch_size`` pairs per call.
    Returns the estimated geometry and the :class:`GeCoResult`."""
    device = estimator_device(geometry, flow)
    pairs = pairs if pairs is not None else frame_pairs(frames.shape[0], config.pairs)
    scene = geometry.estimate_geometry(frames[None].to(device))
    correspondences = pair_correspondences(GeCoLoss(geometry, flow, config), frames, pairs, flow_batch_size, device)
    return scene, geco_from_geometry(scene, correspondences, pairs, config)


def _split_config(config: EvaluationConfig | GeCoConfig | None) -> tuple[EvaluationConfig, EstimatorsConfig]:
    if config is None:
        return EvaluationConfig(), EstimatorsConfig()
    if isinstance(config, GeCoConfig):
        return config.evaluation, config.estimators
    if isinstance(config, EvaluationConfig):
        return config, EstimatorsConfig()
    raise ValueError(f"config must be an EvaluationConfig or a GeCoConfig, got {type(config).__name__}")


def _protocol_frames(cfg: EvaluationConfig) -> Callable[[int, float], list[int]]:
    """The frame selector of the protocol: every window's frames and the motion grid."""

    def select(num_frames: int, fps: float) -> list[int]:
        if num_frames < 2:
            return list(range(num_frames))
        windows = evaluation_windows(num_frames, fps, cfg.window_seconds, cfg.max_windows, cfg.max_fps)
        return sorted({i for w in windows for i in w.indices} | set(motion_grid(num_frames, fps, cfg.max_fps)))

    return select


def protocol_fps(fps: float | None, model: str | None, cfg: EvaluationConfig) -> tuple[float | None, str]:
    """The frame rate the protocol uses and why: ``fps`` (``--fps``) over the model's native rate
    (``--model``, :attr:`EvaluationConfig.model_fps`) over the file's (``None`` here: read later)."""
    if fps is not None:
        if not (fps > 0 and math.isfinite(fps)):
            raise ValueError(f"fps must be a finite number > 0, got {fps}")
        return float(fps), "--fps"
    if model is not None:
        return cfg.fps_of_model(model), f"model {model}"
    return None, "file"  # replaced by the reader's answer: file or default


def _load_frames(video: str | os.PathLike | Tensor, fps: float | None, cfg: EvaluationConfig) -> tuple[VideoFrames, str | None]:
    select = _protocol_frames(cfg)
    if isinstance(video, Tensor):
        if video.ndim != 4 or video.shape[1] != 3 or not video.is_floating_point():
            raise ValueError(f"video must be a float [S, 3, H, W] tensor in [0, 1], got {list(video.shape)} {video.dtype}")
        if fps is None:
            raise ValueError("fps (> 0) is required when video is a tensor")
        if video.shape[0] < 2:
            raise ValueError(f"video must hold at least 2 frames, got {video.shape[0]}")
        indices = select(video.shape[0], fps)
        return VideoFrames(video.detach()[indices].float().cpu(), indices, float(fps), video.shape[0]), None
    clip = read_frames(video, fps=fps, default_fps=cfg.default_fps, select=select, min_frames=2)
    return clip, str(video)


def _window_record(window: Window, rows: list[dict[str, Any]]) -> dict[str, Any]:
    """A window's scores: the mean over its frames with valid pixels, per cue."""
    return {
        "start_s": window.start_s,
        "length_s": window.length_s,
        "frames": list(window.indices),
        **{name: _number(_mean([r[name] for r in rows if r[name] is not None])) for name in CUES},
    }


def _clip_score(windows: list[dict[str, Any]], name: str) -> float:
    """Windows' scores of cue ``name`` averaged with their frame counts as weights (the script's
    frame-weighted mean), over windows with a score."""
    scored = [(w[name], len(w["frames"])) for w in windows if w[name] is not None]
    total = sum(weight for _, weight in scored)
    return sum(value * weight for value, weight in scored) / total if total else math.nan


@torch.no_grad()
def evaluate_video(
    video: str | os.PathLike | Tensor,
    *,
    geometry: Any = None,
    flow: Any = None,
    config: EvaluationConfig | GeCoConfig | None = None,
    fps: float | None = None,
    model: str | None = None,
    maps: bool = False,
) -> EvaluationResult:
    """GeCo scores of a video under the GeCo-Eval protocol (:class:`EvaluationConfig`).

    The clip is covered by overlapping windows of ~3 s (at most 4), each sampled at
    ``min(8, fps)`` fps; GeCo runs on each window (all ordered pairs by default); a frame's score
    is the mean of its map over valid pixels, a window's the mean over its frames, the clip's the
    windows' frame-weighted mean. Total / Mean Motion come from consecutive frames of the clip's
    time grid.

    Args:
        video: a path (mp4 or another ffmpeg format, gif, folder of png/jpg frames) or frames
            ``[S, 3, H, W]`` in ``[0, 1]`` (then ``fps`` or ``model`` is required).
        geometry, flow: a :class:`GeometryEstimator` / :class:`FlowEstimator`; built from the
            config's estimators when ``None`` (pass them to score many videos with one load).
        config: an :class:`EvaluationConfig`, or a whole :class:`GeCoConfig` (its ``evaluation``
            and ``estimators``); ``None``: defaults (VGGT-1B + UFM-Base).
        fps: the source frame rate, overriding everything else.
        model: a model name of ``config.model_fps`` (e.g. ``cogvideox-5b``): its native frame
            rate replaces the file's (the paper's protocol); ``fps`` still wins.
        maps: keep the per-frame maps (:class:`EvaluationMaps`) for :func:`write_maps_video`.

    Raises:
        VideoReadError: unreadable input or fewer than 2 frames (a ValueError).
        ValueError: evaluated frames with NaN/inf values or outside ``[0, 1]``, naming them; an
            unknown ``model``.
    """
    cfg, estimators_cfg = _split_config(config)
    rate, fps_source = protocol_fps(fps, model, cfg)
    clip, source = _load_frames(video, rate, cfg)
    if rate is None:
        fps_source = clip.fps_source  # the file's rate, or default_fps for inputs without one
    # NaN pixels would score NaN (or 0.0 once masked), 0-255 frames garbage: refuse them, by index.
    check_frame_values(clip.frames, "video" if source is None else source, indices=clip.indices)
    if geometry is None or flow is None:
        loaded = load_estimators(estimators_cfg, cfg.device)
        geometry = geometry if geometry is not None else loaded[0]
        flow = flow if flow is not None else loaded[1]
    device = estimator_device(geometry, flow)
    metric = GeCoLoss(geometry, flow, cfg.loss)
    position = {index: k for k, index in enumerate(clip.indices)}

    def frames_of(indices: list[int]) -> Tensor:
        return clip.frames[[position[i] for i in indices]]

    frame_scores: list[dict[str, Any]] = []
    windows: list[dict[str, Any]] = []
    kept_maps: list[list[Tensor]] = []
    kept_frames: list[Tensor] = []
    for w, window in enumerate(evaluation_windows(clip.num_frames, clip.fps, cfg.window_seconds, cfg.max_windows, cfg.max_fps)):
        window_frames = frames_of(window.indices)
        _, result = score_frames(window_frames, geometry, flow, cfg.loss, flow_batch_size=cfg.flow_batch_size)
        rows = []
        for k, index in enumerate(window.indices):
            scores = {
                name: float(result.frame_scores[name][0, k]) if bool(result.frame_has_valid[name][0, k]) else None
                for name in CUES
            }
            rows.append({"index": index, "time_s": index / clip.fps, "window": w, **scores})
        frame_scores.extend(rows)
        windows.append(_window_record(window, rows))
        if maps:
            kept_maps.append([getattr(result.frame_maps, name)[0].cpu() for name in _MAP_FIELDS])
            kept_frames.append(window_frames)

    grid = motion_grid(clip.num_frames, clip.fps, cfg.max_fps)
    steps = [(k, k + 1) for k in range(len(grid) - 1)]
    consecutive = pair_correspondences(metric, frames_of(grid), steps, cfg.flow_batch_size, device)
    stats = motion_statistics(
        consecutive.flow.float(), consecutive.covisibility > cfg.loss.covisibility_threshold,
        duration_s=clip.num_frames / clip.fps,
    )
    evaluation_maps = None
    if maps:
        stacked = [torch.cat(parts) if parts[0].dtype == torch.bool else torch.cat(parts).float() for parts in zip(*kept_maps)]
        evaluation_maps = EvaluationMaps(*stacked, frames=torch.cat(kept_frames))
    return EvaluationResult(
        **{name: _clip_score(windows, name) for name in CUES},
        total_motion=stats.total_motion,
        mean_motion=stats.mean_motion,
        frame_scores=frame_scores,
        windows=windows,
        num_frames=clip.num_frames,
        fps=clip.fps,
        fps_source=fps_source,
        sampled_fps=sampled_rate(clip.fps, cfg.max_fps),
        estimators={"geometry": estimator_id(geometry), "flow": estimator_id(flow)},
        config=asdict(cfg),
        source=source,
        maps=evaluation_maps,
    )


# --------------------------------------------------------------------------------------------
# maps video


def _score_text(value: float | None) -> str:
    return "N/A" if value is None else f"{value:.3f}"


def render_maps(result: EvaluationResult) -> Tensor:
    """The frames of the maps video: ``[N, 3, H', W']``.

    Rows: labelled panels source | motion | structure | fused (:func:`side_by_side`, viridis on
    the fixed :data:`~geco_guide.video.MAP_RANGE`, grey = no valid pixel), the legend
    (:func:`colorbar`), and a line with the frame's time and scores.
    """
    if result.maps is None:
        raise ValueError("the result holds no maps: evaluate with maps=True")
    m = result.maps
    heat = [colorize(getattr(m, name), getattr(m, f"{name}_valid")) for name in MAP_PANELS[1:]]
    grid = side_by_side([m.frames, *heat], [name.upper() for name in MAP_PANELS])
    num, _, _, width = grid.shape
    scale = text_scale(m.frames.shape[-2])
    legend = colorbar(width, scale)[None].expand(num, -1, -1, -1)
    lines = []
    for row in result.frame_scores:
        text = (
            f"T={row['time_s']:.2f}S FUSED {_score_text(row['fused'])} MOTION {_score_text(row['motion'])} "
            f"STRUCTURE {_score_text(row['structure'])}"
        )
        lines.append(text_strip(text, width, scale))
    return torch.cat((grid, legend, torch.stack(lines)), dim=-2)


def write_maps_video(result: EvaluationResult, path: str | os.PathLike) -> Path:
    """Render :func:`render_maps` as an mp4 at the evaluated frame rate, atomically."""
    return write_video(path, render_maps(result), fps=result.sampled_fps)


def write_detection_video(video: str | os.PathLike, stem: Path, geometry: Any, flow: Any, cfg: GeCoConfig) -> Path:
    """``<stem>.detection.mp4``: the per-frame detection maps of every frame of ``video``
    (:mod:`geco_guide.detection`, its defaults: a 20-frame window centred on the frame)."""
    from .detection import (
        detection_maps,
        frame_scores,
        render_detection,
        write_detection,
    )

    clip = read_frames(video, default_fps=cfg.evaluation.default_fps, min_frames=2)
    maps = detection_maps(clip.frames, geometry, flow, cfg.evaluation.loss, flow_batch_size=cfg.evaluation.flow_batch_size)
    (path,) = write_detection(render_detection(maps, frame_scores(maps)), stem, ["mp4"], clip.fps)
    return path


# --------------------------------------------------------------------------------------------
# CLI


@dataclass
class _Input:
    """One video to score (a file or a frame folder), or an input that already failed."""

    path: Path
    name: str
    error: str | None = None


def _holds_frames(folder: Path) -> bool:
    return bool(frame_files(folder))


def expand_inputs(paths: list[str]) -> list[_Input]:
    """Command-line inputs -> videos. A folder with png/jpg frames is one video; any other
    folder stands for its video files and frame sub-folders (one level), and is an error when it
    holds none. Names (output stems) are made unique with ``-2``, ``-3``, ..."""
    items: list[_Input] = []
    for arg in paths:
        path = Path(arg)
        if path.is_dir() and not _holds_frames(path):
            entries = sorted(p for p in path.iterdir() if not p.name.startswith("."))
            videos = [p for p in entries if (p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES) or (p.is_dir() and _holds_frames(p))]
            if not videos:
                kinds = "/".join(s.lstrip(".") for s in VIDEO_SUFFIXES + IMAGE_SUFFIXES)
                items.append(_Input(path, path.name or str(path), f"folder {str(path)!r} holds no video ({kinds})"))
            items.extend(_Input(p, p.stem if p.is_file() else p.name) for p in videos)
        else:
            items.append(_Input(path, path.stem if path.suffix else path.name))
    seen: dict[str, int] = {}
    for item in items:
        count = seen.get(item.name, 0)
        seen[item.name] = count + 1
        if count:
            item.name = f"{item.name}-{count + 1}"
    return items


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    message = text[0] if text else ""
    return message if isinstance(err, ValueError) else f"{type(err).__name__}: {message}"


CSV_COLUMNS = (
    "name", "path", "fused", "motion", "structure", "total_motion", "mean_motion",
    "num_frames", "fps", "fps_source", "sampled_fps", "num_windows", "json", "error",
)
SUMMARY_KEYS = ("fused", "motion", "structure", "total_motion", "mean_motion")


def _write_table(out: Path, rows: list[dict[str, Any]], estimators: dict[str, str], config: dict[str, Any]) -> tuple[Path, Path]:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({key: "" if row.get(key) is None else row[key] for key in CSV_COLUMNS})
    csv_path = write_text_atomic(out / "geco_scores.csv", buffer.getvalue())
    ok = [row for row in rows if row.get("error") is None]
    summary = {
        "num_videos": len(rows),
        "num_ok": len(ok),
        "num_failed": len(rows) - len(ok),
        "mean": {key: _number(_mean([row[key] for row in ok if row[key] is not None])) for key in SUMMARY_KEYS},
        "paper_names": PAPER_NAMES,
        "videos": [{key: row.get(key) for key in ("name", "path", "json", "error")} for row in rows],
        "estimators": estimators,
        "config": config,
    }
    return csv_path, write_json_atomic(out / "geco_summary.json", summary)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m geco_guide.evaluate",
        description="Score videos with GeCo (M_motion, M_struct, M_geo, Total/Mean Motion).",
    )
    p.add_argument("--version", action="version", version=f"geco_guide {__version__}")
    p.add_argument("inputs", nargs="+", metavar="VIDEO|DIR|key=value",
                   help="video files (mp4, gif, ...), folders of frames or of videos; key=value config overrides")
    p.add_argument("--preset", default=None, help="a preset of configs/ (tiny: tiny random models, CPU)")
    p.add_argument("--config", default=None, help="YAML config file (applied after --preset)")
    p.add_argument("--vggt", default=None, metavar="ID_OR_DIR", help="geometry estimator: hub id or local folder")
    p.add_argument("--ufm", default=None, metavar="ID_OR_DIR", help="flow estimator: hub id or local folder")
    p.add_argument("--model", default=None, metavar="NAME",
                   help="the video model that made the inputs (e.g. cogvideox-5b): its native frame rate "
                        "(evaluation.model_fps, the paper's table) replaces the file's")
    p.add_argument("--fps", type=float, default=None, help="source frame rate, overriding --model and the file's")
    p.add_argument("--out", default=None, help="output folder (default: the config's output.dir)")
    p.add_argument("--maps", action="store_true", help="also write <stem>.maps.mp4 with the heat maps")
    p.add_argument("--detection", action="store_true",
                   help="also write <stem>.detection.mp4: every frame's own maps against a window of 20 frames "
                        "around it (python -m geco_guide.detection for the window, anchor and formats)")
    p.add_argument("--pairs", choices=PAIR_MODES, default=None,
                   help="frame pairs per window: all (default, the paper's script: n(n-1) flow pairs for n frames), "
                        "center (2(n-1)) or adjacent (n-1)")
    return p


_OVERRIDE = re.compile(r"^[A-Za-z_][\w.]*=")


def _is_config_key(key: str) -> bool:
    """Whether ``key`` (dotted) names a config option, or an entry of a free mapping such as
    ``evaluation.model_fps.<model>``."""
    node: Any = OmegaConf.structured(GeCoConfig)
    for part in key.split("."):
        if not isinstance(node, DictConfig):
            return False
        if part not in node:
            return OmegaConf.get_type(node) is dict
        node = node[part]
    return True


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_intermixed_args(argv)  # options may follow the inputs
    # key=value arguments are overrides unless they name an existing file.
    overrides = [a for a in args.inputs if _OVERRIDE.match(a) and not Path(a).exists()]
    videos = [a for a in args.inputs if a not in overrides]
    # Neither an input nor an option (a=b.mp4): a missing file, or a mistyped key.
    strays = [a for a in overrides if not _is_config_key(a.partition("=")[0])]
    for option, key in ((args.vggt, "estimators.geometry"), (args.ufm, "estimators.flow"), (args.pairs, "evaluation.loss.pairs")):
        if option is not None:
            overrides.append(f"{key}={option}")
    try:
        if strays:
            raise ValueError(f"{strays[0]!r} is neither an existing file nor a config override "
                             f"({strays[0].partition('=')[0]!r} is not a config key)")
        if not videos:
            raise ValueError("no input video given")
        if args.fps is not None and not (args.fps > 0 and math.isfinite(args.fps)):
            raise ValueError(f"--fps must be a finite number > 0, got {args.fps}")
        cfg = load_config(args.config, args.preset, overrides)
        if args.model is not None:
            cfg.evaluation.fps_of_model(args.model)  # an unknown name fails before the estimators load
        check_device(cfg.evaluation.device, "evaluation.device")
        geometry, flow = load_estimators(cfg.estimators, cfg.evaluation.device)
    except (ValueError, FileNotFoundError) as err:  # WeightsNotFoundError is a FileNotFoundError
        print(f"error: {err}", file=sys.stderr)
        return 2

    out = Path(args.out if args.out is not None else cfg.output.dir)
    items = expand_inputs(videos)
    rows: list[dict[str, Any]] = []
    for item in items:
        row: dict[str, Any] = {"name": item.name, "path": str(item.path), "error": item.error}
        if item.error is None:
            try:
                result = evaluate_video(item.path, geometry=geometry, flow=flow, config=cfg, fps=args.fps,
                                        model=args.model, maps=args.maps)
                json_path = write_json_atomic(out / f"{item.name}.geco.json", result.to_dict())
                maps_note = ""
                if args.maps:
                    maps_note = f", maps {write_maps_video(result, out / f'{item.name}.maps.mp4')}"
                if args.detection:
                    maps_note += f", detection maps {write_detection_video(item.path, out / item.name, geometry, flow, cfg)}"
            except Exception as err:  # one bad input must not stop the others
                row["error"] = _one_line(err)
            else:
                row.update({key: _number(getattr(result, key)) for key in SUMMARY_KEYS})
                row.update(num_frames=result.num_frames, fps=result.fps, fps_source=result.fps_source,
                           sampled_fps=result.sampled_fps,
                           num_windows=len(result.windows), json=str(json_path))
                print(
                    f"{item.name}: M_geo={result.fused:.4f} M_motion={result.motion:.4f} M_struct={result.structure:.4f} "
                    f"TM={result.total_motion:.2f}% MM={result.mean_motion:.2f}%/s "
                    f"({len(result.windows)} windows at {result.sampled_fps:g} fps, source {result.fps:g} fps "
                    f"from {result.fps_source}) "
                    f"-> {json_path}{maps_note}"
                )
        if row["error"] is not None:
            print(f"error: {item.path}: {row['error']}", file=sys.stderr)
        rows.append(row)

    if len(items) > 1 or any(Path(v).is_dir() and not _holds_frames(Path(v)) for v in videos):
        estimators = {"geometry": estimator_id(geometry), "flow": estimator_id(flow)}
        csv_path, summary_path = _write_table(out, rows, estimators, asdict(cfg.evaluation))
        print(f"wrote {csv_path} and {summary_path}")
    return 1 if all(row["error"] is not None for row in rows) else 0

