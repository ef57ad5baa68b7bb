"""BEV registration <-> planar vehicle motion (SE(2), metres) and its covariance.

A registration (``bevo_ros.core.phase_correlation``) says ``curr(q) = prev(c + R(-angle)(q - c) -
shift)`` in BEV pixels. In road-frame metres about the BEV centre ``C = spec.centre`` (the road
frame x forward, y left; BEV row = -x, column = -y, so the same rotation matrix applies):

* the vehicle yaws by ``dyaw``; a fixed ground point ``p`` (base frame at t-1) is seen at
  ``R(-dyaw)(p - d)`` at t, with ``d = (dx, dy)`` the base translation in the base frame at t-1;
* hence ``curr(u) = prev(R(dyaw) u + d)`` for base-frame points ``u``, i.e. in BEV-centred
  coordinates ``v = u - C``: ``curr(v) = prev(R(dyaw) v + R(dyaw) C + d - C)``;
* matching with ``prev(R(-angle) v - s)`` (``s`` the shift in metres, ``s = -mpp * shift``)
  gives ``dyaw = -angle`` and ``d = C - R(dyaw) C + mpp * shift``.

The image rotates about the BEV centre, several metres in front of the vehicle, so a pure yaw
of the vehicle also shows up as a sideways shift of the BEV; ``C - R(dyaw) C`` accounts for it.
"""
from __future__ import annotations

import math

import torch

from .device import constant_cache
from .geometry import BevSpec

Tensor = torch.Tensor


@constant_cache(32)
def _centre_of(spec: BevSpec, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    """The BEV centre ``C (2,)`` and its two entries (0-d). Cached: it depends only on the grid."""
    C = torch.tensor(spec.centre, dtype=dtype, device=device)
    return C, C[0], C[1]


def _centre(spec: BevSpec, like: Tensor) -> Tensor:
    return _centre_of(spec, like.dtype, like.device)[0]


@constant_cache(32)
def _jacobian_constants(spec: BevSpec, dtype: torch.dtype, device: torch.device) -> Tensor:
    """``(1, 3, 3)`` the entries of :func:`motion_jacobian` that do not depend on the angle."""
    J = torch.zeros(1, 3, 3, dtype=dtype, device=device)
    J[:, 0, 1] = spec.metres_per_pixel
    J[:, 1, 2] = spec.metres_per_pixel
    J[:, 2, 0] = -1.0
    return J


def _rotate(angle: Tensor, v: Tensor) -> Tensor:
    """``R(angle) v`` for ``angle (B,)`` and ``v (B, 2)`` or ``(2,)``."""
    c, s = torch.cos(angle), torch.sin(angle)
    v = v.expand(angle.shape[0], 2)
    return torch.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1]], dim=-1)


def vehicle_motion_from_registration(angle: Tensor, shift: Tensor, spec: BevSpec) -> Tensor:
    """Motion of the base from frame t-1 to t, in the base frame at t-1.

    Args:
        angle: ``(B,)`` BEV rotation, radians (see ``phase_correlation``).
        shift: ``(B, 2)`` BEV shift ``(d_row, d_col)``, pixels.
        spec: the BEV grid (centre, metres per pixel).

    Returns:
        ``(B, 3)`` ``(dx, dy, dyaw)``: metres, metres, radians (REP-103: x forward, y left, yaw CCW).
    """
    if angle.ndim != 1 or shift.shape != (angle.shape[0], 2):
        raise ValueError(f"need angle (B,) and shift (B, 2), got {tuple(angle.shape)} and {tuple(shift.shape)}")
    dyaw = -angle
    C = _centre(spec, shift)
    dtype = torch.promote_types(angle.dtype, shift.dtype)  # as _rotate(dyaw, C) computes
    _, cx, cy = _centre_of(spec, dtype, shift.device)
    c, s = torch.cos(dyaw).to(dtype), torch.sin(dyaw).to(dtype)
    rotated = torch.stack([c * cx - s * cy, s * cx + c * cy], dim=-1)  # _rotate(dyaw, C), its entries cached
    d = C - rotated + spec.metres_per_pixel * shift
    return torch.cat([d, dyaw[:, None]], dim=-1)


def registration_from_vehicle_motion(motion: Tensor, spec: BevSpec) -> tuple[Tensor, Tensor]:
    """Exact inverse of :func:`vehicle_motion_from_registration` (training targets).

    Args:
        motion: ``(B, 3)`` ``(dx, dy, dyaw)``.

    Returns:
        angle ``(B,)`` radians and shift ``(B, 2)`` pixels ``(d_row, d_col)``.
    """
    if motion.ndim != 2 or motion.shape[-1] != 3:
        raise ValueError(f"motion must be (B, 3), got {tuple(motion.shape)}")
    dyaw = motion[:, 2]
    C = _centre(spec, motion)
    shift = (motion[:, :2] - C + _rotate(dyaw, C)) / spec.metres_per_pixel
    return -dyaw, shift


def registration_shift_floats(dx: float, dy: float, dyaw: float, spec: BevSpec) -> tuple[float, float]:
    """:func:`registration_from_vehicle_motion`'s shift ``(d_row, d_col)`` (px) of one motion, in
    Python floats (the engine's per-frame prior: one motion, where tensor ops cost tens of us)."""
    cx, cy = spec.centre
    c, s = math.cos(dyaw), math.sin(dyaw)
    mpp = spec.metres_per_pixel
    return (dx - cx + (c * cx - s * cy)) / mpp, (dy - cy + (s * cx + c * cy)) / mpp


