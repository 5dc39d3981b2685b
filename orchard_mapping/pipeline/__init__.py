"""The offline pipeline: bags in, result folder out (docs/results.md). `run()` is the whole job; the names
below are the stages the live nodes (orchard_mapping.ros) and the tests call one by one.

Reads as the paper's steps, per side: front end (RGB-D odometry with keyframes), loop detection, pose graph,
bundle adjustment, TSDF fusion, trunk detection (and trunks from geometry) with trunk cylinders and local
grounds; then the merge of the two sides and the trees; the trees' traits; then the result folder.

One module per stage, each importing only those above it in this list:
sides (the bags opened, a side's frames and keyframe images, the run's timings) -> trunks (trunk and post
modelling, the trunk detector, the worker process) -> views (the trunk views kept beside the front end and in
fusion) -> side (one side: front end, back end, fusion, its trunks) -> merge (the two sides merged, the trees)
-> traits (each tree's height and canopy volume, every point labelled) -> outputs (the result folder's files)
-> block (a drive along several rows: a result folder per row, block.csv) -> runner (`run`).
"""

from orchard_mapping.pipeline.merge import (
    MergeOutcome,
    map_poses,
    merge_sides,
    merge_to_trees,
    ray_in_map,
    tree_of_trunk,
    two_side_trees,
)
from orchard_mapping.pipeline.outputs import write_merge, write_tree_cloud
from orchard_mapping.pipeline.runner import RunResult, run
from orchard_mapping.pipeline.side import SideHandover, SideSession, finish_side, front_end, reconstruct_side
from orchard_mapping.pipeline.sides import (
    SIDES,
    BagKeyframeImages,
    KeyframeImages,
    SpooledKeyframeImages,
    Timings,
    open_sides,
)
from orchard_mapping.pipeline.traits import RowLabels, measure_trees, merge_and_measure
from orchard_mapping.pipeline.trunks import PostView, TrunkJob, TrunkWorker, fit_posts, model_trunks, trunk_detector
from orchard_mapping.pipeline.views import EarlyDetections, TrunkViews

__all__ = [
    "BagKeyframeImages",
    "EarlyDetections",
    "KeyframeImages",
    "MergeOutcome",
    "PostView",
    "RowLabels",
    "RunResult",
    "SIDES",
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
    "measure_trees",
    "merge_and_measure",
    "ray_in_map",
    "tree_of_trunk",
    "merge_sides",
    "merge_to_trees",
    "model_trunks",
    "open_sides",
    "reconstruct_side",
    "run",
    "trunk_detector",
    "two_side_trees",
    "write_merge",
    "write_tree_cloud",
]
