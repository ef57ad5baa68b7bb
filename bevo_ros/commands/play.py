"""Replay a rosbag2 (sqlite3 or mcap) into ROS 2 topics through rclpy.

Messages are read with rosbags and published as their stored CDR bytes (no re-serialisation,
so they arrive bit-exact), in bag-time order, paced by their bag times (scaled by --rate).
/clock (rosgraph_msgs/Clock) carries the bag time for nodes run with use_sim_time:=true.
Every topic is offered reliable (a reliable publisher serves best-effort and reliable subscribers
alike; a bag recorded from best-effort sensor drivers offered the node's reliable replay inputs
nothing) and, where recorded so and always for /tf_static, transient local: a node started later
still gets the rig. Keep-last with a deep queue (--qos-depth) so a subscriber that keeps up loses
nothing. The latched topics' messages up to the start (the newest of each before --start) are
published first and acknowledged before the clock and the data begin, so a node has the rig
before its first image. On a full ROS 2 install `ros2 bag play` reads the same bags.
"""
from __future__ import annotations

import argparse
import math
import importlib
import os
import sys
import time


from bevo_ros.commands import new_parser, prog_name
from bevo_ros.io import bag

EPILOG = """\
examples:
  bevo play seq06_bag                          # real time, with /clock
  bevo play seq06_bag --rate 2 --start 1.5     # twice as fast, from 1.5 s into the bag
  bevo play seq06_bag --topics /imu/data /camera/image_rect --wait-for-subscribers 10
  bevo play seq06_bag --wait-for-subscribers 10 --wait-topics /imu/data /camera/image_rect
  bevo play seq06_bag --wait-for-subscribers 10 --wait-params params/kitti.yaml   # the node's inputs
DDS discovery follows ROS_DOMAIN_ID and ROS_AUTOMATIC_DISCOVERY_RANGE (use LOCALHOST on shared
networks). Ctrl-C stops cleanly (exit code 130).
"""


class UserError(Exception):
    """Expected bad input: reported on stderr with exit code 2."""


def message_class(msgtype: str):
    """``'sensor_msgs/msg/Imu'`` -> the rclpy message class."""
    parts = msgtype.split("/")
    if len(parts) != 3:
        raise UserError(f"cannot map message type {msgtype!r} to a Python class")
    try:
        return getattr(importlib.import_module(f"{parts[0]}.{parts[1]}"), parts[2])
    except (ImportError, AttributeError):
        raise UserError(f"message type {msgtype} is not installed for rclpy (package {parts[0]})") from None


def build_parser() -> argparse.ArgumentParser:
    p = new_parser(__doc__, EPILOG)
    p.add_argument("bag", help="rosbag2 directory (or its .db3 / .mcap file)")
    p.add_argument("--rate", type=float, default=1.0, help="playback speed factor; 0 = as fast as possible (default 1)")
    p.add_argument("--start", type=float, default=0.0, metavar="S", help="skip the first S seconds of the bag")
    p.add_argument("--topics", nargs="+", metavar="TOPIC", help="play only these topics (default: all)")
    p.add_argument("--qos-depth", type=int, default=1000, help="reliable keep-last depth of the publishers (default 1000)")
    p.add_argument("--wait-for-subscribers", type=float, default=0.0, metavar="SEC",
                   help="before playing, wait up to SEC seconds until every topic has a subscriber")
    p.add_argument("--wait-topics", nargs="+", metavar="TOPIC",
                   help="with --wait-for-subscribers: wait only for these (bag) topics, e.g. the node's inputs "
                        "(topics nobody subscribes to, like ground truth, would otherwise hold the start)")
    p.add_argument("--wait-params", metavar="FILE",
                   help="with --wait-for-subscribers: wait too for the inputs bevo_node takes with this parameters "
                        "file (its imu, image, camera_info and, when set, speed topics), as the launch file does")
    p.add_argument("--namespace", default="", metavar="NS",
                   help="publish the bag's topics under this namespace (/imu/data -> /NS/imu/data), for a node "
                        "started in NS; /tf, /tf_static and /clock stay global")
    p.add_argument("--no-clock", action="store_true", help="do not publish /clock")
    p.add_argument("--clock-topic", default="/clock")
    p.add_argument("--clock-rate", type=float, default=100.0, metavar="HZ",
                   help="/clock rate while waiting between messages (default 100; it is also published "
                        "with every message's bag time)")
    p.add_argument("--linger", type=float, default=10.0, metavar="SEC",
                   help="at the end, wait up to SEC seconds for reliable deliveries to be acknowledged (default 10: "
                        "a sample that missed the shared memory is resent only at the next heartbeat, and a "
                        "player that exits first loses it; returns as soon as everything is acknowledged)")
    p.add_argument("--quiet", "-q", action="store_true", help="only print the final counts")
    return p


