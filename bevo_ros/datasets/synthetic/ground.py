"""Procedural road ground with exact intensities: two non-repeating texture tiles (asphalt grain,
stones, cracks, stains, repairs, manholes) plus lane markings along the driven path (:class:`RoadGround`).

The world frame is the road plane (z up along the road normal, the road surface is ``z = 0``).
"""
from __future__ import annotations

import math
from functools import lru_cache

import cv2
import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["RoadGround", "default_ground", "ground_intensity"]

Tensor = torch.Tensor

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
