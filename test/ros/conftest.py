"""Fixtures of the node graph's tests."""

import os

import pytest
from graph_checks import CpuHog


@pytest.fixture
def cpu_hog():
    """Two busy-loop processes beside the test (one per core of the project's 2-core machine), killed when it
    ends: the graph's result must not depend on the machine's load (docs/ros.md, "When a node dies").
    ORCHARD_TEST_HOG=0 runs the test without it (to compare run times)."""
    hog = CpuHog(0 if os.environ.get("ORCHARD_TEST_HOG") == "0" else 2)
    try:
        yield hog
    finally:
        hog.stop()
