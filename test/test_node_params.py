"""params/kitti.yaml documents every bevo_node parameter, loads through rcl into the node, and its
camera extrinsics are the KITTI calibration chain's."""
from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from bevo_ros.config import BevoConfig, load_config  # noqa: E402
from bevo_ros.ros.settings import DESCRIPTIONS, NodeSettings  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
KITTI_PARAMS = REPO / "params" / "kitti.yaml"
from helpers.ros import domain_id_for  # noqa: E402

DOMAIN_ID = domain_id_for(14)
pytestmark = pytest.mark.ros


def declared_parameters() -> list[str]:
    return [f.name for f in dataclasses.fields(NodeSettings)] + list(BevoConfig().to_flat())


def test_every_parameter_is_in_kitti_yaml_with_a_comment():
    lines = KITTI_PARAMS.read_text().splitlines()
    for name in declared_parameters() + ["use_sim_time"]:
        idx = [i for i, line in enumerate(lines) if re.match(rf"\s+{re.escape(name)}:", line)]
        assert len(idx) == 1, f"parameter '{name}' must appear once in {KITTI_PARAMS}"
        i = idx[0]
        above = i - 1  # a block of parameters may share the comment above it
        while above > 0 and re.match(r"\s+[\w.]+:", lines[above]) and "#" not in lines[above]:
            above -= 1
        commented = "#" in lines[i] or "#" in lines[above]
        assert commented, f"parameter '{name}' in {KITTI_PARAMS} has no comment"


def test_every_node_parameter_has_a_description():
    missing = [f.name for f in dataclasses.fields(NodeSettings) if not DESCRIPTIONS.get(f.name)]
    assert not missing, f"bevo_ros/ros/settings.py DESCRIPTIONS lacks {missing}"


@pytest.mark.parametrize("namespace", ["", "car1"])  # launch's namespace:=car1 must not lose the file
def test_kitti_yaml_loads_through_rcl_into_the_node(namespace):
    from bevo_ros.node import BevoNode

    import torch

    threads = torch.get_num_threads()  # the node sets torch_threads process-wide: restore it
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    ctx = rclpy.context.Context()
    rclpy.init(args=["--ros-args", "--params-file", str(KITTI_PARAMS)], context=ctx, domain_id=DOMAIN_ID)
    try:
        node = BevoNode(context=ctx, params_file=str(KITTI_PARAMS), namespace=namespace)
        try:
            config, flat = load_config(KITTI_PARAMS)
            assert node.config == config
            for f in dataclasses.fields(NodeSettings):
                assert getattr(node.settings, f.name) == flat[f.name], f.name
            assert node.learned_path == (REPO / "params" / "learned_default.yaml").resolve()
            # CameraInfo first: no camera until it arrives (the 1226x370 parameters are the fallback)
            assert node.rig.camera is None and node.rig.calibration is None
            assert (config.camera.width, config.camera.height_px) == (1226, 370)
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
        torch.set_num_threads(threads)


def test_node_reads_the_renamed_camera_height_with_a_warning(tmp_path, monkeypatch):
    """A params file with the old name ``camera.height`` still sets the camera's mount height, and the
    node's log says it is deprecated and under which name."""
    from rclpy.impl.rcutils_logger import RcutilsLogger

    from bevo_ros.node import BevoNode

    import torch

    warned: list[str] = []
    warning = RcutilsLogger.warning
    monkeypatch.setattr(RcutilsLogger, "warning", lambda self, msg, **kw: (warned.append(str(msg)),
                                                                          warning(self, msg, **kw))[1])

    old = tmp_path / "old.yaml"
    old.write_text(KITTI_PARAMS.read_text().replace("camera.mount_height: 1.65", "camera.height: 1.4"))
    threads = torch.get_num_threads()
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    ctx = rclpy.context.Context()
    rclpy.init(args=["--ros-args", "--params-file", str(old)], context=ctx, domain_id=DOMAIN_ID)
    try:
        node = BevoNode(context=ctx, params_file=str(old))
        try:
            assert node.config.camera.mount_height == 1.4
            assert any("'camera.height' is deprecated, renamed 'camera.mount_height'" in m for m in warned), warned
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
        torch.set_num_threads(threads)


@pytest.mark.kitti
def test_kitti_extrinsics_are_the_calibration_chain(kitti_root):
    from bevo_ros.datasets.kitti import imu_to_camera_extrinsics, invert_rigid

    expected = invert_rigid(imu_to_camera_extrinsics(kitti_root / "raw" / "2011_09_26"))
    config, _ = load_config(KITTI_PARAMS)
    got = np.array(config.camera.base_T_camera).reshape(4, 4)
    assert np.allclose(got, expected, atol=1e-12, rtol=0)
