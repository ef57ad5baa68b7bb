"""``bevo_ros.rotations``, the one place for numpy / float rotations, against SciPy's ``Rotation`` (the
reference) and the engine's tensor forms (``core.geometry``): conventions ``(x, y, z, w)`` and
``R = Rz(yaw) Ry(pitch) Rx(roll)``, round trips, the canonical sign, and what is no rotation."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from bevo_ros import rotations as rot
from bevo_ros.core import geometry


def _angles(n: int, seed: int = 0) -> np.ndarray:
    """``(n, 3)`` roll, pitch, yaw: any roll and yaw, pitch short of +-90 deg."""
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-math.pi, math.pi, n), rng.uniform(-1.5, 1.5, n),
                            rng.uniform(-math.pi, math.pi, n)])


def test_the_float_forms_agree_with_scipy():
    for roll, pitch, yaw in _angles(200):
        ref = Rotation.from_euler("ZYX", [yaw, pitch, roll])  # intrinsic Z-Y'-X'' = Rz Ry Rx
        q = np.array(rot.quaternion_from_rpy(roll, pitch, yaw))
        assert abs(abs(q @ ref.as_quat()) - 1.0) < 1e-12  # the same rotation (q and -q are)
        R = rot.matrix_from_quaternion(q)
        assert np.abs(R - ref.as_matrix()).max() < 1e-12
        assert np.abs(rot.quaternion_from_matrix(R) - ref.as_quat(canonical=True)).max() < 1e-12  # w >= 0
        assert np.abs(np.array(rot.rpy_from_matrix(R)) - (roll, pitch, yaw)).max() < 1e-9
        assert np.abs(np.array(rot.rpy_from_quaternion(*q)) - (roll, pitch, yaw)).max() < 1e-9
    # Shepperd's branches: a trace <= 0 with each diagonal entry the largest (rotations by pi about x, y, z)
    for axis in np.eye(3):
        R = Rotation.from_rotvec(math.pi * axis).as_matrix()
        q = rot.quaternion_from_matrix(R)
        assert q[3] >= 0 and np.abs(rot.matrix_from_quaternion(q) - R).max() < 1e-12


def test_the_vectorised_forms_agree_with_the_float_ones_and_the_engines():
    a = _angles(64, seed=1).reshape(4, 16, 3)
    R = rot.rotation_z(a[..., 2]) @ rot.rotation_y(a[..., 1]) @ rot.rotation_x(a[..., 0])
    assert R.shape == (4, 16, 3, 3)
    t = torch.from_numpy(a)
    assert np.abs(R - geometry.rotation_from_rpy(t[..., 0], t[..., 1], t[..., 2]).numpy()).max() < 1e-14
    assert np.abs(np.stack(rot.rpy_from_matrices(R), -1) - a).max() < 1e-9
    assert rot.rpy_from_matrix(R[2, 3]) == pytest.approx(tuple(a[2, 3]), abs=1e-9)
    rv = rot.rotation_vector(R)
    assert np.abs(rv - Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(4, 16, 3)).max() < 1e-9
    assert np.array_equal(rot.rotation_vector(np.eye(3)), np.zeros(3))  # no rotation: no NaN


def test_a_quaternion_that_is_no_rotation_is_refused():
    assert np.abs(rot.matrix_from_quaternion((0.0, 0.0, 1.0, 1.0)) - rot.rotation_z(np.float64(math.pi / 2))).max() < 1e-12
    for q in ((0.0, 0.0, 0.0, 0.0), (math.nan, 0.0, 0.0, 1.0), (math.inf, 0.0, 0.0, 1.0)):
        with pytest.raises(ValueError, match="no rotation"):
            rot.matrix_from_quaternion(q)
