"""Configuration: defaults, overlays, and errors that name the offending key."""

from __future__ import annotations

import pytest
import yaml

from orchard_mapping.config import (
    OrchardConfig,
    config_from_dict,
    dump_yaml,
    flatten,
    load_config,
    unflatten,
)
from orchard_mapping.errors import ConfigError


def test_defaults_file_equals_model_defaults():
    # config/default.yaml documents every key; it must not drift from the model's own defaults.
    assert load_config() == OrchardConfig()


def test_user_file_overlays_defaults(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("input:\n  topics:\n    color: /cam/rgb\n  max_pair_dt_s: 0.02\n")
    cfg = load_config(f)
    assert cfg.input.topics.color == "/cam/rgb"
    assert cfg.input.max_pair_dt_s == 0.02
    assert cfg.input.topics.depth == "/camera/aligned_depth_to_color/image_raw"  # untouched default


def test_unknown_key_is_named(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("input:\n  topics:\n    colour: /x\n")
    with pytest.raises(ConfigError, match=r"unknown key 'input\.topics\.colour'") as exc:
        load_config(f)
    assert str(f) in str(exc.value)


@pytest.mark.parametrize(
    ("data", "key"),
    [
        ({"input": {"max_pair_dt_s": -1}}, "input.max_pair_dt_s"),
        ({"input": {"mode": "lidar"}}, "input.mode"),
        ({"evaluate": {"match_radius_m": "far"}}, "evaluate.match_radius_m"),
        ({"seed": [1, 2]}, "seed"),
    ],
)
def test_bad_value_is_named(data, key):
    with pytest.raises(ConfigError, match=rf"bad value for '{key}'"):
        config_from_dict(data)


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("input: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(bad)
    scalar = tmp_path / "scalar.yaml"
    scalar.write_text("42\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(scalar)


def test_dotted_keys_round_trip():
    # ROS parameters use the dotted names; the nested model must come back unchanged.
    cfg = OrchardConfig()
    flat = flatten(cfg.model_dump(mode="json"))
    assert "input.topics.color" in flat
    assert config_from_dict(unflatten(flat)) == cfg


def test_dump_is_loadable_yaml():
    cfg = load_config(overrides={"seed": 7})
    assert config_from_dict(yaml.safe_load(dump_yaml(cfg))) == cfg


def test_set_keeps_on_off_yes_no_as_words():
    """`--set merge.method=off` is the method "off", not YAML 1.1's false (it was rejected as a bad
    value); true/false, numbers and lists still parse."""
    from orchard_mapping.config import load_config, parse_sets, unflatten

    sets = parse_sets(["merge.method=off", "trunks.source=masks", "seed=3", "fusion.keep_color=true"])
    assert sets == {"merge.method": "off", "trunks.source": "masks", "seed": 3, "fusion.keep_color": True}
    assert load_config(overrides=unflatten(parse_sets(["merge.method=off"]))).merge.method == "off"


def test_off_in_a_config_file_is_the_word(tmp_path):
    f = tmp_path / "mine.yaml"
    f.write_text("merge:\n  method: off\ntrunks:\n  source: off\n")
    cfg = load_config(f)
    assert cfg.merge.method == "off" and cfg.trunks.source == "off"
