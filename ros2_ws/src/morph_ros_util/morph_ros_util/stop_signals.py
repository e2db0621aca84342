"""SIGINT and SIGTERM as a request to stop, read by the process's own loop, never an exception.

rclpy's own handlers shut the context down from inside the signal, while the
main thread may be in ``spin_once``: that call then fails on the dead context
(``RCLError: ... context is not valid``), and the ``KeyboardInterrupt`` that
Python raises later lands in whatever cleanup runs then (seen: a Ctrl-C to
the live bringup printed two tracebacks from the trainer). Here the handler
only sets an event; the loop sees it within one spin and stops cleanly.
"""

from __future__ import annotations

import signal
import threading

import rclpy
from rclpy.signals import SignalHandlerOptions

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def init_stopping_on_signals(args=None) -> threading.Event:
    """``rclpy.init(args)`` without rclpy's signal handlers; returns the event that SIGINT and SIGTERM set.

    Call from the main thread (Python runs signal handlers there), before a loop such as
    ``while not stop.is_set(): executor.spin_once(timeout_sec=0.1)``.
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    for sig in STOP_SIGNALS:
        signal.signal(sig, lambda *_: stop.set())
    return stop
