"""Settings: the one place that reads and writes them (learned parameters: ``bevo_ros.io.learned_params``).

* ``BevoConfig``: everything the engine needs (camera, extrinsics, BEV grid, filters), built
  from a ROS 2 parameters file (``params/*.yaml``) or from the node's declared parameters, so
  ``bevo_node`` and the offline `bevo` commands read the very same file the same way.
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable

import numpy as np
import yaml

if TYPE_CHECKING:
    from bevo_ros.io.learned_params import LearnedParams

from bevo_ros.core.dpc_config import DpcConfig

REPO_ROOT = Path(__file__).resolve().parents[1]


class ConfigError(ValueError):
    """A parameters or learned-parameters file is missing or malformed."""


# --------------------------------------------------------------------------- settings
@dataclass
class CameraSettings:
    """Pinhole intrinsics of the rectified image; 0 means "take them from CameraInfo"."""

    fx: float = 0.0
    fy: float = 0.0
    cx: float = 0.0
    cy: float = 0.0
    width: int = 0
    height_px: int = 0
    # Camera centre height above the road (m): the paper's constant-elevation assumption.
    mount_height: float = 1.65
    # Camera (optical frame) pose in the base/IMU frame, 4x4 row-major. Default: KITTI's rig
    # (2011_09_26 chain imu -> velo -> cam0 -> R_rect_00), see params/kitti.yaml.
    base_T_camera: list[float] = field(
        default_factory=lambda: [
            0.0, 0.0, 1.0, 1.08,
            -1.0, 0.0, 0.0, -0.32,
            0.0, -1.0, 0.0, 0.73,
            0.0, 0.0, 0.0, 1.0,
        ]
    )

    def has_intrinsics(self) -> bool:
        return self.fx > 0 and self.fy > 0 and self.width > 0 and self.height_px > 0


@dataclass
class BevSettings:
    size: int = 100
    metres_per_pixel: float = 0.1
    forward_offset: float = 7.5


MOUNTING_REFERENCES = ("base", "camera")  # filter.mounting_reference


@dataclass
class FilterSettings:
    # "euler": exact Euler-angle kinematics (default); "additive": the paper's rates-added model.
    motion_model: str = "euler"
    # Low-pass time constant (s) separating road camber/slope from vehicle attitude; 0 disables.
    road_tilt_time_constant: float = 1.0
    # Longest IMU gap (s) the filter predicts across; longer gaps re-initialise from the accelerometer.
    max_imu_gap: float = 0.5
    # Static attitude of the base frame relative to the road when the vehicle rests on a level road
    # (rad; positive pitch = nose down). The road-tilt low-pass removes every constant, so the
    # mounting tilt of the IMU/camera rig relative to the road must be given here (used only with
    # the low-pass on: without it the gravity-referenced attitude already holds the mounting).
    mounting_pitch: float = 0.0
    mounting_roll: float = 0.0
    # What the mounting holds when the camera's extrinsics come from elsewhere than camera.base_T_camera
    # (the node's /tf_static). "base": the base's attitude on the road, as given. "camera": the camera's
    # tilt to the road that the mounting makes through camera.base_T_camera (what `bevo calibrate`
    # measures: the road plane as the camera sees it); with other extrinsics the base's is re-derived
    # (core/geometry.mounting_for_extrinsics). KITTI's raw calibrations differ by ~1 deg of camera pitch
    # from day to day: a mounting calibrated through one day's files, used as "base" with another's,
    # tilts the BEV by that much (the sample: 21.6 % drift instead of 2.5 %).
    mounting_reference: str = "base"
    # Remove speed x turn rate (centripetal acceleration) from the accelerometer before the DUKF
    # update, with the visual odometry's latest speed. Off by default: it cuts the synthetic roll
    # error from 5.7 to 0.6 deg RMS, but the odometry got worse there (pitch), see the issue notes.
    turn_compensation: bool = False
    # IMU plausibility limits (core/validation.py ImuLimits): samples beyond them are dropped
    # with the reason. Specific-force norm (m/s^2, 8 g) and any gyro axis (rad/s, ~2000 deg/s).
    max_acceleration: float = 78.45
    max_angular_rate: float = 35.0
    # Fused mode: what a gyro sample is. "interval_mean": the mean rate over the interval since the
    # previous sample (KITTI's OXTS: its pitch change over an interval is the end sample times the
    # interval to 0.02 deg, the trapezoid misses by 0.05-0.07 deg; IMUs reporting delta angles).
    # "instantaneous": the rate at the stamp (integrated by the quadratic rule), what many ROS IMU
    # drivers publish (a filtered angular_velocity): set it for those, it matters at 10-50 Hz.
    # core/rate_integration.
    gyro_sampling: str = "interval_mean"
    # Fused mode: the pitch and roll gyro's bias between stops (core/gyro_bias.py), a bias state beside
    # the DUKF that its accelerometer innovations observe: the bias's prior standard deviation (rad/s;
    # a factory-calibrated MEMS part's turn-on bias, ~0.1 deg/s) and its random walk (rad/s/sqrt(s)).
    # 0 leaves the bias to the stops the images confirm (item 9).
    gyro_bias_std: float = 0.002
    gyro_bias_walk: float = 2e-4
    # The camera's tilt to the road measured at the start from the images (core/start_tilt.py): the
    # engine holds its inputs until this many frame pairs have shown their direction of travel (their
    # epipolar geometry), runs them at the base pitch that puts that direction in the road's plane, and
    # keeps it (the roll stays mounting_roll). The first pose comes that many frames late; a start with
    # too few pairs in tilt_hold_frames images keeps mounting_pitch. For rigs whose tilt changes with the
    # load or between calibrations (KITTI's days: up to 1.5 deg, ~2 % of scale per 0.1 deg). 0: off,
    # mounting_pitch as is. Needs the road-tilt low-pass (road_tilt_time_constant > 0).
    tilt_from_images: int = 0
    tilt_hold_frames: int = 150


@dataclass
class OdometrySettings:
    # "fused" (default): vehicle-acceleration-aware attitude, gyro yaw, vehicle motion filter with
    # gates. "paper": the paper's pipeline (accelerometer = gravity, correlation composed as is).
    mode: str = "fused"
    # Fused mode: a correlation peak quality below this marks a frame without information (black,
    # covered, overexposed): rejected and counted, the pose carried by the motion filter.
    min_quality: float = 0.05
    # Fused mode: Mahalanobis distance (sigmas) beyond which a frame's measurement is rejected.
    gate: float = 5.0
    # Fused mode: a frame whose images turn more than this (rad) away from the bias-corrected gyro
    # (plus 1 deg/s and 3 x the bias estimate's standard deviation, times the frame interval) is no
    # measurement of the yaw gyro's bias: something else turned in the BEV (a car ahead)
    # (core/vehicle_filter.py).
    rotation_gate: float = 0.00524
    # Fused mode: the DUKF starts at the mounting attitude with this standard deviation (rad).
    initial_attitude_std: float = 0.0524
    # Fused mode: remove from each frame's forward motion the shift that the engine's own change of
    # the BEV pitch between the two frames (road-tilt low-pass, suspension model) puts into it
    # (core/motion.pitch_change_shift).
    pitch_change_correction: bool = True
    # Fused mode: frames in the running mean frame period that replaces jittered stamp intervals in
    # the motion filter (core/frame_clock.py); 0 takes the stamps as they are.
    frame_clock_window: int = 20
    # Fused mode: a frame whose correlation reads little forward motion is checked for standstill on
    # the raw images (core/standstill.py: the small motion over the road region by brightness
    # constancy); below this speed (m/s) over the frame interval the vehicle is at rest: zero
    # motion, the gyro's biases observed. 0 disables the check.
    standstill_max_speed: float = 0.1
    # Fused mode: the direction of travel is forward from the start and changes only at a standstill
    # the images confirm; the correlation's peak is taken among shifts of that direction (the car
    # ahead pulling away reads as reversing). Off for a vehicle that reverses without stopping.
    direction_lock: bool = True
    # Frames stamped less than this (s) after the last processed one are skipped (counted; no
    # odometry for them): the per-frame constants were learned at 10 Hz, and a faster camera does
    # worse frame by frame than its own frames thinned to 10 Hz (synthetic, 300 Hz IMU, per 0.1 s:
    # stop_and_go 6.44 % at 30 Hz, 4.06 % with 0.09; README). ~0.09 for a 20-30 Hz camera; 0
    # processes every frame (KITTI's 10 Hz frames come 0.07-0.13 s apart by the OXTS clock).
    min_frame_interval: float = 0.0
    # Added to every IMU stamp to put it on the images' clock (s): an IMU whose clock runs ahead of
    # the camera's by d takes -d. A few ms matter (synthetic urban, 100 Hz IMU: 5.8 % per frame, at
    # 10 ms of offset 15 %): the attitude each image is projected with is the IMU's at its stamp.
    # `bevo calibrate BAG --imu-time-offset` measures it.
    imu_time_offset: float = 0.0


@dataclass
class BevoConfig:
    camera: CameraSettings = field(default_factory=CameraSettings)
    bev: BevSettings = field(default_factory=BevSettings)
    filter: FilterSettings = field(default_factory=FilterSettings)
    odometry: OdometrySettings = field(default_factory=OdometrySettings)
    # Phase correlation (core.dpc_config.DpcConfig): the engine's defaults; training sets its own
    # softmax temperatures on top (LOSS_TEMPERATURE).
    dpc: DpcConfig = field(default_factory=DpcConfig)
    # Learned O/Q file; relative paths resolve against the parameters file, then the package.
    learned_params_file: str = "params/learned_default.yaml"
    # "cpu" or "cuda" ("cuda" falls back to CPU with a warning when unavailable).
    device: str = "cpu"
    # The engine's vision kernels (core/compiled.py): "eager" (default: the pinned, bit-reproducible
    # numbers), "compiled" (torch.compile; equal to float32 rounding, the first two frames pay the
    # compilation, seconds) or "auto" (compiled when a C++ compiler is found). README: Benchmarks.
    kernels: str = "eager"

    # ---- flat "a.b" views, the shape ROS parameters take
    def to_flat(self) -> dict[str, Any]:
        return _flatten(dataclasses.asdict(self))

    @classmethod
    def from_flat(cls, flat: dict[str, Any], source: str = "parameters",
                  warn: Callable[[str], None] | None = None) -> "BevoConfig":
        """Build from ``{"camera.fx": ..., ...}``; unknown keys are ignored, bad types raise; a
        renamed key (:data:`RENAMED`) still works, with a warning (``warn``; default a FutureWarning)."""
        return _from_flat(cls, _renamed_keys(flat, source, warn), prefix="", source=source)


# Parameters renamed: old key -> new key. The old one is still read, with a deprecation warning.
RENAMED = {"camera.height": "camera.mount_height"}  # metres above the road, not the image's height_px


def _renamed_keys(flat: dict[str, Any], source: str, warn: Callable[[str], None] | None) -> dict[str, Any]:
    """``flat`` with each old key of :data:`RENAMED` moved to its new name. Both given with different
    values (the new one not at its default: the node declares every key) is an error."""
    if not any(old in flat for old in RENAMED):
        return flat
    flat, defaults = dict(flat), BevoConfig().to_flat()
    for old, new in RENAMED.items():
        if old not in flat:
            continue
        value = flat.pop(old)
        if new in flat and flat[new] != defaults[new] and flat[new] != value:
            raise ConfigError(f"{source}: '{old}' = {value!r} and '{new}' = {flat[new]!r}: '{old}' is the old name "
                              f"of '{new}'; set only '{new}'")
        msg = f"{source}: parameter '{old}' is deprecated, renamed '{new}'; using its value {value!r}"
        if warn is None:
            warnings.warn(msg, FutureWarning, stacklevel=4)
        else:
            warn(msg)
        flat[new] = value
    return flat


def _flatten(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(_flatten(value, name + "."))
        else:
            out[name] = list(value) if isinstance(value, tuple) else value  # ROS arrays are lists
    return out


def _from_flat(cls: type, flat: dict[str, Any], prefix: str, source: str) -> Any:
    kwargs: dict[str, Any] = {}
    defaults = cls()
    for f in dataclasses.fields(cls):
        name = prefix + f.name
        default = getattr(defaults, f.name)
        if dataclasses.is_dataclass(default):
            kwargs[f.name] = _from_flat(type(default), flat, name + ".", source)
        elif name in flat:
            kwargs[f.name] = coerce_setting(flat[name], default, name, source)
    try:
        return cls(**kwargs)
    except ValueError as exc:  # a section's own checks (DpcConfig.__post_init__)
        raise ConfigError(f"{source}: {prefix.rstrip('.') or 'settings'}: {exc}") from None


def coerce_setting(value: Any, default: Any, name: str, source: str | None = None) -> Any:
    """``value`` as the type of ``default`` (one rule for parameters files, the node's parameters and
    ``ros2 param set``): a bool only from a bool; an int from an integral number; a float from a
    finite number (an int written for a float is fine, a bool is not); a list of floats of the
    default's length; a string only from a string. Raises ConfigError naming ``name`` (and ``source``)."""
    try:
        if isinstance(default, bool):
            if isinstance(value, bool):
                return value
        elif isinstance(default, int):
            if not isinstance(value, bool) and int(value) == value:
                return int(value)
        elif isinstance(default, float):
            if not isinstance(value, bool) and math.isfinite(float(value)):
                return float(value)
        elif isinstance(default, (list, tuple)):  # a tuple default (hashable settings) stays a tuple
            out = [float(v) for v in value]
            if len(out) == len(default) and not any(isinstance(v, bool) for v in value):
                return type(default)(out)
        elif isinstance(value, str):
            return value
    except (TypeError, ValueError, OverflowError):  # int(inf): an infinite count
        pass
    # YAML 1.1 reads a bare on / off / yes / no as a bool: where text is expected, say how to write it
    hint = (f" (YAML reads a bare {'on' if value else 'off'} as true/false: quote it, '{'on' if value else 'off'}')"
            if isinstance(value, bool) and isinstance(default, str) else "")
    raise ConfigError((f"{source}: " if source else "") + f"parameter '{name}' = {value!r} is not a valid "
                      f"{type(default).__name__}" + (f" of length {len(default)}" if isinstance(default, (list, tuple))
                                                     else "") + hint)


