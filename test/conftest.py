"""Project-wide pytest set-up.

Every process that starts rclpy in the tests keeps DDS discovery on loopback.
This is forced here, at import time, before any test module imports rclpy;
child processes inherit it. (On a vehicle users choose their own discovery
settings: only the tests, CI, the Makefile and the launcher force it.)
"""

import os
import random

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

# One random ROS domain per test session, so that concurrent test runs on the
# same machine (two developers, CI) never see each other's topics. 0..101 are
# the domain ids that are safe on Linux for any number of participants.
os.environ.setdefault("ROS_DOMAIN_ID", str(random.SystemRandom().randint(1, 101)))

import pytest  # noqa: E402


@pytest.fixture
def out_dir(tmp_path):
    """An empty folder for a test's outputs (removed by pytest's tmp_path policy)."""
    d = tmp_path / "out"
    d.mkdir()
    return d
