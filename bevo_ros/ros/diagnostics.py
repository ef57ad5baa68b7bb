"""What ``bevo_node`` counts and reports: per-input health for ``/diagnostics`` (the way
robot_localization treats sensor timeouts), drops and events by reason with throttled log lines,
latency and correlation quality, and the odometry status built from them.

Each input (IMU, images) keeps its recent arrival times on the steady clock:

* OK    - messages arrive (the rate is measured over the last ``window`` messages);
* WARN  - late: nothing for more than ``late_factor`` x the measured period (or still waiting
          for the first message, before the timeout);
* ERROR - silent for longer than ``timeout`` seconds (or never heard from after ``timeout``);

and goes back to OK as soon as messages flow again.
"""
from __future__ import annotations

import collections
import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

OK, WARN, ERROR = 0, 1, 2  # diagnostic_msgs/DiagnosticStatus levels
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR"}


@dataclass
class SensorState:
    level: int
    message: str
    values: dict[str, str]


class SensorMonitor:
    """Rate and staleness of one input topic (steady clock; ``clock`` is injectable for tests)."""

    def __init__(self, label: str, topic: str, timeout: float, late_factor: float = 3.0, window: int = 50,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.label, self.topic = label, topic
        self.timeout, self.late_factor = float(timeout), float(late_factor)
        self.clock = clock
        self.started = clock()
        self.arrivals: collections.deque[float] = collections.deque(maxlen=max(2, window))
        self.received = 0

    def tick(self, now: float | None = None) -> None:
        """One message arrived."""
        self.arrivals.append(self.clock() if now is None else now)
        self.received += 1

    def period(self) -> float | None:
        """Mean period over the window (s), None with fewer than 2 messages."""
        a = self.arrivals
        if len(a) < 2 or a[-1] <= a[0]:
            return None
        return (a[-1] - a[0]) / (len(a) - 1)

    def state(self, now: float | None = None) -> SensorState:
        now = self.clock() if now is None else now
        period = self.period()
        values = {"topic": self.topic, "received": str(self.received), "timeout_s": f"{self.timeout:g}",
                  "rate_hz": f"{1.0 / period:.2f}" if period else "0.00"}
        if not self.arrivals:
            waited = now - self.started
            values["staleness_s"] = "inf"
            if waited > self.timeout:
                return SensorState(ERROR, f"{self.label}: no message on {self.topic} since start "
                                          f"({waited:.1f} s > timeout {self.timeout:g} s)", values)
            return SensorState(WARN, f"{self.label}: waiting for the first message on {self.topic}", values)
        stale = now - self.arrivals[-1]
        values["staleness_s"] = f"{stale:.3f}"
        if stale > self.timeout:
            return SensorState(ERROR, f"{self.label}: silent for {stale:.1f} s (timeout {self.timeout:g} s) "
                                      f"on {self.topic}", values)
        if period is not None and stale > self.late_factor * period:
            return SensorState(WARN, f"{self.label}: late, last message {stale:.2f} s ago, expected every "
                                     f"{period:.3f} s on {self.topic}", values)
        return SensorState(OK, f"{self.label}: {values['rate_hz']} Hz", values)


def counter_values(prefix: str, counts: dict[str, int]) -> dict[str, str]:
    """Counters as diagnostic key/values ``{"PREFIX.NAME": "N"}``, sorted by name (drops, events, counts)."""
    return {f"{prefix}.{name}": str(n) for name, n in sorted(counts.items())}


def status_message(node_name: str, what: str, state: SensorState, hardware_id: str = "bevo"):
    """A diagnostic_msgs/DiagnosticStatus named ``<node>: <what>``."""
    from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

    return DiagnosticStatus(level=bytes([state.level]), name=f"{node_name}: {what}", message=state.message,
                            hardware_id=hardware_id,
                            values=[KeyValue(key=k, value=v) for k, v in state.values.items()])


class Report:
    """The node's tallies: ``counts`` (imu_in, images_in, camera_info_in, odometry_out), ``drops``
    and ``events`` by reason, the recent log lines (``log_history``), latency and peak quality.

    Args:
        logger: the node's logger.
        settings: the node's settings (``log_throttle_period`` is live, read at each line).
    """

    def __init__(self, logger, settings) -> None:
        self.logger, self.settings = logger, settings
        self.counts: collections.Counter[str] = collections.Counter()
        self.drops: collections.Counter[str] = collections.Counter()
        self.events: collections.Counter[str] = collections.Counter()
        self.log_history: collections.deque[tuple[str, str]] = collections.deque(maxlen=200)
        self._throttle: dict[str, list[float]] = {}
        self.latency: collections.deque[float] = collections.deque(maxlen=settings.latency_window)
        # the frames held for the start's camera tilt (filter.tilt_from_images): seconds late by design, not a
        # running latency; their count and the longest wait, kept apart from the percentiles
        self.start_hold: tuple[int, float] = (0, 0.0)
        self.quality: collections.deque[float] = collections.deque(maxlen=100)
        self._last = (time.monotonic(), collections.Counter())  # (time, counts) of the last values()

    def log(self, key: str, text: str, level: str = "warning") -> None:
        """Log ``text``, at most once per ``log_throttle_period`` per ``key`` (then with a count)."""
        self.log_history.append((key, text))
        now = time.monotonic()
        state = self._throttle.setdefault(key, [-math.inf, 0])
        if now - state[0] < self.settings.log_throttle_period:
            state[1] += 1
            return
        if state[1]:
            text += f" ({state[1]} more since the last report)"
        state[0], state[1] = now, 0
        # rclpy pins one severity per call site: one call per level.
        if level == "error":
            self.logger.error(text)
        elif level == "info":
            self.logger.info(text)
        else:
            self.logger.warning(text)

    def drop(self, reason: str, text: str, level: str = "warning", count: int = 1) -> None:
        """``count`` inputs dropped for ``reason``: counted and logged (throttled)."""
        self.drops[reason] += count
        self.log(reason, f"dropped ({reason}): {text}", level)

    def published(self, arrival: float | None, quality: float, held: bool = False) -> None:
        """One odometry message out: its latency since the image arrived (wall clock), its quality;
        ``held``: a frame the engine held for the start's camera tilt (:attr:`start_hold`)."""
        if arrival is not None and held:
            n, longest = self.start_hold
            self.start_hold = (n + 1, max(longest, time.time() - arrival))
        elif arrival is not None:
            self.latency.append(time.time() - arrival)
        self.counts["odometry_out"] += 1
        if math.isfinite(quality):
            self.quality.append(quality)

    def latency_percentiles(self) -> tuple[float, float, float]:
        """(p50, p99, max) of image arrival -> odometry publication, seconds (nan when empty)."""
        if not self.latency:
            return (math.nan,) * 3
        a = np.asarray(self.latency)
        return float(np.percentile(a, 50)), float(np.percentile(a, 99)), float(a.max())

    def values(self, pending_images: int, tf_backend: str) -> dict[str, str]:
        """The odometry status's key/values; rates are since the previous call."""
        now = time.monotonic()
        last_t, last_counts = self._last
        dt = max(now - last_t, 1e-9)
        self._last = (now, collections.Counter(self.counts))
        rate = lambda k: (self.counts[k] - last_counts[k]) / dt  # noqa: E731
        p50, p99, pmax = self.latency_percentiles()
        values = {
            "imu_rate_hz": f"{rate('imu_in'):.1f}",
            "image_rate_hz": f"{rate('images_in'):.1f}",
            "odometry_rate_hz": f"{rate('odometry_out'):.1f}",
            "imu_received": str(self.counts["imu_in"]),
            "images_received": str(self.counts["images_in"]),
            "odometry_published": str(self.counts["odometry_out"]),
            "drops_total": str(sum(self.drops.values())),
            "latency_p50_ms": f"{p50 * 1e3:.2f}",
            "latency_p99_ms": f"{p99 * 1e3:.2f}",
            "latency_max_ms": f"{pmax * 1e3:.2f}",
            "peak_quality_last": f"{self.quality[-1]:.3f}" if self.quality else "nan",
            "peak_quality_mean": f"{float(np.mean(self.quality)):.3f}" if self.quality else "nan",
            "pending_images": str(pending_images),
            "tf": tf_backend,
        }
        if self.start_hold[0]:  # the latency above is the running frames'
            values["start_hold_frames"] = str(self.start_hold[0])
            values["start_hold_max_ms"] = f"{self.start_hold[1] * 1e3:.2f}"
        if self.counts["speed_in"]:
            values["speeds_received"] = str(self.counts["speed_in"])
        values.update(counter_values("drop", self.drops))
        values.update(counter_values("event", self.events))
        return values

    def summary(self) -> str:
        """One line of totals: inputs received, odometry published, drops and filter events by reason."""
        c = self.counts
        drops = ", ".join(f"{k} {n}" for k, n in sorted(self.drops.items()) if n) or "none"
        events = ", ".join(f"{k} {n}" for k, n in sorted(self.events.items()) if n) or "none"
        speeds = f", speeds {c['speed_in']}" if c["speed_in"] else ""
        return (f"imu {c['imu_in']}, images {c['images_in']}, camera_info {c['camera_info_in']}{speeds} received; "
                f"odometry {c['odometry_out']} published; dropped: {drops}; events: {events}")


# The engine's events for a frame whose image moved nothing: its pose is the motion filter's prediction.
BLIND_FRAME_EVENTS = ("rejected_textureless", "rejected_translation")
BLIND_SHARE = 0.8  # of the frames since the last report (a drive's first frame has no correlation to reject)


def odometry_state(values: dict[str, str], inputs: dict[str, SensorState], calibrated: bool,
                   new_drops: int, new_frames: int = 0, new_blind: int = 0, new_beyond: int = 0) -> SensorState:
    """The odometry's status: ERROR when an input is silent, WARN while uncalibrated, WARN on new
    drops, images without odometry, most new frames blind (``new_blind`` of the ``new_frames``
    published since the last report had :data:`BLIND_FRAME_EVENTS`, at least :data:`BLIND_SHARE`: a
    covered, black or textureless camera, dead reckoning), new frames near the BEV's reach
    (``new_beyond``: the engine's ``beyond_reach``) or a late input, else OK."""
    worst = max((st.level for st in inputs.values()), default=OK)
    if worst == ERROR:  # a silent input is the worse news, calibrated or not
        return SensorState(ERROR, "; ".join(st.message for st in inputs.values() if st.level == ERROR), values)
    if not calibrated:
        return SensorState(WARN, "waiting for CameraInfo", values)
    if new_drops > 0:
        return SensorState(WARN, f"{new_drops} input(s) dropped", values)
    if float(values["image_rate_hz"]) > 0 and float(values["odometry_rate_hz"]) == 0:
        return SensorState(WARN, "images arrive but no odometry is produced", values)
    if new_blind >= 2 and new_blind >= BLIND_SHARE * new_frames:
        return SensorState(WARN, f"{new_blind} of the last {new_frames} frame(s) rejected (a covered, black or "
                                 "textureless camera?): the pose is mostly the motion filter's prediction", values)
    if new_beyond > 0:
        return SensorState(WARN, f"{new_beyond} of the last {new_frames} frame(s) moved more than "
                                 f"{values.get('reach_m', '?')} m, near the BEV's reach: past it a frame's "
                                 "correlation fails (a faster camera, or a longer BEV: README, Limitations, "
                                 "Top speed)", values)
    if worst == WARN:
        return SensorState(WARN, "; ".join(st.message for st in inputs.values() if st.level == WARN), values)
    return SensorState(OK, "running", values)
