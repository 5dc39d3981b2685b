"""The merge does not trust trunk pairs that turn the back side round: when the initial transform from the pairs
turns it more than MAX_TURN_FROM_ALIGNMENT_DEG from the global features' alignment, the sides are merged from the
global features (flagged) instead."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import orchard_mapping.pipeline.merge as merge
from orchard_mapping.config import load_config
from orchard_mapping.core.geometry import make_transform


def _turn_about_up(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])  # up: y


def _side(stamp0: float) -> SimpleNamespace:
    """A side map as merge_sides reads it: two trunk landmarks (ids 0, 1) without grounds, three keyframes."""
    trunks = [SimpleNamespace(id=i, ground=None, diameter_m=0.03, base=np.array([float(i), 0.0, 0.0]), axis=np.array([0.0, 1.0, 0.0]))
              for i in (0, 1)]
    return SimpleNamespace(trunks=trunks, cloud_points=np.zeros((10, 3)), keyframe_poses=np.tile(np.eye(4), (3, 1, 1)),
                           keyframe_stamps=stamp0 + np.arange(3.0), scale_free=False, posts=[])


@pytest.mark.parametrize("turn_deg, trusted", [(4.0, True), (29.0, True), (31.0, False), (170.0, False)])
def test_pairs_that_turn_the_back_side_round_give_way_to_the_global_features(monkeypatch, turn_deg, trusted):
    T_al = make_transform(_turn_about_up(178.0), np.array([0.2, 0.0, 2.9]))  # the sides facing each other
    T_it = make_transform(_turn_about_up(178.0 + turn_deg), np.array([0.3, 0.0, 2.8]))
    al = SimpleNamespace(method="cpd", pairs=((0, 0), (1, 1)), T_front_back=T_al)
    monkeypatch.setattr(merge, "align_sides", lambda *a, **k: al)
    monkeypatch.setattr(merge, "initial_transform", lambda *a, **k: SimpleNamespace(T_front_back=T_it))
    monkeypatch.setattr(merge, "merge_axis", lambda t: t.axis)
    cfg = load_config(overrides={"merge": {"method": "initial", "sigma_alignment_height_m": 0.0}})
    out = merge.merge_sides(_side(0.0), _side(100.0), cfg)
    if trusted:
        assert out.method == "initial" and np.allclose(out.T_front_back, T_it)
    else:
        assert out.method == merge.GLOBAL_FEATURES and np.allclose(out.T_front_back, T_al)
        assert out.initial is None and out.sba is None