def read_yaml(path: Path, what: str) -> Any:
    """The YAML document in ``path``; a ConfigError naming ``what`` (e.g. "checkpoint"), the file
    and the problem if it is missing, unreadable or not YAML."""
    try:
        return yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{what} not found: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{what} {path} cannot be read: {exc}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{what} {path} is not valid YAML: {yaml_error_line(exc)}") from None


def yaml_error_line(exc: Exception) -> str:
    """A YAML parser error on one line: ``line L, column C: problem`` (PyYAML's own text spans
    several lines with an excerpt of the file)."""
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None) or getattr(exc, "context", None) or str(exc)
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    return where + " ".join(str(problem).split())


def load_params_file(path: str | os.PathLike, node_name: str = "bevo_node") -> dict[str, Any]:
    """Read a ROS 2 parameters YAML and return the node's parameters flattened to "a.b" keys: the
    wildcard sections' (``/**``) with the node's own section over them, as ROS 2 applies a file."""
    path = Path(path)
    doc = read_yaml(path, "parameters file")
    if not isinstance(doc, dict):
        raise ConfigError(f"parameters file {path}: expected a mapping at the top level")
    flat: dict[str, Any] = {}
    found = False
    for key in ("/**", "**", f"/{node_name}", node_name):  # the more specific last: it wins
        section = doc.get(key)
        if isinstance(section, dict) and isinstance(section.get("ros__parameters"), dict):
            flat.update(_flatten(section["ros__parameters"]))
            found = True
    if not found:
        raise ConfigError(f"parameters file {path}: no '{node_name}: ros__parameters:' section")
    return flat


