"""Pinhole camera geometry: the one place where pixels, depths and poses meet.

Conventions (shared by the metric, the loss, the estimators and the tests):

* pixel ``(u, v)`` is column ``u``, row ``v``; pixel centres sit at integer coordinates, so an
  ``H x W`` image spans ``[0, W-1] x [0, H-1]`` and bilinear sampling is ``grid_sample`` with
  ``align_corners=True`` on ``2u/(W-1) - 1``;
* intrinsics ``K [B, 3, 3]`` are in pixels of the tensor they describe; every resize or crop of
  an image changes ``K`` through :func:`resize_intrinsics` / :func:`crop_intrinsics`;
* extrinsics ``[B, 3, 4]`` are camera-from-world ``[R | t]`` with OpenCV axes (x right, y down,
  z forward); a relative pose ``src -> tgt`` is a ``[B, 4, 4]`` matrix acting on source-camera
  points;
* depth ``[B, H, W]`` is z-depth, strictly positive where valid.

All functions are batched, differentiable and dtype-preserving (fp32 and fp64).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["MIN_DEPTH", "MIN_INLIERS", "RANSAC_ITERATIONS", "RIGID_TOLERANCE", "SCORED_MATCHES", "check_tensor", "crop_intrinsics", "inside_image", "invert_rigid",
           "kabsch", "kabsch_from_moments", "local_depth_ratio", "pixel_grid", "pose_encoding_to_cameras", "project",
           "quaternion_to_matrix", "ransac_rigid", "relative_pose", "resize_flow", "resize_intrinsics", "rigid_flow",
           "sample_at_projection", "sample_bilinear", "transform_points", "unproject"]

# Depths below this are treated as "not in front of the camera"; it also keeps divisions finite.
MIN_DEPTH = 1e-6


def check_tensor(x: Tensor, name: str, shape: tuple[int | None, ...]) -> None:
    """Raise a ValueError naming ``name`` unless ``x`` is a floating tensor of ``shape``.

    ``None`` entries in ``shape`` match any size.
    """
    if not isinstance(x, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got dtype {x.dtype}")
    ok = x.ndim == len(shape) and all(s is None or s == d for s, d in zip(shape, x.shape))
    if not ok:
        pretty = ", ".join("*" if s is None else str(s) for s in shape)
        raise ValueError(f"{name} must have shape [{pretty}], got {list(x.shape)}")


def _check_batch(name: str, x: Tensor, batch: int) -> None:
    if x.shape[0] != batch:
        raise ValueError(f"{name} has batch size {x.shape[0]}, expected {batch}")


def pixel_grid(height: int, width: int, *, device=None, dtype=torch.float32) -> Tensor:
    """Integer pixel coordinates ``[H, W, 2]`` holding ``(u, v)`` = (column, row)."""
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=dtype),
        torch.arange(width, device=device, dtype=dtype),
        indexing="ij",
    )
    return torch.stack((u, v), dim=-1)


def homogeneous_pose(extrinsics: Tensor) -> Tensor:
    """``[B, 3, 4]`` ``[R | t]`` -> ``[B, 4, 4]`` with a ``[0, 0, 0, 1]`` last row."""
    last = torch.zeros_like(extrinsics[..., :1, :])
    last[..., 0, 3] = 1.0
    return torch.cat((extrinsics, last), dim=-2)


def invert_rigid(pose: Tensor) -> Tensor:
    """Inverse of rigid transforms ``[..., 3|4, 4]`` -> ``[..., 4, 4]`` (``R^T``, ``-R^T t``)."""
    rot_t = pose[..., :3, :3].transpose(-1, -2)
    trans = -(rot_t @ pose[..., :3, 3:])
    return homogeneous_pose(torch.cat((rot_t, trans), dim=-1))


def relative_pose(extr_src: Tensor, extr_tgt: Tensor) -> Tensor:
    """Pose mapping source-camera points to target-camera points.

    Args:
        extr_src: ``[B, 3, 4]`` camera-from-world extrinsics of the source view.
        extr_tgt: ``[B, 3, 4]`` camera-from-world extrinsics of the target view.

    Returns:
        ``[B, 4, 4]`` ``T_tgt @ T_src^-1``.
    """
    check_tensor(extr_src, "extr_src", (None, 3, 4))
    check_tensor(extr_tgt, "extr_tgt", (None, 3, 4))
    _check_batch("extr_tgt", extr_tgt, extr_src.shape[0])
    return homogeneous_pose(extr_tgt) @ invert_rigid(extr_src)


def unproject(depth: Tensor, K: Tensor) -> Tensor:
    """Back-project every pixel to camera coordinates.

    Args:
        depth: ``[B, H, W]`` z-depth.
        K: ``[B, 3, 3]`` intrinsics.

    Returns:
        ``[B, H, W, 3]`` points ``depth * K^-1 [u, v, 1]``.
    """
    height, width = depth.shape[-2:]
    uv = pixel_grid(height, width, device=depth.device, dtype=depth.dtype)
    ones = torch.ones_like(uv[..., :1])
    rays = torch.cat((uv, ones), dim=-1)  # [H, W, 3]
    k_inv = torch.linalg.inv(K)  # general K (skew allowed)
    rays = torch.einsum("bij,hwj->bhwi", k_inv, rays)
    return rays * depth[..., None]


def transform_points(points: Tensor, pose: Tensor) -> Tensor:
    """Apply ``pose [B, 3|4, 4]`` to ``points [B, ..., 3]``."""
    batch = points.shape[0]
    flat = points.reshape(batch, -1, 3)
    moved = flat @ pose[:, :3, :3].transpose(1, 2) + pose[:, None, :3, 3]
    return moved.reshape(points.shape)


def project(points: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """Project camera points ``[B, ..., 3]`` with ``K [B, 3, 3]``.

    Returns:
        ``uv [B, ..., 2]`` pixel coordinates and ``z [B, ..., ]`` depths. Points with
        ``z <= MIN_DEPTH`` get a clamped denominator so ``uv`` stays finite; callers mask them.
    """
    batch = points.shape[0]
    flat = points.reshape(batch, -1, 3)
    cam = flat @ K.transpose(1, 2)
    z = flat[..., 2]
    denom = torch.where(z > MIN_DEPTH, cam[..., 2], torch.full_like(z, MIN_DEPTH))
    uv = cam[..., :2] / denom[..., None]
    return uv.reshape(*points.shape[:-1], 2), z.reshape(points.shape[:-1])


def inside_image(uv: Tensor, height: int, width: int, slack: float = 1e-4) -> Tensor:
    """``[B, ..., 2]`` -> bool mask of coordinates within ``[0, W-1] x [0, H-1]``.

    ``slack`` (pixels) absorbs rounding, so that e.g. an identity pose keeps border pixels.
    Non-finite coordinates are outside (every comparison with NaN is False).
    """
    u, v = uv[..., 0], uv[..., 1]
    return (u >= -slack) & (u <= width - 1 + slack) & (v >= -slack) & (v <= height - 1 + slack)


def _check_camera_inputs(depth_src: Tensor, K_src: Tensor, K_tgt: Tensor, src_to_tgt: Tensor) -> None:
    check_tensor(depth_src, "depth_src", (None, None, None))
    batch = depth_src.shape[0]
    check_tensor(K_src, "K_src", (batch, 3, 3))
    check_tensor(K_tgt, "K_tgt", (batch, 3, 3))
    check_tensor(src_to_tgt, "src_to_tgt", (batch, 4, 4))


def _project_source_pixels(
    depth_src: Tensor, K_src: Tensor, K_tgt: Tensor, src_to_tgt: Tensor
) -> tuple[Tensor, Tensor]:
    """Target-image coordinates ``[B, H, W, 2]`` and target z ``[B, H, W]`` of source pixels."""
    points = transform_points(unproject(depth_src, K_src), src_to_tgt)
    return project(points, K_tgt)


def rigid_flow(
    depth_src: Tensor,
    K_src: Tensor,
    K_tgt: Tensor,
    src_to_tgt: Tensor,
    tgt_hw: tuple[int, int] | None = None,
) -> tuple[Tensor, Tensor]:
    """Flow induced by the camera motion on a static scene.

    Args:
        depth_src: ``[B, H, W]`` source z-depth.
        K_src: ``[B, 3, 3]`` source intrinsics.
        K_tgt: ``[B, 3, 3]`` target intrinsics.
        src_to_tgt: ``[B, 4, 4]`` relative pose (see :func:`relative_pose`).
        tgt_hw: target image size ``(H_t, W_t)`` for the in-image test; default the source's.

    Returns:
        ``flow [B, 2, H, W]`` (du, dv) in target pixels from the integer source grid, 0 where
        invalid, and ``valid [B, H, W]``: source depth > 0, projected depth > 0 and the
        projection inside ``[0, W_t-1] x [0, H_t-1]``.
    """
    _check_camera_inputs(depth_src, K_src, K_tgt, src_to_tgt)
    height, width = depth_src.shape[-2:]
    tgt_h, tgt_w = tgt_hw if tgt_hw is not None else (height, width)
    uv_tgt, z_tgt = _project_source_pixels(depth_src, K_src, K_tgt, src_to_tgt)
    grid = pixel_grid(height, width, device=depth_src.device, dtype=depth_src.dtype)
    valid = (depth_src > MIN_DEPTH) & (z_tgt > MIN_DEPTH) & inside_image(uv_tgt, tgt_h, tgt_w)
    flow = torch.where(valid[..., None], uv_tgt - grid, torch.zeros_like(uv_tgt))
    return flow.permute(0, 3, 1, 2), valid


def sampling_coordinates(uv: Tensor, height: int, width: int) -> Tensor:
    """Pixel coordinates ``uv [B, ..., 2]`` made safe for ``grid_sample``, same shape.

    ``grid_sample``'s backward crashes the process (segmentation fault) on a NaN grid with
    ``padding_mode="border"`` (a PyTorch defect), and NaN/inf coordinates come from any
    non-finite depth, camera or flow upstream. A point with a non-finite coordinate goes to
    ``(-1, -1)`` and finite coordinates are clamped to ``[-1, W] x [-1, H]``, so the grid is
    finite and bounded; :func:`inside_image` is False for exactly the same points before and
    after (it is False for NaN), so callers' in-image masks mark these samples invalid. In-image
    points keep their coordinates and gradients.
    """
    finite = torch.isfinite(uv).all(dim=-1, keepdim=True)
    safe = torch.where(finite, uv, torch.full_like(uv, -1.0))
    return torch.minimum(safe.clamp_min(-1.0), uv.new_tensor([float(width), float(height)]))


def sample_bilinear(image: Tensor, uv: Tensor) -> Tensor:
    """Sample ``image [B, C, H, W]`` at pixel coordinates ``uv [B, ..., 2]``.

    Integer coordinates are pixel centres; outside the image (and at non-finite coordinates,
    see :func:`sampling_coordinates`) the border value is used: callers mask samples that
    :func:`inside_image` rejects. Returns ``[B, C, ...]``.
    """
    height, width = image.shape[-2:]
    batch = uv.shape[0]
    flat = sampling_coordinates(uv, height, width).reshape(batch, 1, -1, 2)
    scale = uv.new_tensor([2.0 / max(width - 1, 1), 2.0 / max(height - 1, 1)])
    grid = flat * scale - 1.0
    sampled = F.grid_sample(image, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return sampled.reshape(batch, image.shape[1], *uv.shape[1:-1])


def sample_at_projection(
    depth_src: Tensor,
    K_src: Tensor,
    K_tgt: Tensor,
    src_to_tgt: Tensor,
    target_maps: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:
    """Project every source pixel into the target view and sample target maps there.

    Args:
        depth_src: ``[B, H, W]`` source z-depth.
        K_src, K_tgt: ``[B, 3, 3]`` intrinsics of the two views.
        src_to_tgt: ``[B, 4, 4]`` relative pose.
        target_maps: ``[B, C, H_t, W_t]`` maps of the target view (e.g. its depth).

    Returns:
        ``z_proj [B, H, W]`` z of each source point in the target camera, ``samples
        [B, C, H, W]`` the maps sampled bilinearly at the projections, and ``valid [B, H, W]``:
        source and projected depth > 0 and the projection inside the target image.
    """
    _check_camera_inputs(depth_src, K_src, K_tgt, src_to_tgt)
    check_tensor(target_maps, "target_maps", (depth_src.shape[0], None, None, None))
    tgt_h, tgt_w = target_maps.shape[-2:]
    uv_tgt, z_proj = _project_source_pixels(depth_src, K_src, K_tgt, src_to_tgt)
    samples = sample_bilinear(target_maps, uv_tgt)
    valid = (depth_src > MIN_DEPTH) & (z_proj > MIN_DEPTH) & inside_image(uv_tgt, tgt_h, tgt_w)
    return z_proj, samples, valid


def local_depth_ratio(depth: Tensor) -> Tensor:
    """``[B, H, W]`` -> ``[B, H, W]`` max/min depth over each pixel's 3x3 neighbourhood.

    Sampled bilinearly at a sub-pixel position, it bounds the ratio of the four depths a
    bilinear depth sample mixes: values well above 1 mean the sample straddles a depth edge.
    """
    padded = F.pad(depth[:, None], (1, 1, 1, 1), mode="replicate")
    local_max = F.max_pool2d(padded, 3, stride=1)
    local_min = -F.max_pool2d(-padded, 3, stride=1)
    return (local_max / local_min.clamp_min(MIN_DEPTH))[:, 0].detach()


def resize_intrinsics(K: Tensor, src_hw: tuple[int, int], dst_hw: tuple[int, int]) -> Tensor:
    """Intrinsics ``[..., 3, 3]`` after resizing the image from ``src_hw`` to ``dst_hw``.

    Matches resampling with ``align_corners=False`` (pixel areas scale, centres at integers):
    ``u' = s (u + 0.5) - 0.5``, so ``fx' = s fx`` and ``cx' = s (cx + 0.5) - 0.5``.
    """
    sy = dst_hw[0] / src_hw[0]
    sx = dst_hw[1] / src_hw[1]
    scale = K.new_tensor([[sx, sx, sx], [sy, sy, sy], [1.0, 1.0, 1.0]])
    shift = K.new_tensor([[0.0, 0.0, 0.5 * sx - 0.5], [0.0, 0.0, 0.5 * sy - 0.5], [0.0, 0.0, 0.0]])
    # The shift multiplies the homogeneous row (K[2, 2] = 1 for a pinhole).
    return K * scale + shift * K[..., 2:3, 2:3]


def crop_intrinsics(K: Tensor, top: float, left: float) -> Tensor:
    """Intrinsics ``[..., 3, 3]`` of the window whose top-left pixel is ``(left, top)``.

    A negative offset un-crops (the window was cut out of a larger image).
    """
    shift = K.new_tensor([[0.0, 0.0, -float(left)], [0.0, 0.0, -float(top)], [0.0, 0.0, 0.0]])
    return K + shift * K[..., 2:3, 2:3]


def resize_flow(flow: Tensor, size: tuple[int, int]) -> Tensor:
    """Bilinearly resize a flow field ``[B, 2, h, w]`` to ``size`` and rescale its vectors.

    Displacements scale with the image (``du' = du W/w``), consistent with
    :func:`resize_intrinsics`.
    """
    height, width = flow.shape[-2:]
    if (height, width) == tuple(size):
        return flow
    resized = F.interpolate(flow, size=size, mode="bilinear", align_corners=False)
    ratio = flow.new_tensor([size[1] / width, size[0] / height]).view(1, 2, 1, 1)
    return resized * ratio


def quaternion_to_matrix(quat: Tensor) -> Tensor:
    """Scalar-last quaternion ``[..., 4]`` (x, y, z, w; any norm) -> rotation ``[..., 3, 3]``."""
    x, y, z, w = quat.unbind(-1)
    s = 2.0 / (quat * quat).sum(-1)
    rows = (
        1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w),
        s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w),
        s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y),
    )
    return torch.stack(rows, dim=-1).unflatten(-1, (3, 3))


def pose_encoding_to_cameras(pose_enc: Tensor, image_hw: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """VGGT's pose encoding ``[..., 9]`` (t, quat xyzw, fov_h, fov_w) -> camera-from-world
    extrinsics ``[..., 3, 4]`` and K ``[..., 3, 3]``.

    K is in pixels of the ``image_hw`` network input with the principal point at ``(W/2, H/2)``
    (continuous pixel convention, as the reference produces it: centres at ``i + 0.5``; subtract
    0.5 from the principal point for this module's integer-centre convention).
    """
    height, width = image_hw
    t, quat, fov_h, fov_w = pose_enc[..., :3], pose_enc[..., 3:7], pose_enc[..., 7], pose_enc[..., 8]
    extrinsics = torch.cat([quaternion_to_matrix(quat), t.unsqueeze(-1)], dim=-1)
    fy = (height / 2.0) / torch.tan(fov_h / 2.0)
    fx = (width / 2.0) / torch.tan(fov_w / 2.0)
    zero, one = torch.zeros_like(fx), torch.ones_like(fx)
    intrinsics = torch.stack(
        [fx, zero, zero + width / 2.0, zero, fy, zero + height / 2.0, zero, zero, one], dim=-1
    ).unflatten(-1, (3, 3))
    return extrinsics, intrinsics


# --- rigid motions of 3-D matches (the automatic masks and the movers' scoring share them) -------


def kabsch_from_moments(mean_source: Tensor, mean_target: Tensor, covariance: Tensor) -> tuple[Tensor, Tensor]:
    """The rigid motion ``(R [..., 3, 3], t [..., 3])`` of matches given by their (weighted)
    means ``[..., 3]`` and cross-covariance ``sum w (s - mean_s)(t - mean_t)^T`` ``[..., 3, 3]``:
    the least-squares fit with ``det R = +1``."""
    u, _, vh = torch.linalg.svd(covariance)
    # Reflections flip the last singular direction so R is a rotation.
    sign = torch.sign(torch.linalg.det(vh.transpose(-1, -2) @ u.transpose(-1, -2)))
    fix = torch.diag_embed(torch.stack((torch.ones_like(sign), torch.ones_like(sign), torch.where(sign == 0, torch.ones_like(sign), sign)), -1))
    rotation = vh.transpose(-1, -2) @ fix @ u.transpose(-1, -2)
    translation = mean_target - (rotation @ mean_source[..., None])[..., 0]
    return rotation, translation


def kabsch(source: Tensor, target: Tensor, weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """The rigid motion ``(R [..., 3, 3], t [..., 3])`` that best maps ``source [..., N, 3]`` onto
    ``target [..., N, 3]`` in the (weighted, ``weights [..., N]``) least-squares sense, ``det R = +1``."""
    w = torch.ones(source.shape[:-1], dtype=source.dtype, device=source.device) if weights is None else weights
    w = w / w.sum(-1, keepdim=True).clamp_min(1e-12)
    mean_s = (w[..., None] * source).sum(-2, keepdim=True)
    mean_t = (w[..., None] * target).sum(-2, keepdim=True)
    cov = ((source - mean_s) * w[..., None]).transpose(-1, -2) @ (target - mean_t)
    return kabsch_from_moments(mean_s[..., 0, :], mean_t[..., 0, :], cov)


#: Matches a RANSAC hypothesis is ranked on, at most.
SCORED_MATCHES = 4096

#: The rigid-fit thresholds the automatic masks and the movers' scoring share by default: a match
#: fits a motion when its 3-D error is at most RIGID_TOLERANCE of its own 3-D displacement, and a
#: motion holds when it fits MIN_INLIERS of the matches; RANSAC_ITERATIONS hypotheses.
RIGID_TOLERANCE = 0.25
MIN_INLIERS = 0.8
RANSAC_ITERATIONS = 64


def ransac_rigid(source: Tensor, target: Tensor, limit: Tensor, iterations: int,
                 generator: torch.Generator) -> tuple[Tensor, Tensor, Tensor, float]:
    """RANSAC + Kabsch on matches ``source, target [N, 3]`` (``N >= 3``).

    Each of ``iterations`` hypotheses is the Kabsch fit of 3 random matches; a match is its inlier
    when the hypothesis maps it to within ``limit [N]`` of its target. Hypotheses are ranked on at
    most :data:`SCORED_MATCHES` matches (a large set's share is estimated as well from a sample);
    the winner is refitted on all the matches it explains.

    Returns:
        ``(R [3, 3], t [3], inliers [N] bool, sampled_fraction)``: the refitted motion, the
        matches it explains within ``limit``, and the winner's inlier fraction on the ranked matches.
    """
    count = source.shape[0]
    draws = torch.randint(count, (iterations, 3), generator=generator)
    rotation, translation = kabsch(source[draws], target[draws])  # [I, 3, 3], [I, 3]
    scored = torch.randperm(count, generator=generator)[:SCORED_MATCHES] if count > SCORED_MATCHES else slice(None)
    moved = torch.einsum("iab,nb->ina", rotation, source[scored]) + translation[:, None]
    inliers = (moved - target[scored]).norm(dim=-1) <= limit[scored]  # [I, N]
    best = int(inliers.sum(-1).argmax())
    sampled_fraction = float(inliers[best].float().mean())
    explained = (source @ rotation[best].T + translation[best] - target).norm(dim=-1) <= limit
    rotation, translation = kabsch(source, target, explained.to(source.dtype))
    refit = (source @ rotation.T + translation - target).norm(dim=-1) <= limit
    return rotation, translation, refit, sampled_fraction
