"""Parameters files and learned-parameters files: round trips and clear errors."""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import pytest
import yaml

from bevo_ros.config import (BevoConfig, ConfigError, REPO_ROOT, build_odometry, camera_model, load_config,
                             load_params_file)
from bevo_ros.io.learned_params import LearnedParams, load_learned_params, save_learned_params


def test_flat_round_trip_and_every_setting_in_the_kitti_params():
    config = BevoConfig()
    assert BevoConfig.from_flat(config.to_flat()) == config
    flat = load_params_file(REPO_ROOT / "params" / "kitti.yaml")
    missing = sorted(set(config.to_flat()) - set(flat))
    assert not missing, f"params/kitti.yaml does not document {missing}"


def test_shipped_params_load_and_build_the_engine():
    for name in ("kitti.yaml", "synthetic.yaml"):
        config, _ = load_config(REPO_ROOT / "params" / name)
        learned = load_learned_params(config.learned_params_file)
        if config.camera.has_intrinsics():
            odo = build_odometry(config, learned)
            assert odo.camera.width == config.camera.width


def test_bad_parameter_types_name_the_parameter(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump({"bevo_node": {"ros__parameters": {"bev": {"size": "big"}}}}))
    with pytest.raises(ConfigError, match="bev.size"):
        load_config(p)
    p.write_text(yaml.safe_dump({"other_node": {"ros__parameters": {}}}))
    with pytest.raises(ConfigError, match="no 'bevo_node"):
        load_config(p)
    p.write_text("bevo_node: [unclosed")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(p)
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "absent.yaml")


def test_renamed_parameter_still_read_with_a_deprecation_warning(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump({"bevo_node": {"ros__parameters": {"camera": {"height": 1.4}}}}))
    with pytest.warns(FutureWarning, match="'camera.height' is deprecated, renamed 'camera.mount_height'"):
        config, _ = load_config(p)
    assert config.camera.mount_height == 1.4 and "height" not in dataclasses.asdict(config.camera)
    p.write_text(yaml.safe_dump({"bevo_node": {"ros__parameters": {"camera": {"height": 1.4, "mount_height": 1.5}}}}))
    with pytest.raises(ConfigError, match="set only 'camera.mount_height'"):
        load_config(p)