# Parameters every ROS 2 node has (not bevo_node's own), which a parameters file may set.
ROS_STANDARD_PARAMETERS = ("use_sim_time", "start_type_description_service", "qos_overrides.")


def unknown_parameters(flat: dict[str, Any], known: Iterable[str]) -> list[str]:
    """The keys of ``flat`` that are none of ``known``, the renamed old names or a ROS node's own
    (:data:`ROS_STANDARD_PARAMETERS`), each with the nearest known name when one is close:
    ``"filter.mountng_pitch (did you mean filter.mounting_pitch?)"``."""
    known = set(known) | set(RENAMED)
    out = []
    for key in sorted(flat):
        if key in known or any(key == p or (p.endswith(".") and key.startswith(p)) for p in ROS_STANDARD_PARAMETERS):
            continue
        near = difflib.get_close_matches(key, known, n=1, cutoff=0.8)
        out.append(key + (f" (did you mean {near[0]}?)" if near else ""))
    return out


def load_config(path: str | os.PathLike, node_name: str = "bevo_node") -> tuple[BevoConfig, dict[str, Any]]:
    """``(BevoConfig, all flat parameters)`` from a parameters file; learned path made absolute. A
    parameter bevo_node does not have (a typo: ``filter.mountng_pitch`` would leave the mounting at
    0 and the KITTI sample at 35 % drift) is named in a warning (``UserWarning``, printed once)."""
    flat = load_params_file(path, node_name)
    if node_name == "bevo_node":
        from bevo_ros.ros.settings import defaults  # the node's parameters (no ROS import)

        unknown = unknown_parameters(flat, defaults())
        if unknown:
            warnings.warn(f"{path}: parameter(s) that bevo_node does not have, ignored: {', '.join(unknown)}",
                          UserWarning, stacklevel=2)
    config = BevoConfig.from_flat(flat, source=str(path))
    config.learned_params_file = str(resolve_path(config.learned_params_file, Path(path).resolve().parent))
    return config, flat


