"""Static scenes with known geometry, ray-cast in torch, and artifacts with known masks.

A :class:`Scene` is a set of axis-aligned boxes (seen from outside, or from inside for a room)
and infinite planes with smooth procedural textures. :func:`render_clip` moves a camera through
it and returns a :class:`SyntheticClip`: frames, z-depth, intrinsics, camera-from-world
extrinsics, and ground-truth correspondences (flow and covisibility) for any frame pair.

Artifacts with known ground truth turn a rigid clip into an inconsistent one:

* :func:`inject_deformation` — a temporally smooth thin-plate-spline warp of an image region
  (affine + ``r^2 log r`` basis, feathered weight, exponential moving average over time), as in
  the GeCo paper's WarpBench, with the maths of :mod:`geco_guide.bench.warp`;
* :func:`occlusion_swap_clip` — an object that is visible, then hidden behind an occluder, then
  re-revealed as a different object, as in the paper's OccluBench, in 3D (a pillar's parallax);
* :func:`deform_mover` — the same warp applied to a moving object alone, following it through
  the clip (a mover that changes shape while it moves);
* :func:`with_warp` / :func:`with_overlay` — the benchmark builders' edits
  (:mod:`geco_guide.bench.warp`, :mod:`geco_guide.bench.occlusion`) applied to a synthetic clip with their
  exact ground truth, so oracle estimators can score them.

Everything uses the conventions of :mod:`geco_guide.geometry`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from ..geometry import (
    inside_image,
    invert_rigid,
    pixel_grid,
    project,
    relative_pose,
    rigid_flow,
    sample_bilinear,
    transform_points,
    unproject,
)
from ..types import Correspondences, SceneGeometry
from .occlusion import OBJECT, OCCLUDER, OcclusionResult

# thin_plate_spline is part of this module's interface (the deformation injector's maths).
from .warp import (
    WarpResult,
    backward_warp,
    control_displacements,
    raised_cosine,
    thin_plate_spline,
    warp_fields,
)

__all__ = ["MovingBox", "SyntheticClip", "default_intrinsics", "deform_mover", "drawn_mover", "inject_deformation",
           "look_at",
           "moving_boxes", "moving_clip",
           "occlusion_swap_clip", "orbit_cameras", "rigid_clip", "thin_plate_spline", "with_overlay",
           "with_warp"]

_NO_HIT = float("inf")


@dataclass
class Box:
    """Axis-aligned box ``[lo, hi]`` in world coordinates.

    ``inside=True`` renders its inner faces (a room around the camera). ``texture_shift`` moves
    the texture with a box that has been translated by it (a moving object keeps its pattern),
    ``texture_scale`` stretches it with a box scaled by it per axis (about the world origin, before
    the shift): a point ``p`` shows the pattern at ``(p - texture_shift) / texture_scale``.
    """

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    color: tuple[float, float, float]
    inside: bool = False
    frequency: float = 3.0
    texture_shift: tuple[float, float, float] = (0.0, 0.0, 0.0)
    texture_scale: tuple[float, float, float] = (1.0, 1.0, 1.0)


@dataclass
class Plane:
    """Infinite plane ``{x : n . x = offset}``."""

    normal: tuple[float, float, float]
    offset: float
    color: tuple[float, float, float]
    frequency: float = 2.0


@dataclass
class Scene:
    """A static scene: the union of its boxes and planes."""

    boxes: list[Box] = field(default_factory=list)
    planes: list[Plane] = field(default_factory=list)

    def primitives(self) -> list[Box | Plane]:
        return [*self.boxes, *self.planes]


def _box_hit(origins: Tensor, dirs: Tensor, box: Box) -> Tensor:
    """Ray parameter of the first hit with ``box`` (slab method), inf where missed. ``[N]``."""
    lo = dirs.new_tensor(box.lo)
    hi = dirs.new_tensor(box.hi)
    safe = torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    t0 = (lo - origins) / safe
    t1 = (hi - origins) / safe
    t_near = torch.minimum(t0, t1).amax(-1)
    t_far = torch.maximum(t0, t1).amin(-1)
    hit = t_far >= t_near
    t = t_far if box.inside else t_near
    return torch.where(hit & (t > 1e-6), t, torch.full_like(t, _NO_HIT))


def _plane_hit(origins: Tensor, dirs: Tensor, plane: Plane) -> Tensor:
    normal = dirs.new_tensor(plane.normal)
    denom = dirs @ normal
    safe = torch.where(denom.abs() < 1e-12, torch.full_like(denom, 1e-12), denom)
    t = (plane.offset - origins @ normal) / safe
    return torch.where(t > 1e-6, t, torch.full_like(t, _NO_HIT))


def raycast(scene: Scene, origins: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
    """First hit of rays ``origins + t dirs``.

    Args:
        origins: ``[N, 3]`` world points.
        dirs: ``[N, 3]`` directions (not necessarily unit; ``t`` is in their units).

    Returns:
        ``t [N]`` (inf where nothing is hit) and the index ``[N]`` of the primitive hit (-1).
    """
    hits = [
        _box_hit(origins, dirs, p) if isinstance(p, Box) else _plane_hit(origins, dirs, p)
        for p in scene.primitives()
    ]
    t, index = torch.stack(hits, dim=-1).min(dim=-1)
    return t, torch.where(torch.isfinite(t), index, torch.full_like(index, -1))


def _texture(points: Tensor, primitive: Box | Plane) -> Tensor:
    """Smooth colourful pattern ``[N, 3]`` in ``[0, 1]`` from world points ``[N, 3]``."""
    f = primitive.frequency
    if isinstance(primitive, Box) and any(primitive.texture_shift):
        points = points - points.new_tensor(primitive.texture_shift)
    if isinstance(primitive, Box) and any(scale != 1.0 for scale in primitive.texture_scale):
        points = points / points.new_tensor(primitive.texture_scale)
    x, y, z = points.unbind(-1)
    pattern = (
        torch.sin(f * (1.3 * x + 0.7 * y) + 0.5)
        + torch.sin(f * (0.9 * y - 1.1 * z) + 1.7)
        + torch.sin(f * (1.7 * z + 0.6 * x) + 2.9)
    ) / 3.0
    base = points.new_tensor(primitive.color)
    return (base * (0.65 + 0.35 * pattern[:, None]) + 0.05 * torch.sin(3.1 * f * x)[:, None]).clamp(0, 1)


def look_at(eye: Tensor, target: Tensor, up: Tensor | None = None) -> Tensor:
    """Camera-from-world ``[3, 4]`` of a camera at ``eye`` looking at ``target`` (OpenCV axes)."""
    up = up if up is not None else eye.new_tensor([0.0, -1.0, 0.0])
    forward = F.normalize(target - eye, dim=0)
    right = F.normalize(torch.linalg.cross(forward, up), dim=0)
    down = torch.linalg.cross(forward, right)
    rot = torch.stack((right, down, forward), dim=0)  # rows: camera axes in world coordinates
    return torch.cat((rot, -(rot @ eye)[:, None]), dim=1)


def default_intrinsics(height: int, width: int, fov_x_deg: float = 60.0, dtype=torch.float64) -> Tensor:
    """Pinhole ``K [3, 3]`` with the principal point at the image centre ``((W-1)/2, (H-1)/2)``."""
    focal = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    return torch.tensor(
        [[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]], dtype=dtype
    )


@dataclass
class Overlay:
    """Image-space layers over a rendered scene (:mod:`geco_guide.bench.occlusion`'s composite).

    Attributes:
        labels: ``[S, H, W]`` int64, the layer each pixel shows (0: the scene).
        offsets: ``[L, S, 2]`` each layer's translation in each frame (row 0 unused).
    """

    labels: Tensor
    offsets: Tensor

    def correspondences(self, scene_flow: Tensor, scene_visible: Tensor, source: int, target: int) -> tuple[Tensor, Tensor]:
        """The clip's flow ``[2, H, W]`` and covisibility ``[H, W]`` from the scene's: a layer
        pixel moves with its layer; any pixel is covisible only where the target shows the
        same layer at its destination (nearest pixel)."""
        height, width = scene_flow.shape[-2:]
        labels = self.labels[source]
        layer_flow = (self.offsets[:, target] - self.offsets[:, source]).to(scene_flow.dtype)  # [L, 2]
        on_layer = labels > 0
        flow = torch.where(on_layer[None], layer_flow[labels].permute(2, 0, 1), scene_flow)
        destination = pixel_grid(height, width, dtype=flow.dtype) + flow.permute(1, 2, 0)
        u = destination[..., 0].round().long().clamp(0, width - 1)
        v = destination[..., 1].round().long().clamp(0, height - 1)
        same = inside_image(destination, height, width) & (self.labels[target][v, u] == labels)
        visible = same & (on_layer | (scene_visible > 0.5))
        return flow, visible.to(scene_flow.dtype)


@dataclass
class SyntheticClip:
    """A rendered clip with its ground truth (no batch dimension).

    Attributes:
        frames: ``[S, 3, H, W]`` in ``[0, 1]``.
        depth: ``[S, H, W]`` z-depth.
        intrinsics: ``[S, 3, 3]``.
        extrinsics: ``[S, 3, 4]`` camera-from-world.
        scenes: the scene seen by each frame (one shared object for a static scene).
        mask: ``[S, H, W]`` bool ground-truth artifact mask (all False for a clean clip).
        warp: ``[S, H, W, 2]`` backward warp of each frame, ``frame(p)`` shows the content of the
            unwarped frame at ``p + warp(p)``; zeros for a clean clip.
        overlay: image-space layers composited over the scene (:func:`with_overlay`), or ``None``.
        objects: ``[S, H, W]`` int64, the moving object each pixel shows (-1: the static
            scene), or ``None`` for a static scene (:func:`moving_clip`).
        object_paths: ``[K, S, 3]`` world translation of each moving object in each frame, or ``None``.
        object_scales: ``[K, S, 3]`` per-axis scale of each object in each frame (a point ``m`` of
            the object's frame-0 shape is at ``scale * m + path``), or ``None``: rigid objects.
    """

    frames: Tensor
    depth: Tensor
    intrinsics: Tensor
    extrinsics: Tensor
    scenes: list[Scene]
    mask: Tensor
    warp: Tensor
    overlay: Overlay | None = None
    objects: Tensor | None = None
    object_paths: Tensor | None = None
    object_scales: Tensor | None = None

    @property
    def num_frames(self) -> int:
        return self.frames.shape[0]

    @property
    def dynamic_mask(self) -> Tensor:
        """``[S, H, W]`` bool: pixels showing an object that moves on its own (the true dynamic
        mask; all False for a static scene), under any overlay layer removed."""
        if self.objects is None:
            return torch.zeros_like(self.depth, dtype=torch.bool)
        moving = self.objects >= 0
        return moving if self.overlay is None else moving & (self.overlay.labels == 0)

    def geometry(self, dtype=torch.float32) -> SceneGeometry:
        """Ground-truth :class:`SceneGeometry` with a batch dimension of 1."""
        return SceneGeometry(
            depth=self.depth[None].to(dtype),
            intrinsics=self.intrinsics[None].to(dtype),
            extrinsics=self.extrinsics[None].to(dtype),
        )

    def rigid_correspondences(self, source: int, target: int) -> tuple[Tensor, Tensor]:
        """Flow ``[2, H, W]`` and covisibility ``[H, W]`` of the underlying static scene."""
        rel = relative_pose(self.extrinsics[source][None], self.extrinsics[target][None])
        flow, valid = rigid_flow(self.depth[source][None], self.intrinsics[source][None], self.intrinsics[target][None], rel)
        visible = valid[0] & _visible_from(self, source, target)
        return flow[0], visible.to(flow.dtype)

    def correspondences(self, source: int, target: int) -> tuple[Tensor, Tensor]:
        """True flow ``[2, H, W]`` and covisibility ``[H, W]`` of the clip's content.

        For a warped clip the content at source pixel ``p`` comes from ``q = p + warp_s(p)``; it
        moves rigidly to ``q'`` and is shown in the target at ``r`` with ``r + warp_t(r) = q'``
        (solved by fixed-point iteration). An overlay's layers move by their own offsets and hide
        what lies under them.
        """
        flow, visible = self._scene_correspondences(source, target)
        return (flow, visible) if self.overlay is None else self.overlay.correspondences(flow, visible, source, target)

    def _scene_correspondences(self, source: int, target: int) -> tuple[Tensor, Tensor]:
        """Flow ``[2, H, W]`` and covisibility ``[H, W]`` of the (possibly warped) scene alone."""
        flow, visible = self._content_correspondences(source, target)
        if not self.warp.any():
            return flow, visible
        height, width = flow.shape[-2:]
        grid = pixel_grid(height, width, dtype=flow.dtype)
        q = grid + self.warp[source]
        moved = q + sample_bilinear(flow[None], q[None])[0].permute(1, 2, 0)
        r = moved.clone()
        for _ in range(20):
            r = moved - sample_bilinear(self.warp[target].permute(2, 0, 1)[None], r[None])[0].permute(1, 2, 0)
        covisible = sample_bilinear(visible[None, None], q[None])[0, 0] > 0.5
        covisible = covisible & inside_image(r, height, width) & inside_image(q, height, width)
        return (r - grid).permute(2, 0, 1), covisible.to(flow.dtype)

    def _content_correspondences(self, source: int, target: int) -> tuple[Tensor, Tensor]:
        """Flow ``[2, H, W]`` and covisibility ``[H, W]`` of the rendered scene: the camera's
        rigid flow, and for a moving object's pixels its own translation on top."""
        if self.objects is None:
            return self.rigid_correspondences(source, target)
        height, width = self.depth.shape[-2:]
        ids = self.objects[source].reshape(-1)
        kept = ids.clamp_min(0)
        if self.object_scales is None:
            shift = self.object_paths[kept, target] - self.object_paths[kept, source]
            points = _world_points(self, source) + torch.where((ids >= 0)[:, None], shift, torch.zeros_like(shift))
        else:
            world = _world_points(self, source)
            shape = (world - self.object_paths[kept, source]) / self.object_scales[kept, source]
            moved = shape * self.object_scales[kept, target] + self.object_paths[kept, target]
            points = torch.where((ids >= 0)[:, None], moved, world)
        camera = transform_points(points[None], self.extrinsics[target][None])
        uv, z = project(camera, self.intrinsics[target][None])
        uv = uv[0].reshape(height, width, 2)
        grid = pixel_grid(height, width, dtype=uv.dtype)
        t = _first_hit_beyond(self, points, target).reshape(height, width)
        visible = (self.depth[source] > 0) & (z[0].reshape(height, width) > 0) & inside_image(uv, height, width) & (t >= 1.0 - 1e-6)
        flow = torch.where(visible[..., None], uv - grid, torch.zeros_like(uv))
        return flow.permute(2, 0, 1), visible.to(flow.dtype)

    def pair_correspondences(self, pairs: list[tuple[int, int]], dtype=torch.float32) -> Correspondences:
        """Ground-truth :class:`Correspondences` for ``pairs`` (batch of 1, pair-major)."""
        flows, covis = zip(*(self.correspondences(i, j) for i, j in pairs))
        return Correspondences(flow=torch.stack(flows).to(dtype), covisibility=torch.stack(covis).to(dtype))

    def residual_displacement(self, source: int, target: int) -> Tensor:
        """``[H, W]`` pixel length of true flow minus rigid flow: the non-rigid motion."""
        return (self.correspondences(source, target)[0] - self.rigid_correspondences(source, target)[0]).norm(dim=0)


def _camera_rays(K: Tensor, extrinsics: Tensor, height: int, width: int) -> tuple[Tensor, Tensor]:
    """World origins and directions ``[H*W, 3]`` with unit camera z (so ``t`` is z-depth)."""
    cam_to_world = invert_rigid(extrinsics[None])[0]
    rays_cam = unproject(torch.ones(1, height, width, dtype=K.dtype), K[None])[0].reshape(-1, 3)
    dirs = rays_cam @ cam_to_world[:3, :3].T
    origins = cam_to_world[:3, 3].expand_as(dirs)
    return origins, dirs


def render_view(scene: Scene, K: Tensor, extrinsics: Tensor, height: int, width: int) -> tuple[Tensor, Tensor, Tensor]:
    """Render one view.

    Returns:
        ``image [3, H, W]`` in ``[0, 1]``, ``depth [H, W]`` (0 where nothing is hit) and the
        primitive index ``[H, W]`` (-1 where nothing is hit).
    """
    origins, dirs = _camera_rays(K, extrinsics, height, width)
    t, index = raycast(scene, origins, dirs)
    hit = index >= 0
    points = origins + dirs * torch.where(hit, t, torch.zeros_like(t))[:, None]
    image = torch.zeros_like(points)
    for i, primitive in enumerate(scene.primitives()):
        sel = index == i
        if sel.any():
            image[sel] = _texture(points[sel], primitive)
    depth = torch.where(hit, t, torch.zeros_like(t))
    return image.T.reshape(3, height, width), depth.reshape(height, width), index.reshape(height, width)


def _world_points(clip: SyntheticClip, frame: int) -> Tensor:
    """``[H*W, 3]`` world points of a frame's pixels."""
    points_cam = unproject(clip.depth[frame][None], clip.intrinsics[frame][None])[0].reshape(-1, 3)
    return transform_points(points_cam[None], invert_rigid(clip.extrinsics[frame][None]))[0]


def _first_hit_beyond(clip: SyntheticClip, points: Tensor, frame: int) -> Tensor:
    """``[N]`` ray parameter of the first surface of ``frame``'s scene on the ray from its
    camera to ``points [N, 3]`` (1 = the point itself)."""
    eye = invert_rigid(clip.extrinsics[frame][None])[0, :3, 3]
    t, _ = raycast(clip.scenes[frame], eye.expand_as(points), points - eye)
    return t


def _seen_through(clip: SyntheticClip, points: Tensor, frame: int, margin_px: float = 1.5) -> Tensor:
    """``[N]`` bool: ``frame`` saw a farther surface along its rays to ``points [N, 3]`` and to
    their neighbours ``margin_px`` pixels away, so the verdict holds at pixel resolution."""
    extr = clip.extrinsics[frame]
    depth = transform_points(points[None], extr[None])[0, :, 2].clamp_min(1e-6)
    footprint = (margin_px * depth / clip.intrinsics[frame][0, 0])[:, None]
    right, down = extr[0, :3], extr[1, :3]  # camera axes in world coordinates
    result = torch.ones(points.shape[0], dtype=torch.bool)
    for offset in (0 * right, right, -right, down, -down):
        result &= _first_hit_beyond(clip, points + footprint * offset, frame) > 1.02
    return result


def _visible_from(clip: SyntheticClip, source: int, target: int) -> Tensor:
    """``[H, W]`` bool: the source pixel's surface point is the first hit seen from the target."""
    t = _first_hit_beyond(clip, _world_points(clip, source), target)
    return ((t >= 1.0 - 1e-6) & (clip.depth[source].reshape(-1) > 0)).reshape(clip.depth.shape[-2:])


def render_clip(
    scene: Scene | list[Scene],
    extrinsics: Tensor,
    K: Tensor,
    height: int,
    width: int,
) -> SyntheticClip:
    """Render a clip.

    Args:
        scene: one static scene, or one scene per frame (for artifacts that change the world).
        extrinsics: ``[S, 3, 4]`` camera-from-world per frame.
        K: ``[3, 3]`` or ``[S, 3, 3]`` intrinsics.
        height, width: image size.
    """
    num_frames = extrinsics.shape[0]
    scenes = scene if isinstance(scene, list) else [scene] * num_frames
    if len(scenes) != num_frames:
        raise ValueError(f"got {len(scenes)} scenes for {num_frames} frames")
    K = K.expand(num_frames, 3, 3) if K.ndim == 2 else K
    views = [render_view(s, K[i], extrinsics[i], height, width) for i, s in enumerate(scenes)]
    frames = torch.stack([v[0] for v in views])
    depth = torch.stack([v[1] for v in views])
    return SyntheticClip(
        frames=frames,
        depth=depth,
        intrinsics=K.clone(),
        extrinsics=extrinsics.clone(),
        scenes=scenes,
        mask=torch.zeros_like(depth, dtype=torch.bool),
        warp=torch.zeros(num_frames, height, width, 2, dtype=depth.dtype),
    )


def gallery_scene() -> Scene:
    """Three textured walls facing the camera (a shallow concave triptych), floor and ceiling.

    Every visible surface is a plane seen at a moderate angle and the depth is continuous
    (creases only), so bilinear depth sampling is accurate: the metric's noise floor on this
    scene with ground-truth geometry is ~1e-5.
    """
    return Scene(
        planes=[
            Plane((0.0, 0.0, 1.0), 6.0, (0.8, 0.7, 0.5)),
            Plane((-0.45, 0.0, 0.89), 6.15, (0.5, 0.7, 0.8), frequency=2.5),
            Plane((0.45, 0.0, 0.89), 6.15, (0.7, 0.8, 0.5), frequency=2.5),
            Plane((0.0, 1.0, 0.0), 5.0, (0.6, 0.6, 0.6)),
            Plane((0.0, -1.0, 0.0), 5.0, (0.6, 0.5, 0.6)),
        ]
    )


def orbit_cameras(num_frames: int, *, radius: float = 0.6, sweep_deg: float = 20.0, target=(0.0, 0.0, 5.0), dtype=torch.float64) -> Tensor:
    """``[S, 3, 4]`` cameras on a horizontal arc around ``target``, with a slight vertical bob."""
    target_t = torch.tensor(target, dtype=dtype)
    poses = []
    for k in range(num_frames):
        a = math.radians(sweep_deg) * (k / max(num_frames - 1, 1) - 0.5)
        eye = torch.tensor([radius * math.sin(a) * 4, -0.2 + 0.1 * math.sin(2 * a * 3), radius * (1 - math.cos(a))], dtype=dtype)
        poses.append(look_at(eye, target_t))
    return torch.stack(poses)


def rigid_clip(num_frames: int = 5, height: int = 48, width: int = 64, scene: Scene | None = None) -> SyntheticClip:
    """A rigid clip of ``scene`` (default :func:`gallery_scene`) under an orbiting camera."""
    scene = scene or gallery_scene()
    return render_clip(scene, orbit_cameras(num_frames), default_intrinsics(height, width), height, width)


# --- objects that move on their own -----------------------------------------------------------


@dataclass
class MovingBox:
    """A box that moves on its own: ``box`` where it stands in frame 0, translated by ``velocity``
    (world units per frame) in later frames, its texture moving with it. ``stretch`` makes it
    non-rigid: its size along each axis grows by that fraction of its frame-0 size per frame,
    about its centre (its parts move apart), the texture stretching with it."""

    box: Box
    velocity: tuple[float, float, float]
    stretch: tuple[float, float, float] = (0.0, 0.0, 0.0)


def moving_boxes() -> list[MovingBox]:
    """The default movers of :func:`moving_clip`: a box sliding sideways in front of the left wall
    and a smaller one rising and approaching on the right, together ~10 % of a frame."""
    return [
        MovingBox(Box(lo=(-1.3, 0.1, 3.6), hi=(-0.4, 1.0, 4.4), color=(0.85, 0.3, 0.25), frequency=4.0), (0.15, 0.0, 0.0)),
        MovingBox(Box(lo=(0.6, -0.3, 4.0), hi=(1.2, 0.3, 4.6), color=(0.25, 0.35, 0.85), frequency=5.0), (0.0, -0.1, -0.08)),
    ]


def drawn_mover(seed: int) -> MovingBox:
    """A box moving on its own through :func:`gallery_scene`, drawn from ``seed``: seed 0 is the
    sliding box of :func:`moving_boxes`; any other draws each side (0.3-1.4), the centre (x in
    -1.8..1.8, y in -0.9..0.9, depth 2.2-4.8: in front of the walls, at the view's edges too) and
    a velocity of 0.06-0.35 per frame in any direction (up to 45 degrees in or out of the view), so
    it may leave the view. Slower boxes move less than the automatic masks' 1 px a frame."""
    if seed == 0:
        return moving_boxes()[0]
    generator = torch.Generator().manual_seed(seed)

    def uniform(low: float, high: float) -> float:
        return low + (high - low) * float(torch.rand((), generator=generator, dtype=torch.float64))

    size = [uniform(0.3, 1.4) for _ in range(3)]
    centre = (uniform(-1.8, 1.8), uniform(-0.9, 0.9), uniform(2.2, 4.8))
    speed, heading, elevation = uniform(0.06, 0.35), uniform(-math.pi, math.pi), uniform(-math.pi / 4, math.pi / 4)
    velocity = (speed * math.cos(elevation) * math.cos(heading), speed * math.cos(elevation) * math.sin(heading),
                speed * math.sin(elevation))
    box = Box(lo=tuple(c - d / 2 for c, d in zip(centre, size)), hi=tuple(c + d / 2 for c, d in zip(centre, size)),
              color=(0.85, 0.3, 0.25), frequency=4.0)
    return MovingBox(box, velocity)


def moving_clip(num_frames: int = 5, height: int = 48, width: int = 64, *, still: bool = False,
                movers: list[MovingBox] | None = None, scene: Scene | None = None) -> SyntheticClip:
    """The rigid clip of ``scene`` (default :func:`gallery_scene`, orbiting camera) with boxes that
    move on their own (default :func:`moving_boxes`), with exact flow, depth and dynamic mask.

    Args:
        num_frames, height, width: clip size.
        still: keep every mover where it stands in frame 0: the same scene, rigid (its
            ``dynamic_mask`` still marks the boxes, for masking a still scene alike).
        movers: the moving boxes.
        scene: the static world around them.

    Returns:
        A :class:`SyntheticClip` with ``objects`` and ``object_paths`` set; its correspondences
        move each box's pixels with the box.
    """
    base = scene or gallery_scene()
    movers = movers if movers is not None else moving_boxes()
    steps = torch.zeros(num_frames) if still else torch.arange(num_frames, dtype=torch.float64)
    velocities = torch.tensor([m.velocity for m in movers], dtype=torch.float64).reshape(-1, 3)
    paths = velocities[:, None] * steps.double()[None, :, None]  # [K, S, 3]
    scales = None
    if any(any(m.stretch) for m in movers):
        stretch = torch.tensor([m.stretch for m in movers], dtype=torch.float64).reshape(-1, 3)
        scales = 1.0 + stretch[:, None] * steps.double()[None, :, None]  # [K, S, 3]
        centres = torch.tensor([[(a + b) / 2 for a, b in zip(m.box.lo, m.box.hi)] for m in movers], dtype=torch.float64)
        paths = paths + centres[:, None] * (1.0 - scales)  # scaled about the centre: scale * m + path
    scenes = []
    for k in range(num_frames):
        boxes = []
        for n, mover in enumerate(movers):
            shift = tuple(float(x) for x in paths[n, k])
            if scales is None:
                boxes.append(replace(mover.box, lo=tuple(a + d for a, d in zip(mover.box.lo, shift)),
                                     hi=tuple(a + d for a, d in zip(mover.box.hi, shift)), texture_shift=shift))
                continue
            scale = tuple(float(x) for x in scales[n, k])
            boxes.append(replace(mover.box, lo=tuple(f * a + d for a, f, d in zip(mover.box.lo, scale, shift)),
                                 hi=tuple(f * a + d for a, f, d in zip(mover.box.hi, scale, shift)),
                                 texture_shift=shift, texture_scale=scale))
        scenes.append(Scene(boxes=boxes + base.boxes, planes=base.planes))
    extrinsics, K = orbit_cameras(num_frames), default_intrinsics(height, width)
    clip = render_clip(scenes, extrinsics, K, height, width)
    # Movers are the first primitives of every frame's scene: a hit index below len(movers) is one.
    hits = torch.stack([render_view(scenes[k], K, extrinsics[k], height, width)[2] for k in range(num_frames)])
    objects = torch.where((hits >= 0) & (hits < len(movers)), hits, torch.full_like(hits, -1))
    return replace(clip, objects=objects, object_paths=paths, object_scales=scales)


# --- deformation (WarpBench-style) -------------------------------------------------------------


def inject_deformation(
    clip: SyntheticClip,
    *,
    center: tuple[float, float] | None = None,
    radius: float | None = None,
    amplitude: float = 3.0,
    smoothing: float = 0.5,
    seed: int = 0,
) -> SyntheticClip:
    """Warp a disc of every frame with a temporally smooth thin-plate spline.

    Args:
        clip: a rigid clip.
        center: ``(u, v)`` of the region (default: image centre).
        radius: region radius in pixels (default: a quarter of the shorter side).
        amplitude: standard deviation of the control-point displacements, in pixels.
        smoothing: EMA factor over time (0 = independent per frame, close to 1 = frozen).
        seed: seeds the control-point displacements.

    Returns:
        The clip with warped frames, ``warp`` set and ``mask`` = warp length > 0.1 px.
    """
    _, _, height, width = clip.frames.shape
    cu, cv = center if center is not None else ((width - 1) / 2, (height - 1) / 2)
    radius = radius if radius is not None else min(height, width) / 4
    generator = torch.Generator().manual_seed(seed)
    # A fixed 3x3 grid of controls over the disc keeps this injector's documented warp; the
    # benchmark builder (geco_guide.bench.warp.warp_clip) samples them by farthest-point sampling.
    offsets = torch.tensor([(du, dv) for du in (-0.5, 0.0, 0.5) for dv in (-0.5, 0.0, 0.5)], dtype=torch.float64)
    controls = torch.tensor([cu, cv], dtype=torch.float64) + radius * offsets
    dist = (pixel_grid(height, width, dtype=torch.float64) - controls.new_tensor([cu, cv])).norm(dim=-1)
    feather = raised_cosine(radius - dist, radius)  # 1 at the centre, smoothly 0 at the rim
    displacements = control_displacements(controls.shape[0], clip.num_frames, amplitude, generator)
    warp = warp_fields(controls, displacements, feather, height, width, smoothing).to(clip.depth.dtype)
    return replace(clip, frames=backward_warp(clip.frames, warp), warp=warp, mask=warp.norm(dim=-1) > 0.1)


def deform_mover(clip: SyntheticClip, mover: int = 0, *, amplitude: float = 1.5, radius: float = 0.5,
                 smoothing: float = 0.5, seed: int = 0) -> SyntheticClip:
    """Warp a moving object alone with a temporally smooth thin-plate spline that moves with it.

    In each frame a 3x3 grid of controls sits around the centre of the object's pixels, spaced by
    half the disc's radius; their displacements (``N(0, amplitude^2)`` pixels per frame, smoothed
    over time by an exponential moving average of factor ``smoothing``) are interpolated by the
    thin-plate spline and feathered over a disc of ``radius`` times the radius of a disc of the
    object's area (raised cosine: full in the centre, 0 at the rim, and 0 off the object). So the
    object changes shape in its middle while it moves, and the same call on the still clip
    (``moving_clip(still=True)``) gives the same warp on a still object.

    Args:
        clip: a :func:`moving_clip`.
        mover: the object's index.
        amplitude, smoothing, seed: the displacements' size (pixels), smoothing and seed.
        radius: the disc's radius as a fraction of the object's equal-area radius.

    Returns:
        The clip with warped frames, ``warp`` set and ``mask`` = warp length > 0.1 px; its
        correspondences follow the warp (:meth:`SyntheticClip.correspondences`).
    """
    if clip.objects is None:
        raise ValueError("deform_mover needs a clip with moving objects (moving_clip)")
    num_frames, _, height, width = clip.frames.shape
    generator = torch.Generator().manual_seed(seed)
    displacements = control_displacements(9, num_frames, amplitude, generator)  # [S, 9, 2]
    grid = pixel_grid(height, width, dtype=torch.float64)
    offsets = torch.tensor([(du, dv) for du in (-0.5, 0.0, 0.5) for dv in (-0.5, 0.0, 0.5)], dtype=torch.float64)
    state = torch.zeros(9, 2, dtype=torch.float64)
    fields = []
    for t in range(num_frames):
        state = smoothing * state + (1 - smoothing) * displacements[t]
        on_object = clip.objects[t] == mover
        if not bool(on_object.any()):
            fields.append(torch.zeros(height, width, 2, dtype=torch.float64))
            continue
        centre = grid[on_object].mean(0)
        disc = radius * math.sqrt(int(on_object.sum()) / math.pi)
        feather = raised_cosine(disc - (grid - centre).norm(dim=-1), disc) * on_object
        field = thin_plate_spline(centre + disc * offsets, state, grid.reshape(-1, 2)).reshape(height, width, 2)
        fields.append(field * feather[..., None])
    warp = torch.stack(fields).to(clip.depth.dtype)
    return replace(clip, frames=backward_warp(clip.frames, warp), warp=warp, mask=warp.norm(dim=-1) > 0.1)


def with_warp(clip: SyntheticClip, warped: WarpResult) -> SyntheticClip:
    """``clip`` edited by :func:`geco_guide.bench.warp.warp_clip` / :func:`~geco_guide.bench.warp.warp_one_frame`
    (run on ``clip.frames``): its frames, warp and mask, so the ground truth follows the warp."""
    return replace(clip, frames=warped.frames, warp=warped.displacement.to(clip.depth.dtype), mask=warped.mask)


# --- occlusion inconsistency (OccluBench-style) ------------------------------------------------

#: Camera-space depth of an occlusion edit's layers, as fractions of the median scene depth in the
#: object's region: both in front of the scene, the occluder nearer.
LAYER_DEPTH = {OCCLUDER: 0.5, OBJECT: 0.8}


def with_overlay(clip: SyntheticClip, edit: OcclusionResult) -> SyntheticClip:
    """``clip`` edited by :func:`geco_guide.bench.occlusion.composite_occlusion` (run on ``clip.frames``).

    The layers become flat sprites at constant camera depths (:data:`LAYER_DEPTH`): their depth
    replaces the scene's where they show, and the correspondences follow their offsets, so an
    oracle answers exactly for the composite.
    """
    left, top, right, bottom = edit.region
    reference = clip.depth[:, top:bottom, left:right]
    reference = float(reference[reference > 0].median()) if (reference > 0).any() else float(clip.depth.max())
    depth = clip.depth.clone()
    for layer, fraction in LAYER_DEPTH.items():
        depth[edit.labels == layer] = fraction * reference
    return replace(clip, frames=edit.frames.to(clip.frames.dtype), depth=depth, mask=edit.mask,
                   overlay=Overlay(edit.labels, edit.offsets))


def occlusion_swap_clip(num_frames: int = 9, height: int = 48, width: int = 64) -> SyntheticClip:
    """A wall region is seen, hidden behind a pillar (camera parallax), and re-revealed with a
    different object.

    The first quarter of the frames sees a small flat box A on the wall; while the pillar hides
    the region, A is replaced by B, a larger box that sticks out further. The ground-truth
    ``mask`` marks the pixels showing B whose surface an earlier frame saw through (it saw a
    farther surface along the same ray): the re-revealed surface that no single static world
    explains. A itself stays consistent: from every later view it lies behind B.
    """
    wall = Box(lo=(-6.0, -3.0, -3.0), hi=(6.0, 2.0, 8.0), color=(0.75, 0.7, 0.6), inside=True, frequency=2.0)
    pillar = Box(lo=(-0.15, -3.0, 3.0), hi=(0.15, 2.0, 3.6), color=(0.5, 0.35, 0.3), frequency=5.0)
    obj_a = Box(lo=(1.45, -0.3, 7.4), hi=(1.95, 0.3, 8.0), color=(0.2, 0.6, 0.3), frequency=4.0)
    obj_b = Box(lo=(1.3, -0.6, 6.3), hi=(2.1, 0.6, 8.0), color=(0.8, 0.2, 0.2), frequency=4.0)
    world_a = Scene(boxes=[wall, pillar, obj_a])
    world_b = Scene(boxes=[wall, pillar, obj_b])
    dtype = torch.float64
    target = torch.tensor([0.0, 0.0, 8.0], dtype=dtype)
    poses = torch.stack(
        [look_at(torch.tensor([5.0 * k / (num_frames - 1) - 3.0, 0.0, 0.0], dtype=dtype), target) for k in range(num_frames)]
    )
    swap = num_frames // 4  # the pillar hides the region around this frame
    scenes = [world_a if k < swap else world_b for k in range(num_frames)]
    K = default_intrinsics(height, width, fov_x_deg=55.0)
    clip = render_clip(scenes, poses, K, height, width)
    object_index = 2  # wall, pillar, object: the object is the third primitive of both worlds
    masks = []
    for k in range(num_frames):
        on_b = render_view(scenes[k], K, poses[k], height, width)[2].reshape(-1) == object_index
        points = _world_points(clip, k)
        seen_through = torch.zeros_like(on_b)
        for j in range(swap if k >= swap else 0):
            seen_through |= _seen_through(clip, points, j)
        masks.append((on_b & seen_through).reshape(height, width))
    return replace(clip, mask=torch.stack(masks))
