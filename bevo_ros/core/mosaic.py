"""The BEVs of the last few metres composed by the odometry into one local mosaic (BEVO+).

One 10 m BEV holds too little of an aerial map's coarse structure (and lane markings alone
slide along the road), so the map measurement registers a mosaic of the keyframes of the last
``length`` metres. Each keyframe's BEV is placed with its odometry pose: the odometry's drift
*within* the window (a few centimetres over 20 m) is all that the mosaic inherits.

Pure torch, differentiable in the BEVs and the poses (``grid_sample``).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from .aerial_map import local_grid, transform_points
from .geometry import BevSpec

Tensor = torch.Tensor


def _gaussian_blur(x: Tensor, sigma: float) -> Tensor:
    """Separable Gaussian blur of ``(N, C, H, W)``, zero padding (used on ``w * x`` and ``w``)."""
    if sigma <= 0.0:
        return x
    r = max(1, int(math.ceil(3.0 * sigma)))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=x.dtype, device=x.device) / sigma) ** 2)
    k = k / k.sum()
    C = x.shape[1]
    x = F.conv2d(x, k.view(1, 1, 1, -1).expand(C, 1, 1, -1), padding=(0, r), groups=C)
    return F.conv2d(x, k.view(1, 1, -1, 1).expand(C, 1, -1, 1), padding=(r, 0), groups=C)


def antialias_bev(bev: Tensor, mask: Tensor, spec: BevSpec, resolution: float) -> tuple[Tensor, Tensor]:
    """Low-pass the BEVs before they are resampled at a coarser ``resolution`` (normalised
    convolution: invalid pixels do not darken the valid ones; the mask is eroded by the blur).
    ``(K, 1, S, S)`` x2 -> same."""
    sigma = 0.5 * resolution / spec.metres_per_pixel if resolution > 1.5 * spec.metres_per_pixel else 0.0
    if sigma <= 0.0:
        return bev, mask
    m = (mask > 0.5).to(bev.dtype)
    num = _gaussian_blur(bev * m, sigma)
    den = _gaussian_blur(m, sigma)
    return num / den.clamp_min(1e-6), (den > 0.98).to(bev.dtype) * m


def compose_mosaic(bevs: Tensor, masks: Tensor, poses: Tensor, anchor: Tensor, spec: BevSpec, size: int,
                   resolution: float) -> tuple[Tensor, Tensor]:
    """Average the keyframe BEVs on a local grid.

    Args:
        bevs, masks: ``(K, 1, S, S)`` keyframe BEVs and their validity masks (BEV convention).
        poses: ``(K, 3)`` keyframe base poses ``(x, y, yaw)`` in one frame (odom).
        anchor: ``(3,)`` pose of the mosaic's centre in that frame (grid axes: :func:`local_grid`).
        spec: the BEVs' grid.
        size, resolution: the mosaic is ``size x size`` pixels at ``resolution`` m/px.

    Returns:
        mosaic ``(1, 1, M, M)`` and coverage ``(1, 1, M, M)`` (1 where at least one keyframe
        saw the ground, soft at the edges).
    """
    if bevs.ndim != 4 or masks.shape != bevs.shape or poses.shape != (bevs.shape[0], 3):
        raise ValueError(f"need bevs, masks (K, 1, S, S) and poses (K, 3), got {tuple(bevs.shape)}, "
                         f"{tuple(masks.shape)}, {tuple(poses.shape)}")
    bevs, masks = antialias_bev(bevs, masks, spec, resolution)
    K, S = bevs.shape[0], spec.size
    pts = transform_points(anchor.reshape(1, 3), local_grid(size, resolution, anchor.dtype, anchor.device))[0]
    # Each keyframe's base coordinates of the mosaic points: R(-yaw_k) (q - t_k).
    c, s = torch.cos(poses[:, 2])[:, None, None], torch.sin(poses[:, 2])[:, None, None]
    qx = pts[None, ..., 0] - poses[:, 0, None, None]
    qy = pts[None, ..., 1] - poses[:, 1, None, None]
    bx, by = c * qx + s * qy, -s * qx + c * qy  # (K, M, M)
    mpp = spec.metres_per_pixel
    row = S - 0.5 - (bx - spec.forward_offset) / mpp
    col = (S - 1) / 2.0 - by / mpp
    grid = torch.stack([(2.0 * col + 1.0) / S - 1.0, (2.0 * row + 1.0) / S - 1.0], dim=-1).to(bevs.dtype)
    val = F.grid_sample(bevs, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    w = F.grid_sample(masks, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    w = (w - 0.5).clamp_min(0.0) * 2.0  # bilinear weights of a 0/1 mask: only well inside counts
    total = w.sum(dim=0, keepdim=True)
    mosaic = (w * val).sum(dim=0, keepdim=True) / total.clamp_min(1e-6)
    return mosaic, total.clamp(0.0, 1.0)


@dataclass
class Keyframe:
    pose: Tensor  # (3,) odom
    bev: Tensor  # (1, S, S)
    mask: Tensor  # (1, S, S)
    variance: tuple[float, float] = (0.0, 0.0)  # accumulated odometry (position m^2, yaw rad^2) at this keyframe


class MosaicBuffer:
    """The keyframes of the last ``length`` metres of path, one every ``spacing`` metres.

    Args:
        spec: the BEV grid.
        length: metres of path kept.
        spacing: a frame becomes a keyframe once it is this far (path length) from the last one.
    """

    def __init__(self, spec: BevSpec, length: float = 20.0, spacing: float = 2.0) -> None:
        if not (length > 0 and spacing > 0 and spacing <= length):
            raise ValueError(f"need 0 < spacing <= length, got spacing {spacing}, length {length}")
        self.spec, self.length, self.spacing = spec, float(length), float(spacing)
        self.frames: deque[tuple[float, Keyframe]] = deque()  # (path length at the keyframe, keyframe)
        self.path = 0.0
        self._last_path = -math.inf

    def reset(self) -> None:
        self.frames.clear()
        self.path = 0.0
        self._last_path = -math.inf

    def advance(self, distance: float) -> None:
        """Account for ``distance`` metres driven (every odometry step, BEV or not)."""
        self.path += abs(float(distance))

    def offer(self, pose: Tensor, bev: Tensor, mask: Tensor, variance: tuple[float, float] = (0.0, 0.0)) -> bool:
        """Keep this frame if it is ``spacing`` beyond the last keyframe. ``bev, mask (S, S)``;
        ``variance``: the odometry's accumulated (position, yaw) variance at this frame, so that
        the mosaic's distortion can be told from the keyframes' differences."""
        if self.path - self._last_path < self.spacing - 1e-9:
            return False
        self.frames.append((self.path, Keyframe(pose.detach().clone(), bev.reshape(1, *bev.shape[-2:]),
                                                mask.reshape(1, *mask.shape[-2:]), tuple(variance))))
        self._last_path = self.path
        while self.frames and self.path - self.frames[0][0] > self.length + 1e-9:
            self.frames.popleft()
        return True

    @property
    def covered_length(self) -> float:
        """Path length between the oldest kept keyframe and now."""
        return self.path - self.frames[0][0] if self.frames else 0.0

    def stacked(self) -> tuple[Tensor, Tensor, Tensor]:
        """Keyframe BEVs ``(K, 1, S, S)``, masks ``(K, 1, S, S)`` and poses ``(K, 3)``."""
        kf = [k for _, k in self.frames]
        return torch.stack([k.bev for k in kf]), torch.stack([k.mask for k in kf]), torch.stack([k.pose for k in kf])

    def anchor(self) -> Tensor:
        """:func:`mosaic_anchor` of the keyframes. -> ``(3,)``."""
        return mosaic_anchor(self.stacked()[2], self.spec)


def mosaic_anchor(poses: Tensor, spec: BevSpec) -> Tensor:
    """Centre of a mosaic of keyframes at ``poses (K, 3)`` (oldest first): the middle of the ground
    they saw, with the newest keyframe's heading (so the map crop is nearly aligned with the road
    ahead). -> ``(3,)``."""
    near, far = spec.forward_offset, spec.forward_offset + spec.extent
    heading = torch.stack([torch.cos(poses[:, 2]), torch.sin(poses[:, 2])], dim=-1)
    # Midway between the oldest BEV's near edge and the newest BEV's far edge: the mosaic's extent.
    mid = 0.5 * (poses[0, :2] + near * heading[0] + poses[-1, :2] + far * heading[-1])
    return torch.cat([mid, poses[-1, 2:3]])




def mosaic_to_map(bevs: Tensor, masks: Tensor, poses: Tensor, spec: BevSpec, resolution: float,
                  margin: float = 2.0, chunk: int = 16):
    """Compose BEVs at known poses into a map (a "previous drive" map from ground truth).

    Args:
        bevs, masks: ``(F, 1, S, S)``.
        poses: ``(F, 3)`` base poses ``(x, y, yaw)`` in the map frame (e.g. ground truth).
        resolution: metres per pixel of the map.
        margin: metres around the BEVs' footprints.

    Returns:
        an :class:`~bevo_ros.core.aerial_map.AerialMap` (grey) whose ``valid`` mask marks the
        pixels some BEV covered.
    """
    from .aerial_map import AerialMap

    near, far = spec.forward_offset, spec.forward_offset + spec.extent
    half = spec.extent / 2.0
    corners = torch.tensor([[near, -half], [near, half], [far, -half], [far, half]], dtype=poses.dtype,
                           device=poses.device)
    world = transform_points(poses, corners).reshape(-1, 2)
    lo = world.min(dim=0).values - margin
    hi = world.max(dim=0).values + margin
    W = int(math.ceil(float(hi[0] - lo[0]) / resolution))
    H = int(math.ceil(float(hi[1] - lo[1]) / resolution))
    origin = (float(lo[0]), float(lo[1]), 0.0)
    col = torch.arange(W, dtype=poses.dtype, device=poses.device)
    row = torch.arange(H, dtype=poses.dtype, device=poses.device)
    gx = lo[0] + (col + 0.5) * resolution
    gy = lo[1] + (H - row - 0.5) * resolution
    num = torch.zeros(H, W, dtype=bevs.dtype, device=bevs.device)
    den = torch.zeros_like(num)
    bevs, masks = antialias_bev(bevs, masks, spec, resolution)
    S, mpp = spec.size, spec.metres_per_pixel
    for k in range(bevs.shape[0]):
        # Only the window around this BEV's footprint.
        fp = transform_points(poses[k:k + 1], corners)[0]
        c0 = max(0, int((float(fp[:, 0].min()) - float(lo[0])) / resolution) - 1)
        c1 = min(W, int((float(fp[:, 0].max()) - float(lo[0])) / resolution) + 2)
        r0 = max(0, int(H - (float(fp[:, 1].max()) - float(lo[1])) / resolution) - 1)
        r1 = min(H, int(H - (float(fp[:, 1].min()) - float(lo[1])) / resolution) + 2)
        x, y, yaw = poses[k]
        qx = gx[None, c0:c1] - x
        qy = gy[r0:r1, None] - y
        c, s = torch.cos(yaw), torch.sin(yaw)
        bx, by = c * qx + s * qy, -s * qx + c * qy
        brow = S - 0.5 - (bx - spec.forward_offset) / mpp
        bcol = (S - 1) / 2.0 - by / mpp
        grid = torch.stack([(2.0 * bcol + 1.0) / S - 1.0, (2.0 * brow + 1.0) / S - 1.0], dim=-1)[None].to(bevs.dtype)
        val = F.grid_sample(bevs[k:k + 1], grid, mode="bilinear", padding_mode="zeros", align_corners=False)[0, 0]
        w = F.grid_sample(masks[k:k + 1], grid, mode="bilinear", padding_mode="zeros", align_corners=False)[0, 0]
        w = (w - 0.5).clamp_min(0.0) * 2.0
        num[r0:r1, c0:c1] += w * val
        den[r0:r1, c0:c1] += w
    image = (num / den.clamp_min(1e-6)).clamp(0.0, 1.0)
    valid = (den > 0.5).to(bevs.dtype)
    return AerialMap(image[None], resolution, origin, valid[None])


__all__ = ["Keyframe", "MosaicBuffer", "antialias_bev", "compose_mosaic", "mosaic_anchor", "mosaic_to_map"]