def field_comments(cls: type, prefix: str = "") -> dict[str, str]:
    """``{"a.b": comment}``: the ``#`` comment lines right above each field of the settings
    dataclass ``cls`` (and of its nested ones), joined, else the field's entry in the class
    docstring's ``Attributes:`` (the engine's own settings); the settings' documentation in one place."""
    import inspect

    out = _docstring_attributes(cls, prefix)
    try:
        lines = inspect.getsource(cls).splitlines()
    except (OSError, TypeError):  # source not shipped
        lines = []
    pending: list[str] = []
    for line in lines:
        text = line.strip()
        if text.startswith("#"):
            pending.append(text.lstrip("#").strip())
            continue
        name = text.split(":", 1)[0].strip()
        if pending and name.isidentifier() and ":" in text:
            out[prefix + name] = " ".join(pending)
        pending = []
    for f in dataclasses.fields(cls):
        default = getattr(cls(), f.name)
        if dataclasses.is_dataclass(default):
            out.update(field_comments(type(default), f"{prefix}{f.name}."))
    return out


def _docstring_attributes(cls: type, prefix: str) -> dict[str, str]:
    """``{"a.b": text}`` from a Google-style ``Attributes:`` section (``name: text`` or
    ``a, b: text``, continuation lines indented deeper)."""
    import inspect

    doc = inspect.getdoc(cls) or ""
    if "Attributes:" not in doc:
        return {}
    out: dict[str, str] = {}
    names: list[str] = []
    for line in doc.split("Attributes:", 1)[1].splitlines():
        if not line.strip():
            continue
        head, _, text = line.strip().partition(": ")
        keys = [k.strip() for k in head.split(",")]
        if line.startswith("    ") and not line.startswith("        ") and text and all(k.isidentifier() for k in keys):
            names = keys
            for k in names:
                out[prefix + k] = text.strip()
        elif line.startswith("        ") and names:
            for k in names:
                out[prefix + k] += " " + line.strip()
        else:
            break
    return out


