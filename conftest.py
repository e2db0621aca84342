"""Settings for every test directory: each pytest-xdist worker in a DDS domain of its own.

``scripts/test.sh`` runs the suite on two workers (``-n``) in one network namespace. Nodes started by a test
inherit the worker's environment, so with a domain per worker one worker's nodes never discover the other's,
whatever their topic names. Without xdist the directories' own fixtures choose the domain (tests/conftest.py).
"""

from __future__ import annotations

import os

XDIST_DOMAIN_BASE = 150
"""worker gwN runs in ROS_DOMAIN_ID 150 + N (Fast DDS takes domains up to 232; tests/conftest.py's own are 1..100)"""


def pytest_configure(config) -> None:
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    if worker.startswith("gw"):
        os.environ["ROS_DOMAIN_ID"] = str(XDIST_DOMAIN_BASE + int(worker[2:]))
