"""Trunk landmarks of one side (core.trunks) on a rendered analytic scene: a trunk on sloping ground
seen by a camera moving along the row; a trunk hidden at the diameter height is flagged, not invented."""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.core.detection import CLASS_TRUNK, Detection
from orchard_mapping.core.ground import GroundParams
from orchard_mapping.core.trunks import TrunkParams, TrunkView, build_trunk_landmarks
from orchard_mapping.core.types import CameraIntrinsics

INTR = CameraIntrinsics(640, 480, 615.0, 615.0, 319.5, 239.5)
GROUND_Y = 0.35  # m below the camera (optical frame: y down): the ground is seen from 0.9 m on
TRUNK = np.array([0.0, GROUND_Y, 1.25])  # trunk axis at the ground
RADIUS = 0.034
UP = np.array([0.0, -1.0, 0.0])


def _render(cam_x: float, occluder: tuple[float, float, float] | None) -> tuple[np.ndarray, np.ndarray]:
    """(depth (H, W) m, trunk mask) from a camera at (cam_x, 0, 0) looking along z.

    The scene: flat ground, a vertical trunk 0.7 m tall, a wall behind at 3 m, and optionally a band of
    leaves (weeds) occluder = (z, lo, hi): at depth z, covering heights lo..hi above the ground.
    """
    v, u = np.mgrid[0:INTR.height, 0:INTR.width]
    dx, dy = (u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy  # ray (dx, dy, 1) from the camera
    z = np.full(u.shape, 3.0)
    ground = np.where(dy > 1e-6, GROUND_Y / np.maximum(dy, 1e-6), np.inf)
    z = np.minimum(z, ground)
    # trunk: (cam_x + s dx - tx)^2 + (s - tz)^2 = r^2
    ox, oz = cam_x - TRUNK[0], -TRUNK[2]
    a, b, c = dx**2 + 1, 2 * (ox * dx + oz), ox**2 + oz**2 - RADIUS**2
    disc = b * b - 4 * a * c
    s = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
    h = GROUND_Y - s * dy  # height above ground of the hit
    s = np.where((h > -0.05) & (h < 0.7), s, np.inf)
    trunk = s < z
    z = np.minimum(z, s)
    if occluder is not None:
        z_occ, lo, hi = occluder
        h_occ = GROUND_Y - z_occ * dy
        leaves = (h_occ > lo) & (h_occ < hi)
        z = np.where(leaves, z_occ, z)
        trunk &= ~leaves
    return z.astype(np.float32), trunk


def _side(occluder=None, seed=0):
    rng = np.random.default_rng(seed)
    views, points, poses = [], [], []
    for k, x in enumerate(np.linspace(-0.45, 0.45, 7)):
        T = np.eye(4)
        T[0, 3] = x
        depth, mask = _render(x, occluder)
        depth = depth + (rng.standard_normal(depth.shape) * 0.002).astype(np.float32)
        views.append(TrunkView(k, float(k), T, depth, [Detection.from_mask(mask, CLASS_TRUNK)]))
        poses.append(T)
        vv, uu = np.nonzero(depth < 2.5)
        sel = rng.choice(len(vv), 40000, replace=False)
        zz = depth[vv[sel], uu[sel]].astype(float)
        points.append(np.stack([(uu[sel] - INTR.cx) / INTR.fx * zz + x, (vv[sel] - INTR.cy) / INTR.fy * zz, zz], 1))
    return np.concatenate(points), np.array(poses), views


def test_a_visible_trunk_gets_its_diameter_axis_and_ground():
    points, poses, views = _side()
    lms = build_trunk_landmarks(points, poses, views, INTR, TrunkParams(), GroundParams(), 0)
    assert len(lms) == 1
    lm = lms[0]
    assert lm.flags == []
    assert lm.diameter_m == pytest.approx(2 * RADIUS, abs=0.001)
    assert np.degrees(np.arccos(abs(lm.axis @ UP))) < 1.0
    assert lm.ground is not None
    assert np.degrees(np.arccos(lm.ground.normal @ UP)) < 0.5
    assert abs(lm.ground.point[1] - GROUND_Y) < 0.005  # where the axis meets the ground
    assert len(lm.observations) == 7
    assert all(o.cylinder_cam is not None for o in lm.observations)


def test_a_trunk_hidden_at_the_diameter_height_is_flagged_not_invented():
    # Weeds 10 cm in front of the trunk, 0.22-0.45 m tall: seen from 0.35 m they hide the trunk from 0.21
    # to 0.46 m above the ground (the diameter band is 0.22-0.38 m) and leave the ground around in view.
    points, poses, views = _side(occluder=(1.15, 0.22, 0.45))
    lms = build_trunk_landmarks(points, poses, views, INTR, TrunkParams(), GroundParams(), 0)
    assert len(lms) == 1  # the trunk is there (above and below the leaves)...
    assert "hidden_at_diameter_height" in lms[0].flags  # ...but not seen where its diameter is read
    assert lms[0].diameter_m is None and lms[0].band is None


def test_without_a_local_ground_the_diameter_height_comes_from_the_wider_ground():
    """Too little ground seen near the trunk (here: more demanded than the 0.5 m disk can hold, 0.79 m^2): no local ground
    is reported, yet the diameter is read above the ground of the 1 m disk, and the trunk says so."""
    points, poses, views = _side()
    local = GroundParams(min_support_m2=1.0)
    lms = build_trunk_landmarks(points, poses, views, INTR, TrunkParams(), local, 0)
    assert len(lms) == 1 and lms[0].ground is None
    assert lms[0].flags == ["no_ground", "diameter_height_from_wide_ground"]
    assert lms[0].diameter_m == pytest.approx(2 * RADIUS, abs=0.001)
    off = GroundParams(min_support_m2=1.0, wide_radius_m=0.0)
    lms = build_trunk_landmarks(points, poses, views, INTR, TrunkParams(), off, 0)
    assert lms[0].flags == ["no_ground"] and lms[0].diameter_m is None


def test_no_detection_gives_no_trunk():
    points, poses, views = _side()
    empty = [TrunkView(v.keyframe, v.stamp, v.T_odom_cam, v.depth, []) for v in views]
    assert build_trunk_landmarks(points, poses, empty, INTR, TrunkParams(), GroundParams(),
                                 0) == []


def test_the_merge_axis_comes_from_the_depth_pixels_not_a_leaning_fused_trunk():
    """A TSDF surface of a thin trunk leans towards the camera as the trunk narrows (0.16 deg at the
    default 4 cm truncation on the simulated rows, 2 deg at 8 cm; docs/history.md). Here the fused trunk
    leans 0.6 deg towards the camera while the keyframes' depth does not: the merge axis must not lean."""
    points, poses, views = _side()
    h = GROUND_Y - points[:, 1]  # m above the ground
    on_trunk = (np.hypot(points[:, 0] - TRUNK[0], points[:, 2] - TRUNK[2]) < RADIUS + 0.01) & (h > 0)
    leaning = points.copy()
    leaning[on_trunk, 2] -= np.tan(np.radians(0.6)) * h[on_trunk]  # the top comes towards the camera (-z)
    lm = build_trunk_landmarks(leaning, poses, views, INTR, TrunkParams(), GroundParams(),
                               0)[0]

    def towards_camera_deg(a: np.ndarray) -> float:
        a = a if a @ UP > 0 else -a
        return float(np.degrees(np.arcsin(-a[2])))

    assert towards_camera_deg(lm.axis) > 0.3  # the fused trunk's own fit follows its lean
    assert abs(towards_camera_deg(lm.merge_axis)) < 0.1


def test_the_foot_lies_on_the_merge_axis_not_on_a_leaning_fused_trunk():
    """The merge's trunk line is the foot plus the merge axis. A fused trunk that leans about its middle
    (a plain cylinder on a tapered trunk does, away from the camera) puts its own axis off the true one at
    the ground: the foot must come from the depth pixels' axis, or the two sides' lines part at the ground
    (docs/history.md, "The trunk's foot": 8 mm in depth on the 10-tree standard row)."""
    points, poses, views = _side()
    h = GROUND_Y - points[:, 1]
    on_trunk = (np.hypot(points[:, 0] - TRUNK[0], points[:, 2] - TRUNK[2]) < RADIUS + 0.01) & (h > 0)
    leaning = points.copy()
    leaning[on_trunk, 2] += np.tan(np.radians(1.2)) * (h[on_trunk] - 0.35)  # the top away from the camera (+z)
    lm = build_trunk_landmarks(leaning, poses, views, INTR, TrunkParams(), GroundParams(),
                               0)[0]

    def off_axis_mm(p: np.ndarray) -> float:  # horizontal distance from the true axis (x, z), mm
        return 1000 * float(np.hypot(p[0] - TRUNK[0], p[2] - TRUNK[2]))

    assert lm.ground is not None
    assert off_axis_mm(lm.ground.point) > 4.0  # where the fused trunk's own axis meets the ground
    assert off_axis_mm(lm.base) < 1.5
    assert abs(lm.base[1] - GROUND_Y) < 0.005


def test_a_sides_trunks_modelled_in_the_worker_process_are_the_ones_modelled_here():
    """`orchard-map run` models the first side's trunks in a spawned process while the next side is tracked:
    the job must pickle whole and give the same landmarks, flags and warnings as modelling them in-process."""
    from orchard_mapping.config import load_config
    from orchard_mapping.pipeline import TrunkJob, TrunkWorker, model_trunks

    points, poses, views = _side()
    job = TrunkJob("front", points.astype(np.float32), poses, np.arange(len(poses), dtype=float), views, [], [3],
                   INTR, load_config())
    here = model_trunks(job)
    worker = TrunkWorker()
    try:
        there = worker.result(worker.submit(model_trunks, job), model_trunks, job)
    finally:
        worker.close()
    assert len(here.trunks) == len(there.trunks) == 1
    a, b = here.trunks[0], there.trunks[0]
    assert a.diameter_m == pytest.approx(2 * RADIUS, abs=0.001)
    assert b.diameter_m == a.diameter_m and np.array_equal(b.axis, a.axis) and np.array_equal(b.base, a.base)
    # keyframe 3 had no detector answer: the trunk beside it is flagged, and the side says so, in both
    assert b.flags == a.flags and "detector_unavailable_nearby" in a.flags
    assert here.warnings == there.warnings and "did not answer for 1 keyframes" in here.warnings[0]
    assert set(there.seconds) == {"trunks_front"}


def test_a_ctrl_c_while_the_trunk_worker_starts_is_held_until_it_has_started():
    """A Ctrl-C as the worker process is launched was raised between its exec and the write of its start-up
    data (the kernel hands the signal to another, unblocked thread and Python raises in the main thread all the
    same): the worker died with its own traceback. It is held until the launch is over, then raised."""
    import os
    import signal
    import threading
    import time

    from orchard_mapping.pipeline.trunks import _sigint_held

    # Python's own handler, as an interactive run has it (a suite started in the background inherits SIGINT
    # ignored, and nothing would be raised at all)
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    stop = threading.Event()
    other = threading.Thread(target=stop.wait)  # started before the mask: SIGINT is delivered to it
    other.start()
    reached_end = False
    try:
        with pytest.raises(KeyboardInterrupt):
            with _sigint_held():
                os.kill(os.getpid(), signal.SIGINT)
                for _ in range(200):  # bytecode boundaries where Python would raise a pending Ctrl-C
                    time.sleep(0.001)
                reached_end = True
    finally:
        stop.set()
        other.join()
        handler_after = signal.getsignal(signal.SIGINT)
        signal.signal(signal.SIGINT, before)
    assert reached_end
    assert handler_after is signal.default_int_handler
