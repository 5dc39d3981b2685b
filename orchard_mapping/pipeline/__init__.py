"""The offline pipeline: bags in, result folder out (docs/results.md). One public `run()`.

Reads as the paper's steps, per side: front end (RGB-D odometry with
keyframes), loop detection, pose graph, bundle adjustment, TSDF fusion, trunk
detection with trunk cylinders and local grounds; then writes each side's
trajectory, cloud, trunks and grounds.
"""

from orchard_mapping.pipeline.side import (
    SIDES,
    BagKeyframeImages,
    EarlyDetections,
    KeyframeImages,
    MergeOutcome,
    PostView,
    RunResult,
    SideHandover,
    SideSession,
    SpooledKeyframeImages,
    Timings,
    TrunkJob,
    TrunkViews,
    TrunkWorker,
    finish_side,
    fit_posts,
    front_end,
    map_poses,
    merge_sides,
    merge_to_trees,
    model_trunks,
    open_sides,
    reconstruct_side,
    run,
    trunk_detector,
    two_side_trees,
    write_merge,
)

__all__ = [
    "SIDES",
    "BagKeyframeImages",
    "EarlyDetections",
    "KeyframeImages",
    "MergeOutcome",
    "PostView",
    "RunResult",
    "SideHandover",
    "SideSession",
    "SpooledKeyframeImages",
    "Timings",
    "TrunkJob",
    "TrunkViews",
    "TrunkWorker",
    "finish_side",
    "fit_posts",
    "front_end",
    "map_poses",
    "merge_sides",
    "merge_to_trees",
    "model_trunks",
    "open_sides",
    "reconstruct_side",
    "run",
    "trunk_detector",
    "two_side_trees",
    "write_merge",
]
