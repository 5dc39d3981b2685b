"""The same scenario and seed give the same recording, bit for bit; another seed gives another row."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="module")
def twin(make_sim, tiny_row):
    """A second run of `tiny_single_pass`'s scenario and seed, in another folder."""
    return make_sim("standard", {**tiny_row, "path.mode": "single_pass"}, 3)


def test_same_seed_same_bytes(tiny_single_pass, twin):
    a, b = tiny_single_pass, twin
    assert a.out != b.out
    assert a.result.truth_path.read_bytes() == b.result.truth_path.read_bytes()
    assert a.result.frames == b.result.frames
    for side in ("front", "back"):
        fa, fb = a.frames(side), b.frames(side)
        assert len(fa) == len(fb) > 0
        for x, y in zip(fa, fb, strict=True):
            assert x.stamp == y.stamp
            assert x.color.tobytes() == y.color.tobytes()
            assert x.depth.tobytes() == y.depth.tobytes()
        ma, mb = a.masks(side), b.masks(side)
        assert [i for i, _, _ in ma] == [i for i, _, _ in mb]
        for (_, _, x), (_, _, y) in zip(ma, mb, strict=True):
            assert x.tobytes() == y.tobytes()


def test_other_seed_differs(tiny_single_pass, make_sim, tiny_row):
    other = make_sim("standard", {**tiny_row, "path.mode": "single_pass"}, 4)
    a, b = tiny_single_pass.truth, other.truth
    assert a["seed"] == 3 and b["seed"] == 4
    pa = np.array([t["position"] for t in a["trees"]])
    pb = np.array([t["position"] for t in b["trees"]])
    assert not np.allclose(pa, pb, atol=1e-3)
    assert [t["trunk"]["diameter_m"] for t in a["trees"]] != [t["trunk"]["diameter_m"] for t in b["trees"]]
    # The images differ too (noise, row and camera path), frame by frame.
    fa, fb = tiny_single_pass.frames("front"), other.frames("front")
    for x, y in zip(fa, fb, strict=False):  # the other seed's row may have a frame more or fewer
        assert x.color.tobytes() != y.color.tobytes()
        assert x.depth.tobytes() != y.depth.tobytes()
