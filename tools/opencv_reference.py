"""A plain OpenCV implementation of BEVO's vision step: the yardstick ``bench_core.py`` times.

Absolute times differ ~2x between machines, so the engine's cost per frame is reported as a
ratio against this reference, measured in the same run on the same frames. The reference is a
real, working implementation (``test/test_bench_reference.py`` checks that it recovers known
motions), written with the stock calls an OpenCV developer would reach for:

1. BEV: ``cv2.remap`` of the uint8 image with maps precomputed from the *same* camera model and
   road-plane homography as ``bevo_ros.core.bev`` (the same ``2 x 2`` sub-samples per cell, the
   same validity rule), then ``cv2.resize(INTER_AREA)`` for the 2x2 cell mean.
2. Weighting: the BEV minus its weighted mean times a fixed weight (soft mask edge x radial Hann,
   as the engine's ``soft_weight``).
3. Rotation: ``cv2.dft`` of the BEV zero-padded to 2x (real input, packed output: ~4x cheaper than
   the complex one), log magnitude on the half plane, ``cv2.warpPolar``
   (linear polar: scale is fixed at 1, as in the engine) onto 360 angle bins over 180 degrees x
   36 radii in 0.05..0.40 cycles/pixel (the engine's grid), ``cv2.phaseCorrelate`` along it.
4. Translation: ``cv2.warpAffine`` rotates the current BEV back, ``cv2.phaseCorrelate`` gives
   the shift (sub-pixel by its centroid).
5. Motion: the registration turned into ``(dx, dy, dyaw)`` as ``bevo_ros.core.motion`` does.

What it leaves out, so the ratio reads as "what the engine's extras cost": no IMU filter, fixed
maps and weight (the engine rebuilds its sampling grid and mask weight every frame from the
filtered attitude; :meth:`OpenCvReference.project_at` is the attitude-following projection with
``cv2.warpPerspective``, timed apart by the bench), point estimates only (no softmax distributions, covariances, overlap
envelope, sub-pixel peak fits, pose composition). ``cv2.phaseCorrelate`` does recompute the
previous frame's spectra each call (the engine keeps them), a small cost in the other direction.

Registration convention (as ``bevo_ros.core.phase_correlation``): ``curr(q) = prev(c + R(-angle)
(q - c) - shift)`` for BEV pixels ``q = (row, col)``, ``shift = (d_row, d_col)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from bevo_ros.core.geometry import BevSpec, CameraModel, camera_pose_on_road

_MIN_DEPTH = 0.1  # metres, as core.bev


def bev_maps(camera: CameraModel, spec: BevSpec, pitch: float = 0.0, roll: float = 0.0,
             supersample: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Image coordinates of every BEV sub-sample, for ``cv2.remap``.

    The fine grid ``BevSpec(n S, mpp / n, forward_offset)`` holds the same ``n x n`` sub-samples per
    cell as ``core.bev`` (fine row ``i n + a`` = strip ``a`` of row ``i``), so an ``n x n`` area mean
    of the remapped fine image is the engine's cell mean. The road plane maps to the image through
    the homography ``(u w, v w, w) = K R^T (p - t)`` of the camera pose on the road.

    Returns:
        map_x, map_y ``(n S, n S)`` float32 pixel coordinates (OpenCV centres; -100 where invalid),
        mask ``(S, S)`` float32: 1 where every sub-sample is in front of the camera and at least
        one pixel inside the image border (the engine's rule).
    """
    n, S = supersample, spec.size
    R, t = camera_pose_on_road(camera.to(dtype=torch.float64), torch.tensor([float(pitch)], dtype=torch.float64),
                               torch.tensor([float(roll)], dtype=torch.float64))
    M = (camera.K.double() @ R[0].T).numpy()
    mt = M @ t[0].numpy()
    k = np.arange(n * S, dtype=np.float64)
    x = spec.forward_offset + (n * S - 0.5 - k) * spec.metres_per_pixel / n  # by fine row
    y = ((n * S - 1) / 2.0 - k) * spec.metres_per_pixel / n  # by fine column
    uvw = M[:, 0, None, None] * x[None, :, None] + M[:, 1, None, None] * y[None, None, :] - mt[:, None, None]
    w = uvw[2]
    u, v = uvw[0] / np.maximum(w, _MIN_DEPTH), uvw[1] / np.maximum(w, _MIN_DEPTH)
    W, H = camera.width, camera.height_px
    valid = (w > _MIN_DEPTH) & (u >= 1) & (u <= W - 2) & (v >= 1) & (v <= H - 2)
    u, v = np.where(valid, u, -100.0), np.where(valid, v, -100.0)
    mask = valid.reshape(S, n, S, n).all(axis=(1, 3)).astype(np.float32)
    return u.astype(np.float32), v.astype(np.float32), mask


