"""Simulator scenarios: a nested pydantic model loaded from config/scenarios/*.yaml.

Lengths in metres, angles in degrees, rates in Hz. A scenario file only states
what differs from the defaults below; unknown keys are errors naming the key.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from orchard_mapping.config import validation_message
from orchard_mapping.errors import ScenarioError
from orchard_mapping.resources import scenario_dir

Range = tuple[float, float]


class _S(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class RowSpec(_S):
    n_trees: int = Field(10, ge=1, le=200)
    spacing_m: float = Field(0.95, gt=0.3)  # mean trunk-to-trunk distance along the row
    spacing_jitter_m: float = Field(0.08, ge=0.0)
    offset_jitter_m: float = Field(0.03, ge=0.0)  # trunk offset across the row
    slope_deg: float = 2.0  # ground slope along the row
    cross_slope_deg: float = 1.0  # ground slope across the row
    undulation_m: float = Field(0.06, ge=0.0)  # amplitude of smooth local ground variation
    undulation_wavelength_m: float = Field(2.5, gt=0.2)
    roughness_m: float = Field(0.008, ge=0.0)  # small-scale ground roughness
    margin_m: float = Field(1.2, ge=0.0)  # path beyond the first / last tree


class TrunkSpec(_S):
    diameter_mean_m: float = Field(0.069, gt=0.0)  # at diameter_height_m
    diameter_sd_m: float = Field(0.0085, ge=0.0)
    diameter_min_m: float = Field(0.04, gt=0.0)
    diameter_max_m: float = Field(0.09, gt=0.0)
    diameter_height_m: float = Field(0.30, gt=0.0)  # height above local ground where diameter is stated
    taper_per_m: float = Field(0.012, ge=0.0)  # diameter lost per metre of trunk
    lean_deg_max: float = Field(4.0, ge=0.0)
    curve_m: float = Field(0.012, ge=0.0)  # sideways bow of the axis at mid-height
    clear_height_m: Range = (0.55, 0.75)  # trunk free of branches up to this height
    # (a - b) / (a + b) of the trunk's elliptical cross-section, drawn per tree (its major axis at random);
    # the stated diameter is a + b, the mean of two caliper readings at right angles. Real trunks: ~0.02-0.1.
    ellipticity: Range = (0.0, 0.0)
    bark_roughness_m: float = Field(0.0, ge=0.0)  # m, sd of smooth radial bumps of the bark


class CanopySpec(_S):
    height_m: Range = (1.9, 2.6)  # tree height above local ground
    radius_along_row_m: Range = (0.5, 0.6)  # half-width along the row (neighbours touch at ~spacing/2)
    radius_across_row_m: Range = (0.38, 0.5)
    branches: tuple[int, int] = (12, 18)
    leaves_per_m3: float = Field(9000.0, gt=0.0)  # leaf density in the canopy envelope
    leaf_size_m: Range = (0.05, 0.08)


class FruitSpec(_S):
    per_tree: tuple[int, int] = (18, 40)
    radius_m: Range = (0.035, 0.045)
    red_fraction: float = Field(0.6, ge=0.0, le=1.0)
    # plain: one saturated red or green per fruit (the standard look); varied: a ground colour from grass
    # green to golden, a red to pink blush over part of each fruit, streaks and speckle, as real varieties
    # show (Fuji, Gala, Golden): drawn from a stream of their own, so the scene's geometry does not change.
    look: Literal["plain", "varied"] = "plain"


class StructureSpec(_S):
    post_every_n_trees: int = Field(5, ge=0)  # 0 = no intermediate posts (end posts always)
    post_diameter_m: float = Field(0.10, gt=0.0)
    post_height_m: float = Field(2.9, gt=0.0)
    wire_heights_m: tuple[float, ...] = (0.9, 1.5, 2.1)
    wire_diameter_m: float = Field(0.004, gt=0.0)
    weeds_per_m2: float = Field(6.0, ge=0.0)
    weed_height_m: Range = (0.05, 0.25)
    hedge_distance_m: float = Field(3.4, gt=1.5)  # neighbouring rows seen in the background
    hedge_height_m: float = Field(2.7, gt=0.0)  # their height: low ones leave sky behind the trunks


class CameraSpec(_S):
    width: int = Field(640, ge=16)
    height: int = Field(480, ge=16)
    fx: float = Field(615.0, gt=0.0)
    fy: float = Field(615.0, gt=0.0)
    cx: float = 319.5
    cy: float = 239.5
    rate_hz: float = Field(15.0, gt=0.0, le=90.0)
    depth_min_m: float = 0.2
    depth_max_m: float = 6.0
    depth_sigma_coeff: float = Field(0.004, ge=0.0)  # depth noise sd = coeff * z^2 (m), RealSense-like
    # px, sd of the Gaussian over which the depth noise is correlated (0: independent per pixel). A stereo
    # camera matches windows of pixels, so its error comes in patches, not pixel by pixel, and a fit over
    # many pixels does not average it away as it would white noise. Same sd per pixel either way.
    depth_noise_correlation_px: float = Field(0.0, ge=0.0, le=50.0)
    dropout: float = Field(0.01, ge=0.0, le=1.0)  # random missing depth
    edge_missing: float = Field(0.35, ge=0.0, le=1.0)  # missing depth at depth edges
    flying_pixels: float = Field(0.3, ge=0.0, le=1.0)  # edge pixels mixed between fore- and background
    color_noise_sd: float = Field(2.0, ge=0.0)  # 8-bit levels
    exposure_jitter: float = Field(0.04, ge=0.0)  # relative gain change per frame


class MotionSpec(_S):
    """How the camera's carrier moves on top of the hand-held jitter (all off by default)."""

    # Walking with a hand-held camera: the body bobs once per step and sways once per stride (two steps).
    step_hz: float = Field(0.0, ge=0.0)  # steps per second (0 = not walking)
    bob_m: float = Field(0.0, ge=0.0)  # vertical amplitude at the step frequency
    sway_deg: float = Field(0.0, ge=0.0)  # yaw and roll amplitude at the stride frequency
    # Quick re-aiming: the camera swings away (random yaw/pitch direction) and back within reaim_s.
    reaim_every_s: float = Field(0.0, ge=0.0)  # mean time between re-aims (0 = none)
    reaim_deg: float = Field(0.0, ge=0.0)  # largest swing of a re-aim
    reaim_s: float = Field(0.8, gt=0.0)  # duration of the swing and its return
    # A ground vehicle on rough turf: engine and wheel vibration, and bumps that excite the suspension.
    vibration_deg: float = Field(0.0, ge=0.0)  # rotation amplitude, 8-20 Hz
    vibration_m: float = Field(0.0, ge=0.0)  # translation amplitude, 8-20 Hz
    bump_every_m: float = Field(0.0, ge=0.0)  # mean distance between bumps (0 = none)
    bump_deg: float = Field(0.0, ge=0.0)  # pitch and roll kick of a bump (damped 2.5 Hz oscillation)
    bump_m: float = Field(0.0, ge=0.0)  # vertical kick of a bump
    bump_decay_s: float = Field(0.25, gt=0.0)  # time constant of the suspension's damping


