"""What ``make setup`` provides (the node's executable, colcon, tf2_msgs, a C++ compiler) is skipped
without it on a user's machine, and a failure under ``CI=true``: a green CI run has tested it."""
from __future__ import annotations

import math

import pytest

from helpers.env import import_outside_ci, skip_outside_ci


def test_a_missing_prerequisite_skips_outside_ci_and_fails_in_it(monkeypatch):
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="colcon missing; CI=true requires it"):
        skip_outside_ci("colcon missing")
    with pytest.raises(pytest.fail.Exception, match="no_such_module_bevo cannot be imported"):
        import_outside_ci("no_such_module_bevo", "built by make setup")
    monkeypatch.setenv("CI", "")
    with pytest.raises(pytest.skip.Exception, match="colcon missing"):
        skip_outside_ci("colcon missing")
    with pytest.raises(pytest.skip.Exception):
        import_outside_ci("no_such_module_bevo", "built by make setup")
    assert import_outside_ci("math", "the standard library") is math
