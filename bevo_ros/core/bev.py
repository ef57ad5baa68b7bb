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

import math
import threading

import torch
import torch.nn.functional as F

from .device import constant_cache
from .geometry import BevSpec, CameraModel, camera_pose_on_road

Tensor = torch.Tensor

_MIN_DEPTH = 0.1  # metres in front of the camera; closer ground points are invalid


@constant_cache(32)
def _ground_axes(spec: BevSpec, supersample: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """Road-frame ``x`` of the sub-sample rows and ``y`` of the sub-sample columns, ``(n, S)`` each.

    The BEV grid is axis-aligned on the road (row -> x, column -> y), so its sub-samples are the
    outer product of these two axes. ``x[a, i]`` is the centre of the ``a``-th of ``n`` strips of
    row ``i`` (likewise ``y[b, j]``), so the mean over ``(a, b)`` is the cell average; ``n = 1`` is
    exactly ``spec.ground_points``. Cached: they depend only on the grid.
    """
    n, S = supersample, spec.size
    fine = BevSpec(S * n, spec.metres_per_pixel / n, spec.forward_offset)  # fine row i n + a
    xy = fine.ground_points(dtype=torch.float64, device="cpu")
    x = xy[:, 0, 0].reshape(S, n).T
    y = xy[0, :, 1].reshape(S, n).T
    return x.to(dtype=dtype, device=device).contiguous(), y.to(dtype=dtype, device=device).contiguous()


@constant_cache(32)
def _pixel_to_grid(size: tuple[int, int], image_size: tuple[int, int] | None, dtype: torch.dtype,
                   device: torch.device) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The pixel -> ``grid_sample`` affine map of :func:`bev_sampling_grid` for a camera of
    ``size (W, H)`` sampled at ``image_size``: ``scale``, ``offset`` ``(2, 1)`` and the inside
    test's centre and half width ``(2, 1, 1)`` in grid units. Cached: they depend only on the sizes."""
    W, H = size
    # Pixel u (OpenCV centres) -> grid_sample g = (2 u + 1) / W - 1, or on an image reduced by an
    # integer factor f, where pixel j covers [f j - 0.5, f j + f - 0.5): u' = (u - (f - 1) / 2) / f.
    f = 1 if image_size is None else W // image_size[0]
    Ws, Hs = (W, H) if image_size is None else image_size
    c = 1.0 - (f - 1.0) / f
    scale = torch.tensor([2.0 / (f * Ws), 2.0 / (f * Hs)], dtype=dtype, device=device)
    offset = torch.tensor([c / Ws - 1.0, c / Hs - 1.0], dtype=dtype, device=device)
    # Inside with a 1-pixel margin, u in [1, W - 2] and v in [1, H - 2], in grid units.
    lo = torch.tensor([1.0, 1.0], dtype=dtype, device=device) * scale + offset
    hi = torch.tensor([W - 2.0, H - 2.0], dtype=dtype, device=device) * scale + offset
    return scale[:, None], offset[:, None], (0.5 * (lo + hi))[:, None, None], (0.5 * (hi - lo))[:, None, None]


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
        grid ``(B, n n S, S, 2)`` normalised ``(x, y)`` for ``grid_sample(align_corners=False)``
        and valid ``(B, n n S, S)`` bool: in front of the camera and at least one pixel inside the
        image border. Sub-sample ``(a, b)`` of cell ``(i, j)`` is at row ``(a n + b) S + i``,
        column ``j``: each sub-sample is an ``(S, S)`` plane, so the cell mean is a mean over
        planes (``n = 1``: the plain ``(B, S, S, 2)`` grid). Invalid samples are finite.
    """
    g, w, margin = _sampling_grid(camera, pitch, roll, spec, supersample, image_size)
    valid = (margin <= 0).all(dim=1) & (w > _MIN_DEPTH)
    return g.permute(0, 2, 3, 1), valid


def _sampling_grid(camera: CameraModel, pitch: Tensor, roll: Tensor, spec: BevSpec, supersample: int,
                   image_size: tuple[int, int] | None) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`bev_sampling_grid` on planar tensors: ``g (B, 2, n n S, S)`` (x, y), the depth
    ``w (B, n n S, S)`` and the inside test's ``margin (B, 2, n n S, S)`` = ``|g - mid| - half``,
    ``<= 0`` exactly where ``|g - mid| <= half`` (IEEE: a difference rounds to 0 only when it is 0,
    and never changes sign), which lets the caller reduce it with ``amax`` rather than boolean ops."""
    _check_attitude(pitch, roll)
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    dtype, device = pitch.dtype, pitch.device
    B, S, n = pitch.shape[0], spec.size, supersample
    R, t = camera_pose_on_road(camera, pitch, roll)  # (B, 3, 3), (B, 3)
    K = camera.K.to(dtype=dtype, device=device)
    size = None if image_size is None else (int(image_size[0]), int(image_size[1]))
    scale, offset, mid, half = _pixel_to_grid((camera.width, camera.height_px), size, dtype, device)
    # The road plane maps to the image through a homography: for a road point p = (x, y, 0),
    # (u w, v w, w) = M (p - t) with M = K R^T. Folding the u -> g affine map into M's first two
    # rows gives g = (A (p - t))_xy / w directly, and as the grid is axis-aligned,
    # A (p - t) = (A[:, 0] x_row - A t) + A[:, 1] y_col: an outer sum, no per-point matmul.
    M = K @ R.transpose(-1, -2)  # (B, 3, 3)
    A = torch.cat([M[:, :2] * scale + offset * M[:, 2:], M[:, 2:]], dim=1)
    x, y = _ground_axes(spec, n, dtype, device)  # (n, S) each
    at = (A @ t[:, :, None])[:, :, :, None]  # (B, 3, 1, 1)
    by_row = A[:, :, 0, None, None] * x - at  # (B, 3, n, S)
    by_col = A[:, :, 1, None, None] * y  # (B, 3, n, S)
    # Planar (B, 3, a, b, i, j) layout: elementwise ops on contiguous planes are fast on CPU.
    gw = (by_row[:, :, :, None, :, None] + by_col[:, :, None, :, None, :]).reshape(B, 3, n * n * S, S)
    w = gw[:, 2]
    g = gw[:, :2] / w.clamp_min(_MIN_DEPTH)[:, None]  # finite everywhere, also behind the camera
    # Inside the 1-pixel margin: |g - mid| <= half on both axes (a test: no gradient).
    return g, w, (g.detach() - mid).abs_().sub_(half)


_buffers = threading.local()  # per thread: {(shape, dtype, device): float image} for _as_float


def _as_float(image: Tensor, g: Tensor, dtype: torch.dtype) -> Tensor:
    """The uint8 ``image (B, C, H, W)`` as floats for sampling at ``g (B, 2, N, S)``: converting a
    whole camera image was the projection's costliest step (0.1-0.2 ms of a 1241x376 one per frame
    on this CPU: a fresh 1.9 MB block each frame, page faults included), while the BEV's road patch
    spans ~a third of its rows. Outside autograd and ``torch.compile`` only the rows that the samples'
    bilinear footprints reach are converted, into a buffer kept per thread, shape and dtype; its other
    rows hold earlier frames' pixels, which no sample reads. Bit for bit what ``image.to(dtype)``
    gives the samples: the same coordinates, the same pixel values. A batch of more than one image
    (offline, batched) is converted whole, as before: its buffer would stay held after the batch; so
    is an image on a GPU, where converting it is cheap and reading the rows' range would sync twice."""
    if g.requires_grad or torch.compiler.is_compiling() or image.shape[0] != 1 or image.device.type != "cpu":
        return image.to(dtype)  # (autograd: a backward pass would read the buffer after it changed)
    H = image.shape[-2]
    lo, hi = (float(v) for v in torch.aminmax(g[:, 1].detach()))
    # grid_sample (align_corners=False) reads rows floor(v) and floor(v) + 1 of v = ((g + 1) H - 1) / 2
    if math.isfinite(lo) and math.isfinite(hi):
        r0 = max(0, math.floor(((lo + 1.0) * H - 1.0) / 2.0) - 1)
        r1 = min(H, math.floor(((hi + 1.0) * H - 1.0) / 2.0) + 3)
    else:  # (not for a valid attitude: the grid is finite by construction)
        r0, r1 = 0, H
    cache = getattr(_buffers, "images", None)
    if cache is None:
        cache = _buffers.images = {}
    key = (tuple(image.shape), dtype, image.device)
    buffer = cache.get(key)
    if buffer is None:
        if len(cache) >= 4:  # a few cameras per thread (the odometry and a localiser side by side)
            del cache[next(iter(cache))]
        with torch.inference_mode(False):  # a normal tensor: written in and outside inference mode alike
            buffer = cache[key] = torch.zeros(image.shape, dtype=dtype, device=image.device)
    if r1 > r0:
        buffer[..., r0:r1, :].copy_(image[..., r0:r1, :])
    return buffer


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
        image: ``(B, 1, H, W)`` (or ``(B, C, H, W)``) float image with intensities in [0, 1], or
            uint8 in [0, 255]: that is sampled in ``pitch``'s float dtype and the BEV scaled by
            1/255 (sampling is linear, so this equals projecting ``image / 255`` without a pass
            over the whole image).
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
    if not (image.is_floating_point() or image.dtype == torch.uint8):
        raise ValueError(f"image must be a float tensor in [0, 1] or uint8, got {image.dtype}")
    B, C, H, W = image.shape
    if (W, H) != (camera.width, camera.height_px):
        raise ValueError(f"image is {W}x{H} but the camera model is {camera.width}x{camera.height_px}")
    _check_attitude(pitch, roll)
    if pitch.shape[0] != B:
        raise ValueError(f"batch mismatch: image has {B} items, pitch/roll have {pitch.shape[0]}")
    if downsample < 1:
        raise ValueError(f"downsample must be >= 1, got {downsample}")
    scale = None
    uint8 = image.dtype == torch.uint8
    if uint8:
        scale = 1.0 / 255.0
        float_dtype = pitch.dtype if pitch.is_floating_point() else torch.float32
        if downsample > 1:
            image = image.to(float_dtype)
    else:
        float_dtype = image.dtype
    pitch, roll = pitch.to(float_dtype), roll.to(float_dtype)
    size = None
    if downsample > 1:
        Hd, Wd = H // downsample, W // downsample
        image = F.avg_pool2d(image[..., : Hd * downsample, : Wd * downsample], downsample)
        size = (Wd, Hd)
    g, w, margin = _sampling_grid(camera, pitch, roll, spec, supersample, size)
    if uint8 and downsample == 1:
        image = _as_float(image, g, float_dtype)
    S, m = spec.size, supersample * supersample
    samples = F.grid_sample(image, g.permute(0, 2, 3, 1), mode="bilinear", padding_mode="zeros", align_corners=False)
    bev = samples.reshape(B, C, m, S, S).mean(dim=2)  # the sub-sample mean: a box filter on the ground
    # Valid only if every sub-sample is (bev_sampling_grid's test, reduced as max / min: 3x cheaper
    # than boolean tensors on the CPU, the same mask).
    inside = margin.reshape(B, 2 * m, S, S).amax(dim=1) <= 0
    mask = (inside & (w.detach().reshape(B, m, S, S).amin(dim=1) > _MIN_DEPTH)).to(image.dtype)[:, None]
    return (bev * mask if scale is None else bev * (mask * scale)), mask


__all__ = ["bev_sampling_grid", "project_to_bev"]
