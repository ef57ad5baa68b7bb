"""bevo_node's parameters as a ROS node declares them: descriptors with ranges, ``read_only`` for
what is fixed at start (``ros2 param set`` is then refused with the reason), and the few that
change live; plus which ``--params-file`` set a parameter (relative paths resolve beside it).
"""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

# Parameters that take effect while the node runs (applied by the node's post-set callback).
# Everything else is read-only: topics, QoS, frames and the engine are built once at start.
LIVE = frozenset({
    "publish_tf", "bev_image_heatmap", "path_max_length", "log_throttle_period", "image_wait",
    "max_pending_images", "max_time_jump_back", "imu_timeout", "image_timeout", "speed_timeout", "sensor_late_factor",
})

INF = 1e9  # "no upper bound" (descriptor ranges are finite)

# name -> (low, high) inclusive; a strictly positive quantity has a small positive low.
RANGES: dict[str, tuple[float, float]] = {
    "path_max_length": (0, 1_000_000),
    "imu_qos_depth": (1, 100_000), "image_qos_depth": (1, 100_000), "output_qos_depth": (1, 100_000),
    "image_wait": (0.001, 60.0),
    "max_pending_images": (1, 10_000),
    "max_time_jump_back": (0.001, INF),
    "diagnostics_period": (0.01, 3600.0),
    "log_throttle_period": (0.0, 3600.0),
    "latency_window": (1, 1_000_000),
    "torch_threads": (0, 1024),
    "camera_info_timeout": (0.0, 3600.0),
    "imu_timeout": (0.01, 3600.0), "image_timeout": (0.01, 3600.0), "speed_timeout": (0.01, 3600.0),
    "sensor_late_factor": (1.0, 1000.0),
    "camera.fx": (0.0, INF), "camera.fy": (0.0, INF), "camera.cx": (-INF, INF), "camera.cy": (-INF, INF),
    "camera.width": (0, 100_000), "camera.height_px": (0, 100_000),
    "camera.mount_height": (0.01, 100.0),
    "bev.size": (8, 4096), "bev.metres_per_pixel": (1e-4, 10.0), "bev.forward_offset": (-1000.0, 1000.0),
    "filter.road_tilt_time_constant": (0.0, 3600.0), "filter.max_imu_gap": (0.001, 3600.0),
    "filter.mounting_pitch": (-math.pi / 2, math.pi / 2), "filter.mounting_roll": (-math.pi / 2, math.pi / 2),
    "filter.gyro_bias_std": (0.0, 1.0), "filter.gyro_bias_walk": (0.0, 1.0),
    "filter.tilt_from_images": (0, 100_000), "filter.tilt_hold_frames": (2, 100_000),
    "filter.max_acceleration": (0.1, INF), "filter.max_angular_rate": (0.01, INF),
    "max_time_jump_forward": (0.001, INF), "time_jump_confirmations": (1, 1000),
    "odometry.min_quality": (0.0, 1.0), "odometry.gate": (1.0, INF), "odometry.rotation_gate": (0.0, math.pi),
    "odometry.initial_attitude_std": (1e-6, math.pi),  # the DUKF and the gyro bias state need a start variance
    "odometry.frame_clock_window": (0, 100_000), "odometry.standstill_max_speed": (0.0, 10.0),
    "odometry.min_frame_interval": (0.0, 10.0), "odometry.imu_time_offset": (-1.0, 1.0),
}

# string parameters with a fixed set of values
CHOICES: dict[str, tuple[str, ...]] = {
    "input_qos": ("sensor_data", "reliable"),
    "undistort": ("auto", "on", "off"),
    "image_transport": ("raw", "compressed"),
    "filter.motion_model": ("euler", "additive"),
    "filter.mounting_reference": ("base", "camera"),  # bevo_ros.config.MOUNTING_REFERENCES
    "filter.gyro_sampling": ("interval_mean", "instantaneous"),  # bevo_ros.core.rate_integration.GYRO_SAMPLING
    "odometry.mode": ("fused", "paper"),  # bevo_ros.core.odometry.MODES
    "kernels": ("eager", "compiled", "auto"),  # bevo_ros.core.compiled.KERNEL_MODES
}


