"""Static extrinsics from ``/tf_static``: tf2_ros's buffer when installed, else a small listener.

ROS 2 wheels carry no tf2_ros; ``tools/build_tf2_msgs.sh`` builds tf2_msgs/TFMessage, which is
all a static-transform reader needs: ``/tf_static`` is latched (transient local, reliable), each
publisher sends its whole set once, and a tree of rigid transforms answers every lookup.
"""
from __future__ import annotations

import numpy as np

from bevo_ros.io.static_tf import StaticTree, matrix_from_transform

# tf2_ros's static listener QoS: a late subscriber still gets every latched transform.
TF_STATIC_DEPTH = 100


class StaticTransforms:
    """``lookup(target, source) -> T_target_source | None`` over /tf_static.

    ``backend``: ``tf2_ros`` (its Buffer and static TransformListener), ``tf2_msgs`` (our
    listener on ``/tf_static``) or ``none`` (no TF message type: parameters only).
    """

    def __init__(self, node, topic: str = "/tf_static") -> None:
        self.tree = StaticTree()
        self._logger = node.get_logger()
        self._buffer = None
        self._sub = None
        self.backend = "none"
        try:
            from tf2_ros import Buffer, TransformListener  # a full ROS 2 install
        except ImportError:
            pass
        else:
            self._buffer = Buffer()
            self._listener = TransformListener(self._buffer, node, static_only=True)
            self.backend = "tf2_ros"
            return
        try:
            from tf2_msgs.msg import TFMessage  # built by tools/build_tf2_msgs.sh (make setup)
        except ImportError:
            return
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        qos = QoSProfile(depth=TF_STATIC_DEPTH, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                         reliability=ReliabilityPolicy.RELIABLE)
        self._sub = node.create_subscription(TFMessage, topic, self._on_tf_static, qos)
        self.backend = "tf2_msgs"

    def poll(self) -> None:
        """Take the /tf_static messages already received, now: a transform published before the
        sensor data (a bag's first message) is then known before that data is used, whatever
        order the executor would have run the callbacks in."""
        sub = self._sub
        if sub is None:
            return
        try:
            with sub.handle:
                for _ in range(1000):
                    taken = sub.handle.take_message(sub.msg_type, sub.raw)
                    if taken is None:
                        break
                    self._on_tf_static(taken[0])
        except (AttributeError, TypeError):  # rclpy internals changed: the callback still delivers them
            self._sub_poll_broken = True

    def _on_tf_static(self, msg) -> None:
        try:
            bad = self.tree.add_message(msg)
        except Exception as exc:  # noqa: BLE001 - a malformed message must not stop the node's executor
            self._logger.error(f"/tf_static message dropped: {exc!r}")
            return
        for what in bad:
            self._logger.warning(f"/tf_static transform left out, no rigid transform: {what}")

    @property
    def version(self) -> int:
        """Changes when the transforms may have changed (tf2_ros: re-read once a second)."""
        if self._buffer is not None:
            import time

            return int(time.monotonic())
        return self.tree.version

    def lookup(self, target: str, source: str) -> np.ndarray | None:
        # tf2 refuses frame ids with a leading '/' (ROS 1 bags carry them) where its buffer strips
        # them from the transforms: stripped here, as the tree (and the offline commands) do.
        target, source = target.lstrip("/"), source.lstrip("/")
        if not target or not source:
            return None
        if self._buffer is not None:
            from rclpy.time import Time

            try:
                t = self._buffer.lookup_transform(target, source, Time())
            except Exception:  # noqa: BLE001 - tf2's LookupException & co: not (yet) known
                return None
            return matrix_from_transform(t.transform)
        return self.tree.lookup(target, source)
