"""Standstill: is the vehicle at rest between two frames? Measured on the images, not the BEVs.

Why not the phase correlation: a BEV is projected with the filtered attitude, and the engine's
attitude keeps moving while the car stands (the DUKF's accelerometer updates on an idling engine's
vibration, the road-tilt low-pass). A change ``D`` of the BEV pitch moves the whole BEV by
``(X^2 + h^2) / h * D`` (:func:`~bevo_ros.core.motion.pitch_change_shift`, 1.4 cm per 0.01 deg on
KITTI), which the correlation reads as motion: on the synthetic stop of 16 s the engine went 1.2 m
and turned 2.4 deg (the yaw gyro's bias) while the car stood still.

What this measures instead: the small motion between two raw images, by brightness constancy
over the road region of the image (a direct, linearised least squares, robust to outliers: its
first weights come from the frame difference less the exposure change, so at rest an object
moving through the region, such as the car ahead pulling away, is left out, not fitted),
with the camera's own small rotations and a brightness gain and offset as nuisance parameters,
so neither the attitude estimate nor the camera's exposure enters. For a forward translation
``dX`` of the base, a road point at depth ``Z`` flows by the projection's derivative
(:func:`ground_flow_basis`); rotations flow independently of depth.

Inside the linear range (a few pixels of flow at the working resolution) the estimate is the
motion itself; beyond it, it saturates, so it is only used to decide standstill: ``|dX|``
below ``max_motion`` with enough texture to know it (its standard deviation small too).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from .geometry import CameraModel, camera_pose_on_road

Tensor = torch.Tensor

__all__ = ["FlowBasis", "ground_flow_basis", "downsample", "small_motion", "SmallMotion", "StandstillDetector",
           "working_factor", "CHECK_BELOW"]

# The phase correlation's forward motion (m per frame) below which the engine asks whether the
# vehicle is at rest: beyond it the car is moving whatever the images' fine flow says, and the
# small-motion estimate leaves its linear range (~0.2 m on KITTI-like geometry).
CHECK_BELOW = 0.15

# Motion parameters of the basis, in this order: the base's forward, lateral and vertical
# translation on the road (m) and the camera's rotations about its optical axes x, y, z (rad).
# The vertical one is the body's heave on its springs: without it, a heave reads as forward motion.
N_MOTION = 6


@dataclass(frozen=True)
class FlowBasis:
    """Image flow per unit motion on a downsampled pixel grid.

    Attributes:
        flow: ``(N_MOTION, 2, h, w)`` (u, v) flow in downsampled pixels per unit of each motion
            parameter (forward translation of the base in metres, camera rotations in radians).
        road: ``(h, w)`` 1 where the pixel sees the road between the near and far distances, else 0.
        factor: the downsampling factor of the grid (image pixels per grid pixel).
    """

    flow: Tensor
    road: Tensor
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

    flows = []
    for axis in range(3):  # the base's translation along the road axes, in the camera frame
        e = torch.zeros(3, dtype=f64)
        e[axis] = 1.0
        flows.append(project_rate((-(R.T @ e)).expand_as(P)))
    for axis in range(3):
        e = torch.zeros(3, dtype=f64)
        e[axis] = 1.0
        flows.append(project_rate(-torch.cross(e.expand_as(P), P, dim=-1)))
    flow = torch.stack(flows, 0) * road
    return FlowBasis(flow.to(dtype=dtype, device=device), road.to(dtype=dtype, device=device), factor)


def downsample(image: Tensor, factor: int) -> Tensor:
    """Box-downsample ``(..., H, W)`` grey images by ``factor`` -> ``(..., H // factor, W // factor)`` float."""
    x = image.float() if not image.is_floating_point() else image
    lead = x.shape[:-2]
    x = x.reshape(-1, 1, *x.shape[-2:])
    return F.avg_pool2d(x, factor).reshape(*lead, x.shape[-2] // factor, x.shape[-1] // factor)


def _smooth(image: Tensor) -> Tensor:
    """Binomial 5x5 blur of ``(h, w)`` (replicated edges): gradients by central differences are
    then exact to a few per cent, and the linear range wider."""
    k = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0], dtype=image.dtype, device=image.device) / 16.0
    x = F.pad(image[None, None], (2, 2, 2, 2), mode="replicate")
    x = F.conv2d(x, k.view(1, 1, 1, 5))
    return F.conv2d(x, k.view(1, 1, 5, 1))[0, 0]


def _tukey(r: Tensor, spread_of: Tensor) -> Tensor:
    """Tukey biweights of residuals ``r`` at 4.685 robust sigmas (the MAD of ``spread_of``)."""
    sigma = 1.4826 * (spread_of - spread_of.median()).abs().median().clamp_min(1e-6)
    u = (r / (4.685 * sigma)).clamp(-1, 1)
    return (1 - u * u) ** 2


@dataclass(frozen=True)
class SmallMotion:
    """``forward``: the base's forward motion between the images (m); ``forward_std``: its standard
    deviation from the residuals; ``inliers``: fraction of road pixels kept by the robust weights."""

    forward: float
    forward_std: float
    inliers: float