def motion_jacobian(angle: Tensor, spec: BevSpec) -> Tensor:
    """``d(dx, dy, dyaw) / d(angle, d_row, d_col)``. ``angle (B,)`` -> ``(B, 3, 3)``."""
    B = angle.shape[0]
    _, cx, cy = _centre_of(spec, angle.dtype, angle.device)
    dyaw = -angle
    c, s = torch.cos(dyaw), torch.sin(dyaw)
    # d/d(angle) of -R(dyaw) C = +dR/d(dyaw) C
    dR_C = torch.stack([-s * cx - c * cy, c * cx - s * cy], dim=-1)  # (B, 2)
    J = _jacobian_constants(spec, angle.dtype, angle.device).repeat(B, 1, 1)
    J[:, :2, 0] = dR_C
    return J


def motion_covariance_from_registration(registration, spec: BevSpec) -> Tensor:
    """First-order covariance ``(B, 3, 3)`` of ``(dx, dy, dyaw)`` from the spread of the
    correlation distributions (``angle_std``, ``shift_cov``), angle and shift taken independent.
    """
    angle = registration.angle
    B = angle.shape[0]
    cov_in = torch.zeros(B, 3, 3, dtype=angle.dtype, device=angle.device)
    cov_in[:, 0, 0] = registration.angle_std.to(angle.dtype) ** 2
    cov_in[:, 1:, 1:] = registration.shift_cov.to(angle.dtype)
    J = motion_jacobian(angle, spec)
    return J @ cov_in @ J.transpose(-1, -2)


def pitch_scale_sensitivity(spec: BevSpec, camera_forward: float, camera_height: float) -> float:
    """``|d ln(dx) / d pitch|`` of the BEV's forward motion, ``2 X / h`` (1/rad).

    A road point ``X`` ahead of a camera at height ``h`` is seen ``atan(h / X)`` below the
    horizon; projected with a pitch off by ``d``, it lands at ``X'`` with
    ``dX'/dd = (X^2 + h^2) / h``, so ground displacements are scaled by ``1 + 2 X d / h``.
    ``X`` is the distance from the camera to the BEV centre. KITTI-like geometry (BEV centre
    12.5 m ahead of the IMU, camera 1.08 m ahead and 1.65 m up): 13.8 per radian, i.e. 0.24 % of
    the forward motion per 0.01 deg (measured by re-projecting rendered frames: 13.5).
    """
    x = spec.centre[0] - camera_forward
    if x <= 0 or camera_height <= 0:
        raise ValueError(f"the BEV centre must be ahead of the camera and the camera above the road, "
                         f"got X = {x:.3f} m, h = {camera_height:.3f} m")
    return 2.0 * x / camera_height


def pitch_change_shift(spec: BevSpec, camera_forward: float, camera_height: float) -> float:
    """``d(dx) / d(pitch change)``: forward motion read per radian of pitch *difference* between
    the two BEVs of a pair, ``(X^2 + h^2) / h`` (m/rad).

    Projected with a pitch off by ``d`` (positive nose down, the engine's convention), a road point
    ``X`` ahead of the camera lands ``(X^2 + h^2) / h * d`` nearer (:func:`pitch_scale_sensitivity`).
    When the previous BEV was projected with an error ``d`` and the current one with ``d + D``, the
    common part only scales the motion, but the change ``D`` moves all of the current BEV towards
    the car, which the correlation reads as motion: ``dx_read = dx (1 - 2 X d / h) + (X^2 + h^2) / h * D``
    (test_pitch_change_shifts_the_forward_motion). KITTI-like geometry (BEV centre 11.4 m ahead of
    a camera 1.65 m up): 80 m/rad, 1.4 cm per 0.01 deg.
    """
    x = spec.centre[0] - camera_forward
    if x <= 0 or camera_height <= 0:
        raise ValueError(f"the BEV centre must be ahead of the camera and the camera above the road, "
                         f"got X = {x:.3f} m, h = {camera_height:.3f} m")
    return (x * x + camera_height * camera_height) / camera_height


def roll_yaw_sensitivity(camera_height: float) -> float:
    """``|d(dyaw)/d roll|`` per metre of forward motion, ``1 / (2 h)`` (1/(m rad)).

    Projected with a roll off by ``d``, a road point at lateral offset ``Y`` lands at a forward
    distance scaled by ``1 + Y d / h``: a forward motion ``dx`` becomes a shear ``dx d / h``
    across the BEV, which phase correlation reads as a rotation of about half of it (exactly half
    for isotropic texture; 0.72-0.84 of that measured on the synthetic road, whose markings run
    along it). Through the BEV centre ``C`` that yaw error is also a lateral one:
    ``d(dy) = -C_x d(dyaw)`` (:func:`motion_jacobian`).
    """
    if camera_height <= 0:
        raise ValueError(f"the camera must be above the road, got h = {camera_height:.3f} m")
    return 0.5 / camera_height


__all__ = [
    "pitch_scale_sensitivity",
    "pitch_change_shift",
    "roll_yaw_sensitivity",
    "vehicle_motion_from_registration",
    "registration_from_vehicle_motion",
    "registration_shift_floats",
    "motion_jacobian",
    "motion_covariance_from_registration",
]
