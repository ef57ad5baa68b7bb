"""Differentiable inverse perspective mapping of a camera image onto the road plane (paper 2.2).

Every BEV pixel is a point on the road plane (``BevSpec.ground_points``, road frame, z = 0). It
is moved into the camera frame with the camera pose on the road for the current attitude
(``camera_pose_on_road``), projected with the pinhole ``K`` and looked up with ``grid_sample``.
Everything is differentiable in pitch and roll.

Pixel-centre convention: ``K`` follows OpenCV/KITTI, i.e. pixel ``(u, v)`` has its centre at
integer coordinates, so the image spans ``[-0.5, W - 0.5]``. ``grid_sample(align_corners=False)``
maps the normalised -1 / +1 to the outer *edges* of the image, hence ``g = (2 u + 1) / W - 1``.

Anti-aliasing: on a KITTI-like camera a 0.1 m BEV cell near the vehicle covers ~12 image columns
and ~3 image rows; point sampling would alias badly (and aliasing moves differently from frame
to frame, which biases phase correlation). Each BEV cell is therefore the mean of
``supersample`` x ``supersample`` bilinear samples spread over the cell (a box filter on the
ground, which is the right footprint for a ground-plane resampling), optionally on an image
first reduced by ``downsample`` (area average) to cut the number of samples needed.
"""
from __future__ import annotations

from functools import lru_cache

import torch
import torch.nn.functional as F

from .geometry import BevSpec, CameraModel, camera_pose_on_road

Tensor = torch.Tensor

_MIN_DEPTH = 0.1  # metres in front of the camera; closer ground points are invalid