def small_motion(prev: Tensor, curr: Tensor, basis: FlowBasis, iterations: int = 3) -> SmallMotion:
    """The forward motion between two downsampled grey images ``(h, w)`` (:func:`downsample`).

    Linearised brightness constancy, ``I_t = -sum_k (I_x u_k + I_y v_k) m_k + g I + o``, solved by
    iteratively reweighted least squares (Tukey weights at 4.7 robust sigmas: a pedestrian or a
    passing car in the road region is an outlier, not a motion). ``prev``, ``curr``: ``(h, w)``
    on ``basis``'s grid. ``iterations``: reweighting passes after the first solve.
    """
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
    cols = [-(gx * basis.flow[k, 0] + gy * basis.flow[k, 1])[m] for k in range(N_MOTION)]
    A = torch.stack(cols + [mean[m], torch.ones_like(mean[m])], 1).double()  # (N, 6)
    y = (b - a)[m].double()
    n = y.numel()
    if n < 50:
        return SmallMotion(float("nan"), float("inf"), 0.0)
    # Column scaling keeps the normal equations well conditioned (metres vs radians vs grey levels).
    scale = A.abs().mean(0).clamp_min(1e-12)
    As = A / scale
    # First weights from the frame difference less the exposure change alone: at rest it is sensor
    # noise on the road, and an object moving in the region (the car ahead pulling away) stands out
    # and is left out, not fitted as part of the motion; when the car moves, the whole road differs
    # and all stay.
    photometric = As[:, N_MOTION:]
    r0 = y - photometric @ torch.linalg.lstsq(photometric, y[:, None]).solution[:, 0]
    wts = _tukey(r0, r0)
    ridge = 1e-9 * torch.eye(As.shape[1], dtype=As.dtype, device=As.device)
    for it in range(iterations + 1):
        Aw = As * wts[:, None]
        H = As.T @ Aw + ridge
        theta = torch.linalg.solve(H, Aw.T @ y)
        r = y - As @ theta
        if it < iterations:
            wts = _tukey(r, r)
    dof = max(float(wts.sum()) - As.shape[1], 1.0)
    s2 = float((wts * r * r).sum()) / dof
    cov = torch.linalg.inv(H) * s2
    forward = float(theta[0] / scale[0])
    std = float(cov[0, 0].clamp_min(0).sqrt() / scale[0])
    return SmallMotion(forward, std, float((wts > 0).double().mean()))


def working_factor(width: int) -> int:
    """Downsampling factor that puts the image's width near 310 pixels (KITTI 1241 -> 4): the road
    texture still resolves, and the least squares stays at about 10^4 pixels."""
    return max(1, round(width / 310))


class StandstillDetector:
    """Remembers the previous frame's image and tells whether the vehicle stood still since.

    Args:
        camera: the camera (its basis is built at the ``attitude`` once, then reused).
        attitude: (pitch, roll) of the base on the road (the mounting attitude), rad.
        max_motion: the vehicle is at rest when the small-motion estimate is below this (m per
            frame) and its standard deviation below half of it; 0 disables the detector.
    """

    def __init__(self, camera: CameraModel, attitude: tuple[float, float], max_motion: float) -> None:
        if not max_motion >= 0:
            raise ValueError(f"max_motion must be >= 0 (0 disables), got {max_motion!r}")
        self.max_motion = float(max_motion)
        self.attitude = (float(attitude[0]), float(attitude[1]))
        self.set_camera(camera)

    @property
    def enabled(self) -> bool:
        return self.max_motion > 0

    def set_camera(self, camera: CameraModel) -> None:
        self.camera = camera
        self._basis: FlowBasis | None = None  # built on first use
        self.reset()

    def reset(self) -> None:
        """Forget the previous image."""
        self._prev: tuple[Tensor, Tensor | None] | None = None  # (image, its downsampled twin or None)
        self._curr: tuple[Tensor, Tensor] | None = None  # the image measure() downsampled

    def _small(self, image: Tensor) -> Tensor:
        return downsample(image, working_factor(self.camera.width))

    def measure(self, image: Tensor) -> SmallMotion | None:
        """The small motion from the remembered image to ``image (H, W)``; None without one (or
        when disabled, or when the two images differ in size)."""
        if not self.enabled or self._prev is None or self._prev[0].shape != image.shape:
            return None
        if self._basis is None:
            self._basis = ground_flow_basis(self.camera, *self.attitude, working_factor(self.camera.width),
                                            device=image.device)
        prev = self._prev[1] if self._prev[1] is not None else self._small(self._prev[0])
        curr = self._small(image)
        self._curr = (image, curr)
        if prev.shape != self._basis.road.shape:
            return None
        return small_motion(prev, curr, self._basis)

    def at_rest(self, motion: SmallMotion | None) -> bool:
        """True when ``motion`` says the vehicle stood still: below ``max_motion``, known to half of it."""
        return (motion is not None and abs(motion.forward) < self.max_motion
                and motion.forward_std < 0.5 * self.max_motion)

    def remember(self, image: Tensor) -> None:
        """Keep ``image (H, W)`` as the previous one for the next frame (a copy: a caller refilling
        one buffer per frame would otherwise make every pair identical, a false standstill)."""
        if not self.enabled:
            return
        small = self._curr[1] if self._curr is not None and self._curr[0] is image else None
        self._prev, self._curr = (image.clone(), small), None