def bev_homography(camera: CameraModel, spec: BevSpec, pitch: float, roll: float, supersample: int = 2) -> np.ndarray:
    """``(3, 3)`` homography from fine-BEV pixels ``(col, row, 1)`` to image ``(u w, v w, w)``: the
    same mapping as :func:`bev_maps`, for ``cv2.warpPerspective(..., WARP_INVERSE_MAP)`` at any
    attitude (numpy, ~10 us: ``core.geometry.camera_pose_on_road`` in floats)."""
    cp, sp, cr, sr = math.cos(pitch), math.sin(pitch), math.cos(roll), math.sin(roll)
    R_road_base = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]]) @ np.array(
        [[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    T = camera.T_base_cam.double().numpy()
    R = R_road_base @ T[:3, :3]
    t = R_road_base @ T[:3, 3]
    t[2] = camera.mount_height
    M = camera.K.double().numpy() @ R.T
    m = spec.metres_per_pixel / supersample
    N = supersample * spec.size
    to_road = np.array([[0.0, -m, spec.forward_offset + (N - 0.5) * m], [-m, 0.0, (N - 1) / 2.0 * m], [0.0, 0.0, 1.0]])
    return np.column_stack([M[:, 0], M[:, 1], -(M @ t)]) @ to_road


def soft_weight(mask: np.ndarray, blur: float = 2.0) -> np.ndarray:
    """(Soft mask edge) x (radial Hann window), as ``core.phase_correlation.soft_weight`` with its
    defaults (a Gaussian blur here instead of the engine's two box filters). ``(S, S)`` -> same."""
    S = mask.shape[0]
    b = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), blur, borderType=cv2.BORDER_REPLICATE)
    t = np.clip(2.0 * b - 1.0, 0.0, 1.0)
    i = np.arange(S) - (S - 1) / 2.0
    r = np.sqrt(i[:, None] ** 2 + i[None, :] ** 2) / (S / 2.0)
    window = 0.5 * (1.0 + np.cos(math.pi * np.clip(r, 0.0, 1.0)))
    return (t * t * (3.0 - 2.0 * t) * mask * window).astype(np.float32)


def ccs_half_magnitude(ccs: np.ndarray) -> np.ndarray:
    """``|Y|`` on the half plane ``(M, N / 2 + 1)`` (columns = non-negative column frequencies) from
    ``cv2.dft``'s packed real output (CCS, ``M``, ``N`` even). ``(M, N)`` -> ``(M, N / 2 + 1)``.

    The real-input DFT is ~4x cheaper than ``DFT_COMPLEX_OUTPUT`` on a 200x200 float32; the
    packed layout holds columns ``1 .. N/2 - 1`` as (Re, Im) pairs and the two real-signal
    columns 0 and ``N/2`` as 1-D packed spectra along the rows.
    """
    M, N = ccs.shape
    out = np.empty((M, N // 2 + 1), np.float32)
    out[:, 1 : N // 2] = cv2.magnitude(np.ascontiguousarray(ccs[:, 1 : N - 1 : 2]),
                                       np.ascontiguousarray(ccs[:, 2 : N - 1 : 2]))
    for src, dst in ((0, 0), (N - 1, N // 2)):
        col = ccs[:, src]
        half = np.hypot(col[1 : M - 1 : 2], col[2 : M - 1 : 2])  # rows 1 .. M/2 - 1
        out[0, dst], out[M // 2, dst] = abs(col[0]), abs(col[M - 1])
        out[1 : M // 2, dst] = half
        out[M // 2 + 1 :, dst] = half[::-1]  # real signal: |Y[M - m]| = |Y[m]|
    return out


@dataclass
class Frame:
    """One BEV made ready: ``image (S, S)`` weighted zero-mean BEV, ``polar (A, R)`` log magnitude."""

    image: np.ndarray
    polar: np.ndarray


class OpenCvReference:
    """BEV projection + rotation and translation phase correlation with stock OpenCV calls.

    Args:
        camera: the camera model (as the engine's).
        spec: the BEV grid (default 100 x 100 at 0.1 m).
        pitch, roll: the fixed road-relative attitude the maps are built for, radians.
        supersample: sub-samples per cell side (the engine's default 2).
        angle_bins: bins over 180 degrees (the engine's 360: 0.5 degrees each).
        radial_range, radial_samples: Fourier radii (cycles/pixel) for the rotation (the engine's).
        padding: zero padding of the rotation FFT (the engine's 2).
    """

    def __init__(self, camera: CameraModel, spec: BevSpec | None = None, pitch: float = 0.0, roll: float = 0.0,
                 supersample: int = 2, angle_bins: int = 360, radial_range: tuple[float, float] = (0.05, 0.40),
                 radial_samples: int = 36, padding: int = 2) -> None:
        self.spec = spec or BevSpec()
        self.camera = camera
        self.supersample = supersample
        map_x, map_y, self.mask = bev_maps(camera, self.spec, pitch, roll, supersample)
        # Fixed-point maps: what cv2.remap users precompute (as with initUndistortRectifyMap).
        self.map1, self.map2 = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2)
        self.weight = soft_weight(self.mask)
        self.weight_sum = float(self.weight.sum())
        S = self.spec.size
        self.padded = padding * S
        lo, hi = radial_range
        # warpPolar samples radius j * max_radius / width: radial_samples radii from lo to hi.
        step = (hi - lo) * self.padded / (radial_samples - 1)
        self.r0 = int(round(lo * self.padded / step))
        self.polar_size = (self.r0 + radial_samples, 2 * angle_bins)  # (width = radii, height = angles over 360)
        self.max_radius = step * self.polar_size[0]
        self.angle_bins = angle_bins
        self.radial_samples = radial_samples
        # The angle axis is periodic (the magnitude repeats every 180 degrees); the radius is not: Hann along it.
        self.polar_window = np.tile(np.hanning(radial_samples + 2)[1:-1].astype(np.float32), (angle_bins, 1))
        self.prev: Frame | None = None

    def reset(self) -> None:
        self.prev = None

    def project(self, image: np.ndarray) -> np.ndarray:
        """``(H, W)`` uint8 image -> ``(S, S)`` float32 BEV in [0, 1], 0 outside the mask."""
        S = self.spec.size
        fine = cv2.remap(image, self.map1, self.map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        bev = cv2.resize(fine.astype(np.float32), (S, S), interpolation=cv2.INTER_AREA) if self.supersample > 1 \
            else fine.astype(np.float32)
        return bev * (self.mask * (1.0 / 255.0) if image.dtype == np.uint8 else self.mask)

    def project_at(self, image: np.ndarray, pitch: float, roll: float) -> np.ndarray:
        """:meth:`project` for any attitude, as the engine does every frame: ``cv2.warpPerspective``
        with the frame's homography instead of fixed maps (the mask stays the fixed one)."""
        S, n = self.spec.size, self.supersample
        H = bev_homography(self.camera, self.spec, pitch, roll, n)
        fine = cv2.warpPerspective(image, H, (n * S, n * S), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                   borderMode=cv2.BORDER_CONSTANT)
        bev = cv2.resize(fine.astype(np.float32), (S, S), interpolation=cv2.INTER_AREA) if n > 1 \
            else fine.astype(np.float32)
        return bev * (self.mask * (1.0 / 255.0) if image.dtype == np.uint8 else self.mask)

    def prepare(self, bev: np.ndarray) -> Frame:
        """Weight the BEV and compute its polar log-magnitude spectrum."""
        S, P = self.spec.size, self.padded
        w = self.weight
        image = w * (bev - float((w * bev).sum()) / self.weight_sum)
        padded = cv2.copyMakeBorder(image, 0, P - S, 0, P - S, cv2.BORDER_CONSTANT, value=0)
        mag = ccs_half_magnitude(cv2.dft(padded))  # (P, P/2 + 1): the half plane of column frequency >= 0
        mag = np.log1p(mag * (1.0 / (float(mag.mean()) + 1e-12)))  # brightness invariant, compressed
        mag = np.roll(mag, P // 2, axis=0)  # DC at (x = 0, y = P/2)
        polar = cv2.warpPolar(mag, self.polar_size, (0.0, P / 2.0), self.max_radius,
                              cv2.INTER_LINEAR | cv2.WARP_POLAR_LINEAR | cv2.WARP_FILL_OUTLIERS)
        # Rows = angle over 360 degrees, columns = radius; the half plane is -90 .. 90 degrees (the
        # magnitude is point symmetric: that is all of it, periodic over 180 degrees).
        A, a = self.angle_bins, self.angle_bins // 2
        polar = np.concatenate([polar[2 * A - a :, self.r0 :], polar[:a, self.r0 :]])
        return Frame(image, polar)

    def register(self, prev: Frame, curr: Frame) -> tuple[float, np.ndarray, float]:
        """-> angle (rad, in [-pi/2, pi/2)), shift ``(d_row, d_col)`` pixels, translation response."""
        (_, d_angle), _ = cv2.phaseCorrelate(prev.polar, curr.polar, self.polar_window)
        A = self.angle_bins
        # warpPolar's angle runs clockwise on screen (towards +row from +col): the engine's angle is minus it.
        angle = -((d_angle + A / 2) % A - A / 2) * math.pi / A
        S = self.spec.size
        c = (S - 1) / 2.0
        # Rotate curr back by -angle: getRotationMatrix2D's positive angle turns the content
        # counter-clockwise on screen, the engine's positive angle.
        rot = cv2.getRotationMatrix2D((c, c), -math.degrees(angle), 1.0)
        derotated = cv2.warpAffine(curr.image, rot, (S, S), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        (d_col, d_row), response = cv2.phaseCorrelate(prev.image, derotated)
        return angle, np.array([d_row, d_col]), float(response)

    def motion(self, angle: float, shift: np.ndarray) -> np.ndarray:
        """Registration -> base motion ``(dx, dy, dyaw)`` (``core.motion.vehicle_motion_from_registration``)."""
        dyaw = -angle
        cx, cy = self.spec.centre
        c, s = math.cos(dyaw), math.sin(dyaw)
        mpp = self.spec.metres_per_pixel
        return np.array([cx - (c * cx - s * cy) + mpp * shift[0], cy - (s * cx + c * cy) + mpp * shift[1], dyaw])

    def step(self, image: np.ndarray) -> np.ndarray | None:
        """One frame: project, prepare, register against the previous frame. -> motion or None (first)."""
        curr = self.prepare(self.project(image))
        prev, self.prev = self.prev, curr
        if prev is None:
            return None
        angle, shift, _ = self.register(prev, curr)
        return self.motion(angle, shift)


__all__ = ["OpenCvReference", "Frame", "bev_homography", "bev_maps", "ccs_half_magnitude", "soft_weight"]
