"""bevo_node's data path from the subscriptions into the engine.

:class:`Intake`: every IMU/image message already received is taken and handled in stamp order
(``ordered_intake``: the offline order, so the IMU keeps up under load), through each stream's
time-jump guard (a lone outlier stamp is dropped, a confirmed jump back resets). An image is large
and DDS orders no topic against another, so a frame can arrive after IMU samples stamped later:
with ``ordered_intake`` the IMU past the sample each frame waits for is held (:class:`ImuHold`)
until the next image arrives (or ``image_wait``), which keeps the offline order.
:class:`EngineFeed`: the engine calls; stamps not after the previous one (a drop, or a reset and
retry for a big jump back); what the engine dropped or rejected (its events) turned into counted,
logged drops and events; the IMU that arrives before the calibration; the ``image_wait`` flush;
the inputs since the engine's start (:class:`Journal`), which an engine rebuilt for a rig that
changed before its second frame is fed again (:meth:`EngineFeed.replay`).
"""
from __future__ import annotations

import collections
import time
from typing import Any, Callable

from bevo_ros.core.odometry import InvalidInputError, OutOfOrderError
from bevo_ros.core.trajectory import check_pose
from bevo_ros.core.validation import ImplausibleImuError, TimeJumpGuard
from bevo_ros.ros.diagnostics import Report
from bevo_ros.io.ros_conversions import stamp_to_sec

KINDS = ("imu", "image")


def label(kind: str) -> str:
    return "IMU" if kind == "imu" else kind


def arrival(info) -> float:
    """Wall-clock seconds when DDS received the message (else now): latency covers queueing."""
    ns = info.get("received_timestamp") if isinstance(info, dict) else None
    return ns * 1e-9 if ns else time.time()


def watch_clock_jumps(node, max_back: float, on_jump: Callable[[Any], None]):
    """Call ``on_jump`` when ROS time (``/clock`` with use_sim_time) jumps back by more than
    ``max_back`` s; returns the handle to keep (None, logged, where rclpy cannot: resets then
    rely on message stamps)."""
    try:
        from rclpy.clock import JumpThreshold
        from rclpy.duration import Duration

        threshold = JumpThreshold(min_forward=None, on_clock_change=False,
                                  min_backward=Duration(nanoseconds=-int(max_back * 1e9)))
        return node.get_clock().create_jump_callback(threshold, post_callback=on_jump)
    except Exception as exc:  # noqa: BLE001 - optional feature
        node.get_logger().warning(f"no clock jump handler (resets then rely on message stamps): {exc}")
        return None


