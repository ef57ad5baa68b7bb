"""Frames, rotations and the camera/BEV geometry every other module shares.

Conventions (REP-103 / REP-105), fixed here once:

* ``base`` frame = the IMU frame: x forward, y left, z up. ``base_link`` in ROS.
* Attitude angles are intrinsic Z-Y-X Euler angles, ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
  Positive pitch = nose down (right-handed about y-left), positive roll = left side up,
  which is also the OXTS convention of KITTI.
* ``road`` frame: origin on the road surface directly below the base origin, z along the road
  normal, x along the vehicle heading projected onto the road. The vehicle's attitude
  relative to it is ``R_road_base = Ry(pitch) @ Rx(roll)``.
* Camera frames are optical frames: z along the optical axis, x right, y down.
  ``T_base_cam`` (4, 4) is the camera pose in the base frame (maps camera points to base).
* The camera centre is held at a fixed height above the road (``CameraModel.mount_height``): the
  paper's constant-elevation assumption, expressed for the camera because that is what a
  user measures.
* BEV pixels: row 0 is the far edge, the last row the near edge; column 0 is the left edge.
  Pixel (row, col) centre sits at ``x = forward_offset + (size - 0.5 - row) * mpp`` and
  ``y = ((size - 1) / 2 - col) * mpp`` in the road frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

Tensor = torch.Tensor


def rotation_x(angle: Tensor) -> Tensor:
    """Rotation about x. ``(...,)`` -> ``(..., 3, 3)``."""
    c, s = torch.cos(angle), torch.sin(angle)
    o, z = torch.ones_like(angle), torch.zeros_like(angle)
    return torch.stack([o, z, z, z, c, -s, z, s, c], dim=-1).reshape(*angle.shape, 3, 3)


def rotation_y(angle: Tensor) -> Tensor:
    """Rotation about y. ``(...,)`` -> ``(..., 3, 3)``."""
    c, s = torch.cos(angle), torch.sin(angle)
    o, z = torch.ones_like(angle), torch.zeros_like(angle)
    return torch.stack([c, z, s, z, o, z, -s, z, c], dim=-1).reshape(*angle.shape, 3, 3)


def rotation_z(angle: Tensor) -> Tensor:
    """Rotation about z. ``(...,)`` -> ``(..., 3, 3)``."""
    c, s = torch.cos(angle), torch.sin(angle)
    o, z = torch.ones_like(angle), torch.zeros_like(angle)
    return torch.stack([c, -s, z, s, c, z, z, z, o], dim=-1).reshape(*angle.shape, 3, 3)


def rotation_from_rpy(roll: Tensor, pitch: Tensor, yaw: Tensor) -> Tensor:
    """``Rz(yaw) @ Ry(pitch) @ Rx(roll)``. ``(...,)`` x3 -> ``(..., 3, 3)``."""
    return rotation_z(yaw) @ rotation_y(pitch) @ rotation_x(roll)


def rpy_from_rotation(rotation: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Inverse of :func:`rotation_from_rpy` (pitch in [-pi/2, pi/2]). ``(..., 3, 3)`` -> 3 x ``(...,)``."""
    r = rotation
    pitch = torch.asin((-r[..., 2, 0]).clamp(-1.0, 1.0))
    roll = torch.atan2(r[..., 2, 1], r[..., 2, 2])
    yaw = torch.atan2(r[..., 1, 0], r[..., 0, 0])
    return roll, pitch, yaw


def wrap_angle(angle: Tensor) -> Tensor:
    """Wrap to ``[-pi, pi)``."""
    return torch.remainder(angle + torch.pi, 2 * torch.pi) - torch.pi


@dataclass
class CameraModel:
    """A pinhole camera rigidly mounted on the vehicle.

    Attributes:
        K: intrinsics ``(3, 3)`` of the (rectified) image.
        width, height_px: image size in pixels.
        T_base_cam: camera pose in the base (IMU) frame, ``(4, 4)``; optical camera axes.
        mount_height: camera centre height above the road plane in metres (held constant).
    """

    K: Tensor
    width: int
    height_px: int
    T_base_cam: Tensor
    mount_height: float = 1.65

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "CameraModel":
        return CameraModel(
            self.K.to(device=device, dtype=dtype),
            self.width,
            self.height_px,
            self.T_base_cam.to(device=device, dtype=dtype),
            self.mount_height,
        )