GLOBAL_TOPICS = ("/tf", "/tf_static", "/clock", "/rosout", "/parameter_events")
LATCHED_TOPICS = ("/tf_static",)  # transient local whatever the bag recorded (tf2's listeners ask for it)


def namespaced(topic: str, namespace: str) -> str:
    """``/imu/data`` under ``car1`` -> ``/car1/imu/data`` (global topics unchanged)."""
    ns = namespace.strip("/")
    if not ns or topic in GLOBAL_TOPICS:
        return topic
    return f"/{ns}/{topic.lstrip('/')}"


class Player:
    """Publishers for a bag's topics plus /clock."""

    def __init__(self, node, topics: dict[str, str], args, recorded: dict[str, bag.TopicQos] | None = None):
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        def qos(topic: str) -> QoSProfile:
            """Reliable (compatible with any subscriber), the recorded durability (/tf_static latched
            even where the bag has no record), keep-last --qos-depth."""
            rec = (recorded or {}).get(topic, bag.TopicQos())
            latched = rec.transient_local or topic in LATCHED_TOPICS
            return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=args.qos_depth,
                              reliability=ReliabilityPolicy.RELIABLE,
                              durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)

        self.node = node
        self.qos = {t: qos(t) for t in topics}
        self.publishers = {t: node.create_publisher(message_class(mt), namespaced(t, args.namespace), self.qos[t])
                           for t, mt in topics.items()}
        self.clock_pub, self.clock_topic = None, args.clock_topic
        if not args.no_clock:
            from rosgraph_msgs.msg import Clock

            self.Clock = Clock
            self.clock_pub = node.create_publisher(Clock, args.clock_topic, QoSProfile(
                depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE))
        self.counts = {t: 0 for t in topics}
        self.clock_count = 0
        self.latched = [t for t, q in self.qos.items() if q.durability == DurabilityPolicy.TRANSIENT_LOCAL]

    def publish_clock(self, stamp_ns: int) -> None:
        if self.clock_pub is None:
            return
        msg = self.Clock()
        msg.clock.sec, msg.clock.nanosec = divmod(int(stamp_ns), 1_000_000_000)
        self.clock_pub.publish(msg)
        self.clock_count += 1

    def wait_for_subscribers(self, timeout: float, topics: list[str] | None = None) -> list[str]:
        """Topics (all, or ``topics``) still without a subscriber after ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        watched = {t: p for t, p in self.publishers.items() if not topics or t in topics}
        while True:
            missing = [t for t, p in watched.items() if p.get_subscription_count() == 0]
            if not missing or time.monotonic() >= deadline:
                return missing
            time.sleep(0.02)

    def wait_for_acks(self, timeout: float) -> list[str]:
        """Let reliable samples reach the subscribers before the publishers go away; returns the
        topics still not acknowledged by every subscriber after ``timeout`` seconds.

        Bounded: DDS acknowledges on its heartbeat period (seconds), usually long after the
        samples themselves arrived.
        """
        from rclpy.duration import Duration

        deadline = time.monotonic() + timeout
        pending = []
        for topic, p in [*self.publishers.items(), *([(self.clock_topic, self.clock_pub)] if self.clock_pub else [])]:
            left = max(0.0, deadline - time.monotonic())
            if not p.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
                pending.append(topic)
        return pending


def node_input_topics(params_file: str) -> list[str]:
    """The topics bevo_node subscribes to with ``params_file``, as its parameters name them (relative
    or absolute): IMU, images (``<image_topic>/compressed`` with ``image_transport: compressed``),
    CameraInfo when it uses it, the speed when set. ConfigError (a ValueError) for a file the
    node's section cannot be read from."""
    from bevo_ros.config import load_params_file
    from bevo_ros.ros.settings import settings_from_flat

    s = settings_from_flat(load_params_file(params_file))
    image = s.image_topic.rstrip("/") + "/compressed" if s.image_transport == "compressed" else s.image_topic
    return [n for n in (s.imu_topic, image, s.camera_info_topic if s.use_camera_info else "", s.speed_topic) if n]