class Intake:
    """Ordered intake and time-jump guards. ``dispatch(kind, (msg, arrival))`` handles a message,
    ``reset()`` restarts the odometry; ``subs`` maps ``imu``/``image`` to their subscriptions."""

    def __init__(self, settings, report: Report, monitors: dict, dispatch: Callable[[str, tuple], None],
                 reset: Callable[[], None]) -> None:
        s = self.settings = settings
        self.report, self.monitors, self.dispatch, self.reset = report, monitors, dispatch, reset
        self.subs: dict[str, Any] = {}
        self.guards = {kind: TimeJumpGuard(s.max_time_jump_back, s.max_time_jump_forward, s.time_jump_confirmations)
                       for kind in KINDS}
        self.hold = ImuHold(dispatch)

    def take_all(self, sub) -> list:
        """Every message ``sub`` has already received, taken now (not one per executor turn).
        rclpy has no public call for it: its subscription handle is used, and when that changes
        ``ordered_intake`` turns itself off (executor order then)."""
        out: list = []
        try:
            with sub.handle:
                while len(out) < 100000:
                    taken = sub.handle.take_message(sub.msg_type, sub.raw)
                    if taken is None:
                        break
                    out.append((taken[0], arrival(taken[1])))
        except (AttributeError, TypeError, KeyError) as exc:
            self.settings.ordered_intake = False
            self.report.log("ordered_intake", f"ordered_intake disabled (rclpy cannot take messages directly: {exc})")
        return out

    def speed(self, msg, info) -> None:
        """Executor callback of the speed input: in its place among the IMU samples (``ImuHold``)."""
        self.report.counts["speed_in"] += 1
        if "speed" in self.monitors:
            self.monitors["speed"].tick()
        self._dispatch("speed", (msg, arrival(info)))

    def received(self, kind: str, msg, info) -> None:
        """Executor callback (message + message info)."""
        item = (msg, arrival(info))
        self.merge([item] if kind == "imu" else [], [item] if kind == "image" else [])

    def merge(self, imus: list, images: list) -> None:
        """Process IMU and image messages in stamp order (IMU first on equal stamps).

        The executor takes one message per subscription per turn, so when the node is behind,
        images would outrun the IMU they wait for (and see an attitude from the wrong time).
        With ``ordered_intake`` everything already received is taken and merged by stamp: the
        offline order. Two streams whose heads are further apart than ``max_time_jump_back``
        (a bag restart inside the backlog) are taken IMU first, in arrival order.
        """
        if self.settings.ordered_intake:
            imus = imus + self.take_all(self.subs["imu"])
            images = images + self.take_all(self.subs["image"])
        i = j = 0
        jump = self.settings.max_time_jump_back
        while i < len(imus) or j < len(images):
            if j >= len(images):
                take_imu = True
            elif i >= len(imus):
                take_imu = False
            else:
                ti, tg = stamp_to_sec(imus[i][0].header.stamp), stamp_to_sec(images[j][0].header.stamp)
                take_imu = ti <= tg or abs(ti - tg) > jump
            if take_imu:
                self._gated("imu", imus[i])
                i += 1
            else:
                self._gated("image", images[j])
                j += 1

    def _gated(self, kind: str, item: tuple) -> None:
        """Count one received ``(msg, arrival)`` and hand it on through the stream's time-jump guard."""
        self.report.counts["imu_in" if kind == "imu" else "images_in"] += 1
        self.monitors[kind].tick()
        self._gate(kind, item)

    def _gate(self, kind: str, item: tuple) -> None:
        guard = self.guards[kind]
        v = guard.check(stamp_to_sec(item[0].header.stamp), item)
        self._drop_outliers(kind, v.outliers)
        if v.accept:
            self._dispatch(kind, item)
            return
        if v.jump is None:
            return  # held until confirmed or found to be an outlier
        self.report.events[f"time_jump_{v.jump}"] += 1
        release = [(kind, it) for it in v.release]
        if v.jump == "back":
            self.reset()
            for other, g in self.guards.items():  # the other inputs move to the new timeline too
                if g is not guard:
                    more, outliers = g.rebase(guard.ref)
                    self._drop_outliers(other, outliers)
                    release += [(other, it) for it in more]
            release.sort(key=lambda r: (stamp_to_sec(r[1][0].header.stamp), r[0] != "imu"))
        self.report.log(f"time_jump_{v.jump}", f"time jumped {v.jump} by {v.jump_size:.3f} s (confirmed by "
                                               f"{len(v.release)} {label(kind)} messages; bag restarted?): "
                                               + ("odometry reset, the trajectory restarts at identity"
                                                  if v.jump == "back" else "continuing on the new timeline"))
        for k, it in release:
            self._dispatch(k, it)

    def _dispatch(self, kind: str, item: tuple) -> None:
        if self.settings.ordered_intake:
            self.hold.dispatch(kind, item)
        else:
            self.hold.release_all()  # switched off (live, or rclpy could not take): nothing stays held
            self.dispatch(kind, item)

    def release_stale(self, wait: float) -> None:
        """Hand on held IMU that has waited ``wait`` seconds (wall) plus a frame interval for an
        image: a frame dropped, the camera stopped or lagging (the flush timer's call). Counted: an
        image that still comes after it may give other poses than ``bevo run``."""
        n = self.hold.release_stale(wait)
        if n and self.hold.last_image is not None:  # before the first image the camera is starting: nothing to say
            self.report.events["imu_hold_timeout"] += 1
            self.report.log("imu_hold_timeout", f"{n} IMU sample(s) waited more than image_wait={wait:g} s plus a "
                                                "frame interval for the next image: fused without it (a frame "
                                                "arriving later than that is processed out of the offline order)",
                            level="info")

    def clear(self) -> None:
        """Forget the held IMU: the odometry was reset (a time jump back: they belong to the old timeline)."""
        self.hold.clear()

    def rejudge(self) -> None:
        """After a reset by a clock jump: held messages are judged again on the new timeline."""
        for kind, guard in self.guards.items():
            for item in guard.reset():
                self._gate(kind, item)

    def _drop_outliers(self, kind: str, items: list) -> None:
        for msg, _ in items:
            self.report.drop("stamp_outlier", f"{label(kind)} stamp {stamp_to_sec(msg.header.stamp):.6f} is off the "
                                              f"{label(kind)} timeline ({self.guards[kind].ref:.6f}) by more than "
                                              "max_time_jump_back/forward and no other message confirmed the jump "
                                              f"(time_jump_confirmations={self.settings.time_jump_confirmations})")


