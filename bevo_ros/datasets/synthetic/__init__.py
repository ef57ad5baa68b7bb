"""Synthetic data with exact ground truth, one concept per module: the procedural road (``ground``), the
drive's analytic motion and presets (``motion``), IMU errors (``imu``), camera rendering and the true
BEV (``render``), their assembly into a :class:`SyntheticDrive` (``drive``), a real drive's OXTS (IMU,
motion) with that camera (``oxts_drive``), other vehicles in the images (``traffic``), and aerial maps of the same ground (``aerial_map``). The drive's public names are importable from here."""
from bevo_ros.datasets.synthetic.ground import RoadGround, default_ground, ground_intensity
from bevo_ros.datasets.synthetic.motion import GRAVITY, PRESETS, REVERSING_PRESETS
from bevo_ros.datasets.synthetic.imu import ImuNoise
from bevo_ros.datasets.synthetic.render import (RenderOptions, RoadProfile, camera_pose_world, ground_patch,
                                                kitti_like_camera, render_frame, render_view, true_bev)
from bevo_ros.datasets.synthetic.drive import (LazyImages, SyntheticDrive, base_poses_4x4, camera_poses_4x4,
                                               make_drive, preset_drive)
from bevo_ros.datasets.synthetic.oxts_drive import drive_from_oxts
from bevo_ros.datasets.synthetic.traffic import TrafficOptions

__all__ = [
    "GRAVITY", "ImuNoise", "LazyImages", "PRESETS", "REVERSING_PRESETS", "RenderOptions", "RoadGround", "RoadProfile", "SyntheticDrive", "TrafficOptions", "base_poses_4x4",
    "camera_pose_world", "camera_poses_4x4", "default_ground", "drive_from_oxts", "ground_intensity", "ground_patch",
    "kitti_like_camera", "make_drive", "preset_drive", "render_frame", "render_view", "true_bev",
]
