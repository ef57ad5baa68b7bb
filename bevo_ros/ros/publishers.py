"""bevo_node's outputs: nav_msgs/Odometry (header stamp = the image's), a bounded nav_msgs/Path
(published while subscribed), the mono8 BEV with the correlation heat-map beside it (computed
while subscribed) and TF ``odom_frame -> base_frame`` (tf2_ros when installed, else our own /tf
publisher)."""
from __future__ import annotations

import collections
from typing import Any, Callable

import numpy as np

from bevo_ros.io.ros_conversions import (bev_to_mono8, gray_to_image_msg, heatmap_to_mono8, odometry_msg,
                                         pose_stamped_from_odometry, transform_from_odometry)


def tf_backend(node) -> tuple[str, Callable[[Any], None] | None]:
    """``(name, send(TransformStamped))``: tf2_ros when installed, else our own /tf publisher."""
    try:
        from tf2_ros import TransformBroadcaster  # full ROS 2 install
    except ImportError:
        pass
    else:
        broadcaster = TransformBroadcaster(node)
        return "tf2_ros", broadcaster.sendTransform
    try:
        from tf2_msgs.msg import TFMessage  # built by tools/build_tf2_msgs.sh (make setup)
    except ImportError:
        return "none", None
    from rclpy.qos import QoSProfile

    pub = node.create_publisher(TFMessage, "/tf", QoSProfile(depth=100))  # tf2_ros's broadcaster QoS

    def send(transform) -> None:
        pub.publish(TFMessage(transforms=[transform]))

    return "tf2_msgs", send


class Outputs:
    """The node's publishers; ``publish_tf`` and ``path_max_length`` change live (:meth:`set_publish_tf`,
    :meth:`set_path_length`)."""

    def __init__(self, node, settings, report) -> None:
        from nav_msgs.msg import Odometry, Path as PathMsg
        from sensor_msgs.msg import Image

        s = self.settings = settings
        self.node = node
        self.odom_pub = node.create_publisher(Odometry, s.odometry_topic, s.output_qos_depth)
        self.path_pub = node.create_publisher(PathMsg, s.path_topic, s.output_qos_depth)  # path_max_length is live
        self.bev_pub = node.create_publisher(Image, s.bev_image_topic, s.output_qos_depth)
        self.path: collections.deque = collections.deque(maxlen=max(1, s.path_max_length))
        self.tf_backend, self._send_tf = ("disabled", None)
        self._tf_made = None  # (backend, send) once created (publish_tf is live)
        if s.publish_tf:
            self.set_publish_tf(True)
            if self._send_tf is None:  # said once, here
                report.log("tf_unavailable",
                           "publish_tf is true but neither tf2_ros nor tf2_msgs is available: TF is DISABLED "
                           "(odometry is still published; run `make setup` to build tf2_msgs, or install "
                           "ROS 2 tf2_ros)")

    def set_publish_tf(self, on: bool) -> None:
        if on and self._tf_made is None:
            self._tf_made = tf_backend(self.node)  # once: a second /tf publisher would be a leak
        self.tf_backend, self._send_tf = self._tf_made if on else ("disabled", None)

    def set_path_length(self, n: int) -> None:
        self.path = collections.deque(list(self.path)[-n:] if n else [], maxlen=max(1, n))

    def odometry(self, step, stamp) -> Any:
        """Publish one step's nav_msgs/Odometry with the header stamp ``stamp``; returns it."""
        odom = odometry_msg(step, stamp, self.settings.odom_frame, self.settings.base_frame)
        self.odom_pub.publish(odom)
        return odom

    def extras(self, step, odom) -> None:
        """TF, path and BEV image of a step whose odometry ``odom`` went out."""
        s = self.settings
        if self._send_tf is not None:
            self._send_tf(transform_from_odometry(odom))
        if s.path_max_length > 0:
            self.path.append(pose_stamped_from_odometry(odom))
            if self.path_pub.get_subscription_count() > 0:
                from nav_msgs.msg import Path as PathMsg

                self.path_pub.publish(PathMsg(header=odom.header, poses=list(self.path)))
        if self.bev_pub.get_subscription_count() > 0:
            self._bev(step, odom.header)

    def _bev(self, step, header) -> None:
        from std_msgs.msg import Header

        img = bev_to_mono8(step.bev, step.bev_mask)
        if self.settings.bev_image_heatmap and step.correlation is not None:
            sep = np.full((img.shape[0], 2), 128, np.uint8)
            img = np.hstack([img, sep, heatmap_to_mono8(step.correlation, img.shape)])
        self.bev_pub.publish(gray_to_image_msg(img, Header(stamp=header.stamp, frame_id=self.settings.base_frame)))


__all__ = ["Outputs", "tf_backend"]
