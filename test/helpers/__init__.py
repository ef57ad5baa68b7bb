"""Helpers shared by the tests (no tests here; fixtures stay in test/conftest.py). ``test/`` is on
``sys.path`` (pytest.ini ``pythonpath``), so a test module imports ``from helpers.drives import ...``.

- :mod:`helpers.env`: the repository, the KITTI sample's place, CI detection.
- :mod:`helpers.ros`: a test module's own ROS domain and rclpy context.
- :mod:`helpers.drives`: synthetic bags with exact ground truth.
- :mod:`helpers.node_support`: bevo_node tests: a small drive as ROS messages, the offline
  reference run, parameters files, a node subprocess, an odometry listener.
"""
