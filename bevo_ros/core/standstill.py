"""Standstill: is the vehicle at rest between two frames? Measured on the images, not the BEVs.

Why not the phase correlation: a BEV is projected with the filtered attitude, and the engine's
attitude keeps moving while the car stands (the DUKF's accelerometer updates on an idling engine's
vibration, the road-tilt low-pass). A change ``D`` of the BEV pitch moves the whole BEV by
``(X^2 + h^2) / h * D`` (:func:`~bevo_ros.core.motion.pitch_change_shift`, 1.4 cm per 0.01 deg on
KITTI), which the correlation reads as motion: on a synthetic 16 s stop the engine went 0.6 m
and turned 2.5 deg (the yaw gyro's bias) while the car stood still.

What this measures instead: the small motion between two raw images, by brightness constancy
over the road region of the image (a direct, linearised least squares), with the camera's own
small rotations, the body's heave and sideways motion and a brightness gain and offset as
nuisance parameters, so neither the attitude estimate nor the camera's exposure enters. For a
translation of the base, a road point at depth ``Z`` flows by the projection's derivative
(:func:`ground_flow_basis`); rotations flow independently of depth. Robust to outliers: the first
weights come from the frame difference less the exposure change, so at rest an object moving
through the region (the car ahead pulling away) is left out, not fitted.

Inside the linear range (a few pixels of flow at the working resolution, ~0.2 m on KITTI-like
geometry) the estimate is the motion itself; beyond it, it falls back towards zero (1 m reads
~0.15 m), so it only decides standstill, and only when the correlation itself reads little
motion (:data:`CHECK_BELOW`); the fused engine also takes it as a *least* motion there (a car
ahead moving with ours reads as a stop to the correlation, not to the road's flow). At rest means all of: the images differ (a repeated frame is no
measurement), the road texture stands well above the sensor noise (:data:`MIN_TEXTURE_SNR`: a
low-contrast night road would dilute the estimate towards zero), the motion below the threshold
over the whole region and over its near and far halves alike (an object moving with the car,
such as a truck ahead in a queue, fills the far half), known to half the threshold.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F

from .geometry import CameraModel, camera_pose_on_road

Tensor = torch.Tensor

__all__ = ["FlowBasis", "ground_flow_basis", "downsample", "small_motion", "SmallMotion", "StandstillDetector",
           "working_factor", "CHECK_BELOW", "MIN_TEXTURE_SNR"]

# The phase correlation's forward motion (m per frame) below which the engine asks whether the
# vehicle is at rest: beyond it the car is moving whatever the images' fine flow says, and the
# small-motion estimate leaves its linear range (~0.2 m on KITTI-like geometry).
CHECK_BELOW = 0.15

# The road texture's gradient energy over what the sensor noise alone would give it, below which
# the images cannot tell 1 cm from 10 cm (noise in the gradients dilutes the estimate towards
# zero: a night road of texture std 1.2 under noise 4 read 5-10 cm as 1 cm).
MIN_TEXTURE_SNR = 10.0

# Motion parameters of the basis, in this order: the base's forward, lateral and vertical
# translation on the road (m) and the camera's rotations about its optical axes x, y, z (rad).
# The vertical one is the body's heave on its springs: without it, a heave reads as forward motion.
N_MOTION = 6


@dataclass(frozen=True)
class FlowBasis:
    """Image flow per unit motion on a downsampled pixel grid.

    Attributes:
        flow: ``(N_MOTION, 2, h, w)`` (u, v) flow in downsampled pixels per unit of each motion
            parameter: the base's forward, lateral and vertical translation (m), the camera's
            rotations about its x, y, z axes (rad).
        road: ``(h, w)`` 1 where the pixel sees the road between the near and far distances, else 0.
        far: ``(h, w)`` 1 on the road pixels beyond the median road distance (the far half), else 0.
        factor: the downsampling factor of the grid (image pixels per grid pixel).
    """

    flow: Tensor
    road: Tensor
    far: Tensor
    factor: int


def ground_flow_basis(camera: CameraModel, pitch: float, roll: float, factor: int,
                      near: float = 4.0, far: float = 30.0, half_width: float = 8.0,
                      dtype: torch.dtype = torch.float32, device=None) -> FlowBasis:
    """The flow basis of ``camera`` at the road attitude ``(pitch, roll)`` (rad) on the image
    downsampled by ``factor``: pixels whose ray meets the road between ``near`` and ``far`` metres
    ahead of the camera and within ``half_width`` of its axis.

    An attitude off by a degree changes the basis by a few per cent: enough for a detector, so one
    basis per camera serves every frame.
    """
    h, w = camera.height_px // factor, camera.width // factor
    f64 = torch.float64
    K = camera.K.to(f64)
    # Grid-pixel centres in image pixels (a factor x factor box's centre).
    u = (torch.arange(w, dtype=f64) + 0.5) * factor - 0.5
    v = (torch.arange(h, dtype=f64) + 0.5) * factor - 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    ray = torch.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], torch.ones_like(uu)], -1)  # (h, w, 3)
    R, t = camera_pose_on_road(camera.to(dtype=f64), torch.tensor([pitch], dtype=f64), torch.tensor([roll], dtype=f64))
    R, t = R[0], t[0]
    ray_road = ray @ R.T
    down = ray_road[..., 2]
    s = torch.where(down < -1e-9, -t[2] / down.clamp(max=-1e-9), torch.zeros_like(down))  # depth Z (ray z = 1)
    ground = t + s[..., None] * ray_road
    ahead = ground[..., 0] - t[0]
    road = (down < -1e-9) & (ahead >= near) & (ahead <= far) & ((ground[..., 1] - t[1]).abs() <= half_width)
    P = s[..., None] * ray  # camera-frame point
    X, Y, Z = P.unbind(-1)
    Zs = torch.where(road, Z, torch.ones_like(Z))
    fx, fy = K[0, 0] / factor, K[1, 1] / factor

    def project_rate(dP: Tensor) -> Tensor:
        du = fx * (dP[..., 0] * Zs - X * dP[..., 2]) / (Zs * Zs)
        dv = fy * (dP[..., 1] * Zs - Y * dP[..., 2]) / (Zs * Zs)
        return torch.stack([du, dv], 0)

    axes = torch.eye(3, dtype=f64)
    flows = [project_rate((-(R.T @ e)).expand_as(P)) for e in axes]  # the base's translations on the road
    flows += [project_rate(-torch.cross(e.expand_as(P), P, dim=-1)) for e in axes]  # the camera's rotations
    flow = torch.stack(flows, 0) * road
    far_half = road & (ahead > (ahead[road].median() if bool(road.any()) else 0.0))
    return FlowBasis(flow.to(dtype=dtype, device=device), road.to(dtype=dtype, device=device),
                     far_half.to(dtype=dtype, device=device), factor)


def downsample(image: Tensor, factor: int) -> Tensor:
    """Box-downsample ``(..., H, W)`` grey images by ``factor`` -> ``(..., H // factor, W // factor)`` float."""
    x = image.float() if not image.is_floating_point() else image
    lead = x.shape[:-2]
    x = x.reshape(-1, 1, *x.shape[-2:])
    return F.avg_pool2d(x, factor).reshape(*lead, x.shape[-2] // factor, x.shape[-1] // factor)


def _smooth(image: Tensor) -> Tensor:
    """Binomial 5x5 blur of ``(h, w)`` (replicated edges): gradients by central differences are
    then exact to a few per cent, and the linear range wider."""
    k = _BINOMIAL.to(dtype=image.dtype, device=image.device)
    x = F.pad(image[None, None], (2, 2, 2, 2), mode="replicate")
    x = F.conv2d(x, k.view(1, 1, 1, 5))
    return F.conv2d(x, k.view(1, 1, 5, 1))[0, 0]


_BINOMIAL = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0], dtype=torch.float64) / 16.0
_SMOOTH_GAIN = float((_BINOMIAL**2).sum()) ** 2  # variance of smoothed white noise, per unit variance
# ... and of one axis' central difference of it (the gradient's noise)
_GRADIENT_GAIN = float((_BINOMIAL**2).sum()) * float((torch.nn.functional.conv1d(
    _BINOMIAL.view(1, 1, -1), torch.tensor([[[0.5, 0.0, -0.5]]], dtype=torch.float64), padding=2) ** 2).sum())