def _yaml_scalar(value: Any) -> str:
    """One value as ROS 2 parameter YAML (a float always with a dot: PyYAML reads 1e-05 as text)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        text = repr(value)
        if "e" in text and "." not in text.split("e")[0]:
            mantissa, exponent = text.split("e")
            text = f"{mantissa}.0e{exponent}"
        return text if ("." in text or "e" in text or "n" in text) else text + ".0"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_yaml_scalar(v) for v in value) + "]"
    return yaml.safe_dump(str(value), default_style='"').strip().removesuffix("...").strip()


def dump_params_yaml(config: BevoConfig | None = None, node_settings: Any = None,
                     descriptions: dict[str, str] | None = None, node_name: str = "/**") -> str:
    """``config`` (default: the defaults) as a ROS 2 parameters file, one ``a.b: value`` line per
    setting with its description as a comment; ``node_settings`` (a dataclass, e.g. the node's
    ``NodeSettings``) first when given. :func:`load_config` reads it back to an equal config."""
    config = BevoConfig() if config is None else config
    docs = field_comments(BevoConfig)
    docs.update(descriptions or {})
    sections: list[tuple[str, dict[str, Any]]] = []
    if node_settings is not None:
        sections.append(("bevo_node (ROS wiring)", {f.name: getattr(node_settings, f.name)
                                                    for f in dataclasses.fields(node_settings)}))
    sections.append(("engine (bevo_ros.config.BevoConfig)", config.to_flat()))
    lines = ["# Every bevo_node / bevo tool setting with its default (`bevo dump-config`).",
             f"{node_name}:", "  ros__parameters:"]
    for title, flat in sections:
        lines.append(f"    # ---- {title}")
        for name, value in flat.items():
            if docs.get(name):
                lines.append(f"    # {docs[name]}")
            lines.append(f"    {name}: {_yaml_scalar(value)}")
    return "\n".join(lines) + "\n"


def package_file(rel: str) -> Path:
    """A file the package ships (``params/kitti.yaml``, ...): the source tree's, else the installed
    ``share/bevo_ros`` one (a colcon install has no ``params/`` beside the Python package)."""
    here = REPO_ROOT / rel
    if here.exists():
        return here
    try:
        from ament_index_python.packages import get_package_share_directory

        return Path(get_package_share_directory("bevo_ros")) / rel
    except Exception:  # noqa: BLE001 - ament index absent or package not installed
        return here


# The shipped learned files, one per odometry.mode (each file's header says which).
SHIPPED_LEARNED = {"fused": "params/learned_default.yaml", "paper": "params/learned_paper.yaml"}


def shipped_learned_for_mode(path: str | Path, mode: str) -> Path:
    """``path`` unless it is one of the shipped learned files of the other mode, which is swapped for
    ``mode``'s (``bevo run --mode paper`` with a params file naming the fused default gets the paper
    pipeline's O/Q, as the README's paper figures do); a user's own file is kept as it is."""
    path = Path(path)
    for other, rel in SHIPPED_LEARNED.items():
        if other != mode and mode in SHIPPED_LEARNED and path.resolve() == package_file(rel).resolve():
            return package_file(SHIPPED_LEARNED[mode])
    return path


