"""Running one rclpy node as a process: start, spin, stop on SIGINT/SIGTERM, exit codes.

``ros2 launch`` stops nodes with SIGINT (then SIGTERM): every stop must end with exit code 0 and
no traceback. rclpy's own signal handler shuts the context down at once, under a running
executor: a subscription taken at that moment raised ``RuntimeError: Unable to convert call
argument '0' to Python object`` out of ``rclpy.spin`` (exit 1 with a traceback, 2 of 8 stops of a
node busy with KITTI-sized images). Here the signals only set a flag; the spin loop checks it
between callbacks, then the executor, the node and the context are shut down in that order.
"""
from __future__ import annotations

import signal
import sys
from typing import Callable

EXIT_OK = 0
EXIT_CONFIG_ERROR = 2


class StopRequest:
    """Installs SIGINT/SIGTERM handlers that set ``requested``; ``restore()`` puts the old ones back."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.requested = False
        self._previous = {sig: signal.signal(sig, self._on_signal) for sig in self.SIGNALS}

    def _on_signal(self, signum, frame) -> None:  # noqa: ARG002 - signal handler signature
        self.requested = True

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def run_node(make_node: Callable[[list[str]], object], name: str, argv: list[str] | None = None,
             refuse: tuple[type[BaseException], ...] = ()) -> int:
    """Init rclpy with ``argv``, build the node with ``make_node(argv)`` and spin it until a
    signal or an external shutdown. Returns the exit code: 0, or 2 when ROS cannot start or the
    node refuses to (one FATAL line; ``refuse`` exceptions are printed without their type)."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    argv = list(sys.argv if argv is None else argv)
    stop = StopRequest()
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # noqa: BLE001 - e.g. an unreadable --params-file
        stop.restore()
        print(f"[FATAL] [{name}]: cannot initialise ROS 2: {one_line(exc)}", file=sys.stderr)
        return EXIT_CONFIG_ERROR
    logger = rclpy.logging.get_logger(name)
    node = executor = None
    try:
        try:
            node = make_node(argv)
        except refuse as exc:
            logger.fatal(f"refusing to start: {one_line(exc)}")
            return EXIT_CONFIG_ERROR
        except Exception as exc:  # noqa: BLE001 - a clear line, no traceback
            logger.fatal(f"refusing to start: {type(exc).__name__}: {one_line(exc)}")
            return EXIT_CONFIG_ERROR
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        try:
            while not stop.requested and rclpy.ok():
                executor.spin_once(timeout_sec=0.1)  # a signal is seen within 0.1 s when idle
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except Exception:  # noqa: BLE001
            if not (stop.requested or not rclpy.ok()):
                raise
            # raised by rclpy while the process is being stopped: nothing left to do but stop
        if stop.requested:
            summary = getattr(node, "summary", None)  # what came in and went out, for whoever reads the log
            logger.info("stopping (signal received)" + (f": {summary()}" if callable(summary) else ""))
    finally:
        try:
            if executor is not None:
                executor.shutdown(timeout_sec=1.0)
            if node is not None:
                node.destroy_node()
        finally:
            rclpy.try_shutdown()
            stop.restore()
    return EXIT_OK


__all__ = ["StopRequest", "run_node", "EXIT_OK", "EXIT_CONFIG_ERROR"]