def test_a_parameter_bevo_node_does_not_have_is_named(tmp_path):
    """A typo (``filter.mountng_pitch``) would leave the real one at its default without a word: the
    offline commands warn, naming it and the nearest parameter; the shipped files have none."""
    import warnings

    text = (REPO_ROOT / "params" / "kitti.yaml").read_text().replace("    filter.mounting_pitch:", "    filter.mountng_pitch:")
    assert "filter.mountng_pitch" in text
    p = tmp_path / "typo.yaml"
    p.write_text(text)
    with pytest.warns(UserWarning, match=r"ignored: filter\.mountng_pitch \(did you mean filter\.mounting_pitch\?\)"):
        load_config(p)
    for name in ("kitti.yaml", "synthetic.yaml", "replay.yaml"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            load_config(REPO_ROOT / "params" / name)
    p.write_text(yaml.safe_dump({"bevo_node": {"ros__parameters": {"use_sim_time": True, "frobnicate": 1}}}))
    with pytest.warns(UserWarning, match=r"ignored: frobnicate$"):  # use_sim_time is any node's
        load_config(p)


def test_camera_extrinsics_are_validated():
    config = BevoConfig()
    config.camera.fx = config.camera.fy = 500.0
    config.camera.width, config.camera.height_px = 640, 480
    config.camera.base_T_camera = [2.0] + config.camera.base_T_camera[1:]
    with pytest.raises(ConfigError, match="orthonormal"):
        camera_model(config.camera)
    with pytest.raises(ConfigError, match="intrinsics"):
        camera_model(BevoConfig().camera)


def test_learned_params_round_trip_is_human_readable_and_atomic(tmp_path):
    path = tmp_path / "learned.yaml"
    save_learned_params(LearnedParams((1e-5, 2e-5), (3e-2, 4e-2), {"bags": ["a", "b"]}), path)
    text = path.read_text()
    assert "process_noise_density" in text and "rad^2/s" in text  # a person can read it
    loaded = load_learned_params(path)
    assert loaded.process_noise_density == (1e-5, 2e-5)
    assert loaded.measurement_noise_variance == (3e-2, 4e-2)
    assert loaded.info["bags"] == ["a", "b"]
    assert [f for f in os.listdir(tmp_path) if f != "learned.yaml"] == []  # no temp files left


@pytest.mark.parametrize("mutate, message", [
    (lambda d: d.pop("format"), "format"),
    (lambda d: d["process_noise_density"].pop("roll"), "process_noise_density.roll"),
    (lambda d: d["measurement_noise_variance"].update(pitch=-1.0), "must be finite and > 0"),
    (lambda d: d["measurement_noise_variance"].update(pitch=".nan"), "must be finite and > 0"),
    (lambda d: d.update(process_noise_density=[1, 2]), "missing section"),
    (lambda d: d.update(suspension_gradient=d.pop("suspension_gradients")), "unknown section.*'suspension_gradient'"),
    (lambda d: d.update(vehicle_filter={"jerk_density": "fast"}), r"'vehicle_filter.jerk_density' = 'fast' must be"),
    (lambda d: d.update(vehicle_filter={"jerk_density": True}), r"'vehicle_filter.jerk_density' = True must be"),
    (lambda d: d.update(vehicle_filter={"jerk_density": -1.0}), r"'vehicle_filter.jerk_density' = -1.0 must be"),
    (lambda d: d.update(vehicle_filter={"jerk_densty": 1.0}), r"unknown 'vehicle_filter.jerk_densty'"),
    (lambda d: d.update(vehicle_filter={"jerk_density": 0.0}), r"'vehicle_filter.jerk_density' = 0.0 must be .*> 0, at"),
    # sizes that break the engine (a read-only review, 2026-12-06): slip_std 1e300 overflowed, a suspension
    # gradient of 1e3 put the BEVs off the image, O / Q beyond any IMU's
    (lambda d: d.update(vehicle_filter={"slip_std": 1e300}), r"'vehicle_filter.slip_std' = 1e\+300 must be .*at most"),
    (lambda d: d["suspension_gradients"].update(pitch=1000.0), r"'suspension_gradients.pitch' = 1000.0 .*at most 0.1"),
    (lambda d: d["process_noise_density"].update(pitch=1e9), r"'process_noise_density.pitch' = 1000000000.0 .*at most"),
    (lambda d: d.update(vehicle_filter={"imu_accel_density": -1.0}), r"imu_accel_density' = -1.0 must be .*>= 0 \(0 = off\)"),
    # YAML that reads as numbers it is not (a read-only review, 2026-12-07): a bool, an integer too large for
    # a float; unknown keys of mixed types
    (lambda d: d["process_noise_density"].update(pitch=True), r"'process_noise_density.pitch' missing or not a number"),
    (lambda d: d["measurement_noise_variance"].update(roll=10**400), r"'measurement_noise_variance.roll' missing or not"),
    (lambda d: d.update(vehicle_filter={"jerk_density": 10**400}), r"'vehicle_filter.jerk_density' = 1000.* must be"),
    (lambda d: d.update(gyro_bias={"std": 10**400, "walk": 0.0}), r"'gyro_bias.std' = 1000.* must be"),
    (lambda d: d.update({1: "a", "x": "b"}), r"unknown section\(s\) '1', 'x'"),
])
def test_malformed_learned_params_name_the_file_and_problem(tmp_path, mutate, message):
    path = tmp_path / "learned.yaml"
    save_learned_params(LearnedParams(), path)
    doc = yaml.safe_load(path.read_text())
    mutate(doc)
    path.write_text(yaml.safe_dump(doc, sort_keys=False).replace("'.nan'", ".nan"))
    with pytest.raises(ConfigError, match=message) as err:
        load_learned_params(path)
    assert str(path) in str(err.value)


def test_the_inertial_speed_input_can_be_switched_off_in_a_learned_file(tmp_path):
    """``imu_accel_density: 0`` (fused item 16 off) is the one vehicle_filter number that may be 0."""
    path = tmp_path / "learned.yaml"
    save_learned_params(LearnedParams(), path)
    path.write_text(path.read_text().replace("vehicle_filter: {}", "vehicle_filter:\n  imu_accel_density: 0"))
    assert load_learned_params(path).vehicle["imu_accel_density"] == 0.0


def test_learned_numbers_written_as_yaml_reads_them(tmp_path):
    """A hand-edited ``jerk_density: 1e-3`` (no dot: a string to YAML 1.1) was refused in the
    vehicle_filter section while the other sections took it: every section reads it as the number."""
    path = tmp_path / "learned.yaml"
    save_learned_params(LearnedParams(), path)
    text = path.read_text()
    assert "vehicle_filter: {}" in text and "  pitch: 0.05\n" in text
    path.write_text(text.replace("vehicle_filter: {}", "vehicle_filter:\n  jerk_density: 1e-3").replace(
        "  pitch: 0.05\n", "  pitch: 5e-2\n", 1))
    loaded = load_learned_params(path)
    assert loaded.vehicle["jerk_density"] == 1e-3 and loaded.measurement_noise_variance[0] == 5e-2


def test_a_learned_file_without_suspension_gradients_says_what_fused_mode_gets(tmp_path):  # or with it empty
    path = tmp_path / "learned.yaml"
    save_learned_params(LearnedParams(), path)
    doc = yaml.safe_load(path.read_text())
    doc.pop("suspension_gradients")
    path.write_text(yaml.safe_dump(doc))
    with pytest.warns(UserWarning, match="no 'suspension_gradients': fused mode then models no suspension lean"):
        assert load_learned_params(path).suspension_gradients == (0.0, 0.0)
    path.write_text(yaml.safe_dump(doc) + "suspension_gradients:\n")  # the section's name, nothing under it
    with pytest.warns(UserWarning, match="no 'suspension_gradients'"):
        assert load_learned_params(path).suspension_gradients == (0.0, 0.0)


def test_missing_or_garbage_learned_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_learned_params(tmp_path / "none.yaml")
    garbage = tmp_path / "g.yaml"
    garbage.write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(ConfigError):
        load_learned_params(garbage)
    Path(tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        load_learned_params(tmp_path / "list.yaml")


def test_one_device_rule_and_one_bev_grid_from_the_settings():
    """build_odometry, training and the map localiser share core.device.resolve_device; the BEV
    grid comes from config.bev_spec wherever settings are turned into an engine."""
    import torch

    from bevo_ros import config as cfg
    from bevo_ros.training import trainer as training
    from bevo_ros.core import map_localization
    from bevo_ros.core.device import resolve_device
    from bevo_ros.core.geometry import BevSpec
    from bevo_ros.io.learned_params import LearnedParams

    assert training.resolve_device is map_localization.resolve_device is resolve_device
    assert training.bev_spec is cfg.bev_spec
    c = cfg.BevoConfig()
    c.bev.size, c.bev.metres_per_pixel, c.bev.forward_offset = 64, 0.2, 5.0
    assert cfg.bev_spec(c) == BevSpec(64, 0.2, 5.0)
    assert resolve_device("cpu") == torch.device("cpu")
    c.device = "tpu"
    with pytest.raises(cfg.ConfigError, match="device"):
        cfg.build_odometry(c, LearnedParams())
    if not torch.cuda.is_available():
        c.device = "cuda"
        logged = []
        with pytest.warns(RuntimeWarning, match="CUDA is not available"):
            assert resolve_device("cuda:0", logged.append) == torch.device("cpu")
        assert logged and "on the CPU" in logged[0]
        from bevo_ros.datasets.synthetic import kitti_like_camera

        with pytest.warns(RuntimeWarning, match="CUDA is not available"):
            assert cfg.build_odometry(c, LearnedParams(), camera=kitti_like_camera()).device == torch.device("cpu")


@pytest.mark.parametrize("value, default, expected", [
    (3, 1.0, 3.0), (2.5, 1.0, 2.5), (4.0, 1, 4), (True, False, True), ("x", "y", "x"),
    ([1, 2], [0.0, 0.0], [1.0, 2.0]),
])
def test_one_coercion_rule_accepts(value, default, expected):
    from bevo_ros.config import coerce_setting

    got = coerce_setting(value, default, "p")
    assert got == expected and type(got) is type(expected)


@pytest.mark.parametrize("value, default", [
    (True, 1.0), (float("nan"), 1.0), (2.5, 1), (True, 1), (1, False), ("on", False), (1, "cpu"), (True, "auto"),
    ([1.0], [0.0, 0.0]), ([True, 1.0], [0.0, 0.0]), ("x", 1.0),
])
def test_one_coercion_rule_rejects_with_the_name(value, default):
    """The same rule for parameters files (BevoConfig), the node's settings and `ros2 param set`."""
    from bevo_ros.config import coerce_setting

    with pytest.raises(ConfigError, match=r"file.yaml: parameter 'a\.b' = .* is not a valid"):
        coerce_setting(value, default, "a.b", "file.yaml")


def test_phase_correlation_settings_reach_the_engine_from_the_parameters_file(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump({"bevo_node": {"ros__parameters": {
        "dpc": {"angle_bins": 180, "radial_range": [0.06, 0.3], "whitening_floor": 0.1}}}}))
    config, _ = load_config(p)
    assert config.dpc.angle_bins == 180 and config.dpc.radial_range == (0.06, 0.3)
    kitti, _ = load_config(REPO_ROOT / "params" / "kitti.yaml")
    odo = build_odometry(config, load_learned_params(config.learned_params_file), camera=camera_model(kitti.camera))
    assert odo.dpc == config.dpc and hash(odo.dpc)  # hashable: the derived grids are cached on it
    p.write_text(yaml.safe_dump({"bevo_node": {"ros__parameters": {"dpc": {"radial_range": [0.3, 0.1]}}}}))
    with pytest.raises(ConfigError, match="dpc.*radial_range"):
        load_config(p)


def test_params_file_sections_merge_as_ros_applies_them(tmp_path):
    """A wildcard section ``/**`` and the node's own: both apply, the node's winning (ROS 2 loads a
    file that way; the offline commands read the same file)."""
    path = tmp_path / "p.yaml"
    path.write_text("/**:\n  ros__parameters:\n    base_frame: vehicle\n    bev.size: 64\n"
                    "bevo_node:\n  ros__parameters:\n    bev.size: 80\n")
    flat = load_params_file(path)
    assert flat == {"base_frame": "vehicle", "bev.size": 80}
    with pytest.raises(ConfigError, match="no 'bevo_node: ros__parameters:' section"):
        path.write_text("other_node:\n  ros__parameters:\n    bev.size: 80\n")
        load_params_file(path)


def test_rig_settings_follow_the_nodes_settings_and_rules():
    """How the offline commands take a bag's rig and calibration: the node's parameters, defaults and
    coercion rule."""
    from bevo_ros.datasets.rosbag import RigSettings
    from bevo_ros.ros.settings import NodeSettings

    node = NodeSettings()
    assert RigSettings() == RigSettings.from_params({}) == RigSettings(
        node.base_frame, node.extrinsics_from_tf, node.use_camera_info, node.camera_info_use_p, node.undistort)
    assert (RigSettings.from_params({"base_frame": "vehicle", "extrinsics_from_tf": False, "undistort": "off"})
            == RigSettings("vehicle", False, undistort="off"))
    with pytest.raises(ConfigError, match="undistort"):
        RigSettings.from_params({"undistort": "sometimes"})
    with pytest.raises(ConfigError, match="extrinsics_from_tf"):
        RigSettings.from_params({"extrinsics_from_tf": "false"})  # a string is no bool (it would read as True)
    with pytest.raises(ConfigError, match="base_frame"):
        RigSettings.from_params({"base_frame": ""})
    # the topics too: a bag recorded in the root namespace holds the node's relative names under /
    rig = RigSettings.from_params({"imu_topic": "car/imu", "camera_info_topic": "/cam2/camera_info"})
    assert rig.read_topics() == {"imu_topic": "/car/imu", "image_topic": "/camera/image_rect",
                                 "camera_info_topic": "/cam2/camera_info"}
    assert (node.imu_topic, node.image_topic, node.camera_info_topic) == (
        RigSettings().imu_topic, RigSettings().image_topic, RigSettings().camera_info_topic)


def test_bad_tf_static_extrinsics_name_their_source():
    """A bag whose /tf_static camera is no rigid transform: a ConfigError that names /tf_static, not
    the parameter the user never set."""
    import numpy as np

    from bevo_ros.datasets.rosbag import camera_for_recording
    from bevo_ros.io.bag import BagContents

    config = BevoConfig()
    config.camera = dataclasses.replace(config.camera, fx=700.0, fy=700.0, cx=600.0, cy=180.0, width=1226, height_px=370)
    rec = BagContents("bag", np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64), None,
                      image_frame_id="cam")
    T = np.eye(4)
    T[:3, :3] *= 2.0  # scaled: not a rotation
    rec.static_tf.add("base_link", "cam", T)
    with pytest.raises(ConfigError, match="camera extrinsics from /tf_static base_link -> cam unusable"):
        camera_for_recording(rec, config)
    rec.static_tf.add("base_link", "cam", np.eye(4))  # rigid: taken
    assert np.allclose(camera_for_recording(rec, config).T_base_cam.numpy(), np.eye(4))