def resolve_path(name: str, base_dir: Path | None = None) -> Path:
    """Absolute path for ``name``: as given, else beside ``base_dir``, else in the repo/package share."""
    p = Path(name).expanduser()
    if p.is_absolute():
        return p
    candidates = []
    if base_dir is not None:
        candidates += [base_dir / p, base_dir.parent / p]
    candidates += [Path.cwd() / p, package_file(str(p))]  # the source tree's, else the installed share's
    for c in candidates:
        if c.exists():
            return c.resolve()
    return candidates[0].resolve() if base_dir is not None else (REPO_ROOT / p)


# --------------------------------------------------------------------------- engine factory
def extrinsics_problem(T) -> str | None:
    """Why ``T (4, 4)`` is no rigid transform (camera extrinsics), or None."""
    T = np.asarray(T, dtype=np.float64).reshape(4, 4)
    if not np.all(np.isfinite(T)):
        return "not finite"
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        return "last row must be [0, 0, 0, 1]"
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), rtol=0, atol=1e-4):
        return "rotation part is not orthonormal"
    if np.linalg.det(R) < 0:  # orthonormal, but a mirror: no camera can be mounted so
        return "rotation part is a reflection (determinant -1), not a rotation"
    return None


def camera_model(settings: CameraSettings, K=None, width: int | None = None, height_px: int | None = None):
    """CameraModel from settings; ``K``/size (e.g. from CameraInfo) override the settings."""
    import torch

    from bevo_ros.core.geometry import CameraModel

    if K is None:
        if not settings.has_intrinsics():
            raise ConfigError("camera intrinsics are not set (camera.fx/fy/cx/cy/width/height_px) "
                              "and no CameraInfo was given")
        K = [[settings.fx, 0.0, settings.cx], [0.0, settings.fy, settings.cy], [0.0, 0.0, 1.0]]
        width, height_px = settings.width, settings.height_px
    T = torch.tensor(settings.base_T_camera, dtype=torch.float64).reshape(4, 4)
    if (problem := extrinsics_problem(T.numpy())) is not None:
        raise ConfigError(f"camera.base_T_camera: {problem}")
    if settings.mount_height <= 0:
        raise ConfigError(f"camera.mount_height must be > 0 m, got {settings.mount_height}")
    from bevo_ros.core.validation import intrinsics_problem

    if (problem := intrinsics_problem(np.asarray(K, dtype=np.float64), width, height_px)) is not None:
        raise ConfigError(f"camera intrinsics are not plausible: {problem}")
    return CameraModel(torch.tensor(np.array(K, dtype=np.float64)).reshape(3, 3), int(width), int(height_px), T,
                       float(settings.mount_height))


