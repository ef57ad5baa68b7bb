"""The learned-parameters YAML (the DUKF's O and Q, the vehicle filter's noise, the suspension
gradients, the pitch and roll gyro's bias prior) that ``bevo train`` writes and bevo_node, ``bevo run``
and the other commands load."""
from __future__ import annotations

import datetime as _dt
import math
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from bevo_ros.config import REPO_ROOT, ConfigError, read_yaml
from bevo_ros.io.files import atomic_write_text

LEARNED_FORMAT = "bevo_learned_params/1"


@dataclass
class LearnedParams:
    """The DUKF's 4 trainable numbers plus provenance.

    process_noise_density: O per axis (pitch, roll), rad^2/s; multiplied by each IMU dt.
    measurement_noise_variance: Q per axis (pitch, roll), rad^2.
    """

    process_noise_density: tuple[float, float] = (1e-6, 1e-6)
    measurement_noise_variance: tuple[float, float] = (5e-2, 5e-2)
    info: dict[str, Any] = field(default_factory=dict)
    # Fused mode: the vehicle motion filter's noise (bevo_ros.core.vehicle_filter.VehicleNoise,
    # learned fields only) and the suspension's (pitch, roll) lean per m/s^2, rad/(m/s^2).
    vehicle: dict[str, float] = field(default_factory=dict)
    suspension_gradients: tuple[float, float] = (0.0, 0.0)
    # Fused item 18: the x / y gyro bias's prior (std rad/s, walk rad/s/sqrt(s)) that ``bevo train``
    # measured against the ground truth (bevo_ros.training.gyro_bias); None: the parameters'
    # ``filter.gyro_bias_std`` / ``gyro_bias_walk`` (bevo_ros.config.gyro_bias_prior).
    gyro_bias: tuple[float, float] | None = None


def learned_to_dict(params: LearnedParams) -> dict[str, Any]:
    o, q = params.process_noise_density, params.measurement_noise_variance
    return {
        "format": LEARNED_FORMAT,
        "process_noise_density": {"pitch": float(o[0]), "roll": float(o[1]), "units": "rad^2/s"},
        "measurement_noise_variance": {"pitch": float(q[0]), "roll": float(q[1]), "units": "rad^2"},
        "vehicle_filter": {k: float(v) for k, v in params.vehicle.items()},
        "suspension_gradients": {"pitch": float(params.suspension_gradients[0]),
                                 "roll": float(params.suspension_gradients[1]), "units": "rad/(m/s^2)"},
        **({} if params.gyro_bias is None else {"gyro_bias": {
            "std": float(params.gyro_bias[0]), "walk": float(params.gyro_bias[1]), "units": "rad/s, rad/s/sqrt(s)"}}),
        "info": dict(params.info),
    }