def _wait_topics_from_params(params_file: str, namespace: str) -> list[str]:
    """``--wait-params``: :func:`node_input_topics` as the bag's names (the player publishes bag topic
    ``/x`` as ``/NS/x``, where a node in NS subscribes to a relative ``x``). A file it cannot read
    (a namespaced section: ``/car1/bevo_node``) or an absolute name under a namespace is said on
    stderr, and the default inputs are waited for instead: the replay goes on either way."""
    from bevo_ros.config import ConfigError
    from bevo_ros.ros.settings import NodeSettings

    try:
        names = node_input_topics(params_file)
    except ConfigError as exc:
        d = NodeSettings()
        names = [d.imu_topic, d.image_topic, d.camera_info_topic]
        print(f"{prog_name('play_bag')}: --wait-params: {exc}; waiting for the default inputs "
              f"{', '.join('/' + n for n in names)}", file=sys.stderr)
    outside = [n for n in names if n.startswith("/")]
    if namespace and outside:
        print(f"{prog_name('play_bag')}: --wait-params: {', '.join(outside)} are absolute: the node subscribes "
              f"to them outside namespace {namespace!r}, where this player does not publish them", file=sys.stderr)
    return ["/" + n.lstrip("/") for n in names]


def publish_latched(player: Player, args, start_ns: int | None, first_ns: int) -> int:
    """Before the clock and the data: each latched topic's messages up to the start (the newest of each
    stamped before ``start_ns``, or those at the bag's first stamp without one: /tf_static), published
    and acknowledged (bounded by ``--linger``), so that a node reads the rig before its first image
    (published in bag order, a node's executor took an image and CameraInfo before /tf_static now and
    then, and started on the parameters' rig). Returns the bag time up to which they were published
    (:func:`play` leaves those out)."""
    if not player.latched:
        return -1
    cutoff = start_ns - 1 if start_ns is not None else first_ns
    newest = {}
    for msg in bag.iter_raw_messages(args.bag, player.latched, stop_ns=cutoff + 1):
        if start_ns is None:
            newest.setdefault(msg.topic, []).append(msg)  # all of the first stamp
        else:
            newest[msg.topic] = [msg]
    for msgs in newest.values():
        for msg in msgs:
            player.publishers[msg.topic].publish(msg.data)
            player.counts[msg.topic] += 1
    if newest:
        from rclpy.duration import Duration

        for topic in newest:
            player.publishers[topic].wait_for_all_acked(Duration(nanoseconds=int(min(args.linger, 2.0) * 1e9)))
        time.sleep(0.2)  # acknowledged by DDS; the subscriber's executor takes it at its next turn
    return cutoff


