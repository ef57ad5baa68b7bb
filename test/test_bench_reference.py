"""tools/opencv_reference.py, the yardstick of tools/bench_core.py, is a real implementation:
it projects the engine's BEV and recovers known motions (not a stub that merely takes time)."""
from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from bevo_ros.core.bev import project_to_bev
from bevo_ros.core.geometry import BevSpec
from bevo_ros.core.motion import registration_from_vehicle_motion
from bevo_ros.datasets.synthetic import (RenderOptions, default_ground, ground_patch, kitti_like_camera,
                                         render_view)
from helpers.tools import load_tool

SPEC = BevSpec()
START = (10.0, 0.5, 0.2)  # world (x, y, yaw) of the first BEV


@pytest.fixture(scope="module")
def ref_module():
    return load_tool("opencv_reference")


@pytest.fixture(scope="module")
def camera():
    return kitti_like_camera()


def _moved(pose, motion):
    """World pose after the base moves by ``motion (dx, dy, dyaw)`` in its own frame."""
    x, y, yaw = pose
    dx, dy, dyaw = motion
    return (x + math.cos(yaw) * dx - math.sin(yaw) * dy, y + math.sin(yaw) * dx + math.cos(yaw) * dy, yaw + dyaw)


def test_projection_is_the_engines_bev(ref_module, camera):
    """Same ground points, homography, 2x2 sub-samples and validity rule as core.bev, also tilted."""
    rng = np.random.default_rng(0)
    noise = rng.normal(0.0, 1.0, (camera.height_px, camera.width)).astype(np.float32)
    smooth = cv2.GaussianBlur(noise, (0, 0), 2.0)
    image = np.clip(128 + 400 * smooth, 0, 255).astype(np.uint8)
    for pitch, roll in ((0.0, 0.0), (0.02, -0.015)):
        ref = ref_module.OpenCvReference(camera, SPEC, pitch, roll)
        bev = ref.project(image)
        engine_bev, engine_mask = project_to_bev(torch.from_numpy(image)[None, None], camera.to(dtype=torch.float32),
                                                 torch.tensor([pitch]), torch.tensor([roll]), SPEC)
        engine_bev, engine_mask = engine_bev[0, 0].numpy(), engine_mask[0, 0].numpy()
        assert ref.mask.mean() > 0.5
        np.testing.assert_array_equal(ref.mask, engine_mask)
        # uint8 remap output and 1/32-pixel fixed-point maps: about one grey level.
        diff = np.abs(bev - engine_bev)
        assert diff.max() <= 2.5 / 255 and diff.mean() <= 0.5 / 255, (diff.max() * 255, diff.mean() * 255)
        # A 1-pixel (10 cm) shift of the grid would be far off: the comparison is sharp.
        assert np.abs(np.roll(bev, 1, axis=0) - engine_bev)[ref.mask > 0].mean() > 5 * diff.mean()
        # The attitude-following variant (warpPerspective at the frame's homography) with the fixed
        # maps' attitude's mask: the same BEV.
        diff_at = np.abs(ref_module.OpenCvReference(camera, SPEC).project_at(image, pitch, roll) - engine_bev)
        assert diff_at[ref.mask * engine_mask > 0].max() <= 2.5 / 255, diff_at.max() * 255


def test_ccs_magnitude_matches_numpy(ref_module):
    x = np.random.default_rng(1).standard_normal((200, 200)).astype(np.float32)
    np.testing.assert_allclose(ref_module.ccs_half_magnitude(cv2.dft(x)), np.abs(np.fft.rfft2(x.astype(np.float64))),
                               atol=1e-3)


@pytest.mark.parametrize("motion", [
    (1.0, 0.0, 0.0),
    (1.2, 0.05, math.radians(3.0)),
    (0.5, -0.1, math.radians(-6.0)),
    (0.0, 0.3, math.radians(10.0)),
    (-0.8, 0.0, math.radians(-1.5)),
])
def test_registration_recovers_known_motion(ref_module, camera, motion):
    """True BEVs of the synthetic ground (same sub-samples as the projection) at two poses."""
    ref = ref_module.OpenCvReference(camera, SPEC)
    g = default_ground()
    prev, curr = (ground_patch(*pose, SPEC, g, supersample=2).numpy() * ref.mask for pose in (START, _moved(START, motion)))
    angle, shift, response = ref.register(ref.prepare(prev), ref.prepare(curr))
    true_angle, true_shift = registration_from_vehicle_motion(torch.tensor([motion], dtype=torch.float64), SPEC)
    assert abs(math.degrees(angle - float(true_angle[0]))) <= 1.0
    assert np.abs(shift - true_shift[0].numpy()).max() <= 1.0
    assert response > 0.2
    if abs(motion[2]) <= math.radians(6.0):  # the car-like range: tighter
        assert abs(math.degrees(angle - float(true_angle[0]))) <= 0.25
        assert np.abs(shift - true_shift[0].numpy()).max() <= 0.3


def test_step_recovers_the_motion_between_rendered_frames(ref_module, camera):
    """End to end on two rendered camera images: remap -> rotation -> translation -> motion."""
    motion = (1.1, 0.04, math.radians(2.0))
    g = default_ground()
    opts = RenderOptions(noise_std=2.0)
    images = [render_view(g, camera, pose, (0.0, 0.0), opts, noise_seed=k)
              for k, pose in enumerate((START, _moved(START, motion)))]
    ref = ref_module.OpenCvReference(camera, SPEC)
    assert ref.step(images[0]) is None
    est = ref.step(images[1])
    assert np.abs(est[:2] - motion[:2]).max() <= 0.05  # metres (half a BEV pixel)
    assert abs(math.degrees(est[2] - motion[2])) <= 0.25
    ref.reset()
    assert ref.step(images[1]) is None


def test_bench_core_prints_the_ratio():
    """The benchmark runs end to end (subprocess: it wraps engine functions to time them)."""
    repo = Path(__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=str(repo) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, str(repo / "tools" / "bench_core.py"), "--frames", "4", "--passes", "1"],
                         capture_output=True, text=True, timeout=300, env=env, cwd=repo)
    assert out.returncode == 0, out.stderr
    ratio = [line for line in out.stdout.splitlines() if line.startswith("RATIO engine full step / OpenCV reference")]
    assert len(ratio) == 1 and float(ratio[0].split(":")[1].split("x")[0]) > 0
    assert "engine mode:" in out.stdout and "OpenCV reference (BEV + 2 PC)" in out.stdout