def camera_pose_on_road(camera: CameraModel, pitch: Tensor, roll: Tensor) -> tuple[Tensor, Tensor]:
    """Camera pose in the road frame for the vehicle attitude (pitch, roll) relative to the road.

    Args:
        camera: the camera model.
        pitch, roll: ``(B,)`` attitude of the base frame relative to the road plane, radians.

    Returns:
        ``R_road_cam (B, 3, 3)`` and ``t_road_cam (B, 3)``; ``t_road_cam[:, 2] == camera.mount_height``.
    """
    dtype, device = pitch.dtype, pitch.device
    R_base_cam = camera.T_base_cam[:3, :3].to(device=device, dtype=dtype)
    t_base_cam = camera.T_base_cam[:3, 3].to(device=device, dtype=dtype)
    R_road_base = rotation_y(pitch) @ rotation_x(roll)
    R_road_cam = R_road_base @ R_base_cam
    t = R_road_base @ t_base_cam
    # The camera height is fixed: the base origin moves up/down with the attitude instead.
    t_road_cam = torch.stack([t[..., 0], t[..., 1], torch.full_like(t[..., 2], camera.mount_height)], dim=-1)
    return R_road_cam, t_road_cam


def mounting_for_extrinsics(mounting: tuple[float, float], T_base_cam_calibrated, T_base_cam) -> tuple[float, float]:
    """The base's (pitch, roll) on the road that keeps the camera's tilt to the road when the
    camera's extrinsics are ``T_base_cam`` instead of ``T_base_cam_calibrated``, the ones the
    ``mounting`` was calibrated with. ``(4, 4)`` (or ``(3, 3)``) arrays or tensors; rad in, rad out.

    A mounting calibration (``bevo calibrate``) fits the images' scale: what it measures is the
    road plane as the camera sees it, its normal in the camera frame. Written as the base's
    attitude it holds only together with the extrinsics it was fitted through. KITTI's raw
    calibrations differ by about 1 deg in the camera's pitch from day to day (the optical axis
    +0.48 deg above the IMU's x axis through the 2011_09_26 files, -0.49 deg through 2011_09_30's),
    while the odometry ground truth shows the camera looking 1.19 deg (2011_09_30 sequences) and
    0.97 deg (2011_10_03) down at the road: a mounting fitted through one day's files and used with
    another's tilts the BEV by that degree, 20 % of scale. The road normal is kept in the camera
    frame; a yaw between the two extrinsics stays the camera's (it does not tilt the road plane).
    Returns ``mounting`` itself when the two rotations agree to 1e-6.
    """
    import numpy as np

    def rot(T) -> "np.ndarray":
        T = T.detach().cpu().numpy() if isinstance(T, Tensor) else T
        return np.asarray(T, dtype=np.float64)[:3, :3]

    R_cal, R_new = rot(T_base_cam_calibrated), rot(T_base_cam)
    if np.abs(R_cal - R_new).max() < 1e-6:
        return float(mounting[0]), float(mounting[1])
    p, r = float(mounting[0]), float(mounting[1])
    cp, sp, cr, sr = np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    up_in_base = np.array([-sp, cp * sr, cp * cr])  # the road normal in the base: Ry(p) Rx(r)'s third row
    up_in_camera = R_cal.T @ up_in_base
    n = R_new @ up_in_camera
    n = n / np.linalg.norm(n)
    return float(-np.arcsin(np.clip(n[0], -1.0, 1.0))), float(np.arctan2(n[1], n[2]))


@dataclass(frozen=True)
class BevSpec:
    """The bird's-eye-view grid on the road plane.

    Attributes:
        size: BEV is ``size x size`` pixels (the paper uses 100).
        metres_per_pixel: ground sampling distance (the paper's DPP).
        forward_offset: distance from the base origin to the BEV's near edge along x, metres.
    """

    size: int = 100
    metres_per_pixel: float = 0.1
    forward_offset: float = 7.5

    @property
    def extent(self) -> float:
        """Side of the square grid on the road (forward and across), metres."""
        return self.size * self.metres_per_pixel

    @property
    def centre(self) -> tuple[float, float]:
        """Road-frame (x, y) of the BEV centre, metres."""
        return (self.forward_offset + self.extent / 2.0, 0.0)

    def ground_points(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
        """Road-frame (x, y) of every pixel centre. -> ``(size, size, 2)``, indexed [row, col]."""
        idx = torch.arange(self.size, dtype=dtype, device=device)
        x = self.forward_offset + (self.size - 0.5 - idx) * self.metres_per_pixel
        y = ((self.size - 1) / 2.0 - idx) * self.metres_per_pixel
        xx, yy = torch.meshgrid(x, y, indexing="ij")
        return torch.stack([xx, yy], dim=-1)
