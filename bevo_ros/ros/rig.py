"""The rig as the node sees it: which camera calibration and extrinsics the engine uses, and how
each IMU frame maps into ``base_frame``.

Calibration: CameraInfo first (re-read when it changes; a broken one is a counted drop that keeps
the last good calibration), the ``camera.*`` parameters as the fallback after
``camera_info_timeout`` s without it. Images that arrive before any calibration are held (bounded)
and handed back once it is known: DDS does not order one topic against another, so a frame's
CameraInfo may come after the frame itself. Extrinsics: /tf_static ``base_frame -> image frame`` when
published, else ``camera.base_T_camera``. Every change rebuilds the camera model and hands it to
``on_camera`` (the node's engine). ``engine_input`` turns a raw input into the engine's with the rig
known then (the IMU into base axes, an image decoded and rectified), and ``imu_axes_changed`` says
when an IMU frame's axes changed since its last sample went in.
"""
from __future__ import annotations

import collections
import dataclasses
import time
from typing import Any, Callable

import numpy as np

from bevo_ros.config import BevoConfig, ConfigError, camera_model
from bevo_ros.core.validation import intrinsics_problem
from bevo_ros.io.static_tf import PARAMETERS_EXTRINSICS, camera_extrinsics, imu_axes
from bevo_ros.ros.camera import (Calibration, CalibrationError, calibration_from_camera_info,
                                 calibration_from_parameters, same_camera_info)
from bevo_ros.ros.diagnostics import ERROR, OK, WARN, Report, SensorState
from bevo_ros.ros.settings import NodeSettings
from bevo_ros.ros.tf import StaticTransforms
from bevo_ros.io.ros_conversions import ImageConversionError, image_to_gray, stamp_to_sec



MAX_IMU_FRAMES = 64  # IMU frame ids whose axes are watched for a change


