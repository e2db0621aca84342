"""Run a node so that SIGINT and SIGTERM always end it, and a node stuck in the middleware ends by itself.

A reliable reader in Fast DDS 2.14 can be driven by a peer into a take that
never returns (a fragmented sample half received, then a GAP for it: the
history frees the sample but leaves it listed, and the take loop retries it
forever). rclpy calls ``rcl_take`` holding the GIL, so such a take stops
every Python thread of the process, signal handlers included (Python runs
them in the main thread, between bytecodes).

So the executor spins in a worker thread, and the main thread waits for a
signal and beats a heart: every ``HEARTBEAT`` s it re-arms
``faulthandler.dump_traceback_later``, whose timer is a C thread that needs
no GIL. If the main thread cannot run for ``WEDGE_TIMEOUT`` s (the GIL held
by a call that does not return) that timer prints every thread's stack (the
stuck call shows) and ends the process with exit code 1: a node never hangs
silently, and a supervisor (a launch file's ``respawn``) starts it again.
On a signal the main thread stops the executor, the node and the context
cleanly if that takes less than ``STOP_GRACE``, then ends the process at
once (the interpreter's own teardown of the DDS participant took seconds).
Shared by both node packages.
"""

from __future__ import annotations

import faulthandler
import os
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence

import rclpy
import rclpy.utilities
from rclpy.exceptions import (
    InvalidParameterException,
    InvalidParameterTypeException,
    InvalidParameterValueException,
)
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.logging import get_logger
from rclpy.node import Node

from morph_ros_util.parameters import NodeParameter, parameters_help
from morph_ros_util.stop_signals import init_stopping_on_signals

STOP_GRACE = 1.2
"""seconds from a signal to the end of the clean stop (executor, node, context); the process exits at
once when that is over, finished or not"""
HEARTBEAT = 0.2
"""seconds between the main thread's re-arming of the wedge timer"""
WEDGE_TIMEOUT = 2.0
"""seconds the main thread may go without running before the process is ended as stuck (a SIGTERM to a
stuck node is thus answered within this time; a switch of the GIL takes milliseconds, so a working node is
far from it even on a loaded machine)"""


PARAMETER_ERRORS = (InvalidParameterException, InvalidParameterTypeException, InvalidParameterValueException)
"""rclpy's refusals of a parameter given at start (out of its declared range, of another type): startup
errors of every node (``-p num_joints:=100`` is one "cannot start" line, not a traceback)"""


def run(
    make_node: Callable[[], Node],
    name: str,
    args=None,
    startup_errors: tuple[type[Exception], ...] = (),
    parameters: Sequence[NodeParameter] = (),
    summary: str = "",
) -> int:
    """Spin ``make_node()`` until SIGINT/SIGTERM; returns the exit code.

    ``-h``/``--help`` among the arguments before ``--ros-args`` prints ``summary`` and the node's
    ``parameters`` (its declaration table, ``morph_ros_util.parameters``) and exits 0 before anything starts.
    An exception of ``startup_errors`` (and of ``PARAMETER_ERRORS``) while the node is made is one fatal log
    line ("cannot start: <error>") and exit code 1, no traceback; an exception in a callback ends the node with its
    traceback and exit code 1.
    """
    argv = list(sys.argv if args is None else args)
    if {"-h", "--help"} & set(rclpy.utilities.remove_ros_args(argv)[1:]):
        usage = f"usage: {name} [-h] [--ros-args -r __ns:=NS -p NAME:=VALUE ...]"
        print("\n\n".join(part for part in (usage, summary, parameters_help(parameters) if parameters else "") if part))
        sys.exit(0)
    stop = init_stopping_on_signals(args)
    logger = get_logger(name)
    try:
        node = make_node()
    except (*startup_errors, *PARAMETER_ERRORS) as err:
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
    while not stop.is_set():  # the main thread stays free to run signal handlers, and beats the heart
        faulthandler.dump_traceback_later(WEDGE_TIMEOUT, exit=True)
        stop.wait(HEARTBEAT)
    faulthandler.dump_traceback_later(STOP_GRACE + WEDGE_TIMEOUT, exit=True)  # the clean stop, stuck or not
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
