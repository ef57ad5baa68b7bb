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
   gives the correction of that pose (the Fourier-magnitude angle refined on a grid of
   translation-peak heights: :func:`register_grid`), with a covariance from the correlation's
   spread about its peak, a floor, and the odometry noise the mosaic inherits.
3. :class:`MapPoseFilter`: an EKF on the SE(2) base pose in ``map`` (plus the odometry's scale
   and yaw drift per metre): predicted with every
   odometry increment and its covariance (plus a per-metre floor for what the odometry's own
   covariance misses), updated with the map measurement behind a peak-quality test and a
   Mahalanobis gate. A wrong match is rejected and counted, never a jump; after
   ``lost_after`` rejections in a row the status says "lost".
4. ``map -> odom`` (REP-105) is ``pose_map (+) pose_odom^-1``: the odometry stays continuous, the
   map frame absorbs its drift.

Appearance: the map is another day, sensor and resolution. :func:`appearance` offers ``raw``,
``lcn`` (local contrast normalisation: removes shadows, illumination and contrast changes that are
smooth over ``appearance_sigma``) and ``gradient`` (locally normalised gradient magnitude of the
log intensity: also invariant to a gamma change); the phase
correlation's whitening (``DpcConfig.whitening_floor = 0``) is the phase-only part.
``tools/bench_localization.py`` measures what each buys.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from .aerial_map import AerialMap
from .device import resolve_device
from .geometry import BevSpec
from .mosaic import MosaicBuffer, _gaussian_blur, compose_mosaic, mosaic_anchor
from .phase_correlation import (DpcConfig, _quadratic_peak_2d, _window_2d, estimate_rotation,
                                estimate_translation, overlap_envelope, prepare, rotate_about_centre,
                                translation_correlation)
from .pose import compose_se2

Tensor = torch.Tensor