# fused mode: frames whose measurement the motion filter rejected (the pose is carried by its
# prediction, the odometry still published): events, not drops
ENGINE_REJECTIONS = (
    ("rejected_textureless", "a correlation peak below odometry.min_quality (black, covered or textureless frame)"),
    ("rejected_translation", "a forward motion beyond the odometry.gate Mahalanobis gate"),
    ("rejected_rotation",
     "an image rotation disagreeing with the gyro beyond the odometry.gate or odometry.rotation_gate"),
    ("rejected_speed", "a speed_topic speed (its mean over the frame) beyond the odometry.gate Mahalanobis gate"),
)
# fused mode: engine counters of frame states, not faults, reported as events: frames at rest (zero
# motion, the gyro's biases observed) and frames whose translation took a correlation peak other
# than the highest (the one nearest the motion filter's prediction, or in the direction of travel:
# a second motion in view, the car ahead, its shadow), and frame pairs over which the pitch-change
# correction was off (the DUKF pulled hard by its accelerometer, or turning with its roll unconverged);
# both modes: frames that moved near the BEV's reach (core.odometry.REACH_SHARE: a WARN in /diagnostics)
ENGINE_STATES = ("standstill", "gated_peak", "pitch_correction_off", "skipped_frame_rate", "beyond_reach")
# engine event -> node drop reason, and why (formatted with the node settings as ``s``)
ENGINE_DROPS = (
    ("dropped_no_imu", "no_imu", "with no IMU sample at or before their stamp (frames before any IMU)"),
    ("dropped_pending_overflow", "pending_overflow",
     "more than max_pending_images={s.max_pending_images} images were waiting for IMU"),
    ("dropped_invalid_bev", "invalid_bev",
     "whose BEV had no valid pixel (pitch/roll put the ground patch out of the image)"),
    ("dropped_held_invalid", "held_invalid",
     "held for the start's camera tilt that the engine refused when they ran (the camera changed meanwhile)"),
)