class BlockSpec(_S):
    """Parallel rows (a block of an orchard); one row unless said."""

    rows: int = Field(1, ge=1, le=20)  # along +y, each with row.n_trees trees of its own
    row_spacing_m: float = Field(3.4, gt=1.0)  # trunk line to trunk line
    # m beyond the path's turns at both ends of the block, a hedge across the row ends (0: none): a turn in the
    # headland looks out of the block, at it, rather than into empty sky
    headland_m: float = Field(0.0, ge=0.0)


class PathSpec(_S):
    # two_sweep: level sweep at trunk height, back along the side with the camera raised and tilted down
    # single_pass: one level sweep per side (trunks only); loop: one drive around the row, one bag
    # block: one drive along both sides of every row of the block (a loop round each row, a turn into the same
    # alley the other way round between them), one bag
    mode: Literal["two_sweep", "single_pass", "loop", "block"] = "two_sweep"
    distance_m: float = Field(1.25, gt=0.3)  # camera to trunk line
    low_height_m: float = Field(0.62, gt=0.0)  # camera above ground, level sweep (sees ~0.15-1.1 m)
    # Raised sweep (camera on a stick): from 1.5 m at 3 m height, tilted down 35 deg, the view spans the trunk
    # line from ~0.8 m up to the tree tops, overlapping the level sweep's upper part (loop closure needs that).
    high_height_m: float = Field(3.0, gt=0.0)  # camera above ground, raised sweep
    high_tilt_deg: float = Field(35.0, ge=0.0, le=80.0)  # downward tilt of the raised sweep
    high_distance_m: float = Field(1.5, gt=0.3)  # camera to trunk line, raised sweep
    speed_mps: float = Field(0.5, gt=0.0)
    turn_s: float = Field(3.0, ge=0.5)  # time spent raising the camera at the row end
    jitter_m: float = Field(0.012, ge=0.0)  # hand-held position jitter amplitude
    jitter_deg: float = Field(0.8, ge=0.0)  # hand-held rotation jitter amplitude
    roll_deg: float = 0.0  # mean camera roll (tilted scenario)
    # fraction of the row [start, end] each side covers (partial_overlap scenario)
    front_span: Range = (0.0, 1.0)
    back_span: Range = (0.0, 1.0)
    # which way the back side is walked: "return" towards -x (round the row, as the front side came), or
    # "same" towards +x like the front side (two passes started at the same row end)
    back_direction: Literal["return", "same"] = "return"
    motion: MotionSpec = MotionSpec()  # walking / vehicle motion (handheld_walk, vehicle scenarios)


RGB = tuple[float, float, float]


