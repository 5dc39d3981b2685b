"""One configuration model for the CLI and the ROS nodes.

Loaded from `config/default.yaml`, optionally overlaid by a user file; the
nodes declare the same dotted keys as ROS parameters. Unknown keys and bad
values are `ConfigError`s naming the dotted key.
"""

from __future__ import annotations

import difflib
import re
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from orchard_mapping.core.alignment_types import AlignmentParams
from orchard_mapping.core.bundle_adjustment import BundleAdjustmentParams
from orchard_mapping.core.fruit import FruitParams
from orchard_mapping.core.fusion import FusionParams
from orchard_mapping.core.ground import GroundParams
from orchard_mapping.core.loop_closure import LoopParams
from orchard_mapping.core.merge import MergeParams
from orchard_mapping.core.odometry import FrontEndParams
from orchard_mapping.core.semantic_ba import SemanticBAParams
from orchard_mapping.core.traits import TraitsParams
from orchard_mapping.core.trunks import TrunkParams
from orchard_mapping.errors import ConfigError
from orchard_mapping.resources import config_dir


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class TopicsConfig(_Section):
    """Input topics (RealSense driver names by default)."""

    color: str = "/camera/color/image_raw"
    depth: str = "/camera/aligned_depth_to_color/image_raw"
    camera_info: str = "/camera/color/camera_info"
    side: str = "/orchard/side"  # std_msgs/String "front"/"back" for single-bag recordings


class InputConfig(_Section):
    topics: TopicsConfig = TopicsConfig()
    # A depth image is paired with the colour image nearest in stamp, if closer than this.
    max_pair_dt_s: float = Field(0.010, gt=0.0, le=1.0)
    # Depth beyond this range is treated as missing (m).
    depth_min_m: float = Field(0.2, ge=0.0)
    depth_max_m: float = Field(6.0, gt=0.0)
    # "rgbd": colour + aligned depth; "rgb": colour only (monocular, up to scale).
    mode: Literal["rgbd", "rgb"] = "rgbd"
    # One bag holding both sides (a continuous drive round the row): "topic" labels frames by the side
    # topic, "trajectory" by the U-turn in the camera's path (core.sides), "auto" the topic when the bag
    # has one. The live odometry node reads it the same way (without a side topic or `side` parameter).
    side_source: Literal["auto", "topic", "trajectory"] = "auto"


class FramesConfig(_Section):
    """Frame ids of the outputs (REP-103/105)."""

    odom_front: str = "odom_front"
    odom_back: str = "odom_back"
    map: str = "map"
    camera: str = "camera_color_optical_frame"


class EvaluateConfig(_Section):
    # A result tree matches a true tree if their trunk positions (x, y in map) are closer than this (m).
    match_radius_m: float = Field(0.3, gt=0.0)


class OrchardConfig(_Section):
    """The whole configuration (dotted keys such as `input.topics.color`)."""

    input: InputConfig = InputConfig()
    frames: FramesConfig = FramesConfig()
    odometry: FrontEndParams = FrontEndParams()
    loop: LoopParams = LoopParams()
    ba: BundleAdjustmentParams = BundleAdjustmentParams()
    fusion: FusionParams = FusionParams()
    trunks: TrunkParams = TrunkParams()
    ground: GroundParams = GroundParams()
    alignment: AlignmentParams = AlignmentParams()
    merge: MergeParams = MergeParams()
    semantic_ba: SemanticBAParams = SemanticBAParams()
    traits: TraitsParams = TraitsParams()
    fruit: FruitParams = FruitParams()
    evaluate: EvaluateConfig = EvaluateConfig()
    seed: int = 0


def default_config_path() -> Path:
    return config_dir() / "default.yaml"


def _deep_merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out


class _Yaml12Loader(yaml.SafeLoader):
    """Safe YAML whose booleans are YAML 1.2's, true and false only: `method: off` is the word "off"
    (YAML 1.1 made it false, and the key then failed validation as not a string)."""


_Yaml12Loader.yaml_implicit_resolvers = {
    first: [r for r in resolvers if r[0] != "tag:yaml.org,2002:bool"]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}
_Yaml12Loader.add_implicit_resolver("tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"),
                                    list("tTfF"))


def parse_yaml(text: str) -> Any:
    """YAML text as configuration files and `--set` values are read (booleans: true/false only)."""
    return yaml.load(text, Loader=_Yaml12Loader)  # noqa: S506 (a SafeLoader subclass)


def parse_sets(items: list[str]) -> dict[str, Any]:
    """`key.sub=value` pairs -> {dotted key: value}; values parsed as YAML (parse_yaml). ValueError naming the
    item that has no `=`."""
    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"--set expects key=value, got '{item}'")
        key, value = item.split("=", 1)
        out[key.strip()] = parse_yaml(value)
    return out


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        data = parse_yaml(path.read_text())
    except FileNotFoundError as err:
        raise ConfigError(f"configuration file not found: {path}") from err
    except yaml.YAMLError as err:
        raise ConfigError(f"configuration file {path} is not valid YAML: {err}") from err
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"configuration file {path} must hold a mapping at top level, not {type(data).__name__}")
    return data


def validation_message(err: ValidationError, source: str, known: list[str] | None = None) -> str:
    """One line per problem, each naming the dotted key; an unknown key with the known key nearest in spelling
    (a typo: `input.topics.colour`), where `known` lists them."""
    lines = []
    for e in err.errors():
        key = ".".join(str(p) for p in e["loc"]) or "<root>"
        if e["type"] in ("extra_forbidden", "unexpected_keyword_argument"):
            near = difflib.get_close_matches(key, known or [], n=1, cutoff=0.75)
            lines.append(f"unknown key '{key}'" + (f" (did you mean '{near[0]}'?)" if near else ""))
        else:
            lines.append(f"bad value for '{key}': {e['msg']} (got {e.get('input')!r})")
    return f"invalid configuration in {source}: " + "; ".join(lines)


def config_from_dict(data: dict[str, Any], source: str = "<dict>") -> OrchardConfig:
    try:
        return OrchardConfig.model_validate(data)
    except ValidationError as err:
        known = list(flatten(OrchardConfig().model_dump(mode="json")))
        raise ConfigError(validation_message(err, source, known)) from err


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> OrchardConfig:
    """Defaults from config/default.yaml, then the user's file, then explicit overrides."""
    data = _read_yaml(default_config_path())
    source = str(default_config_path())
    if path is not None:
        data = _deep_merge(data, _read_yaml(Path(path)))
        source = str(path)
    if overrides:
        data = _deep_merge(data, overrides)
        source += " and the overrides given (--set)"  # the file alone may be right: name both
    return config_from_dict(data, source)


def flatten(data: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested mapping -> dotted keys (the ROS parameter names)."""
    out: dict[str, Any] = {}
    for key, value in data.items():
        dotted = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, dotted + "."))
        else:
            out[dotted] = value
    return out


def unflatten(flat: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for dotted, value in flat.items():
        node = out
        *parents, leaf = dotted.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    return out


def dump_yaml(cfg: OrchardConfig) -> str:
    return yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False)