@lru_cache(maxsize=32)
def _ground_points_h(spec: BevSpec, supersample: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """Road-frame points (x, y, 0) of the sub-samples of every BEV cell. -> ``(S, S, n*n, 3)``.

    Cached: they depend only on the grid (the per-frame cost is the projection, not this).

    The sub-samples sit at the centres of an ``n x n`` split of each cell, so their mean is the
    cell average; with ``n = 1`` this is exactly ``spec.ground_points``.
    """
    n = supersample
    centres = spec.ground_points(dtype=torch.float64, device="cpu")  # (S, S, 2)
    offs = (torch.arange(n, dtype=torch.float64) + 0.5) / n - 0.5  # (n,) in cells
    ox, oy = torch.meshgrid(offs, offs, indexing="ij")
    sub = torch.stack([ox, oy], dim=-1).reshape(n * n, 2) * spec.metres_per_pixel  # (n*n, 2)
    pts = centres[:, :, None, :] + sub[None, None]  # (S, S, n*n, 2)
    pts = torch.cat([pts, torch.zeros_like(pts[..., :1])], dim=-1)
    return pts.to(dtype=dtype, device=device)


def _check_attitude(pitch: Tensor, roll: Tensor) -> None:
    if pitch.ndim != 1 or roll.shape != pitch.shape:
        raise ValueError(f"pitch and roll must both be (B,), got {tuple(pitch.shape)} and {tuple(roll.shape)}")


def bev_sampling_grid(
    camera: CameraModel,
    pitch: Tensor,
    roll: Tensor,
    spec: BevSpec,
    supersample: int = 1,
    image_size: tuple[int, int] | None = None,
) -> tuple[Tensor, Tensor]:
    """Where every BEV (sub-)sample lands in the image, in ``grid_sample`` coordinates.

    Args:
        camera: the camera model (``K``, size, extrinsics, height).
        pitch, roll: ``(B,)`` attitude of the base relative to the road plane, radians.
        spec: the BEV grid.
        supersample: ``n``; each cell gets ``n x n`` sub-samples.
        image_size: ``(W, H)`` of the image actually sampled when it was reduced by an integer
            factor (see :func:`project_to_bev`); defaults to the camera's size.

    Returns:
        grid ``(B, S, S * n * n, 2)`` normalised ``(x, y)`` for ``grid_sample(align_corners=False)``
        (``n = 1``: ``(B, S, S, 2)``), and valid ``(B, S, S * n * n)`` bool: in front of the
        camera and at least one pixel inside the image border.
    """
    _check_attitude(pitch, roll)
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    dtype, device = pitch.dtype, pitch.device
    W, H = camera.width, camera.height_px
    R, t = camera_pose_on_road(camera, pitch, roll)  # (B, 3, 3), (B, 3)
    K = camera.K.to(dtype=dtype, device=device)
    pts = _ground_points_h(spec, supersample, dtype, device)  # (S, S, m, 3)
    S, m = spec.size, supersample * supersample
    p = pts.reshape(1, -1, 3) - t[:, None, :]  # (B, N, 3) road frame, relative to the camera
    # p_cam = R^T p: with row vectors that is p @ R; then project with K in one go.
    uvw = p @ (R @ K.transpose(0, 1))  # (B, N, 3) = (K R^T p)^T
    z = uvw[..., 2]
    front = z > _MIN_DEPTH
    zs = torch.where(front, z, torch.ones_like(z))  # no division by ~0 behind the camera
    u, v = uvw[..., 0] / zs, uvw[..., 1] / zs
    valid = front & (u >= 1.0) & (u <= W - 2.0) & (v >= 1.0) & (v <= H - 2.0)
    if image_size is not None:
        # Image reduced by an integer factor f: pixel j covers [f j - 0.5, f j + f - 0.5).
        f = W // image_size[0]
        u, v = (u - (f - 1) / 2.0) / f, (v - (f - 1) / 2.0) / f
        W, H = image_size
    gx = (2.0 * u + 1.0) / W - 1.0
    gy = (2.0 * v + 1.0) / H - 1.0
    # Keep invalid samples finite (they are masked) so gradients stay clean.
    gx = torch.where(valid, gx, torch.full_like(gx, -2.0))
    gy = torch.where(valid, gy, torch.full_like(gy, -2.0))
    grid = torch.stack([gx, gy], dim=-1).reshape(-1, S, S * m, 2)
    return grid, valid.reshape(-1, S, S * m)


def project_to_bev(
    image: Tensor,
    camera: CameraModel,
    pitch: Tensor,
    roll: Tensor,
    spec: BevSpec,
    supersample: int = 2,
    downsample: int = 1,
) -> tuple[Tensor, Tensor]:
    """Inverse perspective mapping of the image onto the BEV grid.

    Args:
        image: ``(B, 1, H, W)`` (or ``(B, C, H, W)``) float image, intensities in [0, 1].
        camera: the camera model; ``(W, H)`` must match the image.
        pitch, roll: ``(B,)`` attitude of the base relative to the road plane, radians.
        spec: the BEV grid.
        supersample: ``n x n`` bilinear samples averaged per BEV cell (anti-aliasing).
        downsample: integer factor the image is area-averaged by first (1 = off); halves the
            samples needed on high-resolution cameras at the price of detail far away.

    Returns:
        bev ``(B, C, S, S)`` (0 where invalid) and mask ``(B, 1, S, S)`` in {0, 1}: 1 where every
        sub-sample of the cell is in front of the camera and inside the image (1-pixel margin).
    """
    if image.ndim != 4:
        raise ValueError(f"image must be (B, C, H, W), got {tuple(image.shape)}")
    if not image.is_floating_point():
        raise ValueError(f"image must be a float tensor in [0, 1], got {image.dtype}")
    B, C, H, W = image.shape
    if (W, H) != (camera.width, camera.height_px):
        raise ValueError(f"image is {W}x{H} but the camera model is {camera.width}x{camera.height_px}")
    _check_attitude(pitch, roll)
    if pitch.shape[0] != B:
        raise ValueError(f"batch mismatch: image has {B} items, pitch/roll have {pitch.shape[0]}")
    if downsample < 1:
        raise ValueError(f"downsample must be >= 1, got {downsample}")
    pitch, roll = pitch.to(image.dtype), roll.to(image.dtype)
    size = None
    if downsample > 1:
        Hd, Wd = H // downsample, W // downsample
        image = F.avg_pool2d(image[..., : Hd * downsample, : Wd * downsample], downsample)
        size = (Wd, Hd)
    grid, valid = bev_sampling_grid(camera, pitch, roll, spec, supersample, size)
    S, m = spec.size, supersample * supersample
    samples = F.grid_sample(image, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    valid_f = valid.to(image.dtype)
    samples = samples * valid_f[:, None]  # (B, C, S, S*m)
    bev = samples.reshape(B, C, S, S, m).mean(dim=-1)
    mask = valid_f.reshape(B, 1, S, S, m).amin(dim=-1)
    return bev * mask, mask


__all__ = ["bev_sampling_grid", "project_to_bev"]