APPEARANCES = ("raw", "lcn", "gradient")
# Phase correlation for map matching: a wide flat window (the mosaic is a long strip, the
# radial Hann of frame-to-frame matching would keep only its middle) and pure phase whitening.
MAP_DPC = DpcConfig(window_alpha=0.25, mask_blur=2.0, radial_range=(0.04, 0.35), translation_sigma=1.0)


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
    w = _erode(w, 1)  # the mask edge is not an image edge
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
        rotation_search, rotation_step: degrees, the grid refinement of the rotation
            (:func:`register_grid`).
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
    yaw_std_floor: float = math.radians(0.3)
    covariance_scale: float = 1.0
    spread_window: int = 4
    rotation_search: float = 4.0
    rotation_step: float = 0.5

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
        quality: ``(B,)`` translation correlation peak height in [0, 1] (phase coherence).
        overlap: ``(B,)`` fraction of the mosaic's coverage that the map crop covers.
        correlation: ``(B, S, S)`` the translation correlation (fftshifted; the debug heat-map).
        crop, mosaic: the compared images (after :func:`appearance`), ``(B, 1, S, S)``.
    """

    correction: Tensor
    covariance: Tensor
    quality: Tensor
    overlap: Tensor
    correlation: Tensor
    crop: Tensor
    mosaic: Tensor


def _dilate(mask: Tensor, pixels: int) -> Tensor:
    if pixels <= 0:
        return mask
    return F.max_pool2d(mask, 2 * pixels + 1, stride=1, padding=pixels)


def _erode(mask: Tensor, pixels: int) -> Tensor:
    """A 0/1 mask shrunk by ``pixels`` (its edge left out)."""
    return -_dilate(-mask, pixels)


def register_grid(prev: Tensor, curr: Tensor, mask_prev: Tensor, mask_curr: Tensor, config: DpcConfig,
                  half_range: float, step: float) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Rotation then translation of ``curr`` against ``prev`` (``(B, 1, S, S)``), the rotation
    refined on a grid.

    The Fourier-magnitude angle (:func:`~bevo_ros.core.phase_correlation.estimate_rotation`) is
    the global, translation-free estimate; content that the map and the mosaic do not share
    disturbs it by about a degree. Around it, the translation correlation's peak height is
    evaluated at ``2 n + 1`` angles ``step`` apart (``n = half_range / step``, one batched FFT) and
    the angle is the vertex of a log-parabola through the best one and its neighbours: a long
    strip's peak falls off within a degree, so this is several times more precise.

    Returns:
        angle ``(B,)``, shift ``(B, 2)``, rotation log-probabilities ``(B, A)`` (Fourier stage),
        translation correlation and log-probabilities ``(B, S, S)`` at the angle.
    """
    p_prev, p_curr = prepare(prev, mask_prev, config), prepare(curr, mask_curr, config)
    angle0, _, rlog = estimate_rotation(p_prev, p_curr, config)
    envelope = overlap_envelope(p_prev.weight_spectrum, p_curr.weight_spectrum)
    B, S = curr.shape[0], curr.shape[-1]
    n = max(1, int(round(half_range / step)))
    k = torch.arange(-n, n + 1, dtype=angle0.dtype, device=angle0.device)
    cand = (angle0[:, None] + step * k).reshape(-1)  # (B * (2n+1),)
    m = 2 * n + 1
    der = rotate_about_centre(p_curr.image[:, None].repeat_interleave(m, dim=0), -cand)[:, 0]
    corr = translation_correlation(p_prev.spectrum.repeat_interleave(m, dim=0), der, config)
    # only where the weights overlap well: far shifts of a strip would blow up
    corr = corr / envelope.repeat_interleave(m, dim=0).clamp_min(0.5)
    j = corr.reshape(B * m, S * S).argmax(dim=-1)
    _, log_h = _quadratic_peak_2d(corr, j // S, j % S)
    log_h = log_h.reshape(B, m)
    best = log_h.argmax(dim=-1).clamp(1, m - 2)
    lm, l0, lp = (log_h.gather(-1, (best + o)[:, None])[:, 0] for o in (-1, 0, 1))
    den = lm - 2.0 * l0 + lp
    concave = den < -1e-9
    off = torch.where(concave, 0.5 * (lm - lp) / torch.where(concave, den, -torch.ones_like(den)), torch.zeros_like(den))
    angle = angle0 + step * ((best - n).to(angle0.dtype) + off.clamp(-1.0, 1.0))
    derotated = rotate_about_centre(p_curr.image[:, None], -angle)[:, 0]
    shift, tcorr, tlog, _ = estimate_translation(p_prev.spectrum, derotated, config, envelope)
    return angle, shift, rlog, tcorr, tlog


def _local_spread(rotation_log_prob: Tensor, translation_log_prob: Tensor, window: int) -> tuple[Tensor, Tensor]:
    """Spread of the correlation distributions in a window about their peaks: the peak's width
    (sharpness and height), not the far-off noise floor that dominates the global spread of a
    large search grid. -> angle variance ``(B,)`` rad^2, shift covariance ``(B, 2, 2)`` px^2."""
    B, S, _ = translation_log_prob.shape
    j = translation_log_prob.reshape(B, -1).argmax(dim=-1)
    win, d = _window_2d(translation_log_prob, j // S, j % S, window)
    p = torch.softmax(win.reshape(B, -1), dim=-1).reshape(win.shape)
    pr, pc = p.sum(dim=2), p.sum(dim=1)
    mr, mc = (pr * d).sum(-1), (pc * d).sum(-1)
    dr, dc = d[None] - mr[:, None], d[None] - mc[:, None]
    rr, cc = (pr * dr**2).sum(-1), (pc * dc**2).sum(-1)
    rc = (p * dr[:, :, None] * dc[:, None, :]).sum(dim=(1, 2))
    shift_cov = torch.stack([torch.stack([rr, rc], -1), torch.stack([rc, cc], -1)], -2)
    A = rotation_log_prob.shape[-1]
    ja = rotation_log_prob.argmax(dim=-1)
    k = torch.arange(-window, window + 1, device=ja.device)
    wa = rotation_log_prob.gather(-1, (ja[:, None] + k) % A)
    pa = torch.softmax(wa, dim=-1)
    kf = k.to(pa.dtype)
    ma = (pa * kf).sum(-1)
    angle_var = (pa * (kf - ma[:, None]) ** 2).sum(-1) * (math.pi / A) ** 2
    return angle_var, shift_cov


# The map match's position covariance along a direction the mosaic and the map share no texture
# in (a road whose only features are continuous lane markings) is widened: there the phase
# correlation's peak sits where the two windows align, sharp, and says nothing of the position along
# the road (a synthetic 1.5 m error along such a road stayed after the update with 0.15 m claimed,
# Mahalanobis^2 12-1112). The shared texture's structure tensor (the cross products of the two
# appearances' gradients at the matched pose: texture that differs between the map and the car's
# view averages out of it) gives the position information per direction (Cramer-Rao: the variance
# goes as its inverse); where its weak eigenvalue is below WEAK_TEXTURE_RATIO of the strong one,
# the variance along the weak direction is multiplied by WEAK_TEXTURE_RATIO over their ratio, at
# most by WEAK_TEXTURE_MAX_WIDENING. Measured: the heterogeneous synthetic maps
# 0.3-0.6 (unchanged), lane lines with shared asphalt texture 0.2 (recovered to 1 cm), lane lines
# alone or with texture the map does not share <= 0.01.
WEAK_TEXTURE_RATIO = 0.1
WEAK_TEXTURE_MAX_WIDENING = 1e4  # variance: x 100 in standard deviation


def _central_gradients(x: Tensor) -> tuple[Tensor, Tensor]:
    """Row and column central differences of ``(B, 1, S, S)`` (zero on the border)."""
    gr, gc = torch.zeros_like(x), torch.zeros_like(x)
    gr[..., 1:-1, :] = 0.5 * (x[..., 2:, :] - x[..., :-2, :])
    gc[..., :, 1:-1] = 0.5 * (x[..., :, 2:] - x[..., :, :-2])
    return gr, gc


def weak_direction_widening(a: Tensor, b: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
    """How much position information two aligned appearances ``a``, ``b (B, 1, S, S)`` share per
    direction, within ``mask (B, 1, S, S)`` (its edge left out: no image edge).

    Returns:
        ``factor (B,)`` >= 1, the variance's widening along the weak direction (1 where the shared
        texture's weak-to-strong eigenvalue ratio is at least WEAK_TEXTURE_RATIO), and ``direction
        (B, 2)``, that direction's unit vector in (x, y) = (row, column) of the grid (their signs do
        not matter to a covariance).
    """
    w = _erode(mask, 2)
    (ar, ac), (br, bc) = _central_gradients(a), _central_gradients(b)
    n = w.sum(dim=(-1, -2, -3)).clamp_min(1.0)
    jrr = (w * ar * br).sum(dim=(-1, -2, -3)) / n
    jcc = (w * ac * bc).sum(dim=(-1, -2, -3)) / n
    jrc = 0.5 * (w * (ar * bc + ac * br)).sum(dim=(-1, -2, -3)) / n
    half_gap = torch.sqrt(((jrr - jcc) / 2) ** 2 + jrc**2)
    strong, weak = (jrr + jcc) / 2 + half_gap, (jrr + jcc) / 2 - half_gap
    ratio = (weak / strong.clamp_min(1e-12)).clamp(0.0, 1.0)
    widened = (WEAK_TEXTURE_RATIO / ratio.clamp_min(1e-12)).clamp(1.0, WEAK_TEXTURE_MAX_WIDENING)
    factor = torch.where(strong > 0, widened, torch.full_like(ratio, WEAK_TEXTURE_MAX_WIDENING))  # no texture: none
    # the weak eigenvector of [[jrr, jrc], [jrc, jcc]]
    theta = 0.5 * torch.atan2(2 * jrc, jrr - jcc) + math.pi / 2
    return factor, torch.stack([torch.cos(theta), torch.sin(theta)], dim=-1)


def widen_position(cov: Tensor, factor: Tensor, direction: Tensor) -> Tensor:
    """``cov (B, 3, 3)`` with the position's variance along ``direction (B, 2)`` (unit) multiplied
    by ``factor (B,)`` (its cross terms scaled by the root: the correlations kept)."""
    d = direction.to(cov.dtype)
    e = torch.stack([d, torch.stack([-d[:, 1], d[:, 0]], -1)], dim=-1)  # (B, 2, 2) columns: weak, strong
    t = torch.eye(3, dtype=cov.dtype, device=cov.device).repeat(cov.shape[0], 1, 1)
    scale = torch.stack([factor.to(cov.dtype).sqrt(), torch.ones_like(factor, dtype=cov.dtype)], -1)
    t[:, :2, :2] = e @ torch.diag_embed(scale) @ e.transpose(-1, -2)
    return t @ cov @ t.transpose(-1, -2)


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
    grey = aerial.grey()
    crop, inside = grey.crop(predicted.to(aerial.image.dtype), S, r)
    crop = crop.to(mosaic.dtype)
    cov_mask = (coverage > 0.5).to(mosaic.dtype)
    crop_mask = inside.to(mosaic.dtype) * _dilate(cov_mask, int(round(config.mask_margin / r)))
    overlap = (cov_mask * inside).sum(dim=(-1, -2, -3)) / cov_mask.sum(dim=(-1, -2, -3)).clamp_min(1.0)
    sigma = config.appearance_sigma / r
    a_crop = appearance(crop, crop_mask, config.appearance, sigma)
    a_mos = appearance(mosaic, cov_mask, config.appearance, sigma)
    angle, shift, rlog, tcorr, tlog = register_grid(a_crop, a_mos, crop_mask, cov_mask, config.dpc,
                                                    math.radians(config.rotation_search), math.radians(config.rotation_step))
    # curr(q) = prev(c + R(-angle)(q - c) - shift) with BEV axes (row = -x, col = -y): the mosaic
    # point v is the crop point R(-angle) v + mpp * shift (in x, y), i.e. the mosaic's true pose
    # is the predicted one (+) (mpp * shift, -angle).
    correction = torch.stack([r * shift[:, 0], r * shift[:, 1], -angle], dim=-1)
    B = mosaic.shape[0]
    cov = torch.zeros(B, 3, 3, dtype=mosaic.dtype, device=mosaic.device)
    angle_var, shift_cov = _local_spread(rlog, tlog, config.spread_window)
    cov[:, :2, :2] = config.covariance_scale * r * r * shift_cov
    cov[:, 2, 2] = config.covariance_scale * angle_var
    floor = torch.tensor([config.position_std_floor**2] * 2 + [config.yaw_std_floor**2], dtype=cov.dtype,
                         device=cov.device)
    cov = cov + torch.diag(floor)
    with torch.no_grad():  # a factor on the covariance, held constant (the correction's gradients are unchanged)
        dtype = aerial.image.dtype
        at = compose_se2(predicted.to(dtype), correction.detach().to(dtype))  # the matched pose
        crop_at, _ = grey.crop(at, S, r)
        a_at = appearance(crop_at.to(mosaic.dtype), crop_mask, config.appearance, sigma)
        widen = weak_direction_widening(a_mos.detach(), a_at, cov_mask)
    cov = widen_position(cov, *widen)
    quality = tcorr.amax(dim=(-1, -2)).clamp(0.0, 1.0)
    return MapMeasurement(correction, cov, quality, overlap, tcorr, a_crop, a_mos)


# ------------------------------------------------------------------------------------------------
# Filter
# ------------------------------------------------------------------------------------------------
def chi2_threshold(probability: float, dof: int = 3) -> float:
    """Chi-square quantile: bisection on the CDF ``P(dof / 2, x / 2)`` (regularised lower
    incomplete gamma, ``torch.special.gammainc``)."""
    if not 0.0 < probability < 1.0:
        raise ValueError(f"gate probability must be in (0, 1), got {probability}")
    a = torch.tensor(dof / 2.0, dtype=torch.float64)
    lo, hi = 0.0, 10.0 * dof + 100.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if float(torch.special.gammainc(a, torch.tensor(mid / 2.0, dtype=torch.float64))) < probability:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


class MapPoseFilter:
    """EKF on the SE(2) base pose in the map frame, with the odometry's scale and yaw drift
    (numpy float64, one vehicle).

    State ``[x, y, yaw, scale, yaw_drift]``: the odometry increment ``(dx, dy, dyaw)`` moves the
    pose by ``(scale dx, scale dy, dyaw + yaw_drift * distance)``. A monocular BEV's scale hangs
    on the camera pitch (README) and its yaw on the roll, both slowly varying: without these two
    states the pose lags behind the map measurements by the drift accumulated between updates.

    Args:
        gate: Mahalanobis-squared threshold of the update (3 dof).
        odom_noise: ``(fraction, fraction, rad/sqrt(m))``: std of the x/y increment per metre
            driven (as a fraction of it) and the yaw random walk per metre, added to each
            increment's own covariance.
        scale_std, yaw_drift_std: prior std of the scale (fraction) and of the yaw drift (rad/m);
            ``*_walk``: their random walks per sqrt(metre).
    """

    def __init__(self, gate: float = chi2_threshold(0.999), odom_noise=(0.02, 0.02, math.radians(0.05)),
                 scale_std: float = 0.05, yaw_drift_std: float = math.radians(0.05), scale_walk: float = 2e-4,
                 yaw_drift_walk: float = math.radians(2e-4)) -> None:
        self.gate = float(gate)
        self.odom_noise = tuple(float(v) for v in odom_noise)
        self.prior = (float(scale_std), float(yaw_drift_std))
        self.walk = (float(scale_walk), float(yaw_drift_walk))
        self.state: np.ndarray | None = None
        self.cov = np.eye(5)

    @property
    def initialised(self) -> bool:
        return self.state is not None

    @property
    def x(self) -> np.ndarray | None:
        """The pose ``(3,)`` (a view: x, y, yaw)."""
        return None if self.state is None else self.state[:3]

    @property
    def P(self) -> np.ndarray:
        """The pose covariance ``(3, 3)``."""
        return self.cov[:3, :3]

    def reset(self) -> None:
        self.state = None

    def initialise(self, pose, cov) -> None:
        """Start at ``pose (3,)`` with ``cov (3, 3)``; the scale and drift keep their estimates
        when re-initialised (they belong to the odometry, not to the pose)."""
        pose = np.asarray(pose, dtype=np.float64).reshape(3)
        cov = np.asarray(cov, dtype=np.float64).reshape(3, 3)
        if not (np.isfinite(pose).all() and np.isfinite(cov).all()):
            raise ValueError("initial pose and covariance must be finite")
        cov = 0.5 * (cov + cov.T)
        if np.linalg.eigvalsh(cov).min() <= 0:
            raise ValueError("initial covariance must be positive definite")
        old = self.state
        self.state = np.concatenate([pose, [1.0, 0.0] if old is None else old[3:]])
        self.state[2] = wrap(self.state[2])
        C = np.zeros((5, 5))
        C[:3, :3] = cov
        C[3:, 3:] = np.diag(np.square(self.prior)) if old is None else self.cov[3:, 3:]
        self.cov = C

    def predict(self, motion, motion_cov=None) -> None:
        """Apply one odometry increment ``(dx, dy, dyaw)`` (base frame) with its ``(3, 3)`` covariance."""
        if self.state is None:
            return
        m = np.asarray(motion, dtype=np.float64).reshape(3)
        Q = np.zeros((3, 3)) if motion_cov is None else np.asarray(motion_cov, dtype=np.float64).reshape(3, 3)
        dist = math.hypot(m[0], m[1])
        fx, fy, fyaw = self.odom_noise
        Q = Q + np.diag([(fx * dist) ** 2, (fy * dist) ** 2, fyaw**2 * dist])
        x, y, yaw, k, b = self.state
        c, s = math.cos(yaw), math.sin(yaw)
        dx, dy = k * m[0], k * m[1]
        Fj = np.eye(5)
        Fj[0, 2], Fj[1, 2] = -s * dx - c * dy, c * dx - s * dy
        Fj[0, 3], Fj[1, 3] = c * m[0] - s * m[1], s * m[0] + c * m[1]
        Fj[2, 4] = dist
        G = np.zeros((5, 3))
        G[:2, :2] = k * np.array([[c, -s], [s, c]])
        G[2, 2] = 1.0
        self.state = np.array([x + c * dx - s * dy, y + s * dx + c * dy, wrap(yaw + m[2] + b * dist), k, b])
        P = Fj @ self.cov @ Fj.T + G @ Q @ G.T
        P[3, 3] += self.walk[0] ** 2 * dist
        P[4, 4] += self.walk[1] ** 2 * dist
        self.cov = 0.5 * (P + P.T)

    def innovation(self, z, R) -> tuple[np.ndarray, np.ndarray, float]:
        """``(nu (3,), S (3, 3), d2)`` of a full-pose measurement ``z`` with covariance ``R``."""
        nu = np.asarray(z, dtype=np.float64) - self.state[:3]
        nu[2] = wrap(nu[2])
        S = self.cov[:3, :3] + np.asarray(R, dtype=np.float64)
        return nu, S, float(nu @ np.linalg.solve(S, nu))

    def update(self, z, R) -> tuple[bool, float]:
        """Fuse a map-frame pose measurement if it passes the gate. -> ``(accepted, d2)``."""
        nu, S, d2 = self.innovation(z, R)
        if not (math.isfinite(d2) and d2 <= self.gate):
            return False, d2
        H = np.zeros((3, 5))
        H[:, :3] = np.eye(3)
        K = self.cov @ H.T @ np.linalg.inv(S)
        self.state = self.state + K @ nu
        self.state[2] = wrap(self.state[2])
        IK = np.eye(5) - K @ H
        P = IK @ self.cov @ IK.T + K @ np.asarray(R) @ K.T  # Joseph form
        self.cov = 0.5 * (P + P.T)
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
        mosaic_distortion: scale of the covariance the mosaic inherits from the odometry's noise
            between its keyframes (0 = ignore).
        mosaic_scale_correction: place the keyframes with the filter's odometry scale estimate.
    """

    match: MapMatchConfig = field(default_factory=MapMatchConfig)
    mosaic_length: float = 20.0
    keyframe_spacing: float = 2.0
    update_distance: float = 4.0
    min_mosaic_length: float = 10.0
    min_overlap: float = 0.5
    gate_probability: float = 0.999
    odom_noise: tuple[float, float, float] = (0.02, 0.02, math.radians(0.05))
    lost_after: int = 5
    mosaic_distortion: float = 1.0
    mosaic_scale_correction: bool = False


@dataclass
class LocalizerCounters:
    measurements: int = 0
    accepted: int = 0
    rejected_quality: int = 0
    rejected_gate: int = 0
    skipped_no_map: int = 0
    consecutive_rejections: int = 0
    accepted_since_init: int = 0  # since the last initial pose or reset: "tracking" needs one
    consecutive_outside: int = 0  # updates in a row with too little map under the mosaic


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
        self.device = resolve_device(device, what="map localisation")
        self.config = config
        self.spec = spec
        self.map = aerial.grey().resampled(config.match.resolution).to(self.device, torch.float32)
        self.filter = MapPoseFilter(chi2_threshold(config.gate_probability), config.odom_noise)
        self.mosaic = MosaicBuffer(spec, config.mosaic_length, config.keyframe_spacing)
        self.counters = LocalizerCounters()
        self.pose_odom: np.ndarray | None = None
        self.last_measurement: MapMeasurement | None = None
        self._since_update = 0.0
        self._odom_variance = np.zeros(2)  # accumulated (position, yaw) variance of the odometry

    @property
    def status(self) -> str:
        if not self.filter.initialised:
            return "uninitialised"
        if self.counters.consecutive_rejections >= self.config.lost_after:
            return "lost"
        if self.counters.consecutive_outside >= self.config.lost_after:  # dead reckoning off the map
            return "outside_map"
        # the matches since the last (re)initialisation: a new initial pose is no tracking until one confirms it
        return "tracking" if self.counters.accepted_since_init else "initialising"

    def reset(self) -> None:
        """Forget the pose and the mosaic (the odometry was reset)."""
        self.filter.reset()
        self.mosaic.reset()
        self.pose_odom = None
        self._since_update = 0.0
        self.counters.consecutive_rejections = self.counters.consecutive_outside = 0
        self.counters.accepted_since_init = 0

    def set_initial_pose(self, pose_map, cov) -> None:
        """``/initialpose``: the base's map pose ``(x, y, yaw)`` and its ``(3, 3)`` covariance."""
        self.filter.initialise(pose_map, cov)
        self.counters.consecutive_rejections = self.counters.consecutive_outside = 0
        self.counters.accepted_since_init = 0
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
        if motion_cov is not None:
            mc = np.asarray(motion_cov, dtype=np.float64).reshape(3, 3)
            self._odom_variance += [mc[0, 0] + mc[1, 1], mc[2, 2]]
        self.mosaic.advance(dist)
        self._since_update += dist
        if bev is not None:
            dev = self.device
            b = torch.as_tensor(np.asarray(bev, dtype=np.float32), device=dev)
            m = torch.ones_like(b) if mask is None else torch.as_tensor(np.asarray(mask, dtype=np.float32), device=dev)
            self.mosaic.offer(torch.as_tensor(self.pose_odom, dtype=torch.float32, device=dev), b, m,
                              tuple(self._odom_variance))
        out = LocalizerStep(None, None, None, status=self.status)
        if self.filter.initialised and self._since_update >= self.config.update_distance \
                and self.mosaic.covered_length >= self.config.min_mosaic_length and len(self.mosaic.frames) >= 2:
            self._since_update = 0.0
            self._measure_and_update(out)
        if self.filter.initialised:
            out.pose, out.covariance, out.map_to_odom = self.filter.x.copy(), self.filter.P.copy(), self.map_to_odom()
        out.status = self.status
        return out

    def step_odometry(self, step, use_bev: bool = True) -> LocalizerStep:
        """:meth:`step` from a :class:`~bevo_ros.core.odometry.OdometryStep` (the engine's output):
        odom pose from its position/yaw, the increment's covariance from its twist covariance
        (x, y, yaw rows) times ``dt^2``, its BEV and mask when ``use_bev``."""
        pose = np.array([step.position[0], step.position[1], step.rpy[2]], dtype=np.float64)
        idx = [0, 1, 5]
        cov = np.asarray(step.twist_covariance, dtype=np.float64)[np.ix_(idx, idx)] * float(step.dt) ** 2
        if not np.isfinite(cov).all():
            cov = None
        return self.step(pose, step.motion, cov, step.bev if use_bev else None, step.bev_mask if use_bev else None)

    def _mosaic_distortion(self, poses: Tensor, anchor: Tensor) -> np.ndarray:
        """Covariance ``(3, 3)`` the mosaic inherits from the odometry between its keyframes and
        now (each keyframe is placed relative to the current base): the mean over keyframes of
        the accumulated position and yaw variances, the yaw one also acting over the keyframe's
        distance from the mosaic centre. Scaled by ``config.mosaic_distortion``."""
        k = self.config.mosaic_distortion
        if k <= 0:
            return np.zeros((3, 3))
        var = np.array([kf.variance for _, kf in self.mosaic.frames])  # (K, 2)
        rel = np.clip(self._odom_variance[None] - var, 0.0, None)
        d2 = ((poses[:, :2] - anchor[None, :2]).double().cpu().numpy() ** 2).sum(-1)
        pos = float(np.mean(0.5 * rel[:, 0] + d2 * rel[:, 1]))
        return k * np.diag([pos, pos, float(np.mean(rel[:, 1]))])

    def _measure_and_update(self, out: LocalizerStep) -> None:
        cfg = self.config.match
        bevs, masks, poses = self.mosaic.stacked()
        if self.config.mosaic_scale_correction:
            # The keyframes relative to the current base with the estimated odometry scale (right
            # when the scale error is not in the BEVs themselves; a monocular BEV's pitch error
            # magnifies the BEV content as much as the motion, so it is off by default).
            rel = se2_between(self.pose_odom, poses.double().cpu().numpy())
            rel[:, :2] *= self.filter.state[3]
            poses = torch.as_tensor(se2_compose(np.broadcast_to(self.pose_odom, rel.shape), rel),
                                    dtype=torch.float32, device=self.device)
        anchor_odom = mosaic_anchor(poses, self.spec)
        mos, cov = compose_mosaic(bevs, masks, poses, anchor_odom, self.spec, cfg.size, cfg.resolution)
        a_odom = anchor_odom.double().cpu().numpy()
        lever = se2_between(a_odom, self.pose_odom)  # anchor -> current base
        predicted = se2_compose(self.filter.x, se2_inverse(lever))  # anchor in map
        pred_t = torch.as_tensor(predicted, dtype=torch.float32, device=self.device)[None]
        # Overlap from the crop mask is cheap to check before the FFTs.
        _, inside = self.map.crop(pred_t, cfg.size, cfg.resolution)
        covm = (cov > 0.5).float()
        overlap = float((covm * inside).sum() / covm.sum().clamp_min(1.0))
        self.last_overlap = overlap
        if overlap < self.config.min_overlap:
            self.counters.skipped_no_map += 1
            self.counters.consecutive_outside += 1
            out.reason = "outside_map"
            return
        self.counters.consecutive_outside = 0
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
        R = J @ R_delta @ J.T + self._mosaic_distortion(poses, anchor_odom)
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
            self.counters.accepted_since_init += 1
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
