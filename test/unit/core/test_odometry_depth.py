"""Landmark depth at tracked corners (core.odometry.sample_depth): no depth near a depth edge."""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.config import load_config
from orchard_mapping.core.odometry import sample_depth
from orchard_mapping.errors import ConfigError


def _step_image() -> np.ndarray:
    """(60, 80) depth: a trunk at 1.5 m on columns < 40, the background row at 4.5 m beyond."""
    depth = np.full((60, 80), 4.5, np.float32)
    depth[:, :40] = 1.5
    return depth


@pytest.mark.parametrize("window, nearest_kept", [(3, 1), (5, 2), (7, 3)])
def test_corners_within_half_a_window_of_a_depth_edge_get_no_depth(window, nearest_kept):
    depth = _step_image()
    # Corners on the trunk, 1..6 px left of its silhouette (column 39 is the last trunk column).
    uv = np.array([[39 - k, 30.0] for k in range(0, 6)])
    z = sample_depth(depth, uv, edge_m=0.03, sigma_coeff=0.004, edge_window_px=window)
    kept = z > 0
    assert not kept[:nearest_kept].any(), z
    assert kept[nearest_kept:].all(), z
    np.testing.assert_allclose(z[kept], 1.5)


def test_sensor_noise_alone_is_not_an_edge():
    rng = np.random.default_rng(3)
    z_true = 3.0
    depth = (z_true + rng.standard_normal((60, 80)) * 0.004 * z_true ** 2).astype(np.float32)
    uv = np.stack(np.meshgrid(np.arange(5, 75, 3.0), np.arange(5, 55, 3.0)), -1).reshape(-1, 2)
    z = sample_depth(depth, uv, edge_m=0.03, sigma_coeff=0.004, edge_window_px=5)
    assert np.mean(z > 0) > 0.98
    assert abs(np.median(z[z > 0]) - z_true) < 0.01


def test_a_missing_value_in_the_window_rejects_the_depth():
    depth = np.full((40, 40), 2.0, np.float32)
    depth[20, 22] = 0.0  # a dropout 2 px right of the corner
    z = sample_depth(depth, np.array([[20.0, 20.0], [10.0, 10.0]]), 0.03, 0.004, edge_window_px=5)
    assert z[0] == 0.0 and z[1] == pytest.approx(2.0)


def test_an_even_edge_window_is_a_config_error_naming_the_key():
    with pytest.raises(ConfigError, match="depth_edge_window_px"):
        load_config(overrides={"odometry": {"depth_edge_window_px": 4}})