def descriptor(name: str, default: Any, description: str):
    """The ParameterDescriptor of ``name`` (dynamic typing: an int written for a float in a YAML
    file is accepted and converted, as before; ranges show in ``ros2 param describe``)."""
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

    live = name in LIVE
    text = description + (" [live: ros2 param set takes effect]" if live else
                          " [read-only: fixed at start, restart the node to change it]")
    if name in CHOICES:
        text += f" (one of: {', '.join(CHOICES[name])})"
    d = ParameterDescriptor(description=text, dynamic_typing=True, read_only=not live)
    if name in RANGES and not isinstance(default, bool):
        lo, hi = RANGES[name]
        if isinstance(default, int):
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
        elif isinstance(default, float):
            d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
    return d


def check(name: str, value: Any) -> str | None:
    """Why ``value`` is out of range for ``name`` (None when fine); ``value`` already coerced."""
    if name in CHOICES and value not in CHOICES[name]:
        return f"parameter '{name}' must be one of {', '.join(CHOICES[name])}, got {value!r}"
    if name in RANGES and isinstance(value, (int, float)) and not isinstance(value, bool):
        lo, hi = RANGES[name]
        if not (lo <= value <= hi):
            return f"parameter '{name}' = {value} is outside [{lo:g}, {hi:g}]"
    return None


# ------------------------------------------------------------------------------ --params-file
def params_files_from_args(argv: list[str]) -> list[str]:
    """Every ``--params-file X`` among the ROS arguments, in order (rcl applies them in order)."""
    return [argv[i + 1] for i, a in enumerate(argv[:-1]) if a == "--params-file"]


def _node_sections(doc: Any, fq_name: str) -> list[dict]:
    """The ``ros__parameters`` mappings of ``doc`` that apply to the node ``fq_name`` (e.g.
    ``/car1/bevo_node``), as rcl matches them: a key is a fully qualified name (a missing leading
    slash added: a plain ``bevo_node:`` is ``/bevo_node``, not ``/car1/bevo_node``), with the
    wildcards ``*`` (one name token) and ``**`` (any number of them; ``/**`` = every node)."""
    out = []
    if not isinstance(doc, dict):
        return out
    for key, section in doc.items():
        if not isinstance(section, dict) or not isinstance(section.get("ros__parameters"), dict):
            continue
        k = str(key)
        if _node_key_pattern(k if k.startswith("/") else "/" + k).fullmatch(fq_name):
            out.append(section["ros__parameters"])
    return out


def _node_key_pattern(key: str) -> "re.Pattern[str]":
    """A params file's node key as a regex over fully qualified names: ``/**`` any number of
    ``/token`` (none included), ``*`` one token's characters."""
    parts = re.split(r"(/\*\*|\*)", key)
    regex = "".join("(?:/[^/]+)*" if p == "/**" else "[^/]*" if p == "*" else re.escape(p) for p in parts)
    return re.compile(regex)


def _sets(section: dict, name: str) -> bool:
    """Whether a ``ros__parameters`` mapping sets ``name`` (nested ``a: {b: }`` or flat ``a.b``)."""
    from bevo_ros.config import _flatten

    return name in _flatten(section)


def params_file_setting(argv: list[str], name: str, fq_node_name: str) -> str | None:
    """The last ``--params-file`` that sets ``name`` for ``fq_node_name`` (else the last one given).

    Under ``ros2 launch`` with ``parameters=[car.yaml, {'use_sim_time': True}]`` the last file is
    launch's temporary one; a relative ``learned_params_file`` set in ``car.yaml`` must still
    resolve beside ``car.yaml``.
    """
    import yaml

    files = params_files_from_args(argv)
    for path in reversed(files):
        try:
            doc = yaml.safe_load(Path(path).read_text())
        except (OSError, yaml.YAMLError, UnicodeDecodeError):
            continue  # rcl reports unreadable files itself
        if any(_sets(sec, name) for sec in _node_sections(doc, fq_node_name)):
            return path
    return files[-1] if files else None