def _tukey(r: Tensor, spread_of: Tensor) -> Tensor:
    """Tukey biweights of residuals ``r`` at 4.685 robust sigmas (the MAD of ``spread_of``)."""
    sigma = 1.4826 * (spread_of - spread_of.median()).abs().median().clamp_min(1e-6)
    u = (r / (4.685 * sigma)).clamp(-1, 1)
    return (1 - u * u) ** 2


@dataclass(frozen=True)
class SmallMotion:
    """The small-motion estimate between two images.

    Attributes:
        forward: the base's forward motion (m) over the whole road region.
        forward_std: its standard deviation from the residuals (m).
        near, far: the same over the near and the far half of the region (m).
        texture_snr: the road texture's gradient energy over the sensor noise's share of it.
        inliers: fraction of road pixels kept by the robust weights.
        coarse_forward: ``forward`` on images downsampled twice as much (:meth:`StandstillDetector.measure`;
            nan when not computed): twice the linear range.
    """

    forward: float
    forward_std: float
    near: float = float("nan")
    far: float = float("nan")
    texture_snr: float = 0.0
    inliers: float = 0.0
    coarse_forward: float = float("nan")


NO_MOTION = SmallMotion(float("nan"), float("inf"))  # too few road pixels, or non-finite images


def _solve(A: Tensor, w: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
    """Weighted least squares ``A (N, P)``, ``w (N,)``, ``y (N,)`` by ridge-regularised normal
    equations (a rank-deficient pair, such as a flat image, gives a finite answer on any device).
    -> the solution ``(P,)`` and the normal matrix ``(P, P)``."""
    Aw = A * w[:, None]
    H = A.T @ Aw + 1e-9 * torch.eye(A.shape[1], dtype=A.dtype, device=A.device)
    return torch.linalg.solve(H, Aw.T @ y), H


def small_motion(prev: Tensor, curr: Tensor, basis: FlowBasis, iterations: int = 3) -> SmallMotion:
    """The forward motion between two downsampled grey images ``(h, w)`` on ``basis``'s grid
    (:func:`downsample`).

    Linearised brightness constancy, ``I_t = -sum_k (I_x u_k + I_y v_k) m_k + g I + o``, solved by
    iteratively reweighted least squares (Tukey weights at 4.7 robust sigmas; ``iterations``
    reweighting passes after the first solve).
    """
    if not (bool(torch.isfinite(prev).all()) and bool(torch.isfinite(curr).all())):
        return NO_MOTION
    a = _smooth(prev.to(basis.flow.dtype))
    b = _smooth(curr.to(basis.flow.dtype))
    mean = 0.5 * (a + b)
    gx = torch.zeros_like(mean)
    gy = torch.zeros_like(mean)
    gx[:, 1:-1] = 0.5 * (mean[:, 2:] - mean[:, :-2])
    gy[1:-1] = 0.5 * (mean[2:] - mean[:-2])
    valid = basis.road.clone()
    valid[0] = valid[-1] = 0
    valid[:, 0] = valid[:, -1] = 0
    m = valid > 0
    if int(m.sum()) < 50:
        return NO_MOTION
    cols = [-(gx * basis.flow[k, 0] + gy * basis.flow[k, 1])[m] for k in range(N_MOTION)]
    A = torch.stack(cols + [mean[m], torch.ones_like(mean[m])], 1).double()  # (N, N_MOTION + 2)
    y = (b - a)[m].double()
    far = basis.far[m] > 0
    # Column scaling keeps the normal equations well conditioned (metres vs radians vs grey levels).
    scale = A.abs().mean(0).clamp_min(1e-12)
    As = A / scale
    # First weights from the frame difference less the exposure change alone: at rest it is sensor
    # noise on the road, and an object moving in the region (the car ahead pulling away) stands out
    # and is left out, not fitted as part of the motion; when the car moves, the whole road differs
    # and all stay.
    photometric = As[:, N_MOTION:]
    r0 = y - photometric @ _solve(photometric, torch.ones_like(y), y)[0]
    wts = _tukey(r0, r0)
    for it in range(iterations + 1):
        theta, H = _solve(As, wts, y)
        r = y - As @ theta
        if it < iterations:
            wts = _tukey(r, r)
    dof = max(float(wts.sum()) - As.shape[1], 1.0)
    s2 = float((wts * r * r).sum()) / dof
    std = float(torch.linalg.inv(H)[0, 0].clamp_min(0).sqrt() / scale[0]) * s2**0.5
    halves = []
    for part in (~far, far):
        if int(part.sum()) < 50:
            halves.append(float("nan"))
        else:
            halves.append(float(_solve(As[part], wts[part], y[part])[0][0] / scale[0]))
    # Texture against noise: the residual's robust spread is the smoothed temporal noise at rest
    # (more when moving: the test only gets stricter), from which the noise's share of the mean
    # image's gradient energy follows.
    sigma_r2 = float(1.4826 * (r - r.median()).abs().median()) ** 2
    noise_gradient = _GRADIENT_GAIN * sigma_r2 / (2.0 * _SMOOTH_GAIN)  # both axes, of the 2-frame mean
    energy = float((wts * (gx[m] ** 2 + gy[m] ** 2).double()).sum() / wts.sum().clamp_min(1e-12))
    snr = energy / max(noise_gradient, 1e-12)
    return SmallMotion(float(theta[0] / scale[0]), std, halves[0], halves[1], snr, float((wts > 0).double().mean()))


def working_factor(width: int) -> int:
    """Downsampling factor that puts the image's width near 310 pixels (KITTI 1241 -> 4): the road
    texture still resolves, and the least squares stays at about 10^4 pixels."""
    return max(1, round(width / 310))


class StandstillDetector:
    """Remembers the previous frame's image and tells whether the vehicle stood still since.

    Args:
        camera: the camera (its basis is built at the ``attitude`` once, then reused).
        attitude: (pitch, roll) of the base on the road (the mounting attitude), rad.
        max_speed: the vehicle is at rest when the small motion over a frame interval ``dt`` is
            below ``max_speed * dt`` (a speed, so the same at any frame rate); 0 disables it.
    """

    def __init__(self, camera: CameraModel, attitude: tuple[float, float], max_speed: float) -> None:
        if not max_speed >= 0:
            raise ValueError(f"max_speed must be >= 0 (0 disables), got {max_speed!r}")
        self.max_speed = float(max_speed)
        self.attitude = (float(attitude[0]), float(attitude[1]))
        self._warned = False
        self.set_camera(camera)

    @property
    def enabled(self) -> bool:
        return self.max_speed > 0

    def set_attitude(self, attitude: tuple[float, float]) -> None:
        """The base's attitude on the road the flow basis is built at (the start's measured tilt)."""
        self.attitude = (float(attitude[0]), float(attitude[1]))
        self._basis = self._coarse_basis = None  # built again on next use

    def set_camera(self, camera: CameraModel) -> None:
        self.camera = camera
        self._basis: FlowBasis | None = None  # built on first use
        self._coarse_basis: FlowBasis | None = None  # the same at twice the downsampling
        self.reset()

    def reset(self) -> None:
        """Forget the previous image."""
        self._prev: tuple[Tensor, Tensor | None] | None = None  # (image, its downsampled twin or None)
        self._curr: tuple[Tensor, Tensor] | None = None  # the image measure() downsampled

    def _small(self, image: Tensor) -> Tensor:
        return downsample(image, working_factor(self.camera.width))

    def measure(self, image: Tensor, dt: float | None = None) -> SmallMotion | None:
        """The small motion from the remembered image to ``image (H, W)``; None without one, when
        disabled, when the two differ in size, or when they are the same bit for bit (a camera
        driver repeating its last frame: a real sensor's noise never repeats). With the frame
        interval ``dt`` (s) the coarse look is skipped when the fine estimate already rules rest
        out (``coarse_forward`` stays nan; :meth:`at_rest` says the same either way)."""
        if not self.enabled or self._prev is None or self._prev[0].shape != image.shape:
            return None
        if torch.equal(self._prev[0], image):
            return None
        if self._basis is None:
            self._basis = ground_flow_basis(self.camera, *self.attitude, working_factor(self.camera.width),
                                            device=image.device)
            if int(self._basis.road.sum()) < 200 and not self._warned:
                self._warned = True
                warnings.warn(f"standstill check off: the camera sees only {int(self._basis.road.sum())} grid "
                              "pixels of road 4-30 m ahead (is it facing forward, is the mounting right?)",
                              RuntimeWarning, stacklevel=2)
        prev = self._prev[1] if self._prev[1] is not None else self._small(self._prev[0])
        curr = self._small(image)
        self._curr = (image, curr)
        if prev.shape != self._basis.road.shape:
            return None
        fine = small_motion(prev, curr, self._basis)
        if not math.isfinite(fine.forward) or (dt is not None and not self._fine_at_rest(fine, dt)):
            return fine
        # Beyond its linear range the estimate falls back towards zero: on a real drive's rendered
        # frames a 14 cm motion (under CHECK_BELOW) read 0.9 cm, a false stop whose zero-rotation
        # update took 0.8 deg of turn out of the heading. Twice coarser, the range is twice as long
        # (the same motion reads > 10 cm) and a true rest still reads ~0.
        if self._coarse_basis is None:
            self._coarse_basis = ground_flow_basis(self.camera, *self.attitude, 2 * working_factor(self.camera.width),
                                                   device=image.device)
        coarse = small_motion(downsample(prev, 2), downsample(curr, 2), self._coarse_basis)
        return replace(fine, coarse_forward=coarse.forward)

    def at_rest(self, motion: SmallMotion | None, dt: float) -> bool:
        """True when ``motion`` over ``dt`` (s) says the vehicle stood still: texture well above
        the noise, below ``max_speed * dt`` over the region and over its near and far halves,
        known to half of it, and not above it at the coarse scale (``coarse_forward``)."""
        return (motion is not None and self._fine_at_rest(motion, dt)
                and not abs(motion.coarse_forward) >= self.max_speed * dt)

    def _fine_at_rest(self, motion: SmallMotion, dt: float) -> bool:
        """:meth:`at_rest` without the coarse look."""
        limit = self.max_speed * dt
        return (motion.texture_snr >= MIN_TEXTURE_SNR
                and abs(motion.forward) < limit and motion.forward_std < 0.5 * limit
                and abs(motion.near) < limit and abs(motion.far) < limit)

    def remember(self, image: Tensor) -> None:
        """Keep ``image (H, W)`` as the previous one for the next frame (a copy: a caller refilling
        one buffer per frame would otherwise make every pair identical)."""
        if not self.enabled:
            return
        small = self._curr[1] if self._curr is not None and self._curr[0] is image else None
        kept = None if self._prev is None else self._prev[0]
        if (kept is not None and kept is not image and kept.shape == image.shape and kept.dtype == image.dtype
                and kept.device == image.device):
            kept.copy_(image)  # the previous copy's memory again: a fresh one each frame costs page faults
        else:
            with torch.inference_mode(False):  # a normal tensor: written in and outside inference mode alike
                kept = image.clone()
        self._prev, self._curr = (kept, small), None
