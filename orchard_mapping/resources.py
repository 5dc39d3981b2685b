"""Locate the files shipped beside the package (config, scenarios, message definitions).

Works from a source checkout / editable install (repository root) and from an
ament install (share/orchard_mapping).
"""

from __future__ import annotations

import sys
from pathlib import Path

_PKG_DIR = Path(__file__).resolve().parent


def resource_candidates(sub: str) -> list[Path]:
    return [
        _PKG_DIR.parent / sub,  # source checkout / editable install
        Path(sys.prefix) / "share" / "orchard_mapping" / sub,  # ament_python install
    ]


def resource_dir(sub: str) -> Path:
    """First existing folder named `sub` among the known install locations."""
    for path in resource_candidates(sub):
        if path.is_dir():
            return path
    raise FileNotFoundError(f"orchard_mapping resource folder '{sub}' not found in {resource_candidates(sub)}")


def config_dir() -> Path:
    return resource_dir("config")


def scenario_dir() -> Path:
    return config_dir() / "scenarios"


def msg_dir() -> Path:
    """orchard_mapping_msgs/msg: the .msg files that rosbags registers for offline decoding."""
    for path in (_PKG_DIR.parent / "orchard_mapping_msgs" / "msg",
                 Path(sys.prefix) / "share" / "orchard_mapping_msgs" / "msg"):
        if path.is_dir():
            return path
    raise FileNotFoundError("orchard_mapping_msgs/msg not found (source checkout or installed share/)")