class ImuHold:
    """Keeps the offline order when a frame arrives after IMU samples stamped later than it.

    Offline (``bevo run``) a frame is processed right after the first IMU sample at or past its
    stamp (the engine waits for it: the attitude is interpolated to the stamp), and every later
    sample sees that frame's update (the motion filter's speed in the accelerometer's
    compensation). A node fed live can receive the large image message after the next IMU samples;
    fused first, they use the speed before the frame and the poses differ from ``bevo run``
    (millimetres on a synthetic drive). So a sample past the last image is handed on only while
    that image still waits for one (none at or past its stamp handed on yet); later ones are held
    until the next image arrives (before the first image, all of them). Then the held ones up to its
    stamp go on, the image, and, if the image still waits for one, the first held sample past it.
    Held samples delay no output (no frame waits for them). When no image comes (a frame dropped,
    the camera stopped) they go on after ``wait`` plus the last frame interval
    (:meth:`release_stale`, the node's flush timer; counted by the caller: a frame arriving after
    that may differ from ``bevo run`` again). At most ``limit`` are held: beyond it the oldest goes on.
    """

    def __init__(self, sink: Callable[[str, tuple], None], limit: int = 1000) -> None:
        self.sink, self.limit = sink, limit
        self._held: collections.deque = collections.deque()  # (stamp, item, held since: monotonic s, kind)
        self._last_image: float | None = None  # newest image stamp handed on
        self._last_sent: float | None = None  # newest IMU stamp handed on
        self._image_wall: float | None = None  # when the last image was handed on (monotonic s)
        self._period = 0.0  # wall interval between the last two images, s (at most 1 s)

    @property
    def held(self) -> int:
        return len(self._held)

    @property
    def last_image(self) -> float | None:
        return self._last_image

    def _waiting(self) -> bool:
        """The last image still waits for a sample at or past its stamp."""
        return self._last_image is not None and (self._last_sent is None or self._last_sent < self._last_image)

    def _send_imu(self, stamp: float, item: tuple) -> None:
        self._last_sent = stamp if self._last_sent is None else max(self._last_sent, stamp)
        self.sink("imu", item)

    def _send_held(self, n: int) -> None:
        for _ in range(n):
            if not self._held:  # the sink reset the node (clear()) meanwhile
                return
            stamp, item, _, kind = self._held.popleft()
            if kind == "imu":
                self._send_imu(stamp, item)
            else:
                self.sink(kind, item)

    def dispatch(self, kind: str, item: tuple) -> None:
        t = stamp_to_sec(item[0].header.stamp)
        if kind == "speed":  # keeps its place among the IMU samples: the DUKF's compensation reads it
            if self._held:
                self._held.append((t, item, time.monotonic(), kind))
            else:
                self.sink(kind, item)
            return
        if kind == "imu":
            if self._last_image is None or (t > self._last_image and not self._waiting()):
                self._held.append((t, item, time.monotonic(), kind))
                if len(self._held) > self.limit:
                    self._send_held(1)
            else:  # at or before the last image (the engine judges its order), or the sample it waits for
                self._send_imu(t, item)
            return
        n = 0
        while n < len(self._held) and self._held[n][0] <= t:
            n += 1
        self._send_held(n)  # the IMU up to the frame's stamp, before it
        self.sink(kind, item)
        now = time.monotonic()
        if self._image_wall is not None:
            self._period = min(now - self._image_wall, 1.0)
        self._image_wall = now
        self._last_image = t if self._last_image is None else max(self._last_image, t)
        while self._held and self._waiting():
            self._send_held(1)  # the sample the frame waits for (and the speeds held before it)

    def release_stale(self, wait: float) -> int:
        """Hand on everything held when its oldest sample has waited ``wait`` plus the last frame
        interval; -> how many went on."""
        if self._held and time.monotonic() - self._held[0][2] >= wait + self._period:
            n = len(self._held)
            self._send_held(n)
            return n
        return 0

    def release_all(self) -> None:
        self._send_held(len(self._held))

    def clear(self) -> None:
        self._held.clear()
        self._last_image = self._last_sent = self._image_wall = None
        self._period = 0.0


JOURNAL_MAX_IMAGES = 20  # a longer start (images waiting for IMU) takes a late rig as it comes


class Journal:
    """The engine's inputs since its (re)start, in the order it had them, while it has output at
    most ``frames`` frames: what an engine rebuilt for another rig replays (:meth:`EngineFeed.replay`).

    ``(kind, stamp, raw, tag)`` entries (kind ``imu``, ``image``, ``flush``, ``set_pose`` or ``speed``;
    ``raw`` the caller's input before the rig made it the engine's: the IMU in its own axes, the image
    message, the set_pose arguments, the speed, its variance and whether it is signed). Bounded:
    past ``max_imu`` IMU or ``max_images`` image entries, or past ``frames`` frames out, it stops
    (``active`` false) and forgets them until the next restart.
    """

    def __init__(self, max_imu: int, max_images: int, frames: int = 1) -> None:
        self.max_imu, self.max_images, self.frames = max_imu, max_images, frames
        self.entries: list[tuple[str, float, Any, Any]] = []
        self.active = False
        self._counts = {"imu": 0, "image": 0, "flush": 0, "set_pose": 0, "speed": 0}
        self._frames_base = 0  # the engine's frames_out at the restart

    def restart(self, frames_out: int, max_images: int | None = None) -> None:
        """Record anew from an engine whose ``counters.frames_out`` is ``frames_out`` now."""
        self.entries.clear()
        self._counts = dict.fromkeys(self._counts, 0)
        self._frames_base, self.active = frames_out, True
        if max_images is not None:
            self.max_images = max_images

    def rebase(self, frames_out: int) -> None:
        """The engine behind the entries is now one whose ``counters.frames_out`` was ``frames_out`` at their start."""
        self._frames_base = frames_out

    def stop(self) -> None:
        self.entries.clear()
        self.active = False

    def add(self, kind: str, stamp: float, raw: Any = None, tag: Any = None) -> None:
        if not self.active:
            return
        self._counts[kind] += 1
        if max(self._counts["imu"], self._counts["speed"]) > self.max_imu or self._counts["image"] > self.max_images:
            self.stop()  # too long a start to replay: a later rig change is applied as it comes
            return
        self.entries.append((kind, stamp, raw, tag))

    def check(self, frames_out: int) -> None:
        """After an engine call: past its ``frames``-th frame the engine's output is published for good."""
        if self.active and frames_out - self._frames_base > self.frames:
            self.stop()


