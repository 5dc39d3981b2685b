"""Settings, inputs and results of the initial alignment of the two sides (core.alignment; config section
`merge`): what each step of it (core.canonical_frame, core.front_view, core.trunk_alignment) shares."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class AlignmentParams:
    """Settings of the initial alignment (config section `merge`)."""

    __pydantic_config__ = {"extra": "forbid"}

    voxel_m: float = 0.05  # m, the clouds are thinned to this grid first (density then weighs nothing)
    ground_max_tilt_deg: float = 30.0  # deg, the ground normal vs the cameras' mean up
    ground_clearance_m: float = 0.10  # m, front view: points lower than this are ground, left out
    depth_band_m: float = 1.5  # m, front view: points farther than this from the trunk plane (other rows) left out
    view_cell_m: float = 0.03  # m, front view thinned to this grid before the alpha shape
    alpha_m: float = 0.15  # m, the alpha-shape disc radius (occlusion boundary of the front view)
    boundary_points: int = 400  # the boundaries are thinned to at most this many points for CPD
    shift_step_m: float = 0.05  # m, X shifts tried before CPD
    cpd_outlier_weight: float = 0.3  # CPD's w: share of points without a partner (a side sees more of the row)
    cpd_iterations: int = 100
    trunk_height_m: float = 0.30  # m above the ground: where the trunk axes are compared
    pair_radius_m: float = 0.15  # m, trunk axes closer than this after alignment are one tree
    min_pairs: int = 2  # trunks seen from both sides needed for a merge
    shift_candidates: int = 4  # best shifts along the row carried through CPD and the top view
    # mm, median axis gap + median diameter difference of the paired trunks above which the pairs are taken
    # for different trees and the merge refused. The right shift scored 3.0 (9-tree partial_overlap), 5.7
    # (10-tree standard) and 9.8 mm (10-tree slope_weeds); shifts a tree or more off 21-110 mm.
    max_disagreement_mm: float = 16.0
    # pairs from which a smooth bend along the row (quadratic in X) is taken off the gaps before the check
    # above: a long row's own drift, not a sign of different trees (bend_free_gaps)
    bend_min_pairs: int = 10
    # With fewer than min_pairs trunks seen from both sides: "global_features" (the paper's alignment without
    # pairs: the front views' CPD for the along-row shift, height and roll, each side's trunk line for depth and
    # heading; the result is flagged, its error is a trunk's width rather than millimetres) or "refuse".
    fallback: str = "global_features"


@dataclass(frozen=True)
class AlignmentSide:
    """What the alignment needs of one side, all in its odom frame."""

    points: np.ndarray  # (P, 3) m, fused cloud
    poses: np.ndarray  # (K, 4, 4) T_odom_cam of the keyframes (optical frame: z forward, y down)
    trunk_base: np.ndarray  # (T, 3) m, where each trunk axis meets its ground
    trunk_axis: np.ndarray  # (T, 3) unit, up
    trunk_ids: np.ndarray  # (T,) int, the trunk landmarks' ids
    scale_free: bool = False  # True for a colour-only side (up to scale)
    trunk_diameter: np.ndarray | None = None  # (T,) m, NaN where not measured (None: none measured)

    def __post_init__(self) -> None:
        if self.trunk_diameter is None:
            object.__setattr__(self, "trunk_diameter", np.full(len(self.trunk_ids), np.nan))


@dataclass(frozen=True)
class CanonicalFrame:
    T_canon_odom: np.ndarray  # (4, 4) rigid: rows of the rotation are X (row), Y (up), Z (depth)
    ground_inliers: int
    ground_rmse_m: float


@dataclass(frozen=True)
class SideAlignment:
    T_front_back: np.ndarray  # (4, 4) similarity odom_front <- odom_back: [s R | t]
    scale: float
    pairs: tuple[tuple[int, int], ...]  # (front trunk id, back trunk id)
    pair_gaps_m: tuple[float, ...]  # horizontal distance of each pair's axes at trunk_height_m after alignment
    overlap_m: tuple[float, float]  # X range of the row both sides cover, front canonical frame
    boundary_rms_m: float  # RMS of eq. dist between the aligned boundaries (inliers of CPD)
    front: CanonicalFrame
    back: CanonicalFrame
    log: list[str] = field(default_factory=list)
    # "trunk_pairs": the trunks seen from both sides set depth and heading; "trunk_lines": too few pairs, each
    # side's own trunk line did (AlignmentParams.fallback)
    method: str = "trunk_pairs"
