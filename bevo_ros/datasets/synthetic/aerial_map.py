"""Synthetic data for BEVO+ (map-based localisation), with exact ground truth.

* :func:`render_aerial_map`: the synthetic world's ground (:class:`bevo_ros.datasets.synthetic.ground.RoadGround`)
  seen from above at 0.2-0.3 m/px with a *different appearance* (:class:`MapAppearance`): another
  exposure, gamma and contrast, a colour tint, smooth illumination, tree shadows, blur, sensor
  noise, 8-bit quantisation, and changed ground (re-paved patches, parked cars, lane markings
  missing in places).
* :func:`simulate_odometry`: the odometry of a drive with a realistic drift (scale error, yaw bias,
  white noise) and its covariances; :func:`frame_bev`: the BEV a camera would give at a frame (the
  exact ground under the camera's BEV footprint, with its own exposure and noise). Together they
  are the "cheap path" of long drives: no image rendering, no DUKF, so a 2 km drive takes
  seconds, while the localisation sees what it would see behind the real odometry engine.
* :func:`run_localization`: drive a :class:`~bevo_ros.core.map_localization.MapLocalizer` over
  such a drive; :func:`localization_demo`: the BEVO+ row and plot of ``bevo demo``.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import torch

from bevo_ros.core.aerial_map import AerialMap
from bevo_ros.core.geometry import BevSpec
from bevo_ros.core.map_localization import LocalizerConfig, MapLocalizer, se2_compose, wrap
from bevo_ros.datasets.synthetic.drive import SyntheticDrive, make_drive
from bevo_ros.datasets.synthetic.ground import RoadGround
from bevo_ros.datasets.synthetic.render import ground_patch, kitti_like_camera

__all__ = ["HARSH_APPEARANCE", "LocalizationDrive", "MapAppearance", "SAME_APPEARANCE", "bev_footprint", "frame_bev", "localization_demo",
           "make_localization_drive", "render_aerial_map", "run_localization", "simulate_odometry"]


@dataclass(frozen=True)
class MapAppearance:
    """How the aerial map differs from what the car's camera sees (all seeded).

    Attributes:
        gamma, gain, offset: ``offset + gain * I ** gamma`` (another exposure and sensor).
        tint: RGB gains of a colour map (None: grey map).
        illumination: amplitude of a smooth (50 m) multiplicative illumination field.
        shadows: darkening of tree/building shadows (0 = none); ``shadow_cover``: fraction of the
            ground in shadow.
        blur: Gaussian blur sigma, metres (optics + motion of the aerial camera).
        noise: sensor noise std (intensity units).
        repaved: re-paved patches per 100 m of corridor length; ``cars``: parked cars per 100 m.
        missing_markings: fraction of the lane markings' length erased in the map.
    """

    gamma: float = 1.5
    gain: float = 0.85
    offset: float = 0.08
    tint: tuple[float, float, float] | None = (1.0, 0.95, 0.85)
    illumination: float = 0.15
    shadows: float = 0.5
    shadow_cover: float = 0.2
    blur: float = 0.25
    noise: float = 0.02
    repaved: float = 1.0
    cars: float = 2.0
    missing_markings: float = 0.15


# A harsher map: low sun (deep, large shadows), strong gamma, uneven light, noisier, blurrier.
HARSH_APPEARANCE = MapAppearance(gamma=2.2, gain=0.9, offset=0.02, illumination=0.3, shadows=0.75, shadow_cover=0.35,
                                 blur=0.35, noise=0.04, repaved=2.0, cars=4.0, missing_markings=0.3)

SAME_APPEARANCE = MapAppearance(gamma=1.0, gain=1.0, offset=0.0, tint=None, illumination=0.0, shadows=0.0, blur=0.0,
                                noise=0.0, repaved=0.0, cars=0.0, missing_markings=0.0)


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float) -> np.ndarray:
    """Zero-mean, unit-std smooth random field (white noise blurred at ``sigma_px``)."""
    small = max(1.0, sigma_px / 4.0)
    h, w = max(2, int(shape[0] / small) + 2), max(2, int(shape[1] / small) + 2)
    n = cv2.GaussianBlur(rng.normal(size=(h, w)).astype(np.float32), (0, 0), sigma_px / small)
    n = cv2.resize(n, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
    return (n - n.mean()) / max(float(n.std()), 1e-9)


def render_aerial_map(ground: RoadGround, path_xy: np.ndarray, resolution: float = 0.25, margin: float = 30.0,
                      appearance: MapAppearance = MapAppearance(), seed: int = 0, supersample: int = 2) -> AerialMap:
    """The ground along a path as an aerial map (8-bit, grey or RGB) in the world (= map) frame.

    Args:
        ground: the world's ground.
        path_xy: ``(N, 2)`` world points the map must cover (a drive's positions).
        resolution: metres per pixel.
        margin: metres of ground rendered around the path; beyond it the map shows fields
            (a different, smooth texture).
        appearance: the map's appearance changes (:data:`SAME_APPEARANCE` for none).
        seed: of the appearance changes.
        supersample: ``n x n`` ground samples per pixel (area average).
    """
    path_xy = np.asarray(path_xy, dtype=np.float64)
    rng = np.random.default_rng([int(seed), 77])
    lo = path_xy.min(0) - margin - 5.0
    hi = path_xy.max(0) + margin + 5.0
    W = int(math.ceil((hi[0] - lo[0]) / resolution))
    H = int(math.ceil((hi[1] - lo[1]) / resolution))
    origin = (float(lo[0]), float(lo[1]), 0.0)

    def to_px(xy: np.ndarray) -> np.ndarray:
        return np.stack([(xy[:, 0] - lo[0]) / resolution - 0.5, H - (xy[:, 1] - lo[1]) / resolution - 0.5], 1)

    # Corridor: pixels within ``margin`` of the path (polyline drawn thick, sub-pixel precision).
    step = max(1, int(len(path_xy) / 20000))
    pts = np.round(to_px(path_xy[::step]) * 16).astype(np.int32)
    corridor = np.zeros((H, W), np.uint8)
    cv2.polylines(corridor, [pts], False, 1, thickness=max(1, int(2 * margin / resolution)), lineType=cv2.LINE_8,
                  shift=4)
    rows, cols = np.nonzero(corridor)
    ss = int(supersample)
    off = ((np.arange(ss) + 0.5) / ss - 0.5) * resolution
    img = np.zeros((H, W), np.float64)
    chunk = 1_000_000
    for k in range(0, len(rows), chunk):
        r, c = rows[k:k + chunk], cols[k:k + chunk]
        x = lo[0] + (c + 0.5) * resolution
        y = lo[1] + (H - r - 0.5) * resolution
        acc = np.zeros(len(r))
        for ox in off:
            for oy in off:
                acc += ground.intensity(torch.from_numpy(x + ox), torch.from_numpy(y + oy)).double().numpy()
        img[r, c] = acc / (ss * ss)
    a = appearance
    # Fields beyond the corridor: a smooth green-grey texture (no asphalt grain, no markings).
    field_tex = 0.45 + 0.06 * _smooth_noise(rng, (H, W), 3.0 / resolution)
    cm = cv2.GaussianBlur(corridor.astype(np.float32), (0, 0), 1.0 / resolution)
    img = cm * img + (1.0 - cm) * field_tex
    area_m = len(path_xy) and float(np.linalg.norm(np.diff(path_xy, axis=0), axis=1).sum())
    n100 = max(area_m / 100.0, 1.0)
    # Changed ground: erased lane markings (painted over with the local asphalt), re-paved patches,
    # parked cars; each kind drawn into one mask first (one pass over the image per kind).
    if a.missing_markings > 0 and ground.path is not None:
        seg = ground.path
        L = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(seg, axis=0), axis=1))])
        erased = np.zeros((H, W), np.uint8)
        for s0 in rng.uniform(0, L[-1], int(a.missing_markings * L[-1] / 15.0)):
            i0, i1 = np.searchsorted(L, [s0, s0 + 15.0])
            p = np.round(to_px(seg[i0:max(i1, i0 + 2)]) * 16).astype(np.int32)
            cv2.polylines(erased, [p], False, 1, thickness=int(14.0 / resolution), shift=4)
        if erased.any():
            med = cv2.medianBlur((np.clip(img, 0, 1) * 255).astype(np.uint8), 2 * int(0.5 / resolution) + 1) / 255.0
            img = np.where(erased > 0, med, img)
    paint = np.zeros((H, W), np.float32)  # new intensity + 1 where changed, 0 elsewhere

    def draw_box(centre: np.ndarray, size_px: tuple[float, float], angle_deg: float, value: float) -> None:
        c = to_px(centre[None])[0]
        box = ((float(c[0]), float(c[1])), size_px, angle_deg)
        cv2.fillPoly(paint, [np.round(cv2.boxPoints(box)).astype(np.int32)], float(value) + 1.0)

    for _ in range(rng.poisson(a.repaved * n100)):
        c = path_xy[rng.integers(len(path_xy))] + rng.normal(0, 2.0, 2)
        size = rng.uniform(3.0, 10.0, 2) / resolution
        draw_box(c, (float(size[0]), float(size[1])), float(rng.uniform(0, 180)), rng.uniform(0.2, 0.45))
    heading = np.gradient(path_xy, axis=0)
    for _ in range(rng.poisson(a.cars * n100)):
        i = rng.integers(len(path_xy))
        h = heading[i] / max(np.linalg.norm(heading[i]), 1e-9)
        c = path_xy[i] + rng.choice([-1.0, 1.0]) * rng.uniform(4.0, 7.5) * np.array([-h[1], h[0]])
        draw_box(c, (4.5 / resolution, 1.9 / resolution), -math.degrees(math.atan2(h[1], h[0])),
                 rng.choice([0.08, 0.2, 0.6, 0.9]))
    changed = paint > 0
    img[changed] = paint[changed] - 1.0
    # Photometry: another exposure and gamma, smooth illumination, shadows.
    img = np.clip(img, 0.0, 1.0)
    img = a.offset + a.gain * img**a.gamma
    if a.illumination:
        img *= 1.0 + a.illumination * _smooth_noise(rng, (H, W), 50.0 / resolution)
    if a.shadows:
        blob = _smooth_noise(rng, (H, W), 2.5 / resolution)
        thr = np.quantile(blob[::7, ::7], 1.0 - a.shadow_cover)
        shade = np.clip((blob - thr) / 0.3, 0.0, 1.0)
        img *= 1.0 - a.shadows * cv2.GaussianBlur(shade.astype(np.float32), (0, 0), 0.3 / resolution)
    if a.blur:
        img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), a.blur / resolution)
    chans = [img] if a.tint is None else [img * g for g in a.tint]
    out = np.stack(chans, 0)
    if a.noise:
        out = out + rng.normal(0.0, a.noise, out.shape)
    out = np.round(np.clip(out, 0.0, 1.0) * 255.0) / 255.0  # 8-bit like a PNG orthophoto
    return AerialMap(torch.from_numpy(out.astype(np.float32)), resolution, origin)


# ------------------------------------------------------------------------------------------------
# Drives: odometry with drift and BEVs, without rendering
# ------------------------------------------------------------------------------------------------
@lru_cache(maxsize=4)
def bev_footprint(spec: BevSpec = BevSpec()) -> torch.Tensor:
    """The BEV mask of the KITTI-like camera on a level road: ``(S, S)`` float32."""
    from bevo_ros.core.bev import project_to_bev

    cam = kitti_like_camera(dtype=torch.float32)
    img = torch.full((1, 1, cam.height_px, cam.width), 0.5)
    z = torch.zeros(1)
    _, mask = project_to_bev(img, cam, z, z, spec)
    return mask[0, 0]


def frame_bev(drive: SyntheticDrive, index: int, spec: BevSpec = BevSpec(), rng: np.random.Generator | None = None,
              noise: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """The BEV at frame ``index`` (exact ground under the camera footprint, the camera's own
    exposure and noise). -> ``bev (S, S)`` float32 in [0, 1], ``mask (S, S)``."""
    x, y, yaw = drive.poses_xy_yaw[index]
    bev = ground_patch(x, y, yaw, spec, drive.ground).numpy()
    if rng is not None:
        bev = rng.uniform(0.9, 1.1) * bev + rng.uniform(-0.03, 0.03) + rng.normal(0.0, noise, bev.shape)
    mask = bev_footprint(spec).numpy()
    return (np.clip(bev, 0.0, 1.0) * mask).astype(np.float32), mask


@dataclass
class LocalizationDrive:
    """A drive for localisation: ground truth in the world (= map) frame and drifting odometry.

    Attributes:
        drive: the synthetic drive (no images).
        gt: ``(F, 3)`` world poses.
        motion: ``(F-1, 3)`` odometry increments; ``motion_cov``: ``(F-1, 3, 3)``.
        odom: ``(F, 3)`` odometry poses (odom frame, identity at frame 0).
    """

    drive: SyntheticDrive
    gt: np.ndarray
    motion: np.ndarray
    motion_cov: np.ndarray
    odom: np.ndarray

    @property
    def length(self) -> float:
        return float(np.linalg.norm(np.diff(self.gt[:, :2], axis=0), axis=1).sum())

    def odometry_in_map(self, start: np.ndarray | None = None) -> np.ndarray:
        """The odometry alone, started at ``start`` (default: the true first pose). ``(F, 3)``."""
        start = self.gt[0] if start is None else np.asarray(start, dtype=np.float64)
        return se2_compose(np.broadcast_to(start, self.odom.shape), self.odom)


def simulate_odometry(gt_motion: np.ndarray, seed: int = 0, scale_error: float = 0.015,
                      yaw_bias: float = math.radians(0.01), noise=(0.03, 0.02, math.radians(0.05))) -> tuple[np.ndarray, np.ndarray]:
    """Odometry increments with a drift: a scale error, a yaw bias (rad per metre) and white noise
    per frame (std of dx, dy in metres and dyaw in rad). -> ``motion (F-1, 3)``, ``cov (F-1, 3, 3)``
    (the white noise's, as an odometry would report it: it does not know its own bias)."""
    rng = np.random.default_rng([int(seed), 99])
    m = np.asarray(gt_motion, dtype=np.float64).copy()
    dist = np.linalg.norm(m[:, :2], axis=1)
    out = m.copy()
    out[:, :2] *= 1.0 + scale_error
    out[:, 2] += yaw_bias * dist
    out += rng.normal(size=m.shape) * np.asarray(noise)
    cov = np.tile(np.diag(np.asarray(noise, dtype=np.float64) ** 2), (len(m), 1, 1))
    return out, cov


def make_localization_drive(seed: int = 0, length: float = 500.0, speed: float = 10.0, frame_rate: float = 10.0,
                            curvature: float = 1.0, **odometry) -> LocalizationDrive:
    """A drive of about ``length`` metres (no images) with drifting odometry (:func:`simulate_odometry`)."""
    duration = length / speed
    drive = make_drive(seed=seed, duration=duration, frame_rate=frame_rate, imu_rate=frame_rate * 2, bumps=0.0,
                       road_tilt=False, noise=False, render=False, speed_range=(0.8 * speed, 1.2 * speed),
                       curvature=curvature)
    gt = drive.poses_xy_yaw.copy()
    motion, cov = simulate_odometry(drive.relative_motion, seed=seed, **odometry)
    odom = np.zeros((len(gt), 3))
    for i, m in enumerate(motion):
        odom[i + 1] = se2_compose(odom[i], m)
    return LocalizationDrive(drive, gt, motion, cov, odom)


@dataclass
class LocalizationRun:
    """What :func:`run_localization` returns (``(F, 3)`` trajectories in the map frame)."""

    estimate: np.ndarray
    odometry: np.ndarray
    gt: np.ndarray
    covariance: np.ndarray
    steps: list = field(default_factory=list)
    counters: object = None
    seconds_per_frame: float = math.nan
    seconds_per_update: float = math.nan

    def errors(self, start: int = 0) -> dict[str, float]:
        """RMS position (m) and yaw (deg) errors from frame ``start`` on, for both trajectories."""
        def rms(est):
            e = est[start:] - self.gt[start:]
            pos = float(np.sqrt(np.mean(np.sum(e[:, :2] ** 2, axis=1))))
            yaw = float(np.degrees(np.sqrt(np.mean(wrap(e[:, 2]) ** 2))))
            return pos, yaw

        (p, y), (po, yo) = rms(self.estimate), rms(self.odometry)
        end = float(np.linalg.norm(self.odometry[-1, :2] - self.gt[-1, :2]))
        return {"pos_rms": p, "yaw_rms_deg": y, "odom_pos_rms": po, "odom_yaw_rms_deg": yo, "odom_end_error": end,
                "pos_max": float(np.max(np.linalg.norm(self.estimate[start:, :2] - self.gt[start:, :2], axis=1)))}


def run_localization(ld: LocalizationDrive, aerial: AerialMap, initial_pose, initial_std=(3.0, 3.0, math.radians(5.0)),
                     config: LocalizerConfig = LocalizerConfig(), seed: int = 0, spec: BevSpec = BevSpec(),
                     device: str = "cpu", bev_noise: float = 0.02) -> LocalizationRun:
    """Localise a :class:`LocalizationDrive` in ``aerial`` from ``initial_pose`` (world x, y, yaw)
    with the claimed ``initial_std``; BEVs only at keyframe candidates (the cheap path)."""
    loc = MapLocalizer(aerial, spec, config, device=device)
    loc.set_initial_pose(initial_pose, np.diag(np.asarray(initial_std, dtype=np.float64) ** 2))
    rng = np.random.default_rng([int(seed), 5])
    F_ = len(ld.gt)
    est = np.zeros((F_, 3))
    covs = np.zeros((F_, 3, 3))
    est[0], covs[0] = loc.filter.x, loc.filter.P
    loc.pose_odom = ld.odom[0]
    steps = []
    t_update, n_update, t_total = 0.0, 0, 0.0
    for i in range(1, F_):
        # Render a BEV only when the localiser would keep it (the real engine has one every frame).
        d = math.hypot(*ld.motion[i - 1, :2])
        bev = mask = None
        if loc.mosaic.path + d - loc.mosaic._last_path >= loc.mosaic.spacing - 1e-9:
            bev, mask = frame_bev(ld.drive, i, spec, rng, bev_noise)
        ts = time.perf_counter()
        s = loc.step(ld.odom[i], ld.motion[i - 1], ld.motion_cov[i - 1], bev, mask)
        dt = time.perf_counter() - ts
        t_total += dt
        if s.measured:
            t_update += dt
            n_update += 1
        est[i], covs[i] = s.pose, s.covariance
        steps.append(s)
    return LocalizationRun(est, ld.odometry_in_map(), ld.gt, covs, steps, loc.counters, t_total / max(F_ - 1, 1),
                           t_update / max(n_update, 1))


def localization_demo(out_dir: str | Path, length: float = 600.0, seed: int = 1) -> dict[str, float | str]:
    """The BEVO+ row of ``bevo demo``: a synthetic drive of ``length`` metres with drifting
    odometry, localised in a heterogeneous aerial map from a 3 m / 5 deg initial error.
    Writes ``bevo_plus_trajectory.png`` (both trajectories on the map) and returns the figures."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ld = make_localization_drive(seed=seed, length=length)
    aerial = render_aerial_map(ld.drive.ground, ld.gt[:, :2], seed=seed)
    start = ld.gt[0] + np.array([3.0 / math.sqrt(2), -3.0 / math.sqrt(2), math.radians(5.0)])
    run = run_localization(ld, aerial, start, seed=seed)
    err = run.errors(start=len(ld.gt) // 10)
    fig, ax = plt.subplots(figsize=(8, 8))
    step = max(1, max(aerial.width, aerial.height) // 800)  # a plot needs no more pixels than it shows
    img = aerial.image[:, ::step, ::step].permute(1, 2, 0).numpy()
    ox, oy, _ = aerial.origin
    W, H = aerial.extent
    ax.imshow(img if img.shape[-1] == 3 else img[..., 0], cmap="gray", extent=(ox, ox + W, oy, oy + H))
    ax.plot(run.gt[:, 0], run.gt[:, 1], "-", color="lime", lw=3.0, alpha=0.8, label="ground truth")
    ax.plot(run.odometry[:, 0], run.odometry[:, 1], "r--", lw=1.2, label="odometry only (BEVO)")
    ax.plot(run.estimate[:, 0], run.estimate[:, 1], "b-", lw=1.0, label="BEVO+ (map)")
    pad = 40.0
    allxy = np.concatenate([run.gt[:, :2], run.odometry[:, :2]])
    ax.set_xlim(allxy[:, 0].min() - pad, allxy[:, 0].max() + pad)
    ax.set_ylim(allxy[:, 1].min() - pad, allxy[:, 1].max() + pad)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best")
    ax.set_title(f"BEVO+ on a {ld.length:.0f} m synthetic drive: {err['pos_rms']:.2f} m RMS "
                 f"(odometry only {err['odom_pos_rms']:.1f} m)")
    png = out_dir / "bevo_plus_trajectory.png"
    fig.savefig(png, dpi=90, bbox_inches="tight")
    plt.close(fig)
    c = run.counters
    table = ("| BEVO+ (synthetic, heterogeneous map, start 3 m / 5 deg off) | frames | path (m) | position RMS (m) | "
             "yaw RMS (deg) | end error (m) | map updates accepted |\n|---|---|---|---|---|---|---|\n"
             f"| odometry only | {len(ld.gt)} | {ld.length:.0f} | {err['odom_pos_rms']:.2f} | {err['odom_yaw_rms_deg']:.2f} | "
             f"{err['odom_end_error']:.2f} | - |\n"
             f"| BEVO+ (map) | {len(ld.gt)} | {ld.length:.0f} | {err['pos_rms']:.2f} | {err['yaw_rms_deg']:.2f} | "
             f"{float(np.linalg.norm(run.estimate[-1, :2] - run.gt[-1, :2])):.2f} | {c.accepted}/{c.measurements} |\n")
    return {"length_m": ld.length, "frames": len(ld.gt), **err, "accepted": c.accepted, "measurements": c.measurements,
            "plot": str(png), "table": table}