class EngineFeed:
    """The engine behind the node (None until the camera is known; IMU meanwhile waits in a
    bounded backlog). ``reset()`` is the node's (engine, path, backlog); each call returns the
    steps to publish, or None when the input was dropped (counted).

    Inputs come raw (``imu``: the IMU in its own axes, ``image``: the message) and ``inputs(kind,
    stamp, raw)`` (the node's rig) turns them into the engine's arguments (None: dropped, counted
    there) when they go in, so the IMU that waited for the calibration, and a replay, take the rig
    known then."""

    def __init__(self, settings, max_imu_gap: float, report: Report, reset: Callable[[], None],
                 inputs: Callable[[str, float, Any], tuple | None]) -> None:
        self.settings, self.max_imu_gap, self.report, self.reset_node = settings, max_imu_gap, report, reset
        self.inputs = inputs
        self.engine = None
        self.last_imu_stamp: float | None = None
        self._last_gap = 0.0
        self._states_seen = dict.fromkeys(ENGINE_STATES, 0)  # the engine's state counters already reported
        self._imu_backlog: collections.deque = collections.deque(maxlen=max(settings.imu_qos_depth, 1000))
        # a start's inputs: the backlog and as much again (100 Hz: 20 s), the held images and two frames
        self.journal = Journal(2 * self._imu_backlog.maxlen, self._journal_images())
        self._pose_request: dict | None = None  # a set_pose that came before the engine
        self._speed_backlog: collections.deque = collections.deque(maxlen=self._imu_backlog.maxlen)  # likewise
        self._last_image_arrival = time.time()  # wall clock, for the held images' flush (flush_due)

    def start(self, engine, images: list | None = None) -> list:
        """Use ``engine`` from now on: the IMU that arrived before it and the ``images``
        ``(stamp, raw, tag)`` held for the calibration, merged by stamp (IMU first on equal
        stamps: the offline order, so the held frames see the IMU they would have). -> the steps."""
        self.engine = engine
        self._states_seen = self._state_counts()
        engine.max_pending_images = self.settings.max_pending_images
        self.journal.restart(engine.counters.frames_out, self._journal_images())
        if self._pose_request is not None:  # set before the calibration: the engine takes it by its stamp
            request, self._pose_request = self._pose_request, None
            self.set_pose(request)
        backlog = [(t, 0, raw, None) for t, raw in self._imu_backlog] + [(t, 0, raw, "speed")
                                                                          for t, raw in self._speed_backlog]
        self._imu_backlog.clear()
        self._speed_backlog.clear()
        steps: list = []
        for t, rank, raw, tag in sorted(backlog + [(t, 1, raw, tag) for t, raw, tag in images or ()],
                                        key=lambda e: (e[0], e[1])):
            out = self.speed(t, *raw) if tag == "speed" else self.imu(t, raw) if rank == 0 else self.image(t, raw, tag)
            steps += out or []
        return steps

    def _journal_images(self) -> int:
        """Images a start may take to be replayable: the pending ones and two frames, at most
        JOURNAL_MAX_IMAGES + 2 (raw messages: 20 of 1080p rgb8 are 124 MB, beside the engine's own); an
        engine that holds its start for the camera's tilt (``filter.tilt_from_images``) its pairs and ten
        more (a rig that comes during the hold is then replayed too; one that comes later, after pairs
        that gave no direction, is taken by the running engine)."""
        base = min(self.settings.max_pending_images, JOURNAL_MAX_IMAGES) + 2
        if getattr(self.engine, "holding", False):  # duck-typed: a test's engine may not hold
            return max(base, self.engine.tilt_from_images + 12)
        return base

    def replay(self, engine) -> list:
        """Use ``engine`` (another rig) from now on, fed again what the current one had since its
        start (:attr:`journal`, :attr:`replayable`), in the same order, each input taken through the
        rig anew: its state is what it would have been had the rig been known from the start. What
        the inputs gave (drops, events) was reported when they came: not again. -> the steps (the
        caller publishes those of frames it has not published)."""
        self._report_events()  # the old engine's, before it goes
        engine.max_pending_images = self.settings.max_pending_images
        steps: list = []
        # Fed as a local first: if it raises, the old engine stays (the caller falls back to it).
        for kind, t, raw, tag in self.journal.entries:
            try:
                if kind == "flush":
                    steps += engine.flush()
                    continue
                if kind == "set_pose":
                    engine.set_pose(**raw)
                    continue
                if kind == "speed":
                    engine.add_speed(t, *raw)
                    continue
                args = self.inputs(kind, t, raw)
                if args is not None:
                    steps += engine.add_imu(t, *args) if kind == "imu" else engine.add_image(t, *args, tag=tag)
            except (ImplausibleImuError, InvalidInputError):
                pass  # dropped and counted when it came
        engine.take_events()
        if callable(getattr(self.engine, "close", None)):  # duck-typed: its start tilt's threads, if it holds
            self.engine.close()
        self.engine = engine
        self._states_seen = self._state_counts()
        # the journal counts this engine's frames from its start (the old one's count ran on past a reset)
        self.journal.rebase(0)
        self.journal.check(engine.counters.frames_out)
        return steps

    @property
    def replayable(self) -> bool:
        """The engine has output at most its first frame since its start, and every input since
        then is in the journal: :meth:`replay` gives what an engine with the new rig would have."""
        return self.engine is not None and self.journal.active

    def reset(self) -> None:
        if self.engine is not None:
            self.engine.reset()
            self.journal.restart(self.engine.counters.frames_out, self._journal_images())
        self._imu_backlog.clear()
        self._speed_backlog.clear()
        self._pose_request = None
        self.last_imu_stamp = None

    def set_pose(self, request: dict) -> str:
        """The engine's :meth:`~bevo_ros.core.odometry.BevoOdometry.set_pose` with ``request`` (its
        keyword arguments); before the engine exists it is kept for it. -> how it was set (``"kept"``
        until the engine starts). InvalidInputError for a pose that is none."""
        if self.engine is None:
            try:
                check_pose(*(request.get(k, 0.0) for k in ("x", "y", "yaw", "z")), request.get("covariance"))
            except ValueError as exc:
                raise InvalidInputError(str(exc)) from None
            self._pose_request = request
            return "kept"
        how = self.engine.set_pose(**request)
        self._journal("set_pose", float("nan"), request)
        return how

    @property
    def pending_images(self) -> int:
        return self.engine.pending_images if self.engine is not None else 0

    @property
    def held_images(self) -> int:
        """Images the engine holds for the start's camera tilt (``filter.tilt_from_images``)."""
        return getattr(self.engine, "held_images", 0)  # duck-typed: a test's engine may not hold

    def imu(self, t: float, raw) -> list | None:
        """One IMU sample (``raw``: in its own axes, as ``inputs`` takes it)."""
        if self.engine is None:  # kept (bounded) and fused once the camera is known: the filter warms up
            if len(self._imu_backlog) == self._imu_backlog.maxlen:
                self.report.drop("no_camera_info", f"IMU at {self._imu_backlog[0][0]:.6f}: more than "
                                                   f"{self._imu_backlog.maxlen} IMU samples waited for the calibration")
            self._imu_backlog.append((t, raw))
            return None
        args = self.inputs("imu", t, raw)
        if args is None:
            return None
        self._last_gap = 0.0 if self.last_imu_stamp is None else t - self.last_imu_stamp
        steps = self._call("imu", t, lambda: self.engine.add_imu(t, *args))
        if steps is not None:
            self.last_imu_stamp = t
        self._journal("imu", t, raw)
        return steps

    def speed(self, t: float, speed: float, variance: float, signed: bool = True) -> list | None:
        """One vehicle speed (m/s, its variance, whether it is signed: ``add_speed``), finite (the node
        checked it). Before the engine it is kept (bounded, as the IMU) and fed with the IMU once the
        camera is known."""
        newest = self.last_imu_stamp
        if newest is not None and t > newest + self.settings.max_time_jump_forward:
            # one far ahead would make every later speed out of order until a reset
            self.report.drop("speed_future", f"speed stamp {t:.6f} is more than max_time_jump_forward="
                                             f"{self.settings.max_time_jump_forward} s after the newest IMU sample "
                                             f"({newest:.6f})")
            return None
        if self.engine is None:
            if len(self._speed_backlog) == self._speed_backlog.maxlen:
                self.report.drop("no_camera_info", f"speed at {self._speed_backlog[0][0]:.6f}: more than "
                                                   f"{self._speed_backlog.maxlen} speeds waited for the calibration")
            self._speed_backlog.append((t, (speed, variance, signed)))
            return None
        try:
            self.engine.add_speed(t, speed, variance, signed)
        except OutOfOrderError as exc:  # dropped, never a reset: the IMU's and images' timeline decides those
            self.report.drop("speed_duplicate" if exc.jump == 0 else "speed_out_of_order",
                             f"speed stamp {t:.9f} is not after the previous speed stamp {exc.last:.9f}")
            return None
        except ValueError as exc:  # the engine's plausibility check (beyond any car's speed)
            self.report.drop("speed_invalid", f"speed at {t:.6f}: {exc}")
            return None
        self._journal("speed", t, (speed, variance, signed))
        return []

    def image(self, t: float, raw, tag) -> list | None:
        """One image (``raw``: the message, as ``inputs`` takes it); ``tag`` comes back on its step."""
        args = self.inputs("image", t, raw)
        if args is None:
            return None
        self._last_image_arrival = time.time()
        steps = self._call("image", t, lambda: self.engine.add_image(t, *args, tag=tag))
        self._journal("image", t, raw, tag)
        return steps

    def _journal(self, kind: str, t: float, raw=None, tag=None) -> None:
        """After the engine call (a reset inside it restarted the journal, the input went to the restarted engine)."""
        self.journal.add(kind, t, raw, tag)
        self.journal.check(self.engine.counters.frames_out)

    def flush_due(self) -> bool:
        """Images have waited for IMU past their stamp longer than ``image_wait``, or images held for the
        start's camera tilt (``filter.tilt_from_images``) saw no further image for ``image_timeout`` and
        their pairs are measured (the camera stopped, a bag ended: they run at what their pairs show)."""
        if self.held_images:
            # pairs still measured release the start when done (poll), with the IMU still on its way: a loaded
            # machine measuring past image_timeout after a bag's last frame flushed them without it (3.9 mm)
            return (not getattr(self.engine, "measuring", False)
                    and time.time() - self._last_image_arrival >= self.settings.image_timeout)
        if not self.pending_images:
            return False
        oldest = min(tag[-1] for tag in self.engine.pending_tags)  # (stamp, arrival, waiting since)
        return time.time() - oldest >= self.settings.image_wait

    def poll(self) -> list:
        """The engine's start released once the pairs it holds for the camera's tilt are measured, with no
        further input (:meth:`~bevo_ros.core.odometry.BevoOdometry.poll`; duck-typed: a test's engine may not hold)."""
        if not self.held_images or not callable(getattr(self.engine, "poll", None)):
            return []
        steps = self.engine.poll()
        if steps:
            self._report_events()
        return steps

    def flush(self) -> list:
        """Process the waiting images with the IMU fused so far."""
        n, held = self.engine.pending_images, self.held_images
        steps = self.engine.flush()
        if held:
            self._journal("flush", float("nan"))
            self._report_events()
            self.report.log("image_wait", f"{held} image(s) held for the start's camera tilt saw no further image for "
                                          f"image_timeout={self.settings.image_timeout} s: run now ({len(steps)} "
                                          "published)", level="info")
            return steps
        self._journal("flush", float("nan"))
        self.report.events["flushed_images"] += len(steps)
        self._report_events()
        self.report.log("image_wait", f"{n} image(s) waited more than image_wait={self.settings.image_wait} s for "
                                      f"IMU past their stamp: processed with the IMU fused so far ({len(steps)} "
                                      "published)", level="info")
        return steps

    def _call(self, kind: str, t: float, call: Callable[[], list]) -> list | None:
        """Run an engine call; what the engine refuses as input is a counted drop (None). Anything
        else it raises is a bug: it goes on to the callback guard (callback_error), blaming no input."""
        try:
            steps = call()
        except OutOfOrderError as exc:
            steps = None
            try:
                steps = self._out_of_order(kind, exc, t, call)
            except (ImplausibleImuError, InvalidInputError) as exc2:
                self.report.drop(f"{kind}_invalid", f"{label(kind)} at {t:.6f}: {exc2}")
        except (ImplausibleImuError, InvalidInputError) as exc:  # ImplausibleImuError carries its own reason
            steps = None
            self.report.drop(getattr(exc, "reason", f"{kind}_invalid"), f"{label(kind)} at {t:.6f}: {exc}")
        self._report_events()
        return steps

    def _out_of_order(self, kind: str, exc: OutOfOrderError, stamp: float, retry: Callable[[], list]) -> list | None:
        """A stamp not after the previous one: a big jump back resets and retries, else a drop (None)."""
        s = self.settings
        if exc.jump > s.max_time_jump_back:
            self.report.events["time_jump_reset"] += 1
            self.report.log(
                "time_jump_reset", f"{label(kind)} stamp {stamp:.6f} is {exc.jump:.3f} s before the previous one "
                f"(> max_time_jump_back={s.max_time_jump_back} s): time jumped back (bag restarted?) - resetting "
                "the odometry; the trajectory restarts at identity")
            self.reset_node()
            return retry()
        reason = f"{kind}_duplicate" if exc.jump == 0 else f"{kind}_out_of_order"
        self.report.drop(reason, f"{label(kind)} stamp {stamp:.9f} is not after the previous {label(kind)} stamp "
                                 f"{exc.last:.9f} ({exc.jump * 1e3:.3f} ms back)")
        return None

    def _state_counts(self) -> dict[str, int]:
        return {k: getattr(self.engine.counters, k) if self.engine is not None else 0 for k in ENGINE_STATES}

    def _report_events(self) -> None:
        """Turn what the engine dropped or rejected (its events) into counted, logged node drops/events,
        and count its frame states (not faults, ENGINE_STATES)."""
        for kind, n in self._state_counts().items():
            if n > self._states_seen[kind]:
                self.report.events[kind] += n - self._states_seen[kind]
                self._states_seen[kind] = n
        d = collections.Counter(e.kind for e in self.engine.take_events()) if self.engine is not None else {}
        if not d:
            return
        for kind, reason, why in ENGINE_DROPS:
            if d[kind] > 0:
                self.report.drop(reason, f"{d[kind]} image(s) " + why.format(s=self.settings), count=d[kind])
        for kind, why in ENGINE_REJECTIONS:
            if d[kind] > 0:
                self.report.events[kind] += d[kind]
                self.report.log(kind, f"{d[kind]} frame(s) with {why}: carried by the motion filter's prediction")
        if d["imu_gaps"] > 0:
            self.report.events["imu_gap"] += d["imu_gaps"]
            self.report.log("imu_gap", f"IMU gap longer than filter.max_imu_gap={self.max_imu_gap} s (last gap "
                                       f"{self._last_gap:.3f} s): the DUKF re-initialised its pitch/roll from the "
                                       "accelerometer")


__all__ = ["Intake", "EngineFeed", "Journal", "arrival", "watch_clock_jumps", "ENGINE_DROPS", "ENGINE_REJECTIONS"]
