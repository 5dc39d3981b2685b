"""The local_ground_fitter node in this process, fed a side's geometry (the SideMap message the odometry node
publishes once a side is fused) on the analytic trunk scene of the core's trunk tests: the grounds it publishes
are the offline first step's (pipeline.trunks.fit_grounds) exactly, for a local ground, a wide one and none; and
the trunk cylinders fitted against them are those `orchard-map run` fits in one process."""

from __future__ import annotations

import array
import importlib.util
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from orchard_mapping_msgs.msg import LocalGroundArray, SideMap as SideMapMsg  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from orchard_mapping.core.detection import Detection  # noqa: E402
from orchard_mapping.core.sidemap import SideGeometry  # noqa: E402
from orchard_mapping.core.trunks import TrunkView, build_trunk_landmarks, fit_trunk_cylinders  # noqa: E402
from orchard_mapping.core.types import ImagePatch, mask_bounds  # noqa: E402
from orchard_mapping.io.sidemap_codec import SIDE_GEOMETRY_ENCODING, encode_side_geometry  # noqa: E402
from orchard_mapping.pipeline.trunks import fit_grounds  # noqa: E402
from orchard_mapping.ros.messages import TrunkRecord, stamp_header, trunk_grounds_from_msg  # noqa: E402
from orchard_mapping.ros.qos import LATCHED  # noqa: E402

_SCENE = Path(__file__).resolve().parents[1] / "unit" / "core" / "test_trunks.py"


def _scene_module():
    spec = importlib.util.spec_from_file_location("trunk_scene", _SCENE)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _geometry(stamp: float) -> SideGeometry:
    """One trunk seen from 7 keyframes, kept as the pipeline keeps them: a float32 cloud, depth and masks cropped
    around the detections."""
    scene = _scene_module()
    points, poses, views = scene._side()
    kept = []
    for v in views:
        det = v.detections[0]
        rect = mask_bounds(np.asarray(det.mask), 24)
        kept.append(TrunkView(v.keyframe, v.stamp, v.T_odom_cam, ImagePatch.crop(np.asarray(v.depth), rect),
                              [Detection(det.class_id, det.score, det.box, ImagePatch.crop(np.asarray(det.mask), rect))]))
    return SideGeometry("front", "odom_front", stamp, scene.INTR, poses, points[::4].astype(np.float32), kept)


def _spin_until(executor, cond, timeout_s: float = 60.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not cond():
        executor.spin_once(timeout_sec=0.1)
    return cond()


@pytest.fixture
def graph():
    from orchard_mapping.ros.local_ground_fitter import LocalGroundFitterNode

    rclpy.init()
    fitter = LocalGroundFitterNode()
    probe = rclpy.create_node("orchard_test_ground_probe")
    executor = SingleThreadedExecutor()
    executor.add_node(fitter)
    executor.add_node(probe)
    try:
        yield fitter, probe, executor
    finally:
        executor.shutdown()
        probe.destroy_node()
        fitter.destroy_node()
        rclpy.try_shutdown()


def test_the_node_publishes_the_offline_grounds_exactly(graph):
    fitter, probe, executor = graph
    got: list[LocalGroundArray] = []
    probe.create_subscription(LocalGroundArray, "/orchard/front/local_grounds", got.append, LATCHED)
    pub = probe.create_publisher(SideMapMsg, "/orchard/front/side_geometry", LATCHED)
    # the default grounds, then too little ground near the trunk (the wide ground), then no wide ground either
    rounds = [([], "local"), ([Parameter("ground.min_support_m2", value=1.0)], "wide"),
              ([Parameter("ground.wide_radius_m", value=0.0)], "none")]
    for i, (params, kind) in enumerate(rounds):
        if params:
            assert all(r.successful for r in fitter.set_parameters(params))
        geometry = _geometry(12.5 + i)
        msg = SideMapMsg()
        stamp_header(msg.header, geometry.stamp, geometry.frame_id)
        msg.side, msg.encoding = "front", SIDE_GEOMETRY_ENCODING
        msg.keyframes, msg.cloud_points = len(geometry.keyframe_poses), len(geometry.cloud_points)
        msg.data = array.array("B", encode_side_geometry(geometry))
        pub.publish(msg)
        assert _spin_until(executor, lambda n=i + 1: len(got) >= n), (i, fitter.errors)
        answer = got[-1]
        assert (answer.header.stamp.sec, answer.header.stamp.nanosec) == (msg.header.stamp.sec, msg.header.stamp.nanosec)
        frame, _, grounds = trunk_grounds_from_msg(answer)
        cfg = fitter.params.config
        want = fit_grounds(geometry, cfg)
        assert frame == "odom_front" and len(grounds) == len(want) == 1 and answer.grounds[0].kind == kind
        for g, w in zip(grounds, want, strict=True):
            assert (g.id, g.detections, g.bottom_m, g.top_m) == (w.id, w.detections, w.bottom_m, w.top_m)
            np.testing.assert_array_equal(g.point_indices, w.point_indices)
            for a, b in ((g.coarse.origin, w.coarse.origin), (g.coarse.axis, w.coarse.axis)):
                np.testing.assert_array_equal(a, b)
            assert g.coarse.radius == w.coarse.radius
            for a, b in ((g.ground, w.ground), (g.wide_ground, w.wide_ground)):
                assert (a is None) == (b is None)
                if a is not None:
                    assert (a.offset, a.inliers, a.rmse_m, a.candidates, a.support_m2, a.support_offset_m) == (
                        b.offset, b.inliers, b.rmse_m, b.candidates, b.support_m2, b.support_offset_m)
                    for x, y in ((a.normal, b.normal), (a.point, b.point), (a.ground_cells, b.ground_cells)):
                        np.testing.assert_array_equal(x, y)
        # the trunk fitted against the node's grounds is the one fitted in one process
        pts, views = geometry.cloud_points, geometry.views
        live = fit_trunk_cylinders(pts, views, geometry.intrinsics, cfg.trunks, grounds, cfg.seed)
        offline = build_trunk_landmarks(pts, geometry.keyframe_poses, views, geometry.intrinsics, cfg.trunks,
                                        cfg.ground, cfg.seed)
        assert ([TrunkRecord.from_landmark(lm, "front") for lm in live]
                == [TrunkRecord.from_landmark(lm, "front") for lm in offline])
        assert [lm.diameter_m for lm in live] == [lm.diameter_m for lm in offline]
        np.testing.assert_array_equal(live[0].merge_axis, offline[0].merge_axis)
        if kind == "local":
            assert live[0].diameter_m == pytest.approx(0.068, abs=0.001)
    assert fitter.answered == len(rounds) and not fitter.errors


def test_a_payload_that_is_not_a_side_geometry_is_reported_not_answered(graph):
    fitter, probe, executor = graph
    pub = probe.create_publisher(SideMapMsg, "/orchard/back/side_geometry", LATCHED)
    msg = SideMapMsg()
    stamp_header(msg.header, 3.0, "odom_back")
    msg.side, msg.encoding = "back", "orchard_mapping.side_map/1+npz"
    pub.publish(msg)
    assert _spin_until(executor, lambda: bool(fitter.errors))
    assert "this node reads 'orchard_mapping.side_geometry/1+npz'" in fitter.errors[0] and fitter.answered == 0
