"""Synthetic road scenes with exact ground truth: procedural ground, drive, camera renderer and IMU.

The world frame is the road plane (z up along the road normal, the road surface is ``z = 0``),
so the renderer and the BEV projection share the geometry of :mod:`bevo_ros.core.geometry`
exactly (the camera pose comes from :func:`~bevo_ros.core.geometry.camera_pose_on_road`).

Model of the drive (all signals are smooth analytic functions of time, so the IMU is exact to
~1e-8):

* the base (IMU) origin moves on the road with speed ``v(t)`` and heading ``yaw(t)``;
  its road-relative attitude is ``R_road_base = Ry(pitch_rel) @ Rx(roll_rel)`` (suspension:
  sinusoids, bump events, and load transfer from the longitudinal/lateral acceleration) and its
  height follows from the fixed camera height (the geometry module's constant-elevation model);
* the road is tilted against gravity by a slowly varying slope and camber, defined relative to
  the heading (a banked, graded road the car follows):
  ``R_grav_base = Rz(yaw) @ Ry(slope) @ Rx(camber) @ Ry(pitch_rel) @ Rx(roll_rel)``;
* the velocity in the gravity frame is the road-frame velocity carried by the local road tilt,
  ``v_grav = Rz(yaw) Ry(slope) Rx(camber) [v, 0, dz/dt]``; its time derivative is the kinematic
  acceleration of the accelerometer model (rotating the whole world plane by the tilt instead would
  create huge spurious accelerations far from the origin);
* speed and yaw rate are seeded random (sines, curve events) or a named preset (:data:`PRESETS`:
  sustained curve, hard braking, start inside a bend, stop-and-go, bumpy road) built from C4 smooth
  steps with closed-form integrals; the suspension, road tilt and noise stay seeded either way;
* gyro = body angular velocity of ``R_grav_base`` (5-point central differences of the analytic
  rotation, error ~1e-9 rad/s), accel = specific force ``R_grav_base^T (a_grav + [0, 0, g])``
  (error ~3e-8 m/s^2).

Arrays of a :class:`SyntheticDrive` are numpy (float64 unless stated); the BEV helpers
(:func:`true_bev`, :func:`ground_patch`) return torch tensors to compare with ``core.bev``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import Protocol, Sequence

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from bevo_ros.core.geometry import BevSpec, CameraModel, camera_pose_on_road

__all__ = [
    "GRAVITY", "ImuNoise", "LazyImages", "RenderOptions", "RoadGround", "SyntheticDrive", "base_poses_4x4",
    "camera_pose_world", "camera_poses_4x4", "default_ground", "ground_intensity", "ground_patch",
    "kitti_like_camera", "make_drive", "PRESETS", "preset_drive", "render_frame", "render_view", "true_bev",
]

Tensor = torch.Tensor

GRAVITY = 9.80665
KITTI_K = ((718.856, 0.0, 607.1928), (0.0, 718.856, 185.2157), (0.0, 0.0, 1.0))
KITTI_SIZE = (1241, 376)  # width, height

# ---------------------------------------------------------------------------------------------
# Camera
# ---------------------------------------------------------------------------------------------


def kitti_like_camera(
    mount_pitch: float = 0.0,
    mount_height: float = 1.65,
    offset: Sequence[float] = (1.08, 0.0, 0.73),
    dtype: torch.dtype = torch.float64,
) -> CameraModel:
    """The KITTI grey camera (1241x376, fx = fy = 718.856) on the base frame.

    Args:
        mount_pitch: camera pitch on the base, radians; positive looks down (the nose-down sign).
        mount_height: camera centre height above the road, metres.
        offset: camera centre in the base frame (x fwd, y left, z up), metres.
    """
    # Optical axes in base coordinates: x_cam = -y_base (right), y_cam = -z_base (down), z_cam = x_base.
    r_opt = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
    c, s = math.cos(mount_pitch), math.sin(mount_pitch)
    r_y = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float64)
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = r_y @ r_opt
    T[:3, 3] = torch.tensor([float(v) for v in offset], dtype=torch.float64)
    K = torch.tensor(KITTI_K, dtype=torch.float64)
    return CameraModel(K.to(dtype), KITTI_SIZE[0], KITTI_SIZE[1], T.to(dtype), float(mount_height))


# ---------------------------------------------------------------------------------------------
# Ground texture
# ---------------------------------------------------------------------------------------------

_FINE_RES = 0.025  # metres per texel of the fine tile
_FINE_SIZE = 4096  # texels: 102.4 m period
_COARSE_RES = 0.4  # metres per texel of the coarse tile
_COARSE_SIZE = 1024  # 409.6 m period, rotated against the fine tile
_COARSE_ANGLE = 0.61  # rad; the two periods never line up, so the sum does not repeat
_ASPHALT = 0.36
_MARK = 0.86
# (lateral offset d in metres, left positive; dashed?) of the lane markings along the lane path.
_LINES = ((-1.75, False), (1.75, True), (5.25, False))
_LINE_WIDTH = 0.13
_DASH, _DASH_PERIOD = 3.0, 9.0
_EDGE = 0.02  # soft edge of the markings, metres (keeps the ground continuous)


def _periodic_noise(gen: torch.Generator, n: int, res: float, scale_min: float, scale_max: float, beta: float) -> Tensor:
    """Zero-mean, unit-std, seamlessly periodic band-limited noise. -> ``(n, n)`` float32.

    Amplitude spectrum ~ ``f^-beta`` between the wavelengths ``scale_min`` and ``scale_max`` metres.
    """
    fy = torch.fft.fftfreq(n, d=res, dtype=torch.float64)[:, None]
    fx = torch.fft.rfftfreq(n, d=res, dtype=torch.float64)[None, :]
    lo, hi = 1.0 / scale_max, 1.0 / scale_min
    spec = torch.randn((n, n // 2 + 1), dtype=torch.complex64, generator=gen)
    spec_ri = torch.view_as_real(spec)
    for r0 in range(0, n, 256):  # shaped in row blocks, in place: peak memory ~2 spectra
        f2 = fx * fx + fy[r0:r0 + 256] ** 2
        amp = torch.exp(-f2 / hi**2) * (1.0 - torch.exp(-f2 / lo**2)) * f2.clamp_min(0.25 * lo * lo) ** (-0.5 * beta)
        spec_ri[r0:r0 + 256] *= amp.to(torch.float32)[..., None]
    # irfft2 in blocks (columns, then rows): torch's irfft2 would need 3 spectra of scratch.
    for c0 in range(0, spec.shape[1], 256):
        spec[:, c0:c0 + 256] = torch.fft.ifft(spec[:, c0:c0 + 256], dim=0)
    out = torch.empty((n, n), dtype=torch.float32)
    for r0 in range(0, n, 256):
        out[r0:r0 + 256] = torch.fft.irfft(spec[r0:r0 + 256], n=n, dim=1)
    del spec, spec_ri
    out -= out.mean()
    out /= out.std().clamp_min(1e-12)
    return out


def _add_wrapped(tile: np.ndarray, patch: np.ndarray, row: int, col: int) -> None:
    """``tile[row:row+h, col:col+w] += patch`` with periodic wrap-around (in place)."""
    n = tile.shape[0]
    rows = (row + np.arange(patch.shape[0])) % n
    cols = (col + np.arange(patch.shape[1])) % n
    tile[np.ix_(rows, cols)] += patch


def _draw_features(tile: np.ndarray, rng: np.random.Generator, res: float) -> None:
    """Cracks, repairs, stains and manholes, drawn into the periodic tile (in place)."""
    n = tile.shape[0]
    area = (n * res) ** 2
    # Repair patches / different asphalt batches: soft rectangles, brighter or darker.
    for _ in range(int(area / 300)):
        w, h = rng.uniform(0.8, 5.0) / res, rng.uniform(0.6, 3.0) / res
        m = int(math.hypot(w, h)) + 8
        canvas = np.zeros((m, m), np.float32)
        box = cv2.boxPoints(((m / 2, m / 2), (w, h), rng.uniform(0, 180))).astype(np.int32)
        cv2.fillPoly(canvas, [box], 1.0)
        canvas = cv2.GaussianBlur(canvas, (0, 0), 1.5)
        _add_wrapped(tile, canvas * rng.choice([-1.0, 1.0]) * rng.uniform(0.03, 0.08), *rng.integers(0, n, 2))
    # Oil stains / wet spots: dark Gaussian blobs.
    for _ in range(int(area / 150)):
        sig = rng.uniform(0.08, 0.5) / res
        m = int(6 * sig) | 1
        ax = np.arange(m, dtype=np.float32) - m // 2
        ex, ey = sig * rng.uniform(0.5, 1.0), sig
        blob = np.exp(-0.5 * ((ax[None, :] / ex) ** 2 + (ax[:, None] / ey) ** 2))
        _add_wrapped(tile, (-rng.uniform(0.03, 0.1) * blob).astype(np.float32), *rng.integers(0, n, 2))
    # Cracks: persistent random walks, 1-2 texels wide, antialiased.
    for _ in range(int(area / 60)):
        steps = int(rng.uniform(1.0, 6.0) / 0.1)
        heading = rng.uniform(0, 2 * math.pi) + np.cumsum(rng.normal(0, 0.35, steps))
        pts = np.cumsum(np.stack([np.cos(heading), np.sin(heading)], 1) * (0.1 / res), 0)
        pts -= pts.min(0)
        size = int(pts.max()) + 8
        canvas = np.zeros((size, size), np.uint8)
        cv2.polylines(canvas, [np.round((pts + 4) * 16).astype(np.int32)], False, 255,
                      int(rng.integers(1, 3)), cv2.LINE_AA, shift=4)
        _add_wrapped(tile, canvas.astype(np.float32) * (-rng.uniform(0.08, 0.2) / 255.0), *rng.integers(0, n, 2))
    # Manholes: dark disc, bright rim, a grid of grooves.
    for _ in range(int(area / 1500)):
        r = rng.uniform(0.28, 0.4) / res
        m = int(2 * r) + 8
        canvas = np.zeros((m, m), np.float32)
        c = (m // 2, m // 2)
        cv2.circle(canvas, c, int(r), -0.14, -1, cv2.LINE_AA)
        cv2.circle(canvas, c, int(r), 0.12, 2, cv2.LINE_AA)
        for k in range(-3, 4):
            o = int(k * r / 4)
            cv2.line(canvas, (c[0] + o, c[1] - int(r * 0.8)), (c[0] + o, c[1] + int(r * 0.8)), 0.04, 1)
        _add_wrapped(tile, canvas, *rng.integers(0, n, 2))


@lru_cache(maxsize=2)
def _textures(seed: int) -> tuple[Tensor, Tensor]:
    """The fine (102.4 m, 2.5 cm) and coarse (409.6 m, 0.4 m) ground tiles of a seed (cached:
    ~70 MB each, ~1 s to make)."""
    return _make_textures(seed, _FINE_SIZE, _COARSE_SIZE)


def _make_textures(seed: int, n: int, n_coarse: int) -> tuple[Tensor, Tensor]:
    """Fine and coarse tiles, padded by one wrapped texel: ``(1, 1, n + 1, n + 1)`` float32, so
    ``grid_sample(align_corners=True)`` interpolates seamlessly across the period."""
    gen = torch.Generator().manual_seed(int(seed) * 7919 + 17)
    rng = np.random.default_rng([int(seed), 4242])
    fine = _periodic_noise(gen, n, _FINE_RES, 0.05, 5.0, 1.0).numpy()
    # Aggregate stones of 5-15 cm: the saturated high-pass of the same field (no second FFT).
    m = 8  # wrap margin > 3 sigma keeps the tile seamless
    hp = cv2.GaussianBlur(np.pad(fine, m, mode="wrap"), (0, 0), 2.0)[m:-m, m:-m]
    np.subtract(fine, hp, out=hp)
    hp *= 2.0 / max(float(hp.std()), 1e-12)
    np.tanh(hp, out=hp)
    hp *= 0.04
    fine *= 0.055
    fine += hp
    del hp
    _draw_features(fine, rng, _FINE_RES)
    coarse = _periodic_noise(gen, n_coarse, _COARSE_RES, 2.0, 120.0, 1.0).numpy() * 0.05
    return _wrap_pad(fine), _wrap_pad(coarse)


def _wrap_pad(tile: np.ndarray) -> Tensor:
    n = tile.shape[0]
    out = np.empty((n + 1, n + 1), np.float32)
    out[:n, :n] = tile
    out[n, :n] = tile[0]
    out[:, n] = out[:, 0]
    return torch.from_numpy(out)[None, None]


def _sample_periodic(tex: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """Bilinear sample of a wrap-padded ``(1, C, n+1, n+1)`` tile at texel coords ``(N,)`` -> ``(C, N)``."""
    n = tex.shape[-1] - 1
    uu = torch.remainder(u, n) * (2.0 / n) - 1.0
    vv = torch.remainder(v, n) * (2.0 / n) - 1.0
    grid = torch.stack([uu, vv], -1).to(torch.float32)[None, None]
    return F.grid_sample(tex, grid, mode="bilinear", padding_mode="border", align_corners=True)[0, :, 0]


def _smooth_box(x: Tensor, half: float, edge: float) -> Tensor:
    """1 inside ``|x| < half``, 0 outside, with a linear ramp of width ``edge``."""
    return ((half - x.abs()) / edge + 0.5).clamp(0.0, 1.0)


class RoadGround:
    """The road surface intensity as a function of world road-plane coordinates (metres).

    Layers: two procedural tiles of different periods and orientations (asphalt grain, stones,
    cracks, stains, repairs, manholes; no visible repetition) plus lane markings that follow a lane
    path (a polyline): solid line at ``d = -1.75`` m, dashed at ``+1.75`` m, solid at ``+5.25`` m
    (``d`` = signed lateral offset, left positive). Without a path the lane runs along world +x at y = 0.

    Args:
        seed: texture seed.
        path: ``(M, 2)`` lane-centre polyline in world metres (densely sampled), or None.
        tube: markings exist within this lateral distance of the path, metres.
    """

    def __init__(self, seed: int = 0, path: np.ndarray | None = None, tube: float = 9.0) -> None:
        self.seed = int(seed)
        self._coarse_rot = (math.cos(_COARSE_ANGLE), math.sin(_COARSE_ANGLE))
        self._lane_grid: Tensor | None = None
        self._pending_path: tuple[np.ndarray, float] | None = None
        self.path: np.ndarray | None = None
        if path is not None:
            path = np.asarray(path, dtype=np.float64)
            if path.ndim != 2 or path.shape[1] != 2 or len(path) < 2 or not np.isfinite(path).all():
                raise ValueError(f"path must be a finite (M>=2, 2) array, got shape {path.shape}")
            if not tube > 0:
                raise ValueError(f"tube must be > 0, got {tube}")
            self._pending_path = (path, float(tube))  # built on first use: IMU-only users never pay

    def _tiles(self) -> tuple[Tensor, Tensor]:
        return _textures(self.seed)

    # Lane coordinates -----------------------------------------------------------------------
    def _build_lane_grid(self, path: np.ndarray, tube: float, ds: float = 0.125) -> None:
        """Tabulate (s, d) lane coordinates on a grid covering the path's tube (exact nearest point)."""
        seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
        s_raw = np.concatenate([[0.0], np.cumsum(seg)])
        s = np.arange(0.0, s_raw[-1], ds)
        pts = np.stack([np.interp(s, s_raw, path[:, 0]), np.interp(s, s_raw, path[:, 1])], 1)
        tan = np.gradient(pts, axis=0)
        tan /= np.linalg.norm(tan, axis=1, keepdims=True).clip(1e-12)
        lo, hi = pts.min(0) - tube - 1.0, pts.max(0) + tube + 1.0
        # Cell size: 0.25 m (bilinear error ~1 mm) unless the box is huge; cap the grid at ~4 M cells.
        cell = max(0.25, math.sqrt(float(np.prod(hi - lo)) / 4.0e6))
        nx, ny = int(math.ceil((hi[0] - lo[0]) / cell)) + 1, int(math.ceil((hi[1] - lo[1]) / cell)) + 1
        best = np.full((ny, nx), np.inf, np.float32)
        idx = np.zeros((ny, nx), np.int32)
        chunk = 48
        for k0 in range(0, len(pts), chunk):
            p = pts[k0:k0 + chunk]
            c0 = np.floor((p.min(0) - tube - lo) / cell).astype(int).clip(0)
            c1 = np.ceil((p.max(0) + tube - lo) / cell).astype(int) + 1
            gx = lo[0] + np.arange(c0[0], min(c1[0], nx)) * cell
            gy = lo[1] + np.arange(c0[1], min(c1[1], ny)) * cell
            d2 = (gx[None, None, :] - p[:, 0, None, None]) ** 2 + (gy[None, :, None] - p[:, 1, None, None]) ** 2
            k = d2.argmin(0)
            dmin = np.take_along_axis(d2, k[None], 0)[0]
            win = (slice(c0[1], c0[1] + len(gy)), slice(c0[0], c0[0] + len(gx)))
            better = dmin < best[win]
            best[win] = np.where(better, dmin, best[win])
            idx[win] = np.where(better, k + k0, idx[win])
        grid = np.empty((2, ny, nx), np.float32)
        grid[0] = 0.0
        grid[1] = 1.0e4  # outside the tube: no markings
        iy, ix = np.nonzero(best <= tube * tube)
        del best
        k = idx[iy, ix]
        del idx
        qx, qy = lo[0] + ix * cell - pts[k, 0], lo[1] + iy * cell - pts[k, 1]
        tx, ty = tan[k, 0], tan[k, 1]
        grid[0, iy, ix] = s[k] + qx * tx + qy * ty  # foot of the perpendicular on the tangent
        grid[1, iy, ix] = tx * qy - ty * qx
        self._lane_grid = torch.from_numpy(grid)[None]
        self._lane_origin = (float(lo[0]), float(lo[1]))
        self._lane_cell = cell
        self.path = pts

    def lane_coordinates(self, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
        """Arc length ``s`` along the lane path and signed lateral offset ``d`` (left +). ``(N,)`` -> 2 x ``(N,)``."""
        if self._pending_path is not None:
            path, tube = self._pending_path
            self._build_lane_grid(path, tube)
            self._pending_path = None
        if self._lane_grid is None:
            return x, y
        g = self._lane_grid
        ny, nx = g.shape[-2:]
        u = (x - self._lane_origin[0]) / self._lane_cell
        v = (y - self._lane_origin[1]) / self._lane_cell
        inside = (u >= 0) & (u <= nx - 1) & (v >= 0) & (v <= ny - 1)
        grid = torch.stack([u * (2.0 / (nx - 1)) - 1.0, v * (2.0 / (ny - 1)) - 1.0], -1).to(torch.float32)
        sd = F.grid_sample(g, grid[None, None], mode="bilinear", padding_mode="border", align_corners=True)[0, :, 0]
        s = sd[0].to(x.dtype)
        d = torch.where(inside, sd[1].to(x.dtype), torch.full_like(x, 1.0e4))
        return s, d

    # Intensity -------------------------------------------------------------------------------
    def _intensity_torch(self, x: Tensor, y: Tensor) -> Tensor:
        x = x.to(torch.float64)
        y = y.to(torch.float64)
        fine_tex, coarse_tex = self._tiles()
        fine = _sample_periodic(fine_tex, x / _FINE_RES, y / _FINE_RES)[0]
        ca, sa = self._coarse_rot
        coarse = _sample_periodic(coarse_tex, (ca * x + sa * y) / _COARSE_RES, (-sa * x + ca * y) / _COARSE_RES)[0]
        value = _ASPHALT + fine + coarse
        s, d = self.lane_coordinates(x, y)
        alpha = torch.zeros_like(value)
        for offset, dashed in _LINES:
            a = _smooth_box(d - offset, _LINE_WIDTH / 2, _EDGE)
            if dashed:
                phase = torch.remainder(s, _DASH_PERIOD) - _DASH / 2
                a = a * _smooth_box(phase, _DASH / 2, _EDGE)
            alpha = torch.maximum(alpha, a.to(alpha.dtype))
        # Worn paint: the asphalt grain shows through a little.
        paint = _MARK + 0.6 * fine
        return (value + alpha * (paint - value)).clamp(0.0, 1.0)

    def __call__(self, x, y):
        return self.intensity(x, y)

    def intensity(self, x, y):
        """Ground intensity in [0, 1] at world points. ``x, y (...)`` numpy or torch -> same type/shape.

        numpy in -> float64 numpy out; torch in -> float32 torch out on the input's device
        (computed on CPU).
        """
        is_np = not isinstance(x, Tensor)
        xt = torch.as_tensor(np.asarray(x) if is_np else x)
        yt = torch.as_tensor(np.asarray(y) if is_np else y)
        if xt.shape != yt.shape:
            raise ValueError(f"x and y must have the same shape, got {tuple(xt.shape)} and {tuple(yt.shape)}")
        device = xt.device
        out = self._intensity_torch(xt.reshape(-1).cpu(), yt.reshape(-1).cpu()).reshape(xt.shape)
        if is_np:
            return out.numpy().astype(np.float64)
        return out.to(device)


@lru_cache(maxsize=2)
def default_ground(seed: int = 0) -> RoadGround:
    """A ground with a straight lane along world +x (y = 0); same textures as ``make_drive(seed)``."""
    return RoadGround(seed)


def ground_intensity(x, y, ground: RoadGround | None = None):
    """Intensity in [0, 1] of ``ground`` (default: :func:`default_ground`) at world ``x, y (N,)`` -> ``(N,)``."""
    return (ground or default_ground()).intensity(x, y)


# ---------------------------------------------------------------------------------------------
# Drive: analytic motion model
# ---------------------------------------------------------------------------------------------


def _rx(a: np.ndarray) -> np.ndarray:
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([o, z, z, z, c, -s, z, s, c], -1).reshape(*np.shape(a), 3, 3)


def _ry(a: np.ndarray) -> np.ndarray:
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([c, z, s, z, o, z, -s, z, c], -1).reshape(*np.shape(a), 3, 3)


def _rz(a: np.ndarray) -> np.ndarray:
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([c, -s, z, s, c, z, z, z, o], -1).reshape(*np.shape(a), 3, 3)


def _rpy(r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(roll, pitch, yaw) of ``Rz Ry Rx`` rotations ``(..., 3, 3)``."""
    return (np.arctan2(r[..., 2, 1], r[..., 2, 2]), np.arcsin(np.clip(-r[..., 2, 0], -1, 1)),
            np.arctan2(r[..., 1, 0], r[..., 0, 0]))


def _d5(f, t: np.ndarray, h: float = 1e-3) -> np.ndarray:
    """5-point central derivative of a vectorised ``f(t) -> (N, ...)`` (truncation ~h^4)."""
    return (f(t - 2 * h) - 8 * f(t - h) + 8 * f(t + h) - f(t + 2 * h)) / (12 * h)


@dataclass
class _Sines:
    """``sum a_i sin(2 pi f_i t + p_i)``."""

    a: np.ndarray
    f: np.ndarray
    p: np.ndarray

    @staticmethod
    def random(rng: np.random.Generator, n: int, f_lo: float, f_hi: float, total: float) -> "_Sines":
        a = rng.uniform(0.5, 1.0, n)
        return _Sines(a * (total / a.sum()), rng.uniform(f_lo, f_hi, n), rng.uniform(0, 2 * math.pi, n))

    def __call__(self, t: np.ndarray) -> np.ndarray:
        w = 2 * math.pi * self.f
        return (self.a * np.sin(w * t[..., None] + self.p)).sum(-1)

    def deriv(self, t: np.ndarray) -> np.ndarray:
        w = 2 * math.pi * self.f
        return (self.a * w * np.cos(w * t[..., None] + self.p)).sum(-1)

    def integral(self, t: np.ndarray) -> np.ndarray:
        """Integral from 0 to t."""
        w = 2 * math.pi * self.f
        return (self.a / w * (np.cos(self.p) - np.cos(w * t[..., None] + self.p))).sum(-1)


def _window(t: np.ndarray, lo: float, hi: float) -> slice | np.ndarray:
    """Indices of ``t`` in ``[lo, hi]``: a slice for sorted 1-D ``t`` (cheap), else a mask."""
    if t.ndim == 1 and (len(t) < 2 or t[-1] >= t[0]):
        return slice(int(np.searchsorted(t, lo)), int(np.searchsorted(t, hi, side="right")))
    return (t >= lo) & (t <= hi)


_SUPPORT = 9.0  # events are evaluated within +-9 sigma (exp(-40) ~ 4e-18: exact in float64)


@dataclass
class _Bumps:
    """``sum a_k (1 - u^2)^4`` for ``|u| < 1``, ``u = (t - c_k) / w_k``: C3 bumps (the curves of the
    yaw rate) whose integral is a polynomial, so yaw is exact and cheap."""

    a: np.ndarray
    c: np.ndarray
    w: np.ndarray

    def __call__(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        out = np.zeros(t.shape)
        for a, c, w in zip(self.a, self.c, self.w):
            sl = _window(t, c - w, c + w)
            u = (t[sl] - c) / w
            out[sl] += a * (1.0 - u * u) ** 4
        return out

    def deriv(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        out = np.zeros(t.shape)
        for a, c, w in zip(self.a, self.c, self.w):
            sl = _window(t, c - w, c + w)
            u = (t[sl] - c) / w
            out[sl] += a * -8.0 * u * (1.0 - u * u) ** 3 / w
        return out

    @staticmethod
    def _antideriv(u: np.ndarray) -> np.ndarray:
        u = np.clip(u, -1.0, 1.0)
        u2 = u * u
        return u * (1.0 + u2 * (-4.0 / 3.0 + u2 * (6.0 / 5.0 + u2 * (-4.0 / 7.0 + u2 / 9.0))))

    def integral(self, t: np.ndarray) -> np.ndarray:
        """Integral from 0 to t."""
        t = np.asarray(t, dtype=np.float64)
        out = np.zeros(t.shape)
        for a, c, w in zip(self.a, self.c, self.w):
            out += a * w * (self._antideriv((t - c) / w) - self._antideriv(np.asarray(-c / w)))
        return out


@dataclass
class _Gabors:
    """``sum a_k exp(-(t - c_k)^2 / (2 s_k^2)) sin(2 pi f_k (t - c_k) + p_k)``: smooth bump events."""

    a: np.ndarray
    c: np.ndarray
    s: np.ndarray
    f: np.ndarray
    p: np.ndarray

    def __call__(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        out = np.zeros(t.shape)
        for a, c, s, f, p in zip(self.a, self.c, self.s, self.f, self.p):
            w = _window(t, c - _SUPPORT * s, c + _SUPPORT * s)
            dt = t[w] - c
            out[w] += a * np.exp(-0.5 * (dt / s) ** 2) * np.sin(2 * math.pi * f * dt + p)
        return out


# Profiles: speed and yaw rate of a drive, exact in closed form (the IMU and poses stay consistent).


class _Profile(Protocol):
    """A signal of relative time ``t (N,)``: value, time derivative, ``start + integral from 0 to t``."""

    def __call__(self, t: np.ndarray) -> np.ndarray: ...

    def deriv(self, t: np.ndarray) -> np.ndarray: ...

    def integral(self, t: np.ndarray, start: float = 0.0) -> np.ndarray: ...


@dataclass
class _Affine:
    """``mid + half * f(t)`` of a profile ``f`` (the random drive's speed)."""

    mid: float
    half: float
    f: _Sines

    def __call__(self, t):
        return self.mid + self.half * self.f(t)

    def deriv(self, t):
        return self.half * self.f.deriv(t)

    def integral(self, t, start: float = 0.0):
        return start + self.mid * np.asarray(t, dtype=np.float64) + self.half * self.f.integral(t)


@dataclass
class _Sum:
    """The sum of profiles (the random drive's yaw rate: curves + wander)."""

    parts: tuple

    def __call__(self, t):
        out = self.parts[0](t)
        for p in self.parts[1:]:
            out = out + p(t)
        return out

    def deriv(self, t):
        out = self.parts[0].deriv(t)
        for p in self.parts[1:]:
            out = out + p.deriv(t)
        return out

    def integral(self, t, start: float = 0.0):
        out = start
        for p in self.parts:
            out = out + p.integral(t)
        return out


def _smoothstep_antiderivs() -> list[np.polynomial.Polynomial]:
    """``[S', S, int S, int int S]`` on ``[0, 1]`` of the C4 smooth step ``S' = 630 u^4 (1 - u)^4``."""
    u = np.polynomial.Polynomial([0.0, 1.0])
    out = [630.0 * u**4 * (1.0 - u) ** 4]
    for _ in range(3):
        out.append(out[-1].integ())  # lower bound 0: zero at u = 0
    return out


_STEP = _smoothstep_antiderivs()


_STEP_AT1 = [1.0] + [float(p(1.0)) for p in _STEP[2:]]  # Phi_0(1) = 1 (exactly), Phi_1(1), Phi_2(1)


def _step_phi(j: int, u: np.ndarray) -> np.ndarray:
    """``Phi_j(u)``: ``j = -1, 0, 1, 2`` -> the smooth step's derivative, itself, its first and second
    antiderivatives; 0 before ``u = 0``, continued exactly after ``u = 1`` (where ``S = 1``)."""
    u = np.asarray(u, dtype=np.float64)
    uc = np.clip(u, 0.0, 1.0)
    if j == 0:  # S(u) = 1 - S(1 - u): accurate near both ends, so 0 <= S <= 1 (no reversing speed)
        return np.where(uc > 0.5, 1.0 - _STEP[1](1.0 - uc), _STEP[1](uc))
    inside = _STEP[j + 1](uc)
    if j < 0:
        return inside  # S' vanishes at both ends
    e = np.maximum(u - 1.0, 0.0)
    beyond = sum(_STEP_AT1[j - i] * e**i / math.factorial(i) for i in range(j + 1))
    return np.where(u > 1.0, beyond, inside)


@dataclass
class _Ramps:
    """A piecewise-smooth profile: holds joined by C4 smooth steps (closed-form derivative and integral).

    ``order = 0``: the value steps, ``f = base + sum_k delta_k S((t - t_k) / d_k)`` (speed changes, curve
    entries). ``order = 1``: the derivative steps, ``f' = sum_k delta_k S(...)``, ``f(-inf) = base``
    (acceleration held at a level: braking). Constant before the first step.
    """

    base: float
    t: np.ndarray  # (K,) step starts, s
    d: np.ndarray  # (K,) step durations, s
    delta: np.ndarray  # (K,) step heights
    order: int = 0

    def _terms(self, j: int, t) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        out = np.zeros(t.shape)
        for tk, dk, ak in zip(self.t, self.d, self.delta):
            out += ak * dk ** (self.order + j) * _step_phi(self.order + j, (t - tk) / dk)
        return out

    def __call__(self, t):
        return self.base + self._terms(0, t)

    def deriv(self, t):
        return self._terms(-1, t)

    def integral(self, t, start: float = 0.0):
        t = np.asarray(t, dtype=np.float64)
        return start + self.base * t + self._terms(1, t) - self._terms(1, np.zeros(()))


def _levels(start: float, changes: Sequence[tuple[float, float, float]]) -> _Ramps:
    """Value steps from ``start``: ``changes = [(t_start, duration, new_level), ...]`` in time order."""
    lv = [start] + [c[2] for c in changes]
    return _Ramps(float(start), np.array([c[0] for c in changes], float), np.array([c[1] for c in changes], float),
                  np.diff(np.asarray(lv, float)), 0)


def _accel_levels(v0: float, changes: Sequence[tuple[float, float, float]]) -> _Ramps:
    """Speed from acceleration steps: ``changes = [(t_start, duration, new_acceleration), ...]``, speed ``v0``
    before the first."""
    lv = [0.0] + [c[2] for c in changes]
    return _Ramps(float(v0), np.array([c[0] for c in changes], float), np.array([c[1] for c in changes], float),
                  np.diff(np.asarray(lv, float)), 1)


_DEG = math.pi / 180.0


@dataclass
class _Motion:
    """Analytic drive signals of relative time ``t`` (seconds from the first stamp)."""

    speed_profile: _Profile  # v(t) >= 0, m/s
    yaw0: float
    yaw_rate_profile: _Profile  # rad/s; yaw = yaw0 + its integral
    pitch_sines: _Sines
    roll_sines: _Sines
    pitch_bumps: _Gabors
    roll_bumps: _Gabors
    load_pitch: float  # rad per m/s^2 of longitudinal acceleration (braking -> nose down)
    load_roll: float  # rad per m/s^2 of lateral acceleration (body leans out of the curve)
    slope0: float
    camber0: float
    slope_sines: _Sines
    camber_sines: _Sines
    t_base_cam: np.ndarray  # (3,)
    cam_height: float

    def speed(self, t):
        return self.speed_profile(t)

    def speed_dot(self, t):
        return self.speed_profile.deriv(t)

    def yaw_rate(self, t):
        return self.yaw_rate_profile(t)

    def yaw(self, t):
        return self.yaw_rate_profile.integral(t, self.yaw0)

    def pitch_rel(self, t):
        return self.pitch_sines(t) + self.pitch_bumps(t) - self.load_pitch * self.speed_dot(t)

    def roll_rel(self, t):
        return self.roll_sines(t) + self.roll_bumps(t) + self.load_roll * self.speed(t) * self.yaw_rate(t)

    def slope(self, t):
        return self.slope0 + self.slope_sines(t)

    def camber(self, t):
        return self.camber0 + self.camber_sines(t)

    def r_road_base(self, t):
        return _ry(self.pitch_rel(t)) @ _rx(self.roll_rel(t))

    def r_grav_base(self, t):
        return _rz(self.yaw(t)) @ _ry(self.slope(t)) @ _rx(self.camber(t)) @ self.r_road_base(t)

    def z_base(self, t):
        """Base origin height above the road (the camera centre stays at ``cam_height``)."""
        return self.cam_height - (self.r_road_base(t) @ self.t_base_cam)[..., 2]

    def vel_grav(self, t):
        """Base velocity in the gravity frame, ``(N, 3)``."""
        v = np.stack([self.speed(t), np.zeros_like(t), _d5(self.z_base, t)], -1)
        r = _rz(self.yaw(t)) @ _ry(self.slope(t)) @ _rx(self.camber(t))
        return (r @ v[..., None])[..., 0]

    def gyro(self, t):
        """Body angular velocity of ``R_grav_base``, ``(N, 3)`` rad/s."""
        r = self.r_grav_base(t)
        omega = np.swapaxes(r, -1, -2) @ _d5(self.r_grav_base, t)
        return 0.5 * np.stack([omega[..., 2, 1] - omega[..., 1, 2], omega[..., 0, 2] - omega[..., 2, 0],
                               omega[..., 1, 0] - omega[..., 0, 1]], -1)

    def specific_force(self, t):
        """Accelerometer reading without noise, ``(N, 3)`` m/s^2 in the base frame."""
        a = _d5(self.vel_grav, t) + np.array([0.0, 0.0, GRAVITY])
        return (np.swapaxes(self.r_grav_base(t), -1, -2) @ a[..., None])[..., 0]


def _random_motion(rng: np.random.Generator, t_lo: float, t_hi: float, *, speed_range, speed_variation,
                   curvature, max_yaw_rate, max_lateral_accel, bumps, road_tilt, camera: CameraModel,
                   start_yaw: float) -> _Motion:
    vmin, vmax = speed_range
    speed_sines = _Sines.random(rng, 3, 0.015, 0.06, 1.0)
    mid, half = 0.5 * (vmin + vmax), 0.5 * (vmax - vmin) * speed_variation
    # Curves: smooth yaw-rate bumps every 4-10 s, limited by yaw rate and lateral acceleration.
    centres = []
    c = t_lo + rng.uniform(0.0, 4.0)
    while c < t_hi:
        centres.append(c)
        c += rng.uniform(4.0, 10.0)
    centres = np.asarray(centres)
    half_width = rng.uniform(2.0, 6.0, len(centres))
    v_at = mid + half * speed_sines(centres) if len(centres) else centres
    amp = rng.choice([-1.0, 1.0], len(centres)) * rng.uniform(0.25, 1.0, len(centres))
    amp = amp * np.minimum(max_yaw_rate, max_lateral_accel / np.maximum(v_at, 1e-3)) * curvature
    curves = _Bumps(amp, centres, half_width)
    wander = _Sines.random(rng, 2, 0.01, 0.04, 0.012 * curvature)
    # Keep the yaw rate (overlapping events add up) within max_yaw_rate.
    tt = np.linspace(t_lo, t_hi, max(200, int((t_hi - t_lo) * 20)))
    peak = np.abs(curves(tt) + wander(tt)).max() if curvature > 0 else 0.0
    if peak > max_yaw_rate:
        curves = _Bumps(curves.a * (max_yaw_rate / peak), curves.c, curves.w)
        wander = _Sines(wander.a * (max_yaw_rate / peak), wander.f, wander.p)
    # Suspension: continuous oscillation 0.5-3 Hz plus bump events (about one per 3 s).
    n_b = max(1, int((t_hi - t_lo) / 3.0))
    bc = rng.uniform(t_lo, t_hi, n_b)
    bs = rng.uniform(0.15, 0.4, n_b)
    bf = rng.uniform(0.8, 2.0, n_b)
    pitch_bumps = _Gabors(rng.choice([-1.0, 1.0], n_b) * rng.uniform(0.7, 2.0, n_b) * _DEG * bumps, bc, bs, bf,
                          rng.uniform(0, 2 * math.pi, n_b))
    roll_bumps = _Gabors(rng.choice([-1.0, 1.0], n_b) * rng.uniform(0.4, 1.5, n_b) * _DEG * bumps, bc, bs,
                         bf * rng.uniform(0.8, 1.2, n_b), rng.uniform(0, 2 * math.pi, n_b))
    pitch_sines = _Sines.random(rng, 4, 0.5, 3.0, 0.6 * _DEG * bumps)
    roll_sines = _Sines.random(rng, 4, 0.5, 3.0, 0.5 * _DEG * bumps)
    if road_tilt is True:
        slope0, camber0 = rng.uniform(-0.5, 1.5) * _DEG, rng.uniform(1.8, 2.8) * _DEG
        slope_s = _Sines.random(rng, 2, 0.005, 0.03, 0.7 * _DEG)
        camber_s = _Sines.random(rng, 2, 0.005, 0.03, 0.4 * _DEG)
    else:
        slope0, camber0 = (0.0, 0.0) if road_tilt is False else (float(road_tilt[0]), float(road_tilt[1]))
        slope_s = camber_s = _Sines(np.zeros(1), np.ones(1), np.zeros(1))
    return _Motion(
        speed_profile=_Affine(mid, half, speed_sines), yaw0=start_yaw, yaw_rate_profile=_Sum((curves, wander)),
        pitch_sines=pitch_sines, roll_sines=roll_sines, pitch_bumps=pitch_bumps,
        roll_bumps=roll_bumps, load_pitch=0.3 * _DEG * bumps, load_roll=0.5 * _DEG * bumps,
        slope0=slope0, camber0=camber0, slope_sines=slope_s, camber_sines=camber_s,
        t_base_cam=camera.T_base_cam[:3, 3].detach().cpu().double().numpy(), cam_height=float(camera.mount_height),
    )


def _integrate_xy(m: _Motion, t: np.ndarray, start_xy: tuple[float, float], i0: int) -> np.ndarray:
    """Planar position on the uniform grid ``t`` (``t[i0] == 0``): corrected trapezoid, error ~h^4."""
    h = t[1] - t[0]
    v, vd, yaw, w = m.speed(t), m.speed_dot(t), m.yaw(t), m.yaw_rate(t)
    c, s = np.cos(yaw), np.sin(yaw)
    f = np.stack([v * c, v * s], -1)
    fd = np.stack([vd * c - v * w * s, vd * s + v * w * c], -1)
    inc = 0.5 * h * (f[1:] + f[:-1]) + (h * h / 12.0) * (fd[:-1] - fd[1:])
    xy = np.concatenate([np.zeros((1, 2)), np.cumsum(inc, 0)], 0)
    return xy - xy[i0] + np.asarray(start_xy)


# ---------------------------------------------------------------------------------------------
# IMU noise and rendering options
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ImuNoise:
    """IMU error model (all seeded). Per-sample standard deviations; walks per sqrt(second)."""

    gyro_white: float = 0.005  # rad/s
    gyro_bias: float = 0.002  # rad/s, initial bias std per axis
    gyro_bias_walk: float = 2e-4  # rad/s/sqrt(s)
    accel_white: float = 0.05  # m/s^2
    accel_bias: float = 0.05  # m/s^2
    accel_bias_walk: float = 2e-3  # m/s^2/sqrt(s)
    accel_vibration: float = 0.5  # m/s^2 RMS per axis (engine harmonics + road, z 1.5x)

    def scaled(self, k: float) -> "ImuNoise":
        return ImuNoise(*(k * getattr(self, f) for f in self.__dataclass_fields__))


@dataclass(frozen=True)
class RenderOptions:
    """Renderer settings. ``noise_std`` in grey levels; vignette = relative darkening at the corners."""

    supersample: int = 2
    noise_std: float = 2.0
    vignette: float = 0.15
    haze_start: float = 60.0  # metres: far ground fades smoothly into a haze grey (hides aliasing)
    haze_end: float = 300.0
    haze_value: float = 0.55
    sky_horizon: float = 0.75
    sky_zenith: float = 0.95


# ---------------------------------------------------------------------------------------------
# The drive
# ---------------------------------------------------------------------------------------------


class LazyImages:
    """``(F, H, W)`` uint8 frames rendered on access (``images[i]``, slices, iteration, ``np.asarray``)."""

    def __init__(self, drive: "SyntheticDrive") -> None:
        self._drive = drive

    def __len__(self) -> int:
        return len(self._drive.frame_stamps)

    @property
    def shape(self) -> tuple[int, int, int]:
        return (len(self), self._drive.camera.height_px, self._drive.camera.width)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return np.stack([render_frame(self._drive, k) for k in range(*i.indices(len(self)))])
        return render_frame(self._drive, int(i))

    def __iter__(self):
        return (render_frame(self._drive, k) for k in range(len(self)))

    def __array__(self, dtype=None, copy=None):
        out = self[:]
        return out if dtype is None else out.astype(dtype)


@dataclass
class SyntheticDrive:
    """A synthetic drive with exact ground truth. ``F`` frames, ``N`` IMU samples; numpy arrays.

    Stamps are seconds (float64) from ``t0``; frame ``i`` is IMU sample ``frame_imu_index[i]`` and
    ``frame_stamps == imu_stamps[frame_imu_index]`` exactly.
    """

    camera: CameraModel
    ground: RoadGround
    seed: int
    frame_stamps: np.ndarray  # (F,)
    frame_imu_index: np.ndarray  # (F,) int
    images: np.ndarray | LazyImages | None  # (F, H, W) uint8
    imu_stamps: np.ndarray  # (N,)
    gyro: np.ndarray  # (N, 3) rad/s, base frame, with noise
    accel: np.ndarray  # (N, 3) m/s^2, specific force, base frame, with noise
    gyro_true: np.ndarray  # (N, 3) noise-free
    accel_true: np.ndarray  # (N, 3) noise-free
    gyro_bias: np.ndarray  # (N, 3) the bias contained in gyro
    accel_bias: np.ndarray  # (N, 3) the bias contained in accel
    poses_xy_yaw: np.ndarray  # (F, 3) world x, y (m) and yaw (rad, wrapped to [-pi, pi))
    pitch_roll_road: np.ndarray  # (F, 2) base attitude relative to the road
    pitch_roll_gravity: np.ndarray  # (F, 2) base attitude relative to gravity (what OXTS reports)
    road_slope_camber: np.ndarray  # (F, 2) road tilt against gravity, relative to the heading
    relative_motion: np.ndarray  # (F-1, 3) (dx, dy, dyaw) of the base, frame i-1 -> i, in base frame i-1
    speed: np.ndarray  # (F,) m/s
    base_height: np.ndarray  # (F,) base origin above the road, m
    imu_pitch_roll_road: np.ndarray  # (N, 2)
    imu_pitch_roll_gravity: np.ndarray  # (N, 2)
    imu_road_slope_camber: np.ndarray  # (N, 2)
    imu_rotation_gravity: np.ndarray  # (N, 3, 3) R_grav_base
    imu_velocity_gravity: np.ndarray  # (N, 3) base velocity in the gravity frame, m/s
    imu_poses_xy_yaw: np.ndarray  # (N, 3)
    render_options: RenderOptions = field(default_factory=RenderOptions)
    image_noise: bool = True
    _motion: _Motion | None = field(default=None, repr=False)

    @property
    def num_frames(self) -> int:
        return len(self.frame_stamps)

    def __repr__(self) -> str:
        images = type(self.images).__name__ if self.images is not None else "None"
        return (f"SyntheticDrive(seed={self.seed}, frames={self.num_frames}, imu={len(self.imu_stamps)}, "
                f"t={self.imu_stamps[0]:.2f}..{self.imu_stamps[-1]:.2f} s, images={images})")

    def ground_intensity(self, x, y):
        """Ground intensity in [0, 1] at world points (see :meth:`RoadGround.intensity`)."""
        return self.ground.intensity(x, y)

    def image(self, index: int) -> np.ndarray:
        """Frame ``index`` as ``(H, W)`` uint8 (from ``images`` if rendered, else rendered now)."""
        if isinstance(self.images, np.ndarray):
            return self.images[index]
        return render_frame(self, index)

    def to_recording(self, frame_range: tuple[int, int] | None = None):
        """The drive as the datasets' one recording type, :class:`bevo_ros.datasets.rosbag.Recording`,
        without a bag: what ``load_sequence(write_drive_bag(drive, frame_range=...))`` gives (same IMU
        span, ground truth relative to the first frame, gravity-referenced attitude), except that stamps
        keep their float64 seconds (a bag rounds them to ns) and the camera is the drive's own.
        Renders every frame in ``frame_range`` (first, stop) unless the images are already arrays."""
        from bevo_ros.datasets.rosbag import Recording

        f0, f1 = frame_range or (0, self.num_frames)
        t_lo, t_hi = self.frame_stamps[f0], self.frame_stamps[f1 - 1]
        imu = (self.imu_stamps >= t_lo - 0.5) & (self.imu_stamps <= t_hi)  # write_drive_bag's span
        poses = base_poses_4x4(self)
        poses = np.linalg.inv(poses[f0]) @ poses[f0:f1]
        images = np.stack([np.asarray(self.image(i)) for i in range(f0, f1)])
        return Recording(
            imu_stamps=torch.from_numpy(self.imu_stamps[imu]),
            gyro=torch.from_numpy(self.gyro[imu]),
            accel=torch.from_numpy(self.accel[imu]),
            frame_stamps=torch.from_numpy(self.frame_stamps[f0:f1].copy()),
            images=torch.from_numpy(images),
            camera=self.camera,
            gt_poses=torch.from_numpy(poses),
            gt_pitch_roll=torch.from_numpy(self.pitch_roll_gravity[f0:f1].copy()),
            name=f"synthetic-seed{self.seed}",
        )


# ---------------------------------------------------------------------------------------------
# Named drives (presets)
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Preset:
    """A named drive: fixed speed and yaw-rate profiles; suspension, road tilt, noise stay seeded."""

    description: str
    duration: float  # s, the whole manoeuvre (a longer drive holds the last state)
    speed: _Ramps
    yaw_rate: _Ramps
    bumps_gain: float = 1.0  # times the ``bumps`` argument
    vibration_gain: float = 1.0  # times ImuNoise.accel_vibration
    bump_rate: float = 0.0  # extra short bump events per second (potholes, joints)


def _stop_and_go_speed() -> _Ramps:
    # 9 m/s <-> 1 m/s (0.1 m per 10 Hz frame) in 6 s (peak 3.3 m/s^2), the second dip a full stop.
    changes, t = [], 1.0
    for low, hold in ((1.0, 1.5), (0.0, 2.0), (1.0, 1.5)):
        changes += [(t, 6.0, low), (t + 6.0 + hold, 6.0, 9.0)]
        t += 12.0 + hold + 1.5
    return _levels(9.0, changes)


_PRESETS: dict[str, _Preset] = {
    "curve": _Preset(
        "sustained left curve of 100 m radius at 15 m/s (2.25 m/s^2 lateral, 0.15 rad/s = 8.6 deg/s) "
        "from t = 4 s to 12 s; straight 2 s, 2 s smooth entry and exit, straight to 16 s",
        16.0, _levels(15.0, []), _levels(0.0, [(2.0, 2.0, 0.15), (12.0, 2.0, 0.0)])),
    "braking": _Preset(
        "straight, 15 m/s until t = 2 s, then -5 m/s^2 braking (0.5 s smooth onset and release) down to "
        "2 m/s at t = 5.1 s, held to 8 s",
        8.0, _accel_levels(15.0, [(2.0, 0.5, -5.0), (4.6, 0.5, 0.0)]), _levels(0.0, [])),
    "bend_start": _Preset(
        "starts inside a left bend: 12 m/s at 0.18 rad/s (2.16 m/s^2 centripetal at the first sample); "
        "leaves it over t = 3..5 s while speeding up to 14 m/s by t = 7 s; 10 s",
        10.0, _levels(12.0, [(3.0, 4.0, 14.0)]), _levels(0.18, [(3.0, 2.0, 0.0)])),
    "stop_and_go": _Preset(
        "stop-and-go: 9 m/s down to 1 m/s (0.1 m per 10 Hz frame), to a full 2 s stop, and to 1 m/s "
        "again, 6 s ramps (<= 3.7 m/s^2), two gentle turns; 46 s",
        46.0, _stop_and_go_speed(), _levels(0.0, [(9.0, 3.0, 0.1), (13.0, 3.0, 0.0), (25.0, 3.0, -0.08),
                                                  (29.0, 3.0, 0.0)])),
    "bumpy": _Preset(
        "bumpy road: suspension 2.5x, extra short bumps (1 per s), vibration 2x; 7-10 m/s with gentle "
        "curves (<= 0.06 rad/s); 20 s",
        20.0, _levels(8.0, [(4.0, 4.0, 10.0), (12.0, 4.0, 7.0), (17.0, 3.0, 8.0)]),
        _levels(0.0, [(2.0, 3.0, 0.06), (7.0, 3.0, -0.05), (13.0, 3.0, 0.04), (17.0, 3.0, 0.0)]),
        bumps_gain=2.5, vibration_gain=2.0, bump_rate=1.0),
}

PRESETS: dict[str, str] = {name: p.description for name, p in _PRESETS.items()}
"""Named deterministic drives for :func:`make_drive` ``(preset=...)``: name -> description."""


def _with_preset(m: _Motion, p: _Preset, rng: np.random.Generator, t_lo: float, t_hi: float, bumps: float) -> _Motion:
    """The seeded random motion with the preset's speed and yaw rate (and its extra short bumps)."""
    out = replace(m, speed_profile=p.speed, yaw_rate_profile=p.yaw_rate)
    n = int(round(p.bump_rate * (t_hi - t_lo)))
    if not n:
        return out
    c, s, f = rng.uniform(t_lo, t_hi, n), rng.uniform(0.1, 0.25, n), rng.uniform(1.0, 2.5, n)
    pitch_a = rng.choice([-1.0, 1.0], n) * rng.uniform(0.2, 0.6, n) * _DEG * bumps
    roll_a = rng.choice([-1.0, 1.0], n) * rng.uniform(0.2, 0.5, n) * _DEG * bumps
    phase = rng.uniform(0, 2 * math.pi, (2, n))

    def more(g: _Gabors, a: np.ndarray, ph: np.ndarray) -> _Gabors:
        return _Gabors(*(np.concatenate([x, y]) for x, y in zip((g.a, g.c, g.s, g.f, g.p), (a, c, s, f, ph))))

    return replace(out, pitch_bumps=more(m.pitch_bumps, pitch_a, phase[0]), roll_bumps=more(m.roll_bumps, roll_a, phase[1]))


def preset_drive(name: str, seed: int = 0, duration: float | None = None, **kw) -> SyntheticDrive:
    """``make_drive(seed, duration, preset=name, **kw)``: a named drive (see :data:`PRESETS`)."""
    return make_drive(seed, duration, preset=name, **kw)


def _check_positive(**kw) -> None:
    for k, v in kw.items():
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"{k} must be a positive finite number, got {v!r}")


def make_drive(
    seed: int = 0,
    duration: float | None = None,
    frame_rate: float = 10.0,
    imu_rate: float = 100.0,
    bumps: float = 1.0,
    road_tilt: bool | tuple[float, float] = True,
    noise: bool | float | ImuNoise = True,
    render: bool | str = True,
    *,
    camera: CameraModel | None = None,
    speed_range: tuple[float, float] = (5.0, 15.0),
    speed_variation: float = 1.0,
    curvature: float = 1.0,
    max_yaw_rate: float = 0.3,
    max_lateral_accel: float = 4.0,
    t0: float = 1000.0,
    start_pose: tuple[float, float, float] | None = None,
    render_options: RenderOptions | None = None,
    ground_seed: int | None = None,
    preset: str | None = None,
) -> SyntheticDrive:
    """Simulate a drive: trajectory, IMU at ``imu_rate`` and camera frames at ``frame_rate``.

    Args:
        seed: everything (motion, noise, texture unless ``ground_seed``) is deterministic by seed.
        duration: seconds (default 20, or the preset's length); frames at ``t0 + k / frame_rate``,
            IMU at ``t0 + k / imu_rate``.
        bumps: scale of the road-relative pitch/roll (suspension oscillation, bump events,
            load transfer). 0 = rigid body flat on the road.
        road_tilt: True = slowly varying slope/camber; False = none; ``(slope, camber)`` radians
            = constant tilt.
        noise: True/False, a scale factor, or an :class:`ImuNoise`. False also gives ideal images
            (no image noise, no vignette).
        render: True = render every frame now into ``images``; "lazy" = ``images`` renders on
            access; False = ``images`` is None (use :func:`render_frame`).
        speed_variation: 0 = constant speed ``mean(speed_range)``; 1 = the full range.
        curvature: scale of the curves' yaw rates; 0 = straight line.
        start_pose: world ``(x, y, yaw)`` at the first frame; default random.
        preset: a named, deterministic manoeuvre (:data:`PRESETS`: ``curve``, ``braking``,
            ``bend_start``, ``stop_and_go``, ``bumpy``): it fixes speed and yaw rate (``speed_range``,
            ``speed_variation``, ``curvature``, ``max_yaw_rate``, ``max_lateral_accel`` are then unused);
            suspension, bumps, road tilt, start pose and noise still follow ``seed`` and the other
            arguments. None = the seeded random drive.

    Returns:
        a :class:`SyntheticDrive`.
    """
    if preset is not None and preset not in _PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {sorted(_PRESETS)}")
    pre_set = _PRESETS[preset] if preset is not None else None
    if duration is None:
        duration = pre_set.duration if pre_set is not None else 20.0
    _check_positive(duration=duration, frame_rate=frame_rate, imu_rate=imu_rate)
    for name, sd in (("seed", seed), ("ground_seed", 0 if ground_seed is None else ground_seed)):
        if isinstance(sd, bool) or not isinstance(sd, (int, np.integer)) or sd < 0:
            raise ValueError(f"{name} must be an integer >= 0, got {sd!r}")
    if not math.isfinite(t0):
        raise ValueError(f"t0 must be finite, got {t0!r}")
    ratio = imu_rate / frame_rate
    if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
        raise ValueError(f"imu_rate / frame_rate must be a positive integer, got {imu_rate} / {frame_rate}")
    step = int(round(ratio))
    if not (len(speed_range) == 2 and 0 < speed_range[0] <= speed_range[1]):
        raise ValueError(f"speed_range must be (min, max) with 0 < min <= max, got {speed_range}")
    for name, v in (("bumps", bumps), ("speed_variation", speed_variation), ("curvature", curvature)):
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
    if render not in (True, False, "lazy"):
        raise ValueError(f"render must be True, False or 'lazy', got {render!r}")
    if not (road_tilt is True or road_tilt is False or (isinstance(road_tilt, (tuple, list)) and len(road_tilt) == 2)):
        raise ValueError(f"road_tilt must be a bool or (slope, camber) in radians, got {road_tilt!r}")
    if isinstance(noise, ImuNoise):
        imu_noise, noisy = noise, True
    elif isinstance(noise, (bool, int, float)):
        if not (math.isfinite(float(noise)) and float(noise) >= 0):
            raise ValueError(f"noise must be a bool, a scale >= 0 or an ImuNoise, got {noise!r}")
        imu_noise, noisy = ImuNoise().scaled(float(noise)), float(noise) > 0
    else:
        raise ValueError(f"noise must be a bool, a scale >= 0 or an ImuNoise, got {noise!r}")
    if pre_set is not None:
        bumps = bumps * pre_set.bumps_gain
        if pre_set.vibration_gain != 1.0:
            imu_noise = replace(imu_noise, accel_vibration=imu_noise.accel_vibration * pre_set.vibration_gain)
    camera = camera if camera is not None else kitti_like_camera()
    options = render_options if render_options is not None else RenderOptions()
    if not noisy:
        options = replace(options, noise_std=0.0, vignette=0.0)

    rng = np.random.default_rng([int(seed), 1])
    if start_pose is None:
        start_pose = (rng.uniform(-50, 50), rng.uniform(-50, 50), rng.uniform(-math.pi, math.pi))
    n_imu = int(math.floor(duration * imu_rate + 1e-9)) + 1
    n_frames = (n_imu - 1) // step + 1
    t_imu = np.arange(n_imu) / imu_rate
    pre, post = 3.0, 3.0  # extra seconds of lane path around the drive
    motion = _random_motion(
        rng, -pre, t_imu[-1] + post, speed_range=speed_range, speed_variation=speed_variation,
        curvature=curvature, max_yaw_rate=max_yaw_rate, max_lateral_accel=max_lateral_accel, bumps=bumps,
        road_tilt=road_tilt, camera=camera, start_yaw=float(start_pose[2]),
    )
    v_ref = speed_range[1]  # vibration envelope: relative to the fastest speed
    if pre_set is not None:
        motion = _with_preset(motion, pre_set, np.random.default_rng([int(seed), 5]), -pre, t_imu[-1] + post, bumps)
    # Dense grid (>= 1 kHz, containing every IMU stamp) for the position integral.
    sub = max(1, int(math.ceil(1000.0 / imu_rate)))
    h = 1.0 / (imu_rate * sub)
    j_pre, j_post = int(math.ceil(pre / h)), int(math.ceil(post / h))
    j = np.arange(-j_pre, (n_imu - 1) * sub + j_post + 1)
    t_dense = j * h
    xy_dense = _integrate_xy(motion, t_dense, (float(start_pose[0]), float(start_pose[1])), j_pre)
    xy_imu = xy_dense[j_pre + np.arange(n_imu) * sub]
    if pre_set is not None:
        v_dense = motion.speed(t_dense)
        if v_dense.min() < 0:  # a preset bug, never the user's
            raise AssertionError(f"preset {preset!r} reverses (speed {v_dense.min():.3g} m/s)")
        v_ref = float(v_dense.max())

    yaw = motion.yaw(t_imu)
    r_grav = motion.r_grav_base(t_imu)
    roll_g, pitch_g, _ = _rpy(r_grav)
    pr_road = np.stack([motion.pitch_rel(t_imu), motion.roll_rel(t_imu)], -1)
    tilt = np.stack([motion.slope(t_imu), motion.camber(t_imu)], -1)
    gyro_true = motion.gyro(t_imu)
    accel_true = motion.specific_force(t_imu)
    vel = motion.vel_grav(t_imu)

    gyro, accel = gyro_true.copy(), accel_true.copy()
    gyro_bias, accel_bias = np.zeros_like(gyro), np.zeros_like(accel)
    if noisy:
        nrng = np.random.default_rng([int(seed), 2])
        dt = 1.0 / imu_rate
        gyro_bias = nrng.normal(0, imu_noise.gyro_bias, 3) + np.cumsum(
            nrng.normal(0, imu_noise.gyro_bias_walk * math.sqrt(dt), (n_imu, 3)), 0)
        accel_bias = nrng.normal(0, imu_noise.accel_bias, 3) + np.cumsum(
            nrng.normal(0, imu_noise.accel_bias_walk * math.sqrt(dt), (n_imu, 3)), 0)
        # Vibration: engine harmonics (speed-dependent amplitude) + broadband road roughness.
        vib = np.zeros((n_imu, 3))
        env = 0.5 + 0.5 * motion.speed(t_imu) / max(v_ref, 1e-3)
        nyq = 0.5 * imu_rate
        for axis, gain in enumerate((0.7, 0.7, 1.5)):
            for _ in range(3):
                f = nrng.uniform(0.15, 0.9) * nyq
                vib[:, axis] += gain * math.sqrt(2.0) * np.sin(2 * math.pi * f * t_imu + nrng.uniform(0, 2 * math.pi)) / math.sqrt(3)
            vib[:, axis] = 0.8 * vib[:, axis] * env + 0.6 * gain * nrng.normal(0, 1, n_imu)
        vib *= imu_noise.accel_vibration
        gyro = gyro_true + gyro_bias + nrng.normal(0, imu_noise.gyro_white, (n_imu, 3))
        accel = accel_true + accel_bias + vib + nrng.normal(0, imu_noise.accel_white, (n_imu, 3))

    fi = np.arange(n_frames) * step
    poses = np.concatenate([xy_imu, ((yaw + math.pi) % (2 * math.pi) - math.pi)[:, None]], 1)
    xy_f, yaw_f = xy_imu[fi], yaw[fi]
    d = xy_f[1:] - xy_f[:-1]
    c, s = np.cos(yaw_f[:-1]), np.sin(yaw_f[:-1])
    rel = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], yaw_f[1:] - yaw_f[:-1]], 1)

    ground = RoadGround(seed if ground_seed is None else ground_seed, path=_lane_path(xy_dense, motion.yaw(t_dense)))
    stamps = float(t0) + t_imu
    drive = SyntheticDrive(
        camera=camera, ground=ground, seed=int(seed), frame_stamps=stamps[fi], frame_imu_index=fi, images=None,
        imu_stamps=stamps, gyro=gyro, accel=accel, gyro_true=gyro_true, accel_true=accel_true,
        gyro_bias=gyro_bias, accel_bias=accel_bias, poses_xy_yaw=poses[fi], pitch_roll_road=pr_road[fi],
        pitch_roll_gravity=np.stack([pitch_g, roll_g], -1)[fi], road_slope_camber=tilt[fi], relative_motion=rel,
        speed=motion.speed(t_imu)[fi], base_height=motion.z_base(t_imu)[fi], imu_pitch_roll_road=pr_road,
        imu_pitch_roll_gravity=np.stack([pitch_g, roll_g], -1), imu_road_slope_camber=tilt,
        imu_rotation_gravity=r_grav, imu_velocity_gravity=vel, imu_poses_xy_yaw=poses,
        render_options=options, image_noise=noisy, _motion=motion,
    )
    if render == "lazy":
        drive.images = LazyImages(drive)
    elif render:
        drive.images = np.stack([render_frame(drive, i) for i in range(n_frames)])
    return drive