def bev_spec(config: BevoConfig):
    """The engine's BEV grid (``core.geometry.BevSpec``) from the settings."""
    from bevo_ros.core.geometry import BevSpec

    return BevSpec(config.bev.size, config.bev.metres_per_pixel, config.bev.forward_offset)


def mounting_in_use(config: BevoConfig, T_base_cam) -> tuple[float, float]:
    """The base's (pitch, roll) on the road the engine uses with a camera whose extrinsics are
    ``T_base_cam (4, 4)``: ``filter.mounting_*`` as given (``mounting_reference: base``, or the
    extrinsics are ``camera.base_T_camera``'s), else re-derived to keep the camera's tilt to the
    road they were calibrated with (:func:`~bevo_ros.core.geometry.mounting_for_extrinsics`, as
    :class:`~bevo_ros.core.odometry.BevoOdometry` does with ``mounting_extrinsics``). For the code
    that runs the core without the engine (training)."""
    from bevo_ros.core.geometry import mounting_for_extrinsics

    mounting = (float(config.filter.mounting_pitch), float(config.filter.mounting_roll))
    if config.filter.mounting_reference != "camera":
        return mounting
    calibrated = np.asarray(config.camera.base_T_camera, dtype=np.float64).reshape(4, 4)
    return mounting_for_extrinsics(mounting, calibrated, T_base_cam)


def vehicle_noise(config: BevoConfig, learned: LearnedParams):
    """The motion filter's noise: the learned densities with the configured gates
    (``odometry.min_quality``, ``gate``, ``rotation_gate``); the engine's and the training replay's."""
    from bevo_ros.core.vehicle_filter import VehicleNoise

    if not config.odometry.gate >= 1.0:  # sigmas; 0 refused every measurement (and NaN compares false)
        raise ConfigError(f"odometry.gate must be >= 1 (standard deviations; inf = never gate), "
                          f"got {config.odometry.gate}")
    return VehicleNoise(**learned.vehicle, min_quality=config.odometry.min_quality, gate=config.odometry.gate,
                        rotation_gate=config.odometry.rotation_gate)


def gyro_bias_prior(config: BevoConfig, learned: LearnedParams) -> tuple[float, float]:
    """Fused item 18's prior ``(std, walk)``: the learned file's ``gyro_bias`` (what ``bevo train``
    measured against a ground truth and the engine read better with) when it has one, else the
    parameters' ``filter.gyro_bias_std`` / ``gyro_bias_walk`` (the IMU's datasheet)."""
    if learned.gyro_bias is not None:
        return float(learned.gyro_bias[0]), float(learned.gyro_bias[1])
    return float(config.filter.gyro_bias_std), float(config.filter.gyro_bias_walk)


def gyro_bias_prior_note(config: BevoConfig, learned: LearnedParams, learned_path) -> str | None:
    """What bevo_node and ``bevo run`` say when the learned file's ``gyro_bias`` takes the parameters'
    place (fused mode); None when it does not."""
    if learned.gyro_bias is None or config.odometry.mode != "fused":
        return None
    return (f"the pitch and roll gyro's bias prior from {learned_path} (measured by bevo train): std "
            f"{learned.gyro_bias[0]:.3g} rad/s, walk {learned.gyro_bias[1]:.3g} rad/s/sqrt(s), in place of "
            f"filter.gyro_bias_std / walk ({config.filter.gyro_bias_std:g} / {config.filter.gyro_bias_walk:g})")


