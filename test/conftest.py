"""Project-wide pytest set-up.

Every process that starts rclpy in the tests keeps DDS discovery on loopback.
This is forced here, at import time, before any test module imports rclpy;
child processes inherit it. (On a vehicle users choose their own discovery
settings: only the tests, CI, the Makefile and the launcher force it.)
"""

import os
import random

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

# One random ROS domain per test session (forced, like the discovery range), so
# that concurrent test runs on one machine (two developers, CI) never see each
# other's topics. 1..101 are domain ids safe on Linux for any participant count.
os.environ["ROS_DOMAIN_ID"] = str(random.SystemRandom().randint(1, 101))

import pytest  # noqa: E402


@pytest.fixture
def out_dir(tmp_path):
    """An empty folder for a test's outputs (removed by pytest's tmp_path policy)."""
    d = tmp_path / "out"
    d.mkdir()
    return d