def same_axes(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    """Two IMU rotations (None: the base's axes) turn every vector alike."""
    if a is b:  # the cached rotation of an unchanged /tf_static: no comparison per sample
        return True
    return np.allclose(np.eye(3) if a is None else a, np.eye(3) if b is None else b, rtol=0, atol=1e-12)


class Rig:
    """Calibration, camera extrinsics and IMU axes; ``camera`` is None until a calibration is known.

    Args:
        settings, config: the node's settings and engine configuration.
        report: where drops and log lines go.
        logger: the node's logger (one-off info lines).
        static_tf: /tf_static lookups, or None (``extrinsics_from_tf`` false).
        info_topic: the resolved CameraInfo topic (for messages).
        queued_infos: CameraInfo messages already received, taken now (the ordered intake).
        on_camera: called with every new camera model.
    """

    def __init__(self, settings: NodeSettings, config: BevoConfig, report: Report, logger,
                 static_tf: StaticTransforms | None, info_topic: str,
                 queued_infos: Callable[[], list], on_camera: Callable[[Any], None]) -> None:
        self.settings, self.config, self.report, self.logger = settings, config, report, logger
        self.static_tf, self.info_topic = static_tf, info_topic
        self._queued_infos, self._on_camera = queued_infos, on_camera
        self.calibration: Calibration | None = None
        self.camera = None  # the CameraModel handed to on_camera
        self.extrinsics_source = PARAMETERS_EXTRINSICS
        self._base_T_camera: np.ndarray | None = None
        self._camera_frame = ""  # header.frame_id of the images (for /tf_static)
        self._tf_version = -1  # /tf_static tree version the camera was built with
        self._image_size: tuple[int, int] | None = None  # (width, height) of the last decoded image
        self._first_image_wait: float | None = None  # steady time of the first image seen without calibration
        self._R_base_imu: dict[str, tuple[int, np.ndarray | None]] = {}  # IMU frame -> (tf version, R_base_imu)
        self._imu_frame_warned: set[str] = set()
        self._held: collections.deque = collections.deque()  # (msg, arrival) of images before any calibration
        self._axes_used: dict[str, np.ndarray | None] = {}  # IMU frame -> the rotation its last sample went in with

    def start(self) -> None:
        """The calibration known at start: the parameters when CameraInfo is off or not waited for."""
        s, cam = self.settings, self.config.camera
        if not s.use_camera_info:
            if not cam.has_intrinsics():
                raise ConfigError("camera intrinsics are not set (camera.fx, fy, cx, cy, width, height_px) and "
                                  "use_camera_info is false: set them or enable use_camera_info")
            self.apply(calibration_from_parameters(cam))
        elif s.camera_info_timeout == 0 and cam.has_intrinsics():
            self.apply(calibration_from_parameters(cam))

    # ------------------------------------------------------------------ calibration
    def apply(self, calib: Calibration) -> None:
        """Use ``calib`` from now on; the log says where it came from."""
        self.calibration = calib
        self.logger.info(f"camera calibration from {calib.describe()}")
        self.refresh(force=True)

    def camera_info(self, msg) -> None:
        """A CameraInfo (counted): a new calibration when it differs and is usable, else a counted drop."""
        self.report.counts["camera_info_in"] += 1
        if same_camera_info(self.calibration, msg):
            return
        s = self.settings
        try:
            calib = calibration_from_camera_info(msg, s.camera_info_use_p, s.undistort, s.image_topic,
                                                 source=f"CameraInfo on {self.info_topic}")
        except CalibrationError as exc:
            self.report.drop("bad_camera_info", str(exc))
            return
        w, h = calib.width, calib.height
        problem = intrinsics_problem(calib.K, w, h)
        if problem is None and self._image_size not in (None, (w, h)):
            problem = f"its size {w}x{h} disagrees with the images ({self._image_size[0]}x{self._image_size[1]})"
        if problem is not None:
            keep = "keeping the last good calibration" if self.camera is not None else "still waiting for a valid one"
            self.report.drop("bad_camera_info", f"CameraInfo rejected ({keep}): {problem}")
            return
        self.apply(calib)

    def await_calibration(self) -> None:
        """No camera yet: read a CameraInfo already queued, else fall back to the parameters after
        ``camera_info_timeout`` seconds since the first image."""
        if self.calibration is not None:  # known (a camera model failing on its extrinsics is not a missing one)
            return
        s = self.settings
        for msg, _ in self._queued_infos():
            self.camera_info(msg)
        if self.calibration is not None:
            return
        now = time.monotonic()
        if self._first_image_wait is None:
            self._first_image_wait = now
        if s.use_camera_info and now - self._first_image_wait >= s.camera_info_timeout and \
                self.config.camera.has_intrinsics():
            self.report.events["camera_info_timeout"] += 1
            self.logger.warning(
                f"no CameraInfo on {self.info_topic} within camera_info_timeout={s.camera_info_timeout:g} s of the "
                "first image: using the camera.* parameters (a CameraInfo arriving later replaces them)")
            self.apply(calibration_from_parameters(self.config.camera))

    # ------------------------------------------------------------------ extrinsics
    def _extrinsics(self) -> tuple[np.ndarray, str]:
        """``(base_T_camera (4, 4), source)``: /tf_static ``base_frame -> image frame`` when known."""
        return camera_extrinsics(self.static_tf, self.settings.base_frame, self._camera_frame,
                                 self.config.camera.base_T_camera)

    def refresh(self, force: bool = False) -> None:
        """(Re)build the camera model when the calibration or the camera's static TF changed."""
        if self.calibration is None:
            return
        T, source = self._extrinsics()
        old = self._base_T_camera
        if not force and old is not None and np.allclose(old, T, rtol=0, atol=1e-9):
            return
        calib = self.calibration
        settings = dataclasses.replace(self.config.camera, base_T_camera=T.reshape(-1).tolist())
        try:
            camera = camera_model(settings, K=calib.K, width=calib.width, height_px=calib.height)
        except ConfigError as exc:  # e.g. a non-rigid transform on /tf_static
            self.report.drop("bad_extrinsics", f"camera extrinsics from {source} unusable: {exc}", level="error")
            return
        if source != self.extrinsics_source or (old is not None and not np.allclose(old, T, rtol=0, atol=1e-9)):
            self.logger.info(f"camera extrinsics from {source}: camera at "
                             f"{np.round(T[:3, 3], 3).tolist()} m in {self.settings.base_frame}")
        self._base_T_camera, self.extrinsics_source = T, source
        self._on_camera(camera)
        self.camera = camera

    def imu_rotation(self, frame: str) -> np.ndarray | None:
        """Rotation taking vectors from the IMU's ``frame`` into ``base_frame`` (None: same axes)."""
        base = self.settings.base_frame
        frame = frame.lstrip("/")
        if not frame or frame == base.lstrip("/"):
            return None
        cached = self._R_base_imu.get(frame)
        if cached is None and len(self._R_base_imu) >= MAX_IMU_FRAMES:  # a stream of bogus frame ids stays bounded
            self._R_base_imu.clear()
            self._imu_frame_warned.clear()
        version = 0
        if self.static_tf is not None:
            if cached is None or cached[1] is None:
                self.static_tf.poll()  # still unknown: a /tf_static already received counts now
            version = self.static_tf.version
        if cached is not None and cached[0] == version:
            return cached[1]
        R = imu_axes(self.static_tf, base, frame)
        if R is not None and not np.isfinite(R).all():  # a degenerate /tf_static rotation: unknown, not NaN rates
            R = None
        self._R_base_imu[frame] = (version, R)
        if R is not None:
            if cached is None or cached[1] is None or not np.allclose(cached[1], R, rtol=0, atol=1e-12):
                self.logger.info(f"IMU frame '{frame}': rates and accelerations rotated into '{base}' "
                                 f"(/tf_static), rotation {np.round(R, 4).tolist()}")
        elif frame not in self._imu_frame_warned:
            self._imu_frame_warned.add(frame)
            self.report.log("imu_frame", f"IMU frame '{frame}' is not base_frame '{base}' and /tf_static has no "
                                         f"{base} -> {frame}: the IMU axes are taken as the base axes (REP-103 x "
                                         "forward, y left, z up)")
        return R

    def imu_axes_changed(self, frame: str) -> bool:
        """``frame``'s axes (/tf_static) differ from those its last sample went into the engine with."""
        if frame not in self._axes_used:
            return False
        return not same_axes(self.imu_rotation(frame), self._axes_used[frame])

    def engine_input(self, kind: str, t: float, raw: Any) -> tuple | None:
        """An input as the engine takes it, through the rig known now (the node's EngineFeed
        ``inputs``): ``imu`` ``(frame, gyro, accel)`` into base_frame axes, ``image`` a message
        decoded and rectified (None: dropped, counted)."""
        if kind != "imu":
            img = self.image(raw, t)
            return None if img is None else (img,)
        frame, gyro, accel = raw
        R = self.imu_rotation(frame)
        if frame not in self._axes_used and len(self._axes_used) >= MAX_IMU_FRAMES:
            self._axes_used.clear()  # a stream of bogus frame ids stays bounded
        self._axes_used[frame] = R
        # an IMU mounted in another orientation (e.g. z down): into base_frame axes
        return (gyro, accel) if R is None else (R @ gyro, R @ accel)

    # ------------------------------------------------------------------ images
    def calibrated_for(self, msg) -> bool:
        """Whether images like ``msg`` can be processed now: its frame's extrinsics are current and a
        calibration is known (a CameraInfo already queued, or the parameters after the timeout)."""
        frame = msg.header.frame_id
        tf_version = -1
        if self.static_tf is not None:
            self.static_tf.poll()
            tf_version = self.static_tf.version
        if (frame and frame != self._camera_frame) or tf_version != self._tf_version:
            self._camera_frame, self._tf_version = frame or self._camera_frame, tf_version
            self.refresh()
        self.await_calibration()
        return self.camera is not None

    @property
    def held_images(self) -> int:
        return len(self._held)

    def hold(self, msg, t: float, arrival: float) -> None:
        """Keep an image (stamp ``t``) that came before any calibration until one is known; beyond
        ``max_pending_images`` the oldest is dropped (``no_camera_info``, counted)."""
        self._held.append((msg, arrival))
        if len(self._held) == 1:
            self.report.log("waiting_for_calibration", f"image at {t:.6f} held: no calibration yet (waiting for "
                                                       f"CameraInfo on {self.info_topic}; {self._fallback()})",
                            level="info")
        while len(self._held) > self.settings.max_pending_images:
            old, _ = self._held.popleft()
            self.report.drop("no_camera_info", f"image at {stamp_to_sec(old.header.stamp):.6f}: no calibration "
                                               f"while more than max_pending_images={self.settings.max_pending_images} "
                                               f"images waited for one (CameraInfo on {self.info_topic}; "
                                               f"{self._fallback()})")

    def take_held(self) -> list:
        """The held ``(msg, arrival)`` images, oldest first: for the first camera model, as
        :meth:`refresh` hands it over (``on_camera``)."""
        out = list(self._held)
        self._held.clear()
        return out

    def drop_held(self, why: str) -> None:
        """Drop the held images (counted ``no_camera_info``): they belong to a trajectory that was reset."""
        if self._held:
            self.report.drop("no_camera_info", f"{len(self._held)} held image(s): {why}", count=len(self._held))
            self._held.clear()

    def _fallback(self) -> str:
        if self.config.camera.has_intrinsics():
            return f"camera.* parameters after camera_info_timeout={self.settings.camera_info_timeout:g} s"
        return "no camera.* fallback set"

    def image(self, msg, t: float) -> np.ndarray | None:
        """The grey, rectified image of ``msg`` (stamp ``t``; :meth:`calibrated_for` said yes), or
        None when it was dropped (counted): an undecodable image, or a size other than the calibration's."""
        try:
            img = image_to_gray(msg)
        except ImageConversionError as exc:
            self.report.drop(exc.reason, f"image at {t:.6f}: {exc}")
            return None
        self._image_size = (img.shape[1], img.shape[0])
        calib = self.calibration
        if (problem := calib.size_problem(img)) is not None:
            self.report.drop("bad_image_size", f"image at {t:.6f} {problem}")
            return None
        return calib.rectify(img)

    # ------------------------------------------------------------------ diagnostics
    def state(self) -> SensorState:
        """Where the camera model comes from: OK from CameraInfo (or the parameters when chosen with
        use_camera_info false), WARN while waiting or when the parameters stand in for CameraInfo."""
        s, calib = self.settings, self.calibration
        values = {"intrinsics": calib.source if calib else "none yet", "extrinsics": self.extrinsics_source,
                  "undistorting": str(bool(calib and calib.maps is not None)).lower(),
                  "imu_frames": ", ".join(f"{f}: {'tf' if r[1] is not None else 'as base'}"
                                          for f, r in sorted(self._R_base_imu.items())) or "base_frame"}
        if calib is None:
            return SensorState(WARN, f"waiting for CameraInfo on {self.info_topic}", values)
        if self.camera is None:  # calibrated, but no camera model could be built from it (the extrinsics)
            return SensorState(ERROR, f"{calib.describe()}, but the camera extrinsics from "
                                      f"{self.extrinsics_source} are unusable: no odometry", values)
        if s.use_camera_info and not calib.source.startswith("CameraInfo"):
            return SensorState(WARN, "no CameraInfo: the camera.* parameters stand in for it", values)
        return SensorState(OK, calib.describe(), values)


__all__ = ["Rig", "PARAMETERS_EXTRINSICS"]