def play(player: Player, args, start_ns: int | None, latched_until: int = -1) -> None:
    """Publish every message at its bag time (scaled by ``args.rate``), with /clock; latched topics'
    messages up to ``latched_until`` were published already (:func:`publish_latched`)."""
    wall0 = bag0 = None
    clock_period = 1.0 / args.clock_rate if args.clock_rate > 0 else None
    for msg in bag.iter_raw_messages(args.bag, list(player.publishers), start_ns=start_ns):
        if msg.stamp_ns <= latched_until and msg.topic in player.latched:
            continue
        if wall0 is None:
            wall0, bag0 = time.monotonic(), msg.stamp_ns
        if args.rate > 0:
            target = wall0 + (msg.stamp_ns - bag0) * 1e-9 / args.rate
            while True:
                now = time.monotonic()
                if now >= target:
                    break
                if clock_period is not None:
                    # Interpolated bag time while waiting, like `ros2 bag play --clock`.
                    player.publish_clock(bag0 + int((now - wall0) * args.rate * 1e9))
                    time.sleep(min(clock_period, target - now))
                else:
                    time.sleep(target - now)
        player.publish_clock(msg.stamp_ns)
        player.publishers[msg.topic].publish(msg.data)
        player.counts[msg.topic] += 1


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not (args.rate >= 0 and args.start >= 0) or args.qos_depth < 1 or not math.isfinite(args.start):  # NaN too
        print(f"{prog_name('play_bag')}: error: --rate and --start must be >= 0, --qos-depth >= 1", file=sys.stderr)
        return 2
    try:
        topics = {t: mt for t, (mt, _) in bag.bag_topics(args.bag).items()}
        if args.topics:
            missing = [t for t in args.topics if t not in topics]
            if missing:
                raise UserError(f"{args.bag}: no topic {', '.join(missing)} (the bag has: {', '.join(sorted(topics))})")
            topics = {t: topics[t] for t in args.topics}
        for t, mt in list(topics.items()):
            try:
                message_class(mt)
            except UserError as exc:
                if args.topics:
                    raise
                # e.g. /tf_static without tf2_msgs (BEVO_SKIP_TF2_MSGS): play the rest, say so
                print(f"{prog_name('play_bag')}: skipping {t}: {exc}", file=sys.stderr)
                del topics[t]
        if not any(count for t, (_, count) in bag.bag_topics(args.bag).items() if t in topics):
            raise UserError(f"{args.bag}: no messages to play")
        first_ns, last_ns = bag.bag_time_range(args.bag)
        if args.start > (last_ns - first_ns) * 1e-9:  # it played nothing, exit 0
            raise UserError(f"--start {args.start:g} s is past the bag's end ({(last_ns - first_ns) * 1e-9:.3f} s "
                            "after its first message)")
        recorded = bag.topic_qos(args.bag)
        if args.wait_params:
            args.wait_topics = [*(args.wait_topics or []), *_wait_topics_from_params(args.wait_params, args.namespace)]
        if args.wait_for_subscribers > 0 and args.wait_topics and not set(args.wait_topics) & set(topics):
            print(f"{prog_name('play_bag')}: none of the topics to wait for ({', '.join(args.wait_topics)}) is "
                  "played from the bag: not waiting", file=sys.stderr)
    except (UserError, FileNotFoundError, ValueError) as exc:
        print(f"{prog_name('play_bag')}: error: {exc}", file=sys.stderr)
        return 2
    # --start counts from the bag's first message (as `ros2 bag play --start-offset`).
    start_ns = first_ns + int(round(args.start * 1e9)) if args.start > 0 else None

    import rclpy
    from rclpy.exceptions import NameValidationException
    from rclpy.signals import SignalHandlerOptions

    # Python's own SIGINT handling (KeyboardInterrupt) is all we need: no spinning here.
    rclpy.init(args=None, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("bag_player", start_parameter_services=False)
    player = None
    rc = 0
    try:
        player = Player(node, topics, args, recorded)
        if args.wait_for_subscribers > 0:
            missing = player.wait_for_subscribers(args.wait_for_subscribers, args.wait_topics)
            if missing and not args.quiet:
                print(f"{prog_name('play_bag')}: no subscriber after {args.wait_for_subscribers:g} s on: "
                      f"{', '.join(missing)}",
                      file=sys.stderr)
        if not args.quiet:
            print(f"playing {args.bag} ({len(topics)} topics, rate {args.rate:g}, domain "
                  f"{os.environ.get('ROS_DOMAIN_ID', '0')})", file=sys.stderr)
        play(player, args, start_ns, publish_latched(player, args, start_ns, first_ns))
        unacked = player.wait_for_acks(args.linger)
        if unacked:  # a subscriber that lags (or died): what it may not have received
            print(f"{prog_name('play_bag')}: not acknowledged by every subscriber after --linger {args.linger:g} s: "
                  f"{', '.join(unacked)}", file=sys.stderr)
    except KeyboardInterrupt:
        print(f"{prog_name('play_bag')}: interrupted", file=sys.stderr)
        rc = 130
    except (UserError, ValueError, NameValidationException) as exc:  # e.g. --namespace "bad ns", --clock-topic
        print(f"{prog_name('play_bag')}: error: {exc}", file=sys.stderr)
        rc = 2
    finally:
        if player is not None:
            for topic, count in sorted(player.counts.items()):
                print(f"  {topic}: {count} msgs")
            if player.clock_pub is not None:
                print(f"  {args.clock_topic}: {player.clock_count} msgs")
        node.destroy_node()
        rclpy.try_shutdown()
    return rc
