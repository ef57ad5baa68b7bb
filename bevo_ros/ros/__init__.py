"""The ROS side of ``bevo_node`` (``bevo_ros.node`` only wires these together): ``settings``
(parameters), ``rig`` (calibration, extrinsics, IMU frames), ``camera`` (CameraInfo, undistortion),
``tf`` (static transforms), ``intake`` (messages into the engine), ``publishers`` (outputs),
``diagnostics`` (counts, drops, status) and ``parameters`` (descriptors, live set)."""
