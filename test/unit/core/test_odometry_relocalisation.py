"""The RGB-D front end (core.odometry) after a relocalisation: tracking resumes at the next frame.

The recording: the first 45 frames of the front side of the 2-tree `standard` row (15 Hz, 640x480), with
5 % of the depth pixels missing (camera.dropout 0.05 instead of 0.01): a sensor whose depth has more holes
than the simulator's, as real foliage gives. Few corners of a single frame then take landmark depth (a
complete, edge-free 7x7 window), though tracks carried over many keyframes still fill the map. Tracking
is refused at one frame; the frame is relocalised against a keyframe by ORB matching, and the frames after
it must be tracked from the relocalised frame, not relocalised one after the other.
"""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.core.geometry import umeyama
from orchard_mapping.core.odometry import FrontEndParams, RGBDFrontEnd
from orchard_mapping.core.types import RGBDFrame
from orchard_mapping.sim.scenario import load_scenario
from orchard_mapping.sim.simulate import Rig

SEED = 3
N_FRAMES = 45
REFUSED = 25  # tracking refused at this frame: it is relocalised


@pytest.fixture(scope="module")
def holey_row() -> tuple[list[RGBDFrame], np.ndarray]:
    sc = load_scenario("standard", {"row.n_trees": 2, "camera.dropout": 0.05, "masks_every": 0})
    rig = Rig.build(sc, SEED)
    path = rig.path("front", np.random.default_rng([SEED, 1]))
    rng = np.random.default_rng([SEED, 2])
    frames = []
    for i, (stamp, T) in enumerate(zip(path.stamps[:N_FRAMES], path.poses[:N_FRAMES], strict=True)):
        color, depth, _ = rig.shoot(T, rng, float(stamp))
        frames.append(RGBDFrame(float(stamp), color, depth, rig.intrinsics, side="front", index=i))
    return frames, np.asarray(path.poses[:N_FRAMES])


def test_tracking_resumes_after_a_relocalisation_where_few_corners_take_depth(holey_row, monkeypatch):
    frames, truth = holey_row
    real = RGBDFrontEnd._track_klt

    def refusing(self, gray, frame):
        return None if frame.index == REFUSED else real(self, gray, frame)

    monkeypatch.setattr(RGBDFrontEnd, "_track_klt", refusing)
    fe = RGBDFrontEnd(frames[0].intrinsics, FrontEndParams())
    for f in frames:
        fe.track(f)
    res = fe.result()
    reloc = [e for e in res.events if "relocalised" in e or "restarted" in e or "lost" in e]
    # Before the relocalised frame seeded its tracks from the relocalisation's matches, every frame after
    # it was relocalised again (its own depth-passing corners were under min_inliers).
    assert len(reloc) == 1 and reloc[0].startswith(f"frame {REFUSED}: relocalised"), res.events
    assert fe.lost_frames == 1
    placed = np.isfinite(res.frame_poses[:, 0, 0])
    assert placed[REFUSED:].all()
    # The frames after the relocalisation stay on the path: rigid fit of all placed frames to the truth.
    est, true = res.frame_poses[placed, :3, 3], (np.linalg.inv(truth[0])[None] @ truth)[placed, :3, 3]
    fit = umeyama(est, true, with_scale=False)
    err = np.linalg.norm(est @ fit.R.T + fit.t - true, axis=1)
    length = float(np.sum(np.linalg.norm(np.diff(true, axis=0), axis=1)))
    assert err.max() < 0.01 * length, (err.max(), length)
