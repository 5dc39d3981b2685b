"""The configuration as ROS parameters: the same dotted keys as config/default.yaml, read from a parameters
file, and every change checked by the same pydantic model (a bad value refused with its key named)."""

from __future__ import annotations

import pytest
import yaml

rclpy = pytest.importorskip("rclpy")

from rclpy.parameter import Parameter  # noqa: E402

from orchard_mapping.config import flatten, load_config  # noqa: E402
from orchard_mapping.errors import ConfigError  # noqa: E402
from orchard_mapping.resources import config_dir  # noqa: E402
from orchard_mapping.ros.params import ConfigParameters  # noqa: E402


def _node(args: list[str] | None = None):
    rclpy.init(args=args)
    node = rclpy.create_node("orchard_test_params", automatically_declare_parameters_from_overrides=False)
    return node


def test_ros_params_file_holds_the_default_configuration():
    ros = yaml.safe_load((config_dir() / "ros_params.yaml").read_text())["/**"]["ros__parameters"]
    assert flatten(ros) == flatten(load_config().model_dump(mode="json"))


def test_parameters_file_sets_the_configuration_and_bad_values_are_refused_by_key(tmp_path):
    ros = yaml.safe_load((config_dir() / "ros_params.yaml").read_text())
    ros["/**"]["ros__parameters"]["fusion"]["voxel_size_m"] = 0.02
    ros["/**"]["ros__parameters"]["seed"] = 7
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(ros))
    node = _node(["--ros-args", "--params-file", str(path)])
    try:
        params = ConfigParameters(node)
        assert params.config.fusion.voxel_size_m == 0.02 and params.config.seed == 7
        assert len(params.keys) == len(flatten(load_config().model_dump(mode="json")))
        bad = node.set_parameters([Parameter("fusion.voxel_size_m", value="fine")])[0]
        assert not bad.successful and "fusion.voxel_size_m" in bad.reason, bad.reason
        assert params.config.fusion.voxel_size_m == 0.02  # the last good configuration stays
        good = node.set_parameters([Parameter("fusion.voxel_size_m", value=0.015)])[0]
        assert good.successful and params.config.fusion.voxel_size_m == 0.015
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def test_a_bad_value_in_the_parameters_file_stops_the_node_naming_the_key(tmp_path):
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"ba": {"window": "many"}}}}))
    node = _node(["--ros-args", "--params-file", str(path)])
    try:
        with pytest.raises(ConfigError, match=r"ba\.window"):
            ConfigParameters(node)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
