"""Run a node so that SIGINT and SIGTERM always end it, whatever its executor is doing.

A reliable reader in Fast DDS 2.14 can be driven by a peer into a take that
never returns (a fragmented sample half received, then a GAP for it: the
history frees the sample but leaves it listed, and the take loop retries it
forever). A node spinning in the main thread then never sees a signal again:
Python runs handlers only between bytecodes of the main thread. So the
executor spins in a worker thread and the main thread only waits for a
signal; on one it stops the executor, the node and the context cleanly if
that takes less than ``STOP_GRACE``, and then ends the process at once (a
stuck take cannot be cancelled, and the interpreter's own teardown of the
DDS participant took seconds). Shared by both node packages (morph_policy_node depends on this
one).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

STOP_GRACE = 1.2
"""seconds from a signal to the end of the clean stop (executor, node, context); the process exits at
once when that is over, finished or not"""


def run(make_node: Callable[[], Node], name: str, args=None, startup_errors: tuple[type[Exception], ...] = ()) -> int:
    """Spin ``make_node()`` until SIGINT/SIGTERM; returns the exit code.

    An exception of ``startup_errors`` while the node is made is one fatal log line ("cannot start:
    <error>") and exit code 1, no traceback; an exception in a callback ends the node with its
    traceback and exit code 1.
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    logger = get_logger(name)
    try:
        node = make_node()
    except startup_errors as err:
        logger.fatal(f"cannot start: {err}")
        # Nothing runs yet that needs a clean stop, and tearing down a half-made participant can
        # hang (seen once in a dozen concurrent starts): leave at once.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(1)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    failures: list[BaseException] = []

    def spin() -> None:
        try:
            executor.spin()
        except ExternalShutdownException:
            pass
        except Exception as err:
            # A callback that was publishing when the signal shut the context down fails on the
            # dead context: that is still a normal end.
            if rclpy.ok():
                failures.append(err)
                traceback.print_exc()
        finally:
            stop.set()

    worker = threading.Thread(target=spin, name=f"{name}_executor", daemon=True)
    worker.start()
    while not stop.wait(0.5):  # the main thread stays free to run signal handlers
        pass
    deadline = time.monotonic() + STOP_GRACE

    def clean_stop() -> None:
        rclpy.try_shutdown()  # wakes the executor
        worker.join()
        executor.shutdown(timeout_sec=STOP_GRACE)
        node.destroy_node()  # peers see the node leave now, not at its lease's end

    stopper = threading.Thread(target=clean_stop, name=f"{name}_stop", daemon=True)
    stopper.start()
    stopper.join(max(0.0, deadline - time.monotonic()))
    if stopper.is_alive() and worker.is_alive():
        logger.error(f"the executor did not stop within {STOP_GRACE} s (stuck in the middleware): exiting now")
    # Leave without the interpreter's own teardown: finalising the DDS participant there took 1-3 s
    # on a loaded machine, and everything a peer needs to see (the node's endpoints gone) is done.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(1 if failures else 0)
