"""core.pose: the engine's float twins equal the tensor functions training uses."""
from __future__ import annotations

import math

import numpy as np
import torch

from bevo_ros.core.pose import compose_se2, compose_se2_floats, propagate_covariance_se2, propagate_covariance_se2_floats


def test_float_twins_equal_the_tensor_pose_functions():
    rng = np.random.default_rng(0)
    pose, cov = (0.0, 0.0, 0.0), np.zeros((3, 3))
    pose_t, cov_t = torch.zeros(3, dtype=torch.float64), torch.zeros(3, 3, dtype=torch.float64)
    for k in range(200):  # ~4 full turns: the yaw wraps at +-pi both ways
        motion = np.array([rng.uniform(0, 2), rng.normal(0, 0.1), (0.15 if k < 120 else -0.25) + rng.normal(0, 0.02)])
        a = rng.normal(size=(3, 3)) * 1e-2
        motion_cov = a @ a.T
        cov = propagate_covariance_se2_floats(pose[2], cov, motion, motion_cov)
        pose = compose_se2_floats(pose, motion)
        m_t = torch.from_numpy(motion)
        cov_t = propagate_covariance_se2(pose_t, cov_t, m_t, torch.from_numpy(motion_cov))
        pose_t = compose_se2(pose_t, m_t)
        np.testing.assert_allclose(pose[:2], pose_t[:2].numpy(), rtol=0, atol=1e-9)
        d_yaw = (pose[2] - float(pose_t[2]) + math.pi) % (2 * math.pi) - math.pi
        assert abs(d_yaw) < 1e-12 and -math.pi <= pose[2] < math.pi
        np.testing.assert_allclose(cov, cov_t.numpy(), rtol=1e-10, atol=1e-12)
        np.testing.assert_array_equal(cov, cov.T)
