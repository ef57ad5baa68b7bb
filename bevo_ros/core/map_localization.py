"""BEVO+: drift-free localisation of the BEV in an aerial map (paper Section 3.2, Table 2).

Pipeline, for one vehicle (the measurement itself is batched and differentiable):

1. :class:`~bevo_ros.core.mosaic.MosaicBuffer` keeps the keyframe BEVs of the last ~20 m with
   their odometry poses; :func:`~bevo_ros.core.mosaic.compose_mosaic` averages them on a local
   grid at the matching resolution (the aerial map's, 0.25 m/px by default: finer detail is not
   in the map, and the FFTs are 6x cheaper than at the BEV's 0.1 m/px).
2. :func:`measure`: the map is cropped on the same grid at the *predicted* map pose of the mosaic's
   centre (differentiable ``grid_sample``), both images go through an illumination-robust
   :func:`appearance` transform, and the phase correlation of
   :mod:`~bevo_ros.core.phase_correlation` (rotation, then translation; phase-only whitening)
   gives the correction of that pose, with a covariance from the correlation spread.
3. :class:`MapPoseFilter`: an EKF on the SE(2) base pose in ``map``: predicted with every
   odometry increment and its covariance (plus a per-metre floor for what the odometry's own
   covariance misses), updated with the map measurement behind a peak-quality test and a
   Mahalanobis gate. A wrong match is rejected and counted, never a jump; after
   ``lost_after`` rejections in a row the status says "lost".
4. ``map -> odom`` (REP-105) is ``pose_map (+) pose_odom^-1``: the odometry stays continuous, the
   map frame absorbs its drift.

Appearance: the map is another day, sensor and resolution. :func:`appearance` offers ``raw``,
``lcn`` (local contrast normalisation: removes shadows, illumination and contrast changes that are
smooth over ``lcn_sigma``) and ``gradient`` (local-contrast-normalised gradient magnitude of the
log intensity: also invariant to a gamma change and to contrast inversion); the phase
correlation's whitening (``DpcConfig.whitening_floor = 0``) is the phase-only part.
``tools/bench_localization.py`` measures what each buys.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import torch
import torch.nn.functional as F

from .aerial_map import AerialMap
from .geometry import BevSpec
from .mosaic import MosaicBuffer, _gaussian_blur, compose_mosaic
from .phase_correlation import DpcConfig, Registration, _window_2d, register

Tensor = torch.Tensor

APPEARANCES = ("raw", "lcn", "gradient")
# Phase correlation for map matching: a wide flat window (the mosaic is a long strip, the
# radial Hann of frame-to-frame matching would keep only its middle), pure phase whitening, and
# the Fourier-magnitude angle refined by direct alignment (it is disturbed by the content the
# map and the mosaic do not share).
MAP_DPC = DpcConfig(window_alpha=0.25, mask_blur=2.0, rotation_refine_iters=3, rotation_refine_step=1.0,
                    radial_range=(0.04, 0.35), translation_sigma=1.0)


# ------------------------------------------------------------------------------------------------
# SE(2) helpers (x, y, yaw), batched over leading dims
# ------------------------------------------------------------------------------------------------
def wrap(a):
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def se2_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a (+) b`` for numpy ``(..., 3)``."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([a[..., 0] + c * b[..., 0] - s * b[..., 1], a[..., 1] + s * b[..., 0] + c * b[..., 1],
                     wrap(a[..., 2] + b[..., 2])], axis=-1)


def se2_inverse(a: np.ndarray) -> np.ndarray:
    """``a^-1`` for numpy ``(..., 3)``."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([-c * a[..., 0] - s * a[..., 1], s * a[..., 0] - c * a[..., 1], wrap(-a[..., 2])], axis=-1)


