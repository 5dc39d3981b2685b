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


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_small_step_under_the_edge_margin_is_what_the_rough_fraction_drops(seed):
    """A 2.5 cm step (leaf over leaf) in noisy depth at 1 m on a slanted surface passes the edge test (its
    window spans less than 3 cm + 5 sd); the roughest 40 % are the corners whose window holds the step."""
    rng = np.random.default_rng(seed)
    h, w = 120, 160
    cols = np.arange(w, dtype=np.float32)[None, :]
    depth = 1.0 + 0.0005 * cols + np.zeros((h, 1), np.float32)  # slanted, smooth
    depth[:, 80:] += 0.025  # the step, from column 80
    depth = (depth + rng.standard_normal((h, w)) * 0.004).astype(np.float32)
    rows = np.arange(10, 110, 5.0)
    on_step = np.array([[c, r] for r in rows for c in (78.0, 79.0, 80.0, 81.0)])  # 80 corners by the step
    flat = np.array([[c, r] for r in rows for c in (20.0, 40.0, 60.0, 100.0, 120.0, 140.0)])  # 120 far from it
    uv = np.vstack([on_step, flat])
    assert (sample_depth(depth, uv, 0.03, 0.004, 7) > 0).mean() > 0.9  # the edge test alone keeps them
    z = sample_depth(depth, uv, 0.03, 0.004, 7, rough_drop_fraction=0.4)
    step_kept, flat_kept = (z[: len(on_step)] > 0).mean(), (z[len(on_step):] > 0).mean()
    assert step_kept < 0.15, step_kept
    assert flat_kept > 0.85, flat_kept
    np.testing.assert_allclose(z[len(on_step):][z[len(on_step):] > 0], depth[flat[:, 1].astype(int), flat[:, 0].astype(int)][z[len(on_step):] > 0], atol=0.02)


def test_a_rough_fraction_outside_0_1_is_a_config_error_naming_the_key():
    with pytest.raises(ConfigError, match="depth_rough_drop_fraction"):
        load_config(overrides={"odometry": {"depth_rough_drop_fraction": 1.0}})
