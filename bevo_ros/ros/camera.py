"""Camera calibration from sensor_msgs/CameraInfo (or the ``camera.*`` parameters).

The engine needs a pinhole camera without distortion. A CameraInfo gives it directly when the
images are rectified (image_pipeline's ``image_rect``: use ``P[:3, :3]``); for distorted images
(``D`` non-zero on an unrectified topic) the OpenCV undistortion maps are built once per
CameraInfo and every image is remapped into the camera ``P`` (or ``K``) describes.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

UNDISTORT_MODES = ("auto", "on", "off")
# distortion_model -> OpenCV family (REP-104 / sensor_msgs/distortion_models.hpp names)
_PINHOLE_MODELS = ("plumb_bob", "rational_polynomial")
_PINHOLE_COEFFICIENTS = (4, 5, 8, 12, 14)  # what cv2.initUndistortRectifyMap takes
_FISHEYE_MODELS = ("equidistant",)


class CalibrationError(ValueError):
    """A CameraInfo the node cannot use (message says why and what to do)."""


@dataclass
class Calibration:
    """Intrinsics of the images the engine sees, and how to make them.

    K: ``(3, 3)`` pinhole matrix of the (undistorted) image; width/height in px.
    maps: OpenCV ``remap`` maps from the raw image, or None when the image is used as it is.
    source: where it came from, for the log and /diagnostics.
    """

    K: np.ndarray
    width: int
    height: int
    source: str
    maps: tuple[np.ndarray, np.ndarray] | None = None
    key: tuple = field(default=(), repr=False)  # identity of the CameraInfo it was built from

    def describe(self) -> str:
        K = self.K
        text = (f"{self.source}: {self.width}x{self.height} fx={K[0, 0]:.3f} fy={K[1, 1]:.3f} "
                f"cx={K[0, 2]:.3f} cy={K[1, 2]:.3f}")
        return text + (", undistorting every image (OpenCV remap)" if self.maps is not None else "")

    def size_problem(self, img: np.ndarray) -> str | None:
        """Why ``img (H, W)`` cannot be used with this calibration (another size), or None. Checked
        before :meth:`rectify`: its remap returns any image at the maps' size."""
        if (img.shape[1], img.shape[0]) == (self.width, self.height):
            return None
        return (f"is {img.shape[1]}x{img.shape[0]} but the calibration is {self.width}x{self.height} "
                f"(from {self.source})")

    def rectify(self, img: np.ndarray) -> np.ndarray:
        """``(H, W)`` uint8 raw image -> ``(H, W)`` uint8 undistorted (identity without maps)."""
        if self.maps is None:
            return img
        import cv2

        return cv2.remap(img, self.maps[0], self.maps[1], interpolation=cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def is_rectified_topic(topic: str) -> bool:
    """image_pipeline naming: ``.../image_rect`` and ``.../image_rect_color`` are rectified."""
    return topic.rstrip("/").rsplit("/", 1)[-1].startswith("image_rect")


def _key(msg: Any) -> tuple:
    # NaN never equals itself: a field the calibration ignores holding one made every repeat of the
    # same message a new calibration (rebuilt and logged at the camera's rate)
    def rounded(v, decimals: int) -> tuple:
        return tuple(np.round(np.nan_to_num(np.asarray(v, dtype=np.float64), nan=1e30, posinf=1e31, neginf=-1e31), decimals))

    return (int(msg.width), int(msg.height), str(msg.distortion_model), rounded(msg.d, 12), rounded(msg.k, 9),
            rounded(msg.r, 12), rounded(msg.p, 9))


def same_camera_info(calib: Calibration | None, msg: Any) -> bool:
    return calib is not None and calib.key == _key(msg)


def calibration_from_camera_info(msg: Any, use_p: bool = True, undistort: str = "auto",
                                 image_topic: str = "camera/image_rect", source: str = "CameraInfo") -> Calibration:
    """sensor_msgs/CameraInfo -> :class:`Calibration`.

    ``undistort``: ``auto`` undistorts when ``D`` is non-zero and the image topic is not a
    rectified one (``image_rect*``: those images were rectified by image_proc with this very
    CameraInfo, so ``P`` describes them); ``on`` undistorts whenever ``D`` is non-zero; ``off``
    never does (the images must be rectified).

    Raises:
        CalibrationError: no valid camera matrix or size, or a distortion model OpenCV's
            pinhole/fisheye undistortion does not cover.
    """
    from bevo_ros.io.ros_conversions import camera_info_intrinsics

    if undistort not in UNDISTORT_MODES:
        raise CalibrationError(f"undistort must be one of {UNDISTORT_MODES}, got {undistort!r}")
    try:
        M, w, h = camera_info_intrinsics(msg, use_p)
    except ValueError as exc:
        raise CalibrationError(str(exc)) from None
    D = np.asarray(msg.d, dtype=np.float64).reshape(-1)
    distorted = D.size > 0 and bool(np.any(D != 0.0))
    wanted = distorted and (undistort == "on" or (undistort == "auto" and not is_rectified_topic(image_topic)))
    if not wanted:
        return Calibration(M, w, h, source, None, _key(msg))
    if not np.all(np.isfinite(D)):
        raise CalibrationError(f"CameraInfo D has NaN/inf: {D.tolist()}")
    K = np.asarray(msg.k, dtype=np.float64).reshape(3, 3)
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
        raise CalibrationError("CameraInfo D is non-zero but K is not a valid camera matrix: cannot undistort")
    R = np.asarray(msg.r, dtype=np.float64).reshape(3, 3)
    if not np.any(R):
        R = np.eye(3)
    # R rotates the rectified frame: NaN in it remapped every image to black with the calibration "OK"
    if not (np.all(np.isfinite(R)) and np.allclose(R @ R.T, np.eye(3), rtol=0, atol=1e-3) and np.linalg.det(R) > 0):
        raise CalibrationError(f"CameraInfo R is not a rotation: {np.round(R, 6).tolist()}")
    P = np.asarray(msg.p, dtype=np.float64).reshape(3, 4)
    if not np.all(np.isfinite(P[:, :3])):
        raise CalibrationError(f"CameraInfo P has NaN/inf: {P.tolist()}")
    new_K = P[:, :3].copy() if P[0, 0] > 0 and P[1, 1] > 0 else K.copy()
    import cv2

    model = str(msg.distortion_model)
    if model in _PINHOLE_MODELS:
        if D.size not in _PINHOLE_COEFFICIENTS:  # OpenCV raises (cv2.error) for any other count
            raise CalibrationError(f"{model} distortion with {D.size} coefficients in CameraInfo D: OpenCV takes "
                                   f"{', '.join(map(str, _PINHOLE_COEFFICIENTS))}")
        maps = cv2.initUndistortRectifyMap(K, D, R, new_K, (w, h), cv2.CV_16SC2)
    elif model in _FISHEYE_MODELS:
        if D.size < 4:
            raise CalibrationError(f"equidistant distortion needs 4 coefficients, CameraInfo D has {D.size}")
        maps = cv2.fisheye.initUndistortRectifyMap(K, D[:4], R, new_K, (w, h), cv2.CV_16SC2)
    else:
        raise CalibrationError(
            f"CameraInfo distortion_model '{model}' with non-zero D is not supported (supported: "
            f"{', '.join(_PINHOLE_MODELS + _FISHEYE_MODELS)}): publish rectified images (image_proc) and set "
            "undistort: off")
    return Calibration(new_K, w, h, f"{source} ({model}, undistorted)", maps, _key(msg))


def calibration_from_parameters(settings) -> Calibration:
    """The ``camera.*`` parameters (:class:`bevo_ros.config.CameraSettings`) as a Calibration."""
    K = np.array([[settings.fx, 0.0, settings.cx], [0.0, settings.fy, settings.cy], [0.0, 0.0, 1.0]])
    return Calibration(K, int(settings.width), int(settings.height_px), "parameters camera.*")
