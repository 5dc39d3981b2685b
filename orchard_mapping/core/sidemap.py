"""Value objects of single-side reconstruction (paper: "Single-Side Reconstruction").

Frames: every pose is T_odom_cam of the colour optical frame (x right, y down,
z forward) in the side's reconstruction frame `odom_<side>` (the first
keyframe's camera frame). Lengths in metres, pixels in px.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from orchard_mapping.core.fruit import SideFruit
from orchard_mapping.core.types import CameraIntrinsics


@dataclass(frozen=True)
class Keyframe:
    """A frame kept for bundle adjustment, loop detection and fusion."""

    id: int  # keyframe number, 0.. in order
    frame_index: int  # index of the frame in its stream
    stamp: float  # s
    T_odom_cam: np.ndarray  # (4, 4) front-end estimate
    keypoints: np.ndarray  # (N, 2) float32 px, features used for loop detection
    descriptors: np.ndarray  # (N, 32) uint8 ORB descriptors of `keypoints`
    keypoint_depth: np.ndarray  # (N,) float32 m, 0 = no valid depth
    keypoint_landmark: np.ndarray  # (N,) int64 landmark id, -1 = none


@dataclass(frozen=True)
class Observations:
    """Landmark observations at keyframes, as flat arrays (one row per observation)."""

    keyframe: np.ndarray  # (M,) int64 keyframe id
    landmark: np.ndarray  # (M,) int64 landmark id
    uv: np.ndarray  # (M, 2) float64 px, colour image
    depth: np.ndarray  # (M,) float64 m along the optical axis, 0 = no depth (RGB-only or missing)

    def __len__(self) -> int:
        return len(self.keyframe)


@dataclass(frozen=True)
class LoopClosure:
    """A verified revisit between two keyframes: T_a_b maps keyframe b's camera frame into a's."""

    kf_a: int
    kf_b: int
    T_a_b: np.ndarray  # (4, 4)
    inliers: int  # RANSAC inlier matches
    score: float  # appearance score that proposed the pair


@dataclass(frozen=True)
class FrontEndResult:
    """What the front end hands the back end."""

    intrinsics: CameraIntrinsics
    keyframes: list[Keyframe]
    landmarks: np.ndarray  # (L, 3) initial landmark positions in odom
    observations: Observations
    frame_stamps: np.ndarray  # (F,) s, every input frame
    frame_poses: np.ndarray  # (F, 4, 4) front-end T_odom_cam of every frame (NaN where lost)
    events: list[str] = field(default_factory=list)  # e.g. "frame 120: tracking lost, relocalised"


@dataclass(frozen=True)
class SideMap:
    """One side's reconstruction after bundle adjustment (and fusion, when depth exists)."""

    side: str  # "front" / "back"
    frame_id: str  # odom_front / odom_back
    intrinsics: CameraIntrinsics
    keyframe_stamps: np.ndarray  # (K,) s
    keyframe_poses: np.ndarray  # (K, 4, 4) optimised T_odom_cam
    landmarks: np.ndarray  # (L, 3) optimised, odom
    observations: Observations
    loops: list[LoopClosure]
    cloud_points: np.ndarray  # (P, 3) float32 fused dense cloud, odom
    cloud_colors: np.ndarray  # (P, 3) uint8 RGB
    scale_free: bool = False  # True in RGB-only mode: the map is up to an unknown scale
    odometry_poses: np.ndarray | None = None  # (K, 4, 4) front-end keyframe poses, before loop closure and BA
    # trunk landmarks with their local grounds (core.trunks.TrunkLandmark), when trunks.source is not "off"
    trunks: list = field(default_factory=list)
    # trellis posts seen (core.posts.PostLandmark): they tie the side's sweeps in the semantic BA
    posts: list = field(default_factory=list)
    # the side's fruit (core.fruit.SideFruit, odom), None where the fruit stage did not run
    fruit: SideFruit | None = None


@dataclass(frozen=True)
class SideGeometry:
    """One side once fused, before its trunks: what fitting its trunks' local grounds reads
    (core.trunks.fit_side_grounds). The live odometry node sends it to the local_ground_fitter node."""

    side: str  # "front" / "back"
    frame_id: str  # odom_<side>
    stamp: float  # s, the side's last keyframe (the side map's stamp)
    intrinsics: CameraIntrinsics
    keyframe_poses: np.ndarray  # (K, 4, 4) optimised T_odom_cam (the side's up direction)
    cloud_points: np.ndarray  # (P, 3) float32 fused dense cloud, odom
    views: list  # core.trunks.TrunkView: the keyframes given to the detector, their depth and detections