def save_learned_params(params: LearnedParams, path: str | os.PathLike) -> Path:
    """Write the learned parameters YAML atomically (temp file in the same dir + rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = (
        "# BEVO learned DUKF noise parameters (human-readable; loaded by bevo_node and the bevo commands).\n"
        "# O = process noise density of the [pitch, roll] random walk (rad^2/s, times each IMU dt);\n"
        "# Q = accelerometer pitch/roll measurement noise variance (rad^2).\n"
    )
    text = header + yaml.safe_dump(learned_to_dict(params), sort_keys=False, default_flow_style=False)
    atomic_write_text(path, text)
    return path


# The largest sizes a learned file's numbers may have: far beyond any car's, short of what breaks the
# engine (a suspension gradient of 1e3 rad/(m/s^2) put 45 of the KITTI sample's 51 BEVs off the image,
# a slip_std of 1e300 overflowed): O and Q (rad^2/s, rad^2), the motion filter's densities and
# standard deviations, the suspension's lean per m/s^2 (rad; 5.7 deg per m/s^2, a car leans < 1).
LIMITS = {"variance": 1e6, "vehicle": 1e6, "suspension": 0.1}

# The sections a learned-parameters file may have.
LEARNED_SECTIONS = ("format", "process_noise_density", "measurement_noise_variance", "vehicle_filter",
                    "suspension_gradients", "gyro_bias", "info")


def load_learned_params(path: str | os.PathLike) -> LearnedParams:
    """Load and validate; raises ConfigError naming the file and the problem."""
    path = Path(path)
    doc = read_yaml(path, "learned-parameters file")
    if not isinstance(doc, dict):
        raise ConfigError(f"learned-parameters file {path}: expected a mapping, got {type(doc).__name__}")
    if doc.get("format") != LEARNED_FORMAT:
        raise ConfigError(f"learned-parameters file {path}: 'format' must be '{LEARNED_FORMAT}', got {doc.get('format')!r}")

    def pair(key: str, positive: bool = True, default: tuple[float, float] | None = None,
             limit: float = LIMITS["variance"]) -> tuple[float, float]:
        section = doc.get(key)
        if section is None and default is not None:  # absent, or an empty section (warned about below)
            return default
        if not isinstance(section, dict):
            raise ConfigError(f"learned-parameters file {path}: missing section '{key}' with 'pitch' and 'roll'")
        out = []
        for axis in ("pitch", "roll"):
            try:
                if isinstance(section[axis], bool):  # YAML's true is no variance
                    raise TypeError
                v = float(section[axis])
            except (KeyError, TypeError, ValueError, OverflowError):
                raise ConfigError(f"learned-parameters file {path}: '{key}.{axis}' missing or not a number") from None
            if not (math.isfinite(v) and (v > 0 or not positive) and abs(v) <= limit):
                raise ConfigError(f"learned-parameters file {path}: '{key}.{axis}' = {v} must be finite"
                                  + (" and > 0" if positive else "") + f", at most {limit:g} in size")
            out.append(v)
        return out[0], out[1]

    unknown = sorted(map(str, set(doc) - set(LEARNED_SECTIONS)))
    if unknown:  # a misspelt section would otherwise silently be its default (suspension_gradient: no lean)
        raise ConfigError(f"learned-parameters file {path}: unknown section(s) {', '.join(map(repr, unknown))} "
                          f"(known: {', '.join(LEARNED_SECTIONS)})")
    info = doc.get("info") or {}
    if not isinstance(info, dict):
        raise ConfigError(f"learned-parameters file {path}: 'info' must be a mapping")
    from bevo_ros.core.vehicle_filter import VehicleNoise

    vehicle = doc.get("vehicle_filter") or {}
    if not isinstance(vehicle, dict):
        raise ConfigError(f"learned-parameters file {path}: 'vehicle_filter' must be a mapping")
    numbers = {}
    for k, v in vehicle.items():
        if k not in VehicleNoise.LEARNED:
            raise ConfigError(f"learned-parameters file {path}: unknown 'vehicle_filter.{k}' "
                              f"(known: {', '.join(VehicleNoise.LEARNED)})")
        try:  # a number as the other sections take it: YAML reads 1e-3 (no dot) as a string
            numbers[k] = float(v) if not isinstance(v, bool) else math.nan
        except (TypeError, ValueError, OverflowError):
            numbers[k] = math.nan
        zero_ok = k in VehicleNoise.OFF_WHEN_ZERO
        if not (math.isfinite(numbers[k]) and (numbers[k] >= 0 if zero_ok else numbers[k] > 0)
                and numbers[k] <= LIMITS["vehicle"]):  # slip_std 1e300 overflowed the engine
            raise ConfigError(f"learned-parameters file {path}: 'vehicle_filter.{k}' = {v!r} must be a finite number "
                              + (">= 0 (0 = off)" if zero_ok else "> 0") + f", at most {LIMITS['vehicle']:g}")
    gyro_bias = None
    if "gyro_bias" in doc:  # optional: without it the parameters' filter.gyro_bias_std / walk hold
        section = doc["gyro_bias"]
        if not isinstance(section, dict):
            raise ConfigError(f"learned-parameters file {path}: 'gyro_bias' must be a mapping with 'std' and 'walk'")
        values = []
        for key in ("std", "walk"):
            v = section.get(key)
            try:
                x = float(v) if not isinstance(v, bool) else math.nan
            except (TypeError, ValueError, OverflowError):
                x = math.nan
            if not (math.isfinite(x) and 0.0 <= x <= 1.0):  # the parameters' range (ros/parameters.py)
                raise ConfigError(f"learned-parameters file {path}: 'gyro_bias.{key}' = {v!r} must be a number in "
                                  f"[0, 1] (rad/s, rad/s/sqrt(s))")
            values.append(x)
        gyro_bias = (values[0], values[1])
    learned = LearnedParams(pair("process_noise_density"), pair("measurement_noise_variance"), info, numbers,
                            pair("suspension_gradients", positive=False, default=(0.0, 0.0),
                                 limit=LIMITS["suspension"]), gyro_bias)
    if doc.get("suspension_gradients") is None:  # said once the file is known good (a bad one is refused alone)
        warnings.warn(f"learned-parameters file {path} has no 'suspension_gradients': fused mode then models no "
                      f"suspension lean (0, 0); params/learned_default.yaml holds the defaults", UserWarning,
                      stacklevel=2)
    return learned


def provenance(extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """Date and code version for the learned-parameters file."""
    from bevo_ros import __version__

    info: dict[str, Any] = {"date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                            "code_version": __version__}
    try:
        import subprocess

        sha = subprocess.run(["git", "-C", str(REPO_ROOT), "rev-parse", "--short", "HEAD"],
                             capture_output=True, text=True, timeout=5)
        if sha.returncode == 0:
            info["code_version"] += f"+g{sha.stdout.strip()}"
    except Exception:  # noqa: BLE001 - not a git checkout
        pass
    if extra:
        info.update(extra)
    return info
