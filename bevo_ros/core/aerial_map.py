"""A geo-referenced top-down image (orthophoto, satellite or drone map, or a BEV mosaic) and
differentiable crops of it (BEVO+, paper Section 3.2).

Conventions (nav2 ``map_server``'s YAML, REP-105 ``map`` frame):

* ``resolution``: metres per pixel; ``origin = (x, y, yaw)``: the map-frame pose of the
  *lower-left* corner of the image (nav2 semantics), image row 0 at the top. With yaw 0, the
  centre of pixel ``(row, col)`` is at ``x = ox + (col + 0.5) r``, ``y = oy + (H - row - 0.5) r``.
* Local grids (crops, mosaics) use the BEV's pixel convention of :mod:`bevo_ros.core.geometry`:
  row 0 towards local +x, column 0 towards local +y, centred on the grid's pose; so the
  phase-correlation angle/shift meaning of :mod:`bevo_ros.core.phase_correlation` carries over
  exactly (row = -x, column = -y in metres about the centre).

Pure torch, no files (``bevo_ros.io.maps`` reads and writes the YAML + image).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

Tensor = torch.Tensor

LUMA = (0.299, 0.587, 0.114)  # ITU-R BT.601, what OpenCV's BGR2GRAY uses


@dataclass
class AerialMap:
    """A top-down map image in the ``map`` frame.

    Attributes:
        image: ``(C, H, W)`` float in [0, 1] (C = 1 grey, 3 RGB).
        resolution: metres per pixel.
        origin: ``(x, y, yaw)`` of the image's lower-left corner in the map frame.
        valid: optional ``(1, H, W)`` mask (1 = known ground; e.g. a mosaic's coverage).
    """

    image: Tensor
    resolution: float
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    valid: Tensor | None = None

    def __post_init__(self) -> None:
        if self.image.ndim != 3 or self.image.shape[0] not in (1, 3, 4):
            raise ValueError(f"map image must be (C, H, W) with C in 1, 3, 4, got {tuple(self.image.shape)}")
        if not (math.isfinite(self.resolution) and self.resolution > 0):
            raise ValueError(f"map resolution must be > 0 metres per pixel, got {self.resolution!r}")
        if len(self.origin) != 3 or not all(math.isfinite(float(v)) for v in self.origin):
            raise ValueError(f"map origin must be finite (x, y, yaw), got {self.origin!r}")
        self.origin = tuple(float(v) for v in self.origin)
        if self.valid is not None and self.valid.shape != (1, *self.image.shape[1:]):
            raise ValueError(f"valid must be (1, H, W) = (1, {self.image.shape[1]}, {self.image.shape[2]}), "
                             f"got {tuple(self.valid.shape)}")

    @property
    def height(self) -> int:
        return self.image.shape[-2]

    @property
    def width(self) -> int:
        return self.image.shape[-1]

    @property
    def extent(self) -> tuple[float, float]:
        """Width and height in metres."""
        return self.width * self.resolution, self.height * self.resolution

    def grey(self) -> "AerialMap":
        """Luminance (C = 1) version; grey maps are returned as they are."""
        if self.image.shape[0] == 1:
            return self
        w = torch.tensor(LUMA, dtype=self.image.dtype, device=self.image.device)
        return AerialMap((self.image[:3] * w[:, None, None]).sum(0, keepdim=True), self.resolution, self.origin,
                         self.valid)

    def to(self, device=None, dtype: torch.dtype | None = None) -> "AerialMap":
        valid = None if self.valid is None else self.valid.to(device=device, dtype=dtype)
        return AerialMap(self.image.to(device=device, dtype=dtype), self.resolution, self.origin, valid)

    def resampled(self, resolution: float) -> "AerialMap":
        """The map at a coarser ``resolution`` exactly (anti-aliased: a box average of ~the factor,
        then bilinear at the new pixel centres); finer or equal resolutions return the map itself
        (upsampling adds nothing). The lower-left corner stays where it was; the image keeps the
        whole new pixels that fit (a partial strip at the top and right is left out). Before
        2026-12-06 each axis was rounded to its own size and the width's pixel size taken for both:
        a 2 km corridor map resampled 0.1 -> 0.25 m/px put a feature 1950 m up 6.5 m off."""
        factor = resolution / self.resolution
        if factor <= 1.0 + 1e-6:
            return self
        H, W = max(1, math.floor(self.height / factor + 1e-9)), max(1, math.floor(self.width / factor + 1e-9))
        k = max(1, int(round(factor)))
        k += 1 - k % 2  # odd: centred
        blur = lambda x: F.avg_pool2d(x[None], k, stride=1, padding=k // 2, count_include_pad=False)[0]  # noqa: E731
        dtype, device = self.image.dtype, self.image.device
        # new pixel (row i, col j) centre, in the old image's pixel coordinates (rows down from its top)
        col = (torch.arange(W, dtype=torch.float64, device=device) + 0.5) * factor - 0.5
        row = self.height - (H - torch.arange(H, dtype=torch.float64, device=device) - 0.5) * factor - 0.5
        grid = torch.stack([((2.0 * col + 1.0) / self.width - 1.0)[None, :].expand(H, W),
                            ((2.0 * row + 1.0) / self.height - 1.0)[:, None].expand(H, W)], dim=-1)
        grid = grid[None].to(dtype)

        def resample(x: Tensor) -> Tensor:
            return F.grid_sample(blur(x)[None], grid, mode="bilinear", padding_mode="border", align_corners=False)[0]

        img = resample(self.image)
        valid = None if self.valid is None else (resample(self.valid) > 0.999).to(img.dtype)
        return AerialMap(img, float(resolution), self.origin, valid)

    def pixel_coordinates(self, xy: Tensor) -> Tensor:
        """Map-frame points ``(..., 2)`` -> continuous ``(col, row)`` pixel coordinates ``(..., 2)``
        (integer values at pixel centres)."""
        ox, oy, oyaw = self.origin
        dx, dy = xy[..., 0] - ox, xy[..., 1] - oy
        c, s = math.cos(oyaw), math.sin(oyaw)
        u, v = c * dx + s * dy, -s * dx + c * dy  # in the image's own axes, from its lower-left corner
        return torch.stack([u / self.resolution - 0.5, self.height - v / self.resolution - 0.5], dim=-1)

    def world_coordinates(self, colrow: Tensor) -> Tensor:
        """Inverse of :func:`pixel_coordinates`: ``(..., 2)`` ``(col, row)`` -> map ``(x, y)``."""
        ox, oy, oyaw = self.origin
        u = (colrow[..., 0] + 0.5) * self.resolution
        v = (self.height - colrow[..., 1] - 0.5) * self.resolution
        c, s = math.cos(oyaw), math.sin(oyaw)
        return torch.stack([ox + c * u - s * v, oy + s * u + c * v], dim=-1)

    def sample(self, xy: Tensor) -> tuple[Tensor, Tensor]:
        """Bilinear samples at map points ``xy (B, H', W', 2)`` -> values ``(B, C, H', W')`` and a
        validity mask ``(B, 1, H', W')`` (inside the image and, if given, the ``valid`` mask).
        Differentiable in ``xy`` and in the image."""
        pix = self.pixel_coordinates(xy)
        grid = torch.stack([(2.0 * pix[..., 0] + 1.0) / self.width - 1.0,
                            (2.0 * pix[..., 1] + 1.0) / self.height - 1.0], dim=-1).to(self.image.dtype)
        B = xy.shape[0]
        img = self.image[None].expand(B, -1, -1, -1)
        values = F.grid_sample(img, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        ones = torch.ones_like(self.image[:1]) if self.valid is None else self.valid
        inside = F.grid_sample(ones[None].expand(B, -1, -1, -1), grid.detach(), mode="bilinear",
                               padding_mode="zeros", align_corners=False)
        return values, (inside > 0.999).to(values.dtype)

    def crop(self, pose: Tensor, size: int, resolution: float) -> tuple[Tensor, Tensor]:
        """The map seen from a local ``size x size`` grid at ``resolution`` m/px centred on each
        ``pose (B, 3)`` (map-frame x, y, yaw of the grid centre; :func:`local_grid` axes).
        -> image ``(B, C, S, S)``, mask ``(B, 1, S, S)``. Resample the map to about
        ``resolution`` first (:meth:`resampled`) when it is much finer, or it aliases."""
        pts = transform_points(pose, local_grid(size, resolution, pose.dtype, pose.device))
        return self.sample(pts)


def local_grid(size: int, resolution: float, dtype: torch.dtype = torch.float32, device=None) -> Tensor:
    """Local ``(x, y)`` metres of the pixel centres of a ``size x size`` grid centred on 0, BEV
    axes (row 0 at +x, column 0 at +y). -> ``(S, S, 2)``."""
    i = ((size - 1) / 2.0 - torch.arange(size, dtype=torch.float64)) * resolution
    xx, yy = torch.meshgrid(i, i, indexing="ij")
    return torch.stack([xx, yy], dim=-1).to(dtype=dtype, device=device)


def transform_points(pose: Tensor, points: Tensor) -> Tensor:
    """``pose (B, 3)`` (x, y, yaw) applied to local points ``(..., 2)`` -> ``(B, ..., 2)``."""
    B = pose.shape[0]
    extra = (None,) * (points.ndim - 1)
    x, y, yaw = (pose[:, k][(slice(None),) + extra] for k in range(3))
    c, s = torch.cos(yaw), torch.sin(yaw)
    px, py = points[..., 0][None], points[..., 1][None]
    out = torch.stack([x + c * px - s * py, y + s * px + c * py], dim=-1)
    return out.reshape(B, *points.shape)


__all__ = ["AerialMap", "LUMA", "local_grid", "transform_points"]
