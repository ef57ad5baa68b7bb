"""Camera rendering of the synthetic ground and its true BEV.

The renderer and the BEV projection share the geometry of :mod:`bevo_ros.core.geometry` exactly (the
camera pose comes from :func:`~bevo_ros.core.geometry.camera_pose_on_road`). The BEV helpers
(:func:`true_bev`, :func:`ground_patch`) return torch tensors to compare with ``core.bev``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from bevo_ros.core.geometry import BevSpec, CameraModel, camera_pose_on_road
from bevo_ros.datasets.synthetic.ground import RoadGround, _periodic_noise, _sample_periodic, _wrap_pad, default_ground
from bevo_ros.datasets.synthetic.traffic import GROUND_CLEARANCE

if TYPE_CHECKING:
    from bevo_ros.datasets.synthetic.drive import SyntheticDrive

__all__ = [
    "RenderOptions", "RoadProfile", "camera_pose_world", "ground_patch", "kitti_like_camera", "render_frame",
    "render_view", "true_bev",
]

Tensor = torch.Tensor

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
    scale: float = 1.0,
) -> CameraModel:
    """The KITTI grey camera (1241x376, fx = fy = 718.856) on the base frame.

    Args:
        mount_pitch: camera pitch on the base, radians; positive looks down (the nose-down sign).
        mount_height: camera centre height above the road, metres.
        offset: camera centre in the base frame (x fwd, y left, z up), metres.
        scale: image resolution factor (0.5: the tests' and tools' 620x188 camera, K's first two
            rows scaled, the size rounded down).
    """
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive finite number, got {scale!r}")
    # Optical axes in base coordinates: x_cam = -y_base (right), y_cam = -z_base (down), z_cam = x_base.
    r_opt = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
    c, s = math.cos(mount_pitch), math.sin(mount_pitch)
    r_y = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float64)
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = r_y @ r_opt
    T[:3, 3] = torch.tensor([float(v) for v in offset], dtype=torch.float64)
    K = torch.tensor(KITTI_K, dtype=torch.float64)
    K[:2] *= scale
    width, height = int(KITTI_SIZE[0] * scale), int(KITTI_SIZE[1] * scale)
    return CameraModel(K.to(dtype), width, height, T.to(dtype), float(mount_height))


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
    vehicles: np.ndarray | None = None,
    road_height: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
) -> np.ndarray:
    """Render the camera image at a vehicle pose. -> ``(H, W)`` uint8.

    Every (sub-)pixel ray is intersected with the road plane ``z = 0`` (or the road bent by
    ``road_height``); the pixel shows the ground
    intensity there (bilinear texture), the sky for rays that do not hit the ground, or the nearest
    of the other ``vehicles`` (boxes, :mod:`.traffic`) when one is hit first; a vehicle's shadow
    darkens the road under it.

    Args:
        ground: the road surface.
        camera: pinhole camera; integer pixel coordinates are pixel centres (KITTI/OpenCV).
        pose_xy_yaw: world ``(x, y, yaw)`` of the base.
        pitch_roll_road: ``(pitch, roll)`` of the base relative to the road, radians.
        options: renderer settings; image noise is drawn from ``noise_seed``.
        vehicles: ``(K, 7)`` other vehicles (:data:`~.traffic.VEHICLE_FIELDS`), or None.
        road_height: ``u -> (height, d height / du)`` (numpy, m) of the road at ``u`` m ahead of
            the base along its heading, against the plane ``z = 0`` (crests and sags:
            :meth:`RoadProfile.height_ahead`); each ray shows the first point where it goes below
            it within the haze's reach (``_meet_bent_road``), the sky or the haze where none.
    """
    options = options or RenderOptions()
    boxes = _vehicle_frames(vehicles)
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
    bounds = None if boxes is None else _image_bounds(boxes, camera, r_wc, t_wc, ss)
    rows = max(1, 96 // ss)  # image rows per block: bounded memory (~30 MB) whatever the size
    table = None if road_height is None else _height_table(road_height, options.haze_end)
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
        if table is not None:
            # the first point where the ray meets the bent road within the haze's reach: a ray
            # above the plane's horizon can meet a sag's rising road; one aimed down that passes
            # over a crest and meets nothing within the reach shows the haze
            lam, hit = _meet_bent_road(table, pose_xy_yaw, t_wc, d, horiz, options.haze_end)
            out = torch.where(hit, options.haze_value, out)
            down = hit
        dist = lam * horiz  # horizontal range of the ground point
        near = down & (dist < options.haze_end)
        # The vehicles whose image rectangle meets this block, and the block's part they can cover.
        here = [] if boxes is None else _vehicles_in_block(bounds, r0 * ss, r0 * ss + d.shape[0])
        if near.any():
            lam_all = torch.where(near, lam, 0.0)
            gx_all, gy_all = t_wc[0] + lam_all * d[..., 0], t_wc[1] + lam_all * d[..., 1]
            val = ground._intensity_torch(gx_all[near], gy_all[near]).double()
            if here:
                shade = torch.ones_like(lam_all)
                for k, sl in here:
                    shade[sl] = shade[sl] * _shadow(boxes[k], gx_all[sl], gy_all[sl])
                val = val * shade[near]
            # Far ground fades into haze (hides texture aliasing near the horizon).
            dist = dist[near]
            wh = ((dist - options.haze_start) / (options.haze_end - options.haze_start)).clamp(0.0, 1.0)
            wh = wh * wh * (3 - 2 * wh)
            out[near] = val * (1 - wh) + options.haze_value * wh
        if here:
            ground_lam = torch.where(near, lam, math.inf)
            best = torch.full_like(ground_lam, math.inf)
            for k, sl in here:
                hit, value = _hit_vehicle(boxes[k], t_wc, d[sl].reshape(-1, 3))
                hit, value = hit.reshape(best[sl].shape), value.reshape(best[sl].shape)
                front = (hit < ground_lam[sl]) & (hit < best[sl])
                best[sl] = torch.where(front, hit, best[sl])
                out[sl] = torch.where(front, value, out[sl])
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


@dataclass
class RoadProfile:
    """A road's vertical profile: its slope along the distance travelled (crests and sags), by which
    the renderer bends the road ahead of each frame (the plane ``z = 0`` is the road under the base).

    Attributes:
        distance: ``(M,)`` m, increasing, covering every frame's view ahead (past it the slope is held).
        slope: ``(M,)`` rad, positive = descending (nose down, as REP-103's pitch).
        frame_distance: ``(F,)`` the distance of each frame.
    """

    distance: np.ndarray
    slope: np.ndarray
    frame_distance: np.ndarray

    def __post_init__(self) -> None:
        s, g = np.asarray(self.distance, np.float64), np.asarray(self.slope, np.float64)
        if s.ndim != 1 or s.shape != g.shape or len(s) < 2 or not (np.diff(s) > 0).all() or not np.isfinite(g).all():
            raise ValueError("RoadProfile needs increasing distances and finite slopes of the same length (>= 2)")
        self.distance, self.slope = s, g
        # the slope's integral (trapezoid): the height change along the road is its negative
        self._integral = np.concatenate([[0.0], np.cumsum(0.5 * (g[1:] + g[:-1]) * np.diff(s))])

    def _slope_and_integral(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The slope at distances ``s`` and its integral, exact for the piecewise-linear slope and
        continued at the end slopes (held) outside the profile."""
        d, g, big = self.distance, self.slope, self._integral
        slope = np.interp(s, d, g)
        i = np.clip(np.searchsorted(d, s, side="right") - 1, 0, len(d) - 2)
        inside = big[i] + (s - d[i]) * 0.5 * (g[i] + slope)
        before, after = big[0] + (s - d[0]) * g[0], big[-1] + (s - d[-1]) * g[-1]
        return slope, np.where(s < d[0], before, np.where(s > d[-1], after, inside))

    def height_ahead(self, s0: float):
        """``u (m ahead of the base at distance s0) -> (height, d height / du)`` against the road's
        plane under the base (small angles: the slope ahead less the slope here, integrated)."""
        g0, big0 = (float(v[0]) for v in self._slope_and_integral(np.array([float(s0)])))

        def height(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            g, big = self._slope_and_integral(s0 + np.asarray(u, np.float64))
            return -(big - big0 - g0 * u), -(g - g0)

        return height


def _meet_bent_road(table, pose_xy_yaw, t_wc: Tensor, d: Tensor, horiz: Tensor, reach: float,
                    iterations: int = 10) -> tuple[Tensor, Tensor]:
    """Ray parameters where rays ``t_wc + lam d`` (``d (..., 3)``, ``horiz`` its horizontal length)
    meet the bent road (``table``: ``u -> (height, slope)`` ahead of the base) within ``reach`` m
    of horizontal range -> ``(lam, hit)``. Bracketed from the plane's crossing (a sag's road is
    already above the ray there: between the camera and it; a crest's is still below: stepping on
    by 25 % until the ray goes under it), then Newton's method kept inside the bracket (a bisection
    step where it would leave it). A ray that meets the road twice before the plane's crossing (a
    rise the ray grazes, far ahead) may show the second meeting."""
    x, y, yaw = (float(v) for v in pose_xy_yaw)
    c, s = math.cos(yaw), math.sin(yaw)
    u0 = (float(t_wc[0]) - x) * c + (float(t_wc[1]) - y) * s  # the camera's distance ahead of the base
    du = d[..., 0] * c + d[..., 1] * s  # forward distance per unit of lam
    rz = d[..., 2]
    far = reach / horiz.clamp_min(1e-9)  # lam at the reach

    def above(lam: Tensor, sel=...) -> Tensor:  # the ray's height over the road
        return t_wc[2] + lam * rz[sel] - table(u0 + lam * du[sel])[0]

    start = torch.where(rz < 0, -t_wc[2] / rz.clamp(max=-1e-12), far).clamp(max=far)
    f0 = above(start)
    lo = torch.where(f0 > 0, start, torch.zeros_like(start))  # the camera is above the road
    hi = torch.where(f0 > 0, torch.full_like(start, math.inf), start)
    lam, still = start.clone(), (f0 > 0) & (start < far)
    while bool(still.any()):  # a crest: on by 25 % steps, the open rays only (<= ~30 steps to the reach)
        sel = still.nonzero(as_tuple=True)
        nxt = torch.minimum(lam[sel] * 1.25, far[sel])
        under = above(nxt, sel) <= 0
        hi[sel] = torch.where(under, nxt, hi[sel])
        lo[sel] = torch.where(under, lo[sel], nxt)
        lam[sel] = nxt
        still[sel] = ~under & (nxt < far[sel])
    hit = torch.isfinite(hi)
    lam = torch.where(hit, hi, 0.0)  # Newton from the far end: monotone on a crest's or a sag's curve
    lo = torch.where(hit, lo, 0.0)
    for _ in range(iterations):
        z, dz = table(u0 + lam * du)
        f = t_wc[2] + lam * rz - z
        lo, hi = torch.where(f > 0, lam, lo), torch.where(f > 0, hi, lam)
        slope = rz - dz * du
        step = lam - f / torch.where(slope < 0, slope, -1.0)
        lam = torch.where((slope < 0) & (step >= lo) & (step <= hi), step, 0.5 * (lo + hi))
    return torch.where(hit, lam, 0.0), hit


def _height_table(road_height, reach: float, step: float = 0.02):
    """``road_height`` tabulated every ``step`` m over ``[-10, reach + 10]`` m ahead: ``u (...) ->
    (height, slope)`` by linear interpolation (height error ~curvature x step^2 / 8 < 1e-7 m)."""
    grid = np.arange(-10.0, reach + 10.0 + step, step)
    z, dz = (torch.as_tensor(np.asarray(a, dtype=np.float64)) for a in road_height(grid))

    def lookup(u: Tensor) -> tuple[Tensor, Tensor]:
        pos = ((u - grid[0]) / step).clamp(0.0, len(grid) - 1.000001)
        i = pos.floor().long()
        w = pos - i
        return z[i] * (1 - w) + z[i + 1] * w, dz[i] * (1 - w) + dz[i + 1] * w

    return lookup


def _vehicle_frames(vehicles: np.ndarray | None) -> Tensor | None:
    """Vehicle rows ``(K, 7)`` -> float64 tensor, validated; None when there are none."""
    if vehicles is None or len(vehicles) == 0:
        return None
    v = torch.as_tensor(np.asarray(vehicles, dtype=np.float64))
    if v.ndim != 2 or v.shape[1] != 7 or not torch.isfinite(v).all() or (v[:, 3:6] <= 0).any():
        raise ValueError(f"vehicles must be a finite (K, 7) array with positive sizes, got shape {tuple(v.shape)}")
    return v


def _image_bounds(boxes: Tensor, camera: CameraModel, r_wc: Tensor, t_wc: Tensor, ss: int) -> list:
    """Per vehicle, the sub-pixel rectangle ``(u0, u1, v0, v1)`` (half-open, sub-pixel indices) that
    its box and its shadow (0.25 m around the footprint) can cover; the whole image when the box
    reaches behind the camera plane; None when it lies wholly behind."""
    K = camera.K.detach().cpu().double()
    W, H = camera.width * ss, camera.height_px * ss
    out = []
    for k in range(len(boxes)):
        x, y, yaw, length, width, height = (float(v) for v in boxes[k, :6])
        a, b = length / 2 + 0.25, width / 2 + 0.25
        c, s_ = math.cos(yaw), math.sin(yaw)
        corners = torch.tensor([[x + c * i * a - s_ * j * b, y + s_ * i * a + c * j * b, z]
                                for i in (-1, 1) for j in (-1, 1) for z in (0.0, height)], dtype=torch.float64)
        cam = (corners - t_wc) @ r_wc  # camera coordinates (x right, y down, z forward)
        z = cam[:, 2]
        if bool((z <= 0.05).all()):
            out.append(None)
            continue
        if bool((z <= 0.05).any()):
            out.append((0, W, 0, H))
            continue
        uv = (cam @ K.T)[:, :2] / z[:, None]
        u0, v0 = (uv.min(0).values * ss).floor().long().tolist()
        u1, v1 = (uv.max(0).values * ss).ceil().long().tolist()
        u0, u1, v0, v1 = max(0, u0 - ss), min(W, u1 + 2 * ss), max(0, v0 - ss), min(H, v1 + 2 * ss)
        out.append((u0, u1, v0, v1) if u0 < u1 and v0 < v1 else None)
    return out


def _vehicles_in_block(bounds: list, v_lo: int, v_hi: int) -> list:
    """``(k, (row slice, column slice))`` of the block's sub-pixel rows ``[v_lo, v_hi)`` each vehicle
    can cover."""
    out = []
    for k, bd in enumerate(bounds):
        if bd is None:
            continue
        u0, u1, v0, v1 = bd
        r0, r1 = max(v0, v_lo), min(v1, v_hi)
        if r0 < r1:
            out.append((k, (slice(r0 - v_lo, r1 - v_lo), slice(u0, u1))))
    return out


def _to_box(box: Tensor, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
    """World road-plane points -> the frame (forward, left) of ``box`` (a vehicle row), metres."""
    c, s = math.cos(float(box[2])), math.sin(float(box[2]))
    dx, dy = x - box[0], y - box[1]
    return c * dx + s * dy, -s * dx + c * dy


def _shadow(box: Tensor, x: Tensor, y: Tensor, darkness: float = 0.6, spread: float = 0.25) -> Tensor:
    """Road brightness factor under a vehicle's soft shadow at world points ``(...)`` -> same shape."""
    a, b = _to_box(box, x, y)
    inside = (((box[3] / 2 + spread - a.abs()) / spread).clamp(0, 1)
              * ((box[4] / 2 + spread - b.abs()) / spread).clamp(0, 1))
    return 1.0 - darkness * inside


@lru_cache(maxsize=1)
def _skin() -> Tensor:
    """A seamless noise tile for the vehicles' skins (fixed: vehicles differ by shade and offset)."""
    gen = torch.Generator().manual_seed(12345)
    return _wrap_pad(_periodic_noise(gen, 256, 0.02, 0.05, 1.0, 1.0).numpy())


def _hit_vehicle(box: Tensor, origin: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
    """Hit of rays ``origin + lam d`` (``d (N, 3)``) with a vehicle's box: ``lam (N,)`` (inf: none) and
    the skin's intensity there ``(N,)`` (slab method; windows dark in the upper third)."""
    lam_out = torch.full((d.shape[0],), math.inf, dtype=torch.float64)
    value = torch.zeros(d.shape[0], dtype=torch.float64)
    c, s = math.cos(float(box[2])), math.sin(float(box[2]))
    ox, oy = _to_box(box, origin[0:1], origin[1:2])
    dx, dy = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
    lo = torch.tensor([-box[3] / 2, -box[4] / 2, GROUND_CLEARANCE], dtype=torch.float64)
    hi = torch.tensor([box[3] / 2, box[4] / 2, box[5]], dtype=torch.float64)
    o = torch.stack([ox[0], oy[0], origin[2]])
    dirs = torch.stack([dx, dy, d[:, 2]], 1)
    inv = 1.0 / torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    t1, t2 = (lo - o) * inv, (hi - o) * inv
    t_near, axis = torch.minimum(t1, t2).max(1)
    t_far = torch.maximum(t1, t2).min(1).values
    hit = (t_near <= t_far) & (t_near > 0)
    if not hit.any():
        return lam_out, value
    lam, ax = t_near[hit], axis[hit]
    p = o + lam[:, None] * dirs[hit]
    # Skin coordinates: along the face (the side's length, the end's width) and up.
    along = torch.where(ax == 1, p[:, 0], p[:, 1])
    up = torch.where(ax == 2, p[:, 0], p[:, 2])
    seed = 1000.0 * float(box[6])  # where on the skin tile: by the vehicle (its shade), not its order
    tex = _sample_periodic(_skin(), along / 0.02 + seed, up / 0.02 + 0.37 * seed)[0].double()
    window = (ax != 2) & (p[:, 2] > GROUND_CLEARANCE + 0.62 * (box[5] - GROUND_CLEARANCE))
    shade = float(box[6]) * torch.where(window, 0.35, torch.where(ax == 2, 1.15, 1.0))
    lam_out[hit] = lam
    value[hit] = (shade * (1.0 + 0.25 * tex)).clamp(0.0, 1.0)
    return lam_out, value


def render_frame(drive: SyntheticDrive, index: int, options: RenderOptions | None = None) -> np.ndarray:
    """Render frame ``index`` of a drive (deterministic: image noise seeded by drive seed + index)."""
    n = drive.num_frames
    if not -n <= index < n:
        raise ValueError(f"frame index {index} out of range for {n} frames")
    index = index % n
    opts = options or drive.render_options
    vehicles = drive.traffic[index] if drive.traffic is not None else None
    profile = drive.road_profile
    return render_view(drive.ground, drive.camera, drive.poses_xy_yaw[index], drive.pitch_roll_road[index], opts,
                       noise_seed=[drive.seed, 3, index], vehicles=vehicles,
                       road_height=None if profile is None else profile.height_ahead(float(profile.frame_distance[index])))


# ---------------------------------------------------------------------------------------------
# True BEV
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
    from bevo_ros.datasets.synthetic.drive import SyntheticDrive  # the drive renders through this module

    if isinstance(source, SyntheticDrive):
        poses = source.poses_xy_yaw if frame is None else source.poses_xy_yaw[frame]
        return ground_patch(poses[..., 0], poses[..., 1], poses[..., 2], spec, source.ground, supersample, dtype)
    pose = np.asarray(source, dtype=np.float64)
    if pose.shape[-1:] != (3,) or pose.ndim > 2:
        raise ValueError(f"pose must be (3,) or (B, 3) world (x, y, yaw), got shape {pose.shape}")
    return ground_patch(pose[..., 0], pose[..., 1], pose[..., 2], spec, None, supersample, dtype)
