"""Fixtures of the node graph's tests."""

import os

import pytest
from graph_checks import CpuHog


@pytest.fixture
def cpu_hog():
    """A busy-loop process beside the test (half of the project's 2-core machine), killed when it ends: the
    graph's result must not depend on the machine's load (docs/ros.md, "When a node dies"). One, not one per
    core: with two, the two fault tests took 250 s of the suite's 19 minutes in CI. ORCHARD_TEST_HOG=N runs
    it with N (0: none, to compare run times)."""
    hog = CpuHog(int(os.environ.get("ORCHARD_TEST_HOG", "1")))
    try:
        yield hog
    finally:
        hog.stop()