class AppearanceSpec(_S):
    """Colours, light and texture of the scene (randomised per scene for detector training data)."""

    bark_rgb: RGB = (0.36, 0.27, 0.2)  # trunk and branch albedo
    bark_gain: Range = (0.85, 1.15)  # per-tree multiplier
    bark_texture_gain: tuple[float, float] = (0.4, 1.2)  # texture = a + b * noise: contrast of the furrows
    leaf_rgb_a: RGB = (0.17, 0.38, 0.10)  # leaves: a mix of these two colours
    leaf_rgb_b: RGB = (0.35, 0.48, 0.14)
    leaf_gain: Range = (0.7, 1.25)
    post_rgb: RGB = (0.55, 0.45, 0.33)
    post_gain: Range = (0.85, 1.1)
    weed_rgb: RGB = (0.28, 0.5, 0.15)
    weed_gain: Range = (0.7, 1.25)
    hedge_rgb: RGB = (0.2, 0.36, 0.14)
    hedge_gain: Range = (0.6, 1.3)
    soil_rgb: RGB = (0.44, 0.35, 0.25)  # ground: soil and turf patches
    turf_rgb: RGB = (0.30, 0.44, 0.17)
    sky_horizon_rgb: RGB = (0.62, 0.74, 0.9)
    sky_zenith_rgb: RGB = (0.42, 0.58, 0.86)
    sun_dir: tuple[float, float, float] = (0.35, -0.45, 0.82)  # world, towards the sun
    ambient: float = Field(0.45, ge=0.0)
    diffuse: float = Field(0.75, ge=0.0)
    texture_scale: float = Field(1.0, gt=0.0)  # multiplies every texture's texels per metre
    blur_sigma_px: float = Field(0.0, ge=0.0)  # optical blur of the colour image (Gaussian sd)


class WindSpec(_S):
    enabled: bool = False
    amplitude_m: float = Field(0.03, ge=0.0)  # leaf displacement at the canopy edge
    frequency_hz: float = Field(1.2, gt=0.0)


class Scenario(_S):
    name: str = "custom"
    description: str = ""
    row: RowSpec = RowSpec()
    trunk: TrunkSpec = TrunkSpec()
    canopy: CanopySpec = CanopySpec()
    fruit: FruitSpec = FruitSpec()
    structure: StructureSpec = StructureSpec()
    camera: CameraSpec = CameraSpec()
    path: PathSpec = PathSpec()
    block: BlockSpec = BlockSpec()
    wind: WindSpec = WindSpec()
    appearance: AppearanceSpec = AppearanceSpec()
    masks_every: int = Field(1, ge=0)  # write an instance mask every n-th frame (0 = none)
    canopy_alpha_m: float = Field(0.8, gt=0.0)  # alpha of the canopy-volume definition

    @model_validator(mode="after")
    def _check(self) -> "Scenario":
        t = self.trunk
        if not t.diameter_min_m <= t.diameter_mean_m <= t.diameter_max_m:
            raise ValueError("trunk.diameter_mean_m must lie in [diameter_min_m, diameter_max_m]")
        if not 0.0 <= t.ellipticity[0] <= t.ellipticity[1] < 0.5:
            raise ValueError("trunk.ellipticity must satisfy 0 <= low <= high < 0.5")
        if self.path.mode == "block" and self.block.row_spacing_m < 2 * self.path.distance_m + 0.3:
            # the turn from a row's back side into the next row's front side is made in the alley between them
            raise ValueError(f"block.row_spacing_m ({self.block.row_spacing_m} m) must leave room for the turn "
                             f"between two rows' camera lines: at least 2 x path.distance_m + 0.3 m "
                             f"({2 * self.path.distance_m + 0.3:.2f} m)")
        for key in ("front_span", "back_span"):
            a, b = getattr(self.path, key)
            if not 0.0 <= a < b <= 1.0:
                raise ValueError(f"path.{key} must satisfy 0 <= start < end <= 1")
        return self


def list_scenarios() -> list[str]:
    return sorted(p.stem for p in scenario_dir().glob("*.yaml"))


def load_scenario(name_or_path: str | Path, overrides: dict[str, Any] | None = None) -> Scenario:
    """A scenario by name (config/scenarios/NAME.yaml) or by file path, plus dotted-free nested overrides."""
    path = Path(name_or_path)
    if not path.suffix:
        path = scenario_dir() / f"{name_or_path}.yaml"
        if not path.is_file():
            raise ScenarioError(f"unknown scenario '{name_or_path}'; known: {', '.join(list_scenarios())}")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as err:
        raise ScenarioError(f"cannot read scenario file {path}: {err}") from err
    if not isinstance(data, dict):
        raise ScenarioError(f"scenario file {path} must hold a mapping")
    data.setdefault("name", path.stem)
    for key, value in (overrides or {}).items():
        node = data
        *parents, leaf = key.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    try:
        return Scenario.model_validate(data)
    except ValidationError as err:
        raise ScenarioError(validation_message(err, str(path))) from err
