"""bevo_ros: BEV-based visual-inertial odometry (BEVO) as a ROS 2 package.

``bevo_ros.core`` is the framework-free PyTorch engine; ``bevo_ros.node`` the thin rclpy layer.
"""
__version__ = "0.1.0"
