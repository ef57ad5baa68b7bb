"""Static extrinsics from ``/tf_static``: tf2_ros's buffer when installed, else a small listener.

ROS 2 wheels carry no tf2_ros; ``tools/build_tf2_msgs.sh`` builds tf2_msgs/TFMessage, which is
all a static-transform reader needs: ``/tf_static`` is latched (transient local, reliable), each
publisher sends its whole set once, and a tree of rigid transforms answers every lookup.
"""
from __future__ import annotations

from typing import Any

import numpy as np

# tf2_ros's static listener QoS: a late subscriber still gets every latched transform.
TF_STATIC_DEPTH = 100


def matrix_from_transform(t: Any) -> np.ndarray:
    """geometry_msgs/Transform -> ``(4, 4)`` (pose of the child in the parent)."""
    from bevo_ros.io.bag import matrix_from_quaternion

    q, p = t.rotation, t.translation
    T = np.eye(4)
    T[:3, :3] = matrix_from_quaternion((q.x, q.y, q.z, q.w))
    T[:3, 3] = (p.x, p.y, p.z)
    return T


class StaticTree:
    """The static transforms received so far: ``child -> (parent, T_parent_child)``."""

    def __init__(self) -> None:
        self.edges: dict[str, tuple[str, np.ndarray]] = {}
        self.version = 0  # bumped whenever an edge changes (callers re-read what they derived)

    def add(self, parent: str, child: str, T: np.ndarray) -> None:
        parent, child = parent.lstrip("/"), child.lstrip("/")
        old = self.edges.get(child)
        if old is None or old[0] != parent or not np.allclose(old[1], T, rtol=0, atol=1e-12):
            self.edges[child] = (parent, np.asarray(T, dtype=np.float64))
            self.version += 1

    def _to_root(self, frame: str) -> tuple[str, np.ndarray]:
        """``(root, T_root_frame)``: up the tree from ``frame`` (cycle-safe)."""
        T, seen = np.eye(4), {frame}
        while frame in self.edges:
            parent, T_pc = self.edges[frame]
            if parent in seen:
                break
            T = T_pc @ T
            seen.add(parent)
            frame = parent
        return frame, T

    def lookup(self, target: str, source: str) -> np.ndarray | None:
        """``T_target_source`` (pose of ``source`` in ``target``), None when not connected."""
        target, source = target.lstrip("/"), source.lstrip("/")
        if target == source:
            return np.eye(4)
        root_s, T_rs = self._to_root(source)
        root_t, T_rt = self._to_root(target)
        if root_s != root_t:
            return None
        return np.linalg.inv(T_rt) @ T_rs


class StaticTransforms:
    """``lookup(target, source) -> T_target_source | None`` over /tf_static.

    ``backend``: ``tf2_ros`` (its Buffer and static TransformListener), ``tf2_msgs`` (our
    listener on ``/tf_static``) or ``none`` (no TF message type: parameters only).
    """

    def __init__(self, node, topic: str = "/tf_static") -> None:
        self.tree = StaticTree()
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
        for t in msg.transforms:
            self.tree.add(t.header.frame_id, t.child_frame_id, matrix_from_transform(t.transform))

    @property
    def version(self) -> int:
        """Changes when the transforms may have changed (tf2_ros: re-read once a second)."""
        if self._buffer is not None:
            import time

            return int(time.monotonic())
        return self.tree.version

    def lookup(self, target: str, source: str) -> np.ndarray | None:
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
