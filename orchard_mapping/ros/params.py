"""The configuration as ROS parameters: every dotted key of `config/default.yaml` is a parameter of each node
(same names, e.g. `fusion.voxel_size_m`), declared with a descriptor and checked by the same pydantic model
as the CLI's configuration. A bad value, at start (a parameters file) or later (`ros2 param set`), is
refused with the dotted key named; the node keeps its last good configuration.
"""

from __future__ import annotations

from typing import Any

from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter

from orchard_mapping.config import OrchardConfig, config_from_dict, flatten, load_config, unflatten
from orchard_mapping.errors import ConfigError

__all__ = ["ConfigParameters"]


class ConfigParameters:
    """Declares the configuration's keys on `node` and keeps `config` (an OrchardConfig) in step with them."""

    def __init__(self, node: Node, base: OrchardConfig | None = None) -> None:
        self._node = node
        defaults = flatten((base or load_config()).model_dump(mode="json"))  # dotted key -> scalar
        self.keys = tuple(defaults)
        for key, value in defaults.items():
            # dynamic typing: a parameters file may give 1 for a float key; the pydantic model types it
            node.declare_parameter(key, value, ParameterDescriptor(
                description=f"configuration key {key} (config/default.yaml); default {value!r}",
                dynamic_typing=True))
        self.config = self._validate({k: node.get_parameter(k).value for k in self.keys}, "parameters at start")
        node.add_on_set_parameters_callback(self._on_set)

    def _validate(self, flat: dict[str, Any], source: str) -> OrchardConfig:
        return config_from_dict(unflatten(flat), source=f"{self._node.get_name()} {source}")

    def _on_set(self, params: list[Parameter]) -> SetParametersResult:
        changed = {p.name: p.value for p in params if p.name in self.keys}
        if not changed:
            return SetParametersResult(successful=True)
        current = flatten(self.config.model_dump(mode="json"))
        try:
            self.config = self._validate({**current, **changed}, "set parameters")
        except ConfigError as err:
            return SetParametersResult(successful=False, reason=str(err))
        return SetParametersResult(successful=True)
