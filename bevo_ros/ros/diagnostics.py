"""Per-input health for ``/diagnostics``, the way robot_localization treats sensor timeouts.

Each input (IMU, images) keeps its recent arrival times on the steady clock:

* OK    - messages arrive (the rate is measured over the last ``window`` messages);
* WARN  - late: nothing for more than ``late_factor`` x the measured period (or still waiting
          for the first message, before the timeout);
* ERROR - silent for longer than ``timeout`` seconds (or never heard from after ``timeout``);

and goes back to OK as soon as messages flow again.
"""
from __future__ import annotations

import collections
import time
from dataclasses import dataclass
from typing import Callable

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


def status_message(node_name: str, what: str, state: SensorState, hardware_id: str = "bevo"):
    """A diagnostic_msgs/DiagnosticStatus named ``<node>: <what>``."""
    from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

    return DiagnosticStatus(level=bytes([state.level]), name=f"{node_name}: {what}", message=state.message,
                            hardware_id=hardware_id,
                            values=[KeyValue(key=k, value=v) for k, v in state.values.items()])