def se2_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a^-1 (+) b``."""
    return se2_compose(se2_inverse(a), b)


# ------------------------------------------------------------------------------------------------
# Appearance
# ------------------------------------------------------------------------------------------------
def _local_stats(x: Tensor, w: Tensor, sigma: float) -> tuple[Tensor, Tensor]:
    den = _gaussian_blur(w, sigma).clamp_min(1e-6)
    mean = _gaussian_blur(w * x, sigma) / den
    var = _gaussian_blur(w * (x - mean) ** 2, sigma) / den
    return mean, var


def appearance(image: Tensor, mask: Tensor, mode: str = "lcn", sigma: float = 6.0) -> Tensor:
    """An illumination-robust representation of ``image (B, 1, S, S)`` with ``mask (B, 1, S, S)``.

    ``sigma`` (pixels) is the scale of the local statistics; masked pixels do not leak in
    (normalised convolution). Modes: ``raw`` (as is), ``lcn`` ((x - local mean) / local std),
    ``gradient`` (Sobel magnitude of ``log(x + 0.02)``, divided by its local RMS).
    """
    if mode not in APPEARANCES:
        raise ValueError(f"appearance must be one of {APPEARANCES}, got {mode!r}")
    if mode == "raw":
        return image
    w = (mask > 0.5).to(image.dtype)
    if mode == "lcn":
        mean, var = _local_stats(image, w, sigma)
        return w * (image - mean) / torch.sqrt(var + 1e-4)
    x = torch.log(image.clamp_min(0.0) + 0.02)
    kx = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]], dtype=image.dtype,
                      device=image.device) / 8.0
    g = F.conv2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), torch.stack([kx, kx.t()])[:, None])
    mag = torch.sqrt(g.pow(2).sum(dim=1, keepdim=True) + 1e-8)
    w = w * (-F.max_pool2d(-w, 3, stride=1, padding=1))  # the mask edge is not an image edge
    _, var = _local_stats(mag, w, sigma)
    mean_sq = var + _local_stats(mag, w, sigma)[0] ** 2
    return w * mag / torch.sqrt(mean_sq + 1e-6)


# ------------------------------------------------------------------------------------------------
# Measurement
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MapMatchConfig:
    """Settings of the map measurement.

    Attributes:
        resolution: metres per pixel of the matching grid (about the map's).
        size: the grid is ``size x size`` (a power of two for the FFTs).
        appearance: ``raw``, ``lcn`` or ``gradient`` (:func:`appearance`).
        appearance_sigma: metres, scale of the local statistics.
        mask_margin: metres by which the map crop's weight extends beyond the mosaic's coverage
            (room for the search; the rest of the crop is not compared).
        dpc: phase-correlation settings.
        min_quality: a translation peak below this is "no match" (phase coherence in [0, 1]).
        position_std_floor, yaw_std_floor: metres / radians added (in quadrature) to the
            correlation spread: the mosaic's own distortion and the map's registration error.
        covariance_scale: multiplies the correlation-spread covariance.
        spread_window: half-width (pixels / angle bins) of the window about the peaks in which the
            spread is taken.
    """

    resolution: float = 0.25
    size: int = 128
    appearance: str = "lcn"
    appearance_sigma: float = 1.5
    mask_margin: float = 2.0
    dpc: DpcConfig = MAP_DPC
    min_quality: float = 0.12
    position_std_floor: float = 0.15
    yaw_std_floor: float = math.radians(0.2)
    covariance_scale: float = 1.0
    spread_window: int = 4

    def __post_init__(self) -> None:
        if self.appearance not in APPEARANCES:
            raise ValueError(f"appearance must be one of {APPEARANCES}, got {self.appearance!r}")
        if not (self.resolution > 0 and self.size >= 16 and self.appearance_sigma > 0 and self.mask_margin >= 0):
            raise ValueError("need resolution > 0, size >= 16, appearance_sigma > 0, mask_margin >= 0")


@dataclass
class MapMeasurement:
    """Result of :func:`measure` (batched).

    Attributes:
        correction: ``(B, 3)`` ``(dx, dy, dyaw)``: the true map pose of the mosaic centre is
            ``predicted (+) correction`` (metres / radians, in the predicted pose's frame).
        covariance: ``(B, 3, 3)`` of the correction.
        quality, rotation_quality: ``(B,)`` correlation peak heights in [0, 1].
        overlap: ``(B,)`` fraction of the mosaic's coverage that the map crop covers.
        registration: the phase-correlation result; ``crop``/``mosaic``: the compared images
            (after :func:`appearance`), ``(B, 1, S, S)``.
    """

    correction: Tensor
    covariance: Tensor
    quality: Tensor
    rotation_quality: Tensor
    overlap: Tensor
    registration: Registration
    crop: Tensor
    mosaic: Tensor


def _dilate(mask: Tensor, pixels: int) -> Tensor:
    if pixels <= 0:
        return mask
    return F.max_pool2d(mask, 2 * pixels + 1, stride=1, padding=pixels)


def _local_spread(reg: Registration, window: int) -> tuple[Tensor, Tensor]:
    """Spread of the correlation distributions in a window about their peaks: the peak's width
    (sharpness and height), not the far-off noise floor that dominates the global spread of a
    large search grid. -> angle variance ``(B,)`` rad^2, shift covariance ``(B, 2, 2)`` px^2."""
    B, S, _ = reg.translation_log_prob.shape
    flat = reg.translation_log_prob.reshape(B, -1)
    j = flat.argmax(dim=-1)
    win, d = _window_2d(reg.translation_log_prob, j // S, j % S, window)
    p = torch.softmax(win.reshape(B, -1), dim=-1).reshape(win.shape)
    pr, pc = p.sum(dim=2), p.sum(dim=1)
    mr, mc = (pr * d).sum(-1), (pc * d).sum(-1)
    dr, dc = d[None] - mr[:, None], d[None] - mc[:, None]
    rr, cc = (pr * dr**2).sum(-1), (pc * dc**2).sum(-1)
    rc = (p * dr[:, :, None] * dc[:, None, :]).sum(dim=(1, 2))
    shift_cov = torch.stack([torch.stack([rr, rc], -1), torch.stack([rc, cc], -1)], -2)
    A = reg.rotation_log_prob.shape[-1]
    ja = reg.rotation_log_prob.argmax(dim=-1)
    k = torch.arange(-window, window + 1, device=ja.device)
    wa = reg.rotation_log_prob.gather(-1, (ja[:, None] + k) % A)
    pa = torch.softmax(wa, dim=-1)
    kf = k.to(pa.dtype)
    ma = (pa * kf).sum(-1)
    angle_var = (pa * (kf - ma[:, None]) ** 2).sum(-1) * (math.pi / A) ** 2
    return angle_var, shift_cov


def measure(mosaic: Tensor, coverage: Tensor, aerial: AerialMap, predicted: Tensor,
            config: MapMatchConfig = MapMatchConfig()) -> MapMeasurement:
    """Register mosaics against the map crops at their predicted map poses.

    Args:
        mosaic: ``(B, 1, S, S)`` local mosaics (:func:`~bevo_ros.core.mosaic.compose_mosaic`) on the
            ``config.size`` grid at ``config.resolution``.
        coverage: ``(B, 1, S, S)`` their coverage.
        aerial: the map (grey or colour; used as luminance; resample it to about
            ``config.resolution`` first: :meth:`AerialMap.resampled`).
        predicted: ``(B, 3)`` predicted map pose ``(x, y, yaw)`` of each mosaic's centre.

    Differentiable in ``mosaic``, the map image and ``predicted``.
    """
    S, r = config.size, config.resolution
    if mosaic.shape[-2:] != (S, S) or coverage.shape != mosaic.shape:
        raise ValueError(f"mosaic and coverage must be (B, 1, {S}, {S}), got {tuple(mosaic.shape)}, "
                         f"{tuple(coverage.shape)}")
    crop, inside = aerial.grey().crop(predicted.to(aerial.image.dtype), S, r)
    crop = crop.to(mosaic.dtype)
    cov_mask = (coverage > 0.5).to(mosaic.dtype)
    crop_mask = inside.to(mosaic.dtype) * _dilate(cov_mask, int(round(config.mask_margin / r)))
    overlap = (cov_mask * inside).sum(dim=(-1, -2, -3)) / cov_mask.sum(dim=(-1, -2, -3)).clamp_min(1.0)
    sigma = config.appearance_sigma / r
    a_crop = appearance(crop, crop_mask, config.appearance, sigma)
    a_mos = appearance(mosaic, cov_mask, config.appearance, sigma)
    reg = register(a_crop, a_mos, crop_mask, cov_mask, config.dpc)
    # curr(q) = prev(c + R(-angle)(q - c) - shift) with BEV axes (row = -x, col = -y): the mosaic
    # point v is the crop point R(-angle) v + mpp * shift (in x, y), i.e. the mosaic's true pose
    # is the predicted one (+) (mpp * shift, -angle).
    correction = torch.stack([r * reg.shift[:, 0], r * reg.shift[:, 1], -reg.angle], dim=-1)
    B = mosaic.shape[0]
    cov = torch.zeros(B, 3, 3, dtype=mosaic.dtype, device=mosaic.device)
    angle_var, shift_cov = _local_spread(reg, config.spread_window)
    cov[:, :2, :2] = config.covariance_scale * r * r * shift_cov
    cov[:, 2, 2] = config.covariance_scale * angle_var
    floor = torch.tensor([config.position_std_floor**2] * 2 + [config.yaw_std_floor**2], dtype=cov.dtype,
                         device=cov.device)
    cov = cov + torch.diag(floor)
    return MapMeasurement(correction, cov, reg.quality, reg.rotation_quality, overlap, reg, a_crop, a_mos)


# ------------------------------------------------------------------------------------------------
# Filter
# ------------------------------------------------------------------------------------------------
def chi2_threshold(probability: float, dof: int = 3) -> float:
    """Chi-square quantile (Wilson-Hilferty approximation, < 1 % off for dof >= 2)."""
    if not 0.0 < probability < 1.0:
        raise ValueError(f"gate probability must be in (0, 1), got {probability}")
    z = math.sqrt(2.0) * _erfinv(2.0 * probability - 1.0)
    k = float(dof)
    return k * (1.0 - 2.0 / (9.0 * k) + z * math.sqrt(2.0 / (9.0 * k))) ** 3


def _erfinv(y: float) -> float:
    return float(torch.erfinv(torch.tensor(y, dtype=torch.float64)))


class MapPoseFilter:
    """EKF on the SE(2) base pose ``(x, y, yaw)`` in the map frame (numpy float64, one vehicle).

    Args:
        gate: Mahalanobis-squared threshold of the update (3 dof).
        odom_noise: ``(fraction, fraction, rad/m)``: std of the x/y increment per metre driven (as a
            fraction of it) and of yaw per metre, added to each increment's own covariance.
    """

    def __init__(self, gate: float = chi2_threshold(0.999), odom_noise=(0.02, 0.02, math.radians(0.05))) -> None:
        self.gate = float(gate)
        self.odom_noise = tuple(float(v) for v in odom_noise)
        self.x: np.ndarray | None = None
        self.P = np.eye(3)

    @property
    def initialised(self) -> bool:
        return self.x is not None

    def initialise(self, pose, cov) -> None:
        pose = np.asarray(pose, dtype=np.float64).reshape(3)
        cov = np.asarray(cov, dtype=np.float64).reshape(3, 3)
        if not (np.isfinite(pose).all() and np.isfinite(cov).all()):
            raise ValueError("initial pose and covariance must be finite")
        cov = 0.5 * (cov + cov.T)
        if np.linalg.eigvalsh(cov).min() <= 0:
            raise ValueError("initial covariance must be positive definite")
        self.x = pose.copy()
        self.x[2] = wrap(self.x[2])
        self.P = cov

    def predict(self, motion, motion_cov=None) -> None:
        """Apply one odometry increment ``(dx, dy, dyaw)`` (base frame) with its ``(3, 3)`` covariance."""
        if self.x is None:
            return
        m = np.asarray(motion, dtype=np.float64).reshape(3)
        Q = np.zeros((3, 3)) if motion_cov is None else np.asarray(motion_cov, dtype=np.float64).reshape(3, 3)
        dist = math.hypot(m[0], m[1])
        fx, fy, fyaw = self.odom_noise
        Q = Q + np.diag([(fx * dist) ** 2, (fy * dist) ** 2, fyaw**2 * dist])
        c, s = math.cos(self.x[2]), math.sin(self.x[2])
        Fj = np.array([[1.0, 0.0, -s * m[0] - c * m[1]], [0.0, 1.0, c * m[0] - s * m[1]], [0.0, 0.0, 1.0]])
        G = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        self.x = se2_compose(self.x, m)
        P = Fj @ self.P @ Fj.T + G @ Q @ G.T
        self.P = 0.5 * (P + P.T)

    def innovation(self, z, R) -> tuple[np.ndarray, np.ndarray, float]:
        """``(nu (3,), S (3, 3), d2)`` of a full-pose measurement ``z`` with covariance ``R``."""
        nu = np.asarray(z, dtype=np.float64) - self.x
        nu[2] = wrap(nu[2])
        S = self.P + np.asarray(R, dtype=np.float64)
        return nu, S, float(nu @ np.linalg.solve(S, nu))

    def update(self, z, R) -> tuple[bool, float]:
        """Fuse a map-frame pose measurement if it passes the gate. -> ``(accepted, d2)``."""
        nu, S, d2 = self.innovation(z, R)
        if not (math.isfinite(d2) and d2 <= self.gate):
            return False, d2
        K = self.P @ np.linalg.inv(S)
        self.x = self.x + K @ nu
        self.x[2] = wrap(self.x[2])
        IK = np.eye(3) - K
        P = IK @ self.P @ IK.T + K @ np.asarray(R) @ K.T  # Joseph form
        self.P = 0.5 * (P + P.T)
        return True, d2


# ------------------------------------------------------------------------------------------------
# The localiser
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LocalizerConfig:
    """Settings of :class:`MapLocalizer` (see the module docstring).

    Attributes:
        match: the measurement.
        mosaic_length: metres of path in the mosaic.
        keyframe_spacing: metres between keyframes.
        update_distance: metres driven between map measurements (the update's rate).
        min_mosaic_length: no measurement before the mosaic spans this much path.
        min_overlap: no measurement if the map covers less of the mosaic than this fraction.
        gate_probability: of the Mahalanobis gate (3 dof).
        odom_noise: see :class:`MapPoseFilter`.
        lost_after: consecutive rejected measurements after which the status is "lost".
    """

    match: MapMatchConfig = field(default_factory=MapMatchConfig)
    mosaic_length: float = 20.0
    keyframe_spacing: float = 2.0
    update_distance: float = 4.0
    min_mosaic_length: float = 10.0
    min_overlap: float = 0.8
    gate_probability: float = 0.999
    odom_noise: tuple[float, float, float] = (0.02, 0.02, math.radians(0.05))
    lost_after: int = 5


@dataclass
class LocalizerCounters:
    measurements: int = 0
    accepted: int = 0
    rejected_quality: int = 0
    rejected_gate: int = 0
    skipped_no_map: int = 0
    consecutive_rejections: int = 0


@dataclass
class LocalizerStep:
    """One odometry step through :class:`MapLocalizer` (``pose``/``covariance`` None before the
    initial pose). ``reason``: why a measurement was not fused (``""`` when fused or none made)."""

    pose: np.ndarray | None  # (3,) base in map
    covariance: np.ndarray | None  # (3, 3)
    map_to_odom: np.ndarray | None  # (3,)
    measured: bool = False
    accepted: bool = False
    reason: str = ""
    quality: float = math.nan
    d2: float = math.nan
    status: str = "uninitialised"
    measurement: np.ndarray | None = None  # (3,) the map measurement of the base pose, when measured
    measurement_covariance: np.ndarray | None = None  # (3, 3)


class MapLocalizer:
    """Odometry (+ BEVs) in, the base pose in the map frame and ``map -> odom`` out.

    Args:
        aerial: the map.
        spec: the BEV grid of the BEVs that will be given.
        config: settings.
        device: torch device of the measurement ("cuda" falls back to the CPU when unavailable).
    """

    def __init__(self, aerial: AerialMap, spec: BevSpec, config: LocalizerConfig = LocalizerConfig(),
                 device: str | torch.device = "cpu") -> None:
        if str(device).startswith("cuda") and not torch.cuda.is_available():
            device = "cpu"
        self.device = torch.device(device)
        self.config = config
        self.spec = spec
        self.map = aerial.grey().resampled(config.match.resolution).to(self.device, torch.float32)
        self.filter = MapPoseFilter(chi2_threshold(config.gate_probability), config.odom_noise)
        self.mosaic = MosaicBuffer(spec, config.mosaic_length, config.keyframe_spacing)
        self.counters = LocalizerCounters()
        self.pose_odom: np.ndarray | None = None
        self.last_measurement: MapMeasurement | None = None
        self._since_update = 0.0

    @property
    def status(self) -> str:
        if not self.filter.initialised:
            return "uninitialised"
        if self.counters.consecutive_rejections >= self.config.lost_after:
            return "lost"
        return "tracking" if self.counters.accepted else "initialising"

    def reset(self) -> None:
        """Forget the pose and the mosaic (the odometry was reset)."""
        self.filter.x = None
        self.mosaic.reset()
        self.pose_odom = None
        self._since_update = 0.0
        self.counters.consecutive_rejections = 0

    def set_initial_pose(self, pose_map, cov) -> None:
        """``/initialpose``: the base's map pose ``(x, y, yaw)`` and its ``(3, 3)`` covariance."""
        self.filter.initialise(pose_map, cov)
        self.counters.consecutive_rejections = 0
        self._since_update = self.config.update_distance  # measure as soon as the mosaic allows

    def map_to_odom(self) -> np.ndarray | None:
        """``T_map_odom`` as ``(x, y, yaw)`` (REP-105), None before an initial pose and odometry."""
        if self.filter.x is None or self.pose_odom is None:
            return None
        return se2_compose(self.filter.x, se2_inverse(self.pose_odom))

    def step(self, pose_odom, motion, motion_cov=None, bev=None, mask=None) -> LocalizerStep:
        """One odometry step.

        Args:
            pose_odom: ``(3,)`` base pose in odom after this step.
            motion: ``(3,)`` increment ``(dx, dy, dyaw)`` since the previous step (base frame).
            motion_cov: ``(3, 3)`` its covariance (None: the per-metre floor alone).
            bev, mask: ``(S, S)`` this frame's BEV and mask, when available.
        """
        self.pose_odom = np.asarray(pose_odom, dtype=np.float64).reshape(3)
        motion = np.asarray(motion, dtype=np.float64).reshape(3)
        self.filter.predict(motion, motion_cov)
        dist = math.hypot(motion[0], motion[1])
        self.mosaic.advance(dist)
        self._since_update += dist
        if bev is not None:
            dev = self.device
            b = torch.as_tensor(np.asarray(bev, dtype=np.float32), device=dev)
            m = torch.ones_like(b) if mask is None else torch.as_tensor(np.asarray(mask, dtype=np.float32), device=dev)
            self.mosaic.offer(torch.as_tensor(self.pose_odom, dtype=torch.float32, device=dev), b, m)
        out = LocalizerStep(None, None, None, status=self.status)
        if self.filter.initialised and self._since_update >= self.config.update_distance \
                and self.mosaic.covered_length >= self.config.min_mosaic_length and len(self.mosaic.frames) >= 2:
            self._since_update = 0.0
            self._measure_and_update(out)
        if self.filter.initialised:
            out.pose, out.covariance, out.map_to_odom = self.filter.x.copy(), self.filter.P.copy(), self.map_to_odom()
        out.status = self.status
        return out

    def _measure_and_update(self, out: LocalizerStep) -> None:
        cfg = self.config.match
        bevs, masks, poses = self.mosaic.stacked()
        anchor_odom = self.mosaic.anchor()
        mos, cov = compose_mosaic(bevs, masks, poses, anchor_odom, self.spec, cfg.size, cfg.resolution)
        a_odom = anchor_odom.double().cpu().numpy()
        lever = se2_between(a_odom, self.pose_odom)  # anchor -> current base
        predicted = se2_compose(self.filter.x, se2_inverse(lever))  # anchor in map
        pred_t = torch.as_tensor(predicted, dtype=torch.float32, device=self.device)[None]
        # Overlap from the crop mask is cheap to check before the FFTs.
        _, inside = self.map.crop(pred_t, cfg.size, cfg.resolution)
        covm = (cov > 0.5).float()
        if float((covm * inside).sum() / covm.sum().clamp_min(1.0)) < self.config.min_overlap:
            self.counters.skipped_no_map += 1
            out.reason = "outside_map"
            return
        with torch.no_grad():
            meas = measure(mos, cov, self.map, pred_t, cfg)
        self.last_measurement = meas
        self.counters.measurements += 1
        out.measured = True
        out.quality = float(meas.quality[0])
        delta = meas.correction[0].double().cpu().numpy()
        R_delta = meas.covariance[0].double().cpu().numpy()
        z = se2_compose(se2_compose(predicted, delta), lever)
        # d z / d delta at delta = 0: z = a (+) delta (+) L.
        ca, sa = math.cos(predicted[2]), math.sin(predicted[2])
        Ra = np.array([[ca, -sa], [sa, ca]])
        J = np.eye(3)
        J[:2, :2] = Ra
        J[:2, 2] = Ra @ np.array([-lever[1], lever[0]])
        R = J @ R_delta @ J.T
        out.measurement, out.measurement_covariance = z, R
        if out.quality < cfg.min_quality:
            self.counters.rejected_quality += 1
            self.counters.consecutive_rejections += 1
            out.reason = "low_quality"
            out.d2 = self.filter.innovation(z, R)[2]
            return
        accepted, d2 = self.filter.update(z, R)
        out.d2 = d2
        if accepted:
            self.counters.accepted += 1
            self.counters.consecutive_rejections = 0
            out.accepted = True
        else:
            self.counters.rejected_gate += 1
            self.counters.consecutive_rejections += 1
            out.reason = "gate"


__all__ = [
    "APPEARANCES", "LocalizerConfig", "LocalizerCounters", "LocalizerStep", "MAP_DPC", "MapLocalizer",
    "MapMatchConfig", "MapMeasurement", "MapPoseFilter", "appearance", "chi2_threshold", "measure",
    "se2_between", "se2_compose", "se2_inverse",
]