def build_odometry(config: BevoConfig, learned: LearnedParams, camera=None):
    """The engine both the node and the offline commands (bevo_ros.pipeline) run: one construction, one behaviour."""
    from bevo_ros.core.device import resolve_device
    from bevo_ros.core.dukf import DUKF
    from bevo_ros.core.odometry import BevoOdometry

    if config.filter.motion_model not in ("euler", "additive"):
        raise ConfigError(f"filter.motion_model must be 'euler' or 'additive', got {config.filter.motion_model!r}")
    try:
        device = str(resolve_device(config.device))
    except ValueError as exc:
        raise ConfigError(f"device: {exc}") from None
    from bevo_ros.core.compiled import KERNEL_MODES
    from bevo_ros.core.odometry import MODES

    if config.kernels not in KERNEL_MODES:
        raise ConfigError(f"kernels must be one of {', '.join(KERNEL_MODES)}, got {config.kernels!r}")

    if config.filter.mounting_reference not in MOUNTING_REFERENCES:
        raise ConfigError(f"filter.mounting_reference must be one of {', '.join(MOUNTING_REFERENCES)}, "
                          f"got {config.filter.mounting_reference!r}")
    # "camera": the mounting was calibrated through camera.base_T_camera; with a camera whose
    # extrinsics differ (the node's /tf_static) the engine keeps the camera's tilt to the road.
    mounting_extrinsics = (np.asarray(config.camera.base_T_camera, dtype=np.float64).reshape(4, 4)
                           if config.filter.mounting_reference == "camera" else None)
    if config.odometry.mode not in MODES:
        raise ConfigError(f"odometry.mode must be one of {', '.join(MODES)}, got {config.odometry.mode!r}")
    from bevo_ros.core.rate_integration import GYRO_SAMPLING

    if config.filter.gyro_sampling not in GYRO_SAMPLING:
        raise ConfigError(f"filter.gyro_sampling must be one of {', '.join(GYRO_SAMPLING)}, "
                          f"got {config.filter.gyro_sampling!r}")
    dukf = DUKF(process_var=learned.process_noise_density, measurement_var=learned.measurement_noise_variance,
                motion_model=config.filter.motion_model).double()
    vehicle = vehicle_noise(config, learned)
    spec = bev_spec(config)
    limits = imu_limits(config)
    gyro_bias_std, gyro_bias_walk = gyro_bias_prior(config, learned)
    from bevo_ros.core.travel_direction import MIN_PAIRS

    f = config.filter
    if f.tilt_from_images != 0 and not MIN_PAIRS <= f.tilt_from_images < f.tilt_hold_frames:
        raise ConfigError(f"filter.tilt_from_images must be 0 (off) or {MIN_PAIRS} up to filter.tilt_hold_frames - 1 "
                          f"({f.tilt_hold_frames - 1}), got {f.tilt_from_images!r}")
    odometry = BevoOdometry(
        camera=camera if camera is not None else camera_model(config.camera),
        spec=spec,
        dukf=dukf,
        road_tilt_time_constant=config.filter.road_tilt_time_constant,
        mounting_attitude=(config.filter.mounting_pitch, config.filter.mounting_roll),
        mounting_extrinsics=mounting_extrinsics,
        dpc=config.dpc,
        max_imu_gap=config.filter.max_imu_gap,
        turn_compensation=config.filter.turn_compensation,
        device=device,
        mode=config.odometry.mode,
        vehicle_noise=vehicle,
        suspension_gradients=learned.suspension_gradients,
        initial_attitude_std=config.odometry.initial_attitude_std,
        pitch_change_correction=config.odometry.pitch_change_correction,
        frame_clock_window=config.odometry.frame_clock_window,
        gyro_sampling=config.filter.gyro_sampling,
        kernels=config.kernels,
        standstill_max_speed=config.odometry.standstill_max_speed,
        direction_lock=config.odometry.direction_lock,
        min_frame_interval=config.odometry.min_frame_interval,
        imu_time_offset=config.odometry.imu_time_offset,
        gyro_bias_std=gyro_bias_std,
        gyro_bias_walk=gyro_bias_walk,
        tilt_from_images=config.filter.tilt_from_images,
        tilt_hold_frames=config.filter.tilt_hold_frames,
    )
    odometry.imu_limits = limits
    return odometry


def imu_limits(config: BevoConfig):
    """The engine's IMU plausibility limits from ``filter.max_acceleration/max_angular_rate``."""
    from bevo_ros.core.validation import ImuLimits

    f = config.filter
    for name in ("max_acceleration", "max_angular_rate"):
        if getattr(f, name) <= 0:
            raise ConfigError(f"filter.{name} must be > 0, got {getattr(f, name)}")
    return ImuLimits(f.max_acceleration, f.max_angular_rate)
