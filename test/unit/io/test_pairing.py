"""io.pairing: the one pairing rule of colour and depth images, for a bag (read_rgbd) and for live topics."""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.io.pairing import Marker, Paired, RGBDPairer, Unpaired, pair_stamps

TOL = 10_000_000  # ns, input.max_pair_dt_s = 10 ms


def _nearest(c: np.ndarray, d: np.ndarray, tol: int) -> np.ndarray:
    """Brute force: each colour stamp's nearest depth stamp within tol (ties: the earlier), -1 if none."""
    out = []
    for s in c:
        cand = [(abs(int(x) - int(s)), int(x)) for x in d if abs(int(x) - int(s)) <= tol]
        out.append(min(cand)[1] if cand else -1)
    return np.array(out, dtype=np.int64)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_a_whole_recording_pairs_each_colour_image_with_its_nearest_depth_image(seed):
    rng = np.random.default_rng(seed)
    c = np.sort(rng.integers(0, 2 * 10**9, 150))
    # depth near most colour stamps (jitter up to 1.5 tol: some out of reach), a few lost
    d = np.sort((c + rng.integers(-15_000_000, 15_000_000, c.size))[rng.random(c.size) < 0.85])
    got = pair_stamps(c, d, TOL)
    stamps = np.where(got >= 0, d[np.maximum(got, 0)], -1)
    assert np.array_equal(stamps, _nearest(c, d, TOL))
    assert 0 < np.sum(got < 0) < c.size  # the case holds both paired and dropped frames


def test_a_colour_image_midway_between_two_depth_images_takes_the_earlier():
    got = pair_stamps(np.array([100]), np.array([96, 104]), 10)
    assert got.tolist() == [0]


def test_live_messages_wait_for_a_nearer_depth_and_a_marker_keeps_its_place():
    p = RGBDPairer(TOL)
    p.add_colour(0, "c0")
    p.add_depth(3_000_000, "d3")
    assert list(p.pop()) == []  # a depth nearer than 3 ms may still come
    p.add_marker("back")
    p.add_depth(1_000_000, "d1")  # arrives late, nearer
    p.add_depth(20_000_000, "d20")  # at least TOL later: the colour image is decided
    assert list(p.pop()) == [Paired("c0", "d1", 0), Marker("back")]
    p.add_colour(40_000_000, "c40")
    p.add_depth(40_000_000, "d40")  # the same stamp: nothing nearer can come
    assert list(p.pop()) == [Paired("c40", "d40", 40_000_000)]


def test_hold_keeps_frames_back_but_not_markers_and_flush_drops_what_has_no_depth():
    p = RGBDPairer(TOL)
    p.add_marker("front")
    p.add_colour(0, "c0")
    p.add_depth(0, "d0")
    p.add_colour(50_000_000, "c50")
    assert list(p.pop(hold=True)) == [Marker("front")]
    assert p.waiting == 2
    out = list(p.pop(flush=True))
    assert out[0] == Paired("c0", "d0", 0)
    assert out[1] == Unpaired("c50", 50_000_000, True, (0, 0))
    assert p.waiting == 0


def test_a_non_positive_tolerance_is_refused():
    with pytest.raises(ValueError, match="max_dt_ns"):
        RGBDPairer(0)
