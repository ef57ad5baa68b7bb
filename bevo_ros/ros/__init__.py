"""ROS-graph helpers of ``bevo_node`` (rclpy-side, no engine state): calibration from CameraInfo,
static TF, parameter descriptors, per-input diagnostics and image decoding. The node wires them."""