def _lane_path(xy_dense: np.ndarray, yaw_dense: np.ndarray, extend: float = 120.0) -> np.ndarray:
    """The lane-centre polyline: the driven path plus straight extensions at both ends (the camera
    sees ~100 m ahead of the last frame)."""
    seg = np.linalg.norm(np.diff(xy_dense, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    keep = np.searchsorted(s, np.arange(0.0, s[-1], 0.1))
    pts = xy_dense[keep]
    head0 = np.array([math.cos(yaw_dense[0]), math.sin(yaw_dense[0])])
    head1 = np.array([math.cos(yaw_dense[-1]), math.sin(yaw_dense[-1])])
    k = np.arange(1, int(extend / 0.5) + 1)[:, None] * 0.5
    before = xy_dense[0] - k[::-1] * head0
    after = xy_dense[-1] + k * head1
    return np.concatenate([before, pts, xy_dense[-1:], after], 0)


# ---------------------------------------------------------------------------------------------
# Rendering
# ---------------------------------------------------------------------------------------------

def camera_pose_world(camera: CameraModel, pose_xy_yaw, pitch_roll_road) -> tuple[Tensor, Tensor]:
    """World pose of the camera: ``R_world_cam (3, 3)``, ``t_world_cam (3,)`` float64.

    Uses :func:`camera_pose_on_road` (road frame under the base) rotated by yaw and moved to (x, y).
    """
    x, y, yaw = (float(v) for v in pose_xy_yaw)
    p = torch.tensor([float(pitch_roll_road[0])], dtype=torch.float64)
    r = torch.tensor([float(pitch_roll_road[1])], dtype=torch.float64)
    r_road_cam, t_road_cam = camera_pose_on_road(camera, p, r)
    c, s = math.cos(yaw), math.sin(yaw)
    rz = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return rz @ r_road_cam[0], rz @ t_road_cam[0] + torch.tensor([x, y, 0.0], dtype=torch.float64)


def render_view(
    ground: RoadGround,
    camera: CameraModel,
    pose_xy_yaw,
    pitch_roll_road,
    options: RenderOptions | None = None,
    noise_seed: Sequence[int] | int | None = None,
) -> np.ndarray:
    """Render the camera image at a vehicle pose. -> ``(H, W)`` uint8.

    Every (sub-)pixel ray is intersected with the road plane ``z = 0``; the pixel shows the ground
    intensity there (bilinear texture), the sky for rays that do not hit the ground.

    Args:
        ground: the road surface.
        camera: pinhole camera; integer pixel coordinates are pixel centres (KITTI/OpenCV).
        pose_xy_yaw: world ``(x, y, yaw)`` of the base.
        pitch_roll_road: ``(pitch, roll)`` of the base relative to the road, radians.
        options: renderer settings; image noise is drawn from ``noise_seed``.
    """
    options = options or RenderOptions()
    ss = int(options.supersample)
    if ss < 1:
        raise ValueError(f"supersample must be >= 1, got {options.supersample}")
    if not 0 < options.haze_start < options.haze_end:
        raise ValueError(f"need 0 < haze_start < haze_end, got {options.haze_start}, {options.haze_end}")
    r_wc, t_wc = camera_pose_world(camera, pose_xy_yaw, pitch_roll_road)
    # World direction of the ray through sub-pixel (u, v): M @ [u, v, 1].
    m = r_wc @ torch.linalg.inv(camera.K.detach().cpu().double())
    w, h = camera.width, camera.height_px
    off = (torch.arange(ss, dtype=torch.float64) + 0.5) / ss - 0.5
    us = (torch.arange(w, dtype=torch.float64)[:, None] + off).reshape(-1)  # (W*ss,)
    vs = (torch.arange(h, dtype=torch.float64)[:, None] + off).reshape(-1)  # (H*ss,)
    img = torch.empty(h, w, dtype=torch.float32)
    rows = max(1, 96 // ss)  # image rows per block: bounded memory (~30 MB) whatever the size
    for r0 in range(0, h, rows):
        v = vs[r0 * ss:(r0 + rows) * ss]
        # Ray directions (n_v, W*ss, 3): column-wise affine in u and v.
        d = m[:, 0] * us[None, :, None] + (m[:, 1] * v[:, None, None] + m[:, 2])
        rz = d[..., 2]
        horiz = torch.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2)
        sin_elev = rz / torch.sqrt(horiz * horiz + rz * rz)  # sky: brighter with elevation, no texture
        out = options.sky_horizon + (options.sky_zenith - options.sky_horizon) * (sin_elev / 0.35).clamp(0.0, 1.0)
        down = rz < -1e-12
        out = torch.where(down, options.haze_value, out)
        lam = -t_wc[2] / torch.where(down, rz, -1.0)
        dist = lam * horiz  # horizontal range of the ground point
        near = down & (dist < options.haze_end)
        if near.any():
            lam, dn, dist = lam[near], d[near], dist[near]
            val = ground._intensity_torch(t_wc[0] + lam * dn[:, 0], t_wc[1] + lam * dn[:, 1]).double()
            # Far ground fades into haze (hides texture aliasing near the horizon).
            wh = ((dist - options.haze_start) / (options.haze_end - options.haze_start)).clamp(0.0, 1.0)
            wh = wh * wh * (3 - 2 * wh)
            out[near] = val * (1 - wh) + options.haze_value * wh
        n_r = out.shape[0] // ss
        img[r0:r0 + n_r] = F.avg_pool2d(out.float()[None, None], ss)[0, 0] if ss > 1 else out.float()
    if options.vignette:
        vv = torch.arange(h, dtype=torch.float32)[:, None] - (h - 1) / 2
        uu = torch.arange(w, dtype=torch.float32)[None, :] - (w - 1) / 2
        img *= 1.0 - options.vignette * (uu * uu + vv * vv) / ((w / 2) ** 2 + (h / 2) ** 2)
    out_np = img.numpy() * 255.0
    if options.noise_std:
        out_np += np.random.default_rng(noise_seed).normal(0.0, options.noise_std, out_np.shape).astype(np.float32)
    return np.clip(np.rint(out_np), 0, 255).astype(np.uint8)


def render_frame(drive: SyntheticDrive, index: int, options: RenderOptions | None = None) -> np.ndarray:
    """Render frame ``index`` of a drive (deterministic: image noise seeded by drive seed + index)."""
    n = drive.num_frames
    if not -n <= index < n:
        raise ValueError(f"frame index {index} out of range for {n} frames")
    index = index % n
    opts = options or drive.render_options
    return render_view(drive.ground, drive.camera, drive.poses_xy_yaw[index], drive.pitch_roll_road[index], opts,
                       noise_seed=[drive.seed, 3, index])


# ---------------------------------------------------------------------------------------------
# Ground truth helpers
# ---------------------------------------------------------------------------------------------


def ground_patch(x, y, yaw, spec: BevSpec, ground: RoadGround | None = None, supersample: int = 1,
                 dtype: torch.dtype = torch.float32) -> Tensor:
    """The true BEV of a vehicle at world pose ``(x, y, yaw)``: the ground sampled at
    ``spec.ground_points()`` moved by the pose. Scalars -> ``(S, S)``; arrays ``(B,)`` -> ``(B, S, S)``.

    ``supersample > 1`` averages ``ss x ss`` points per BEV cell (area-averaged BEV).
    """
    ground = ground or default_ground()
    x_t = torch.as_tensor(np.asarray(x, dtype=np.float64))
    batched = x_t.ndim > 0
    x_t = x_t.reshape(-1)
    y_t = torch.as_tensor(np.asarray(y, dtype=np.float64)).reshape(-1)
    yaw_t = torch.as_tensor(np.asarray(yaw, dtype=np.float64)).reshape(-1)
    if not (x_t.shape == y_t.shape == yaw_t.shape):
        raise ValueError(f"x, y, yaw must have the same shape, got {x_t.shape}, {y_t.shape}, {yaw_t.shape}")
    ss = int(supersample)
    if ss < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    pts = spec.ground_points(dtype=torch.float64)  # (S, S, 2)
    if ss > 1:
        off = ((torch.arange(ss, dtype=torch.float64) + 0.5) / ss - 0.5) * spec.metres_per_pixel
        ox, oy = torch.meshgrid(off, off, indexing="ij")
        pts = pts[:, :, None, :] + torch.stack([ox, oy], -1).reshape(1, 1, -1, 2)
    else:
        pts = pts[:, :, None, :]
    c, s = torch.cos(yaw_t), torch.sin(yaw_t)
    px, py = pts[..., 0][None], pts[..., 1][None]
    b = (slice(None),) + (None,) * 3
    wx = x_t[b] + c[b] * px - s[b] * py
    wy = y_t[b] + s[b] * px + c[b] * py
    val = ground.intensity(wx, wy).mean(-1).to(dtype)
    return val if batched else val[0]


def true_bev(source, spec: BevSpec, frame: int | None = None, supersample: int = 1,
             dtype: torch.dtype = torch.float32) -> Tensor:
    """The exact BEV (ground truth for ``core.bev.project_to_bev``).

    Args:
        source: a :class:`SyntheticDrive` (BEV of ``frame``, or of all frames when None ->
            ``(F, S, S)``), or a world pose ``(x, y, yaw)`` ``(3,)`` / ``(B, 3)`` on the default ground.
        spec: BEV grid.

    Returns:
        ``(S, S)`` (or batched) intensities in [0, 1].
    """
    if isinstance(source, SyntheticDrive):
        poses = source.poses_xy_yaw if frame is None else source.poses_xy_yaw[frame]
        return ground_patch(poses[..., 0], poses[..., 1], poses[..., 2], spec, source.ground, supersample, dtype)
    pose = np.asarray(source, dtype=np.float64)
    if pose.shape[-1:] != (3,) or pose.ndim > 2:
        raise ValueError(f"pose must be (3,) or (B, 3) world (x, y, yaw), got shape {pose.shape}")
    return ground_patch(pose[..., 0], pose[..., 1], pose[..., 2], spec, None, supersample, dtype)


def base_poses_4x4(drive: SyntheticDrive, at_imu: bool = False) -> np.ndarray:
    """World (road-frame) poses of the base incl. road-relative pitch/roll and height. -> ``(F, 4, 4)``."""
    if at_imu:
        xy_yaw, pr = drive.imu_poses_xy_yaw, drive.imu_pitch_roll_road
        z = drive._motion.z_base(drive.imu_stamps - drive.imu_stamps[0]) if drive._motion else None
    else:
        xy_yaw, pr, z = drive.poses_xy_yaw, drive.pitch_roll_road, drive.base_height
    T = np.tile(np.eye(4), (len(xy_yaw), 1, 1))
    T[:, :3, :3] = _rz(xy_yaw[:, 2]) @ _ry(pr[:, 0]) @ _rx(pr[:, 1])
    T[:, 0, 3], T[:, 1, 3], T[:, 2, 3] = xy_yaw[:, 0], xy_yaw[:, 1], z
    return T


def camera_poses_4x4(drive: SyntheticDrive) -> np.ndarray:
    """World poses of the camera at the frames, ``base_poses_4x4 @ T_base_cam``. -> ``(F, 4, 4)``."""
    return base_poses_4x4(drive) @ drive.camera.T_base_cam.detach().cpu().double().numpy()
