"""Pinned behaviour: a refactor leaves the numbers identical (issue 10).

Compares, against values recorded before the move (test/data/pinned_behaviour.json):
run_bag's trajectories (stamp and position per frame, to 1e-9) of the KITTI sample and of a short
synthetic bumpy drive, in both odometry modes, and the O/Q learned by a 1-epoch fixed-seed
train_from_bag (relative 1e-9). What is computed and how is tools/record_pinned.py; the test only
compares.

When a change of the numbers is intended (e.g. the fused engine changed), re-record and commit
the JSON with that change, in one command:

    PYTHONPATH=$PWD .venv/bin/python tools/record_pinned.py                        # everything
    PYTHONPATH=$PWD .venv/bin/python tools/record_pinned.py --only kitti/fused synthetic/fused
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from bevo_ros.cli import load_tool

record = load_tool("record_pinned")
PINNED = json.loads(record.PINNED.read_text())


@pytest.fixture(scope="module")
def synthetic_values(tmp_path_factory):
    return record.compute(["synthetic/fused", "synthetic/paper", "training"], tmp_path_factory.mktemp("pinned"),
                          kitti_root=None)


@pytest.fixture(scope="module")
def kitti_values(kitti_root, tmp_path_factory):
    return record.compute(["kitti/fused", "kitti/paper"], tmp_path_factory.mktemp("pinned_kitti"), kitti_root)


def assert_same_trajectory(got: list, expected: list, part: str) -> None:
    got, expected = np.asarray(got), np.asarray(expected)
    assert got.shape == expected.shape, f"{part}: {got.shape[0]} frames, recorded {expected.shape[0]}"
    diff = np.abs(got - expected).max(axis=0)
    print(f"\n{part}: {len(got)} frames, max |stamp| diff {diff[0]:.1e} s, max |position| diff {diff[1:].max():.1e} m")
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9, err_msg=f"{part} moved; if intended, re-record "
                               "(see this module's docstring)")


@pytest.mark.parametrize("mode", record.MODES)
def test_synthetic_trajectory_is_pinned(synthetic_values, mode):
    part = f"synthetic/{mode}"
    assert_same_trajectory(synthetic_values[part], PINNED[part], part)


@pytest.mark.kitti
@pytest.mark.parametrize("mode", record.MODES)
def test_kitti_trajectory_is_pinned(kitti_values, mode):
    part = f"kitti/{mode}"
    assert_same_trajectory(kitti_values[part], PINNED[part], part)


def test_training_result_is_pinned(synthetic_values):
    got, expected = synthetic_values["training"], PINNED["training"]
    print(f"\nlearned O {got['O']}, Q {got['Q']}; after Adam O {got['O_after_adam']}, Q {got['Q_after_adam']}")
    for key in ("O", "Q", "O_after_adam", "Q_after_adam"):
        np.testing.assert_allclose(got[key], expected[key], rtol=1e-9, atol=0, err_msg=f"training {key} moved")


def test_the_pin_can_fail():
    """The comparison sees a 1e-8 m change (the recorded trajectory, moved)."""
    moved = np.asarray(PINNED["synthetic/paper"])
    moved[-1, 1] += 1e-8
    with pytest.raises(AssertionError):
        assert_same_trajectory(moved.tolist(), PINNED["synthetic/paper"], "synthetic/paper")
