"""Which backbone stages the detector's FPN reads, and how a checkpoint of another FPN layout is carried over
(orchard_mapping.train.detector): plain Python and numpy stand-ins, so it runs without torch."""

from types import SimpleNamespace

import numpy as np
import pytest

from orchard_mapping.train.detector import fpn_stage_blocks, match_fpn_levels


def _mobilenet_v3_large_marks():
    # torchvision's MobileNetV3-Large `features`: blocks 2, 4, 7 and 13 are strided (`_is_cn`); the stem
    # (block 0) halves the image, so the strides after each block are 2 2 4 4 8 8 8 16 ... 32 32 32 32
    marked = {2, 4, 7, 13}
    return [SimpleNamespace(_is_cn=i in marked) for i in range(17)]


def test_stage_blocks_are_the_last_block_at_each_stride():
    features = _mobilenet_v3_large_marks()
    assert fpn_stage_blocks(features, (8, 16, 32)) == [6, 12, 16]
    assert fpn_stage_blocks(features, (16, 32)) == [12, 16]
    assert fpn_stage_blocks(features, (4,)) == [3]


@pytest.mark.parametrize("strides", [(), (64,), (32, 16), (8, 8), (3, 8)])
def test_stage_blocks_refuse_strides_the_backbone_has_not(strides):
    with pytest.raises(ValueError, match="fpn_strides"):
        fpn_stage_blocks(_mobilenet_v3_large_marks(), strides)


def _fpn(levels_in: list[int], fill: float, c: int = 4) -> dict[str, np.ndarray]:
    d = {}
    for lvl, cin in enumerate(levels_in):
        d[f"backbone.fpn.inner_blocks.{lvl}.0.weight"] = np.full((c, cin, 1, 1), fill + lvl)
        d[f"backbone.fpn.inner_blocks.{lvl}.0.bias"] = np.full((c,), fill + lvl)
        d[f"backbone.fpn.layer_blocks.{lvl}.0.weight"] = np.full((c, c, 3, 3), fill + lvl)
        d[f"backbone.fpn.layer_blocks.{lvl}.0.bias"] = np.full((c,), fill + lvl)
    d["roi_heads.box_head.fc6.weight"] = np.full((2, 3), fill)
    return d


def test_a_checkpoint_of_the_same_layout_is_taken_whole():
    state = _fpn([160, 960], 1.0)
    out, fresh = match_fpn_levels(state, _fpn([160, 960], 0.0))
    assert out is state and fresh == []


def test_levels_are_matched_by_the_stage_they_read_and_new_ones_stay_fresh():
    # the models up to step 5 read blocks 13 (160 channels) and 16 (960); the new layout reads 6 (40),
    # 12 (112) and 16 (960): its stride-32 level must take the old level 1, the others start fresh
    state = _fpn([160, 960], 1.0)
    own = _fpn([40, 112, 960], 0.0)
    out, fresh = match_fpn_levels(state, own)
    for kind in ("inner_blocks", "layer_blocks"):
        for part in ("weight", "bias"):
            np.testing.assert_array_equal(out[f"backbone.fpn.{kind}.2.0.{part}"],
                                          state[f"backbone.fpn.{kind}.1.0.{part}"])
            for lvl in (0, 1):
                key = f"backbone.fpn.{kind}.{lvl}.0.{part}"
                assert key in fresh and key not in out
    assert len(fresh) == 8
    # outside the FPN nothing is renamed or dropped
    np.testing.assert_array_equal(out["roi_heads.box_head.fc6.weight"], state["roi_heads.box_head.fc6.weight"])
    assert not any(k.startswith("backbone.fpn.") and k not in own for k in out)


def test_an_fpn_with_group_norm_is_matched_by_its_convolutions():
    # the efficientnet_lite0 backbone's FPN has a group norm after each convolution: its 1-D weights
    # ('inner_blocks.0.1.weight') are no level's input channels (they made the matching fail with an IndexError)
    def normed(levels_in, fill):
        d = _fpn(levels_in, fill)
        for lvl in range(len(levels_in)):
            for kind in ("inner_blocks", "layer_blocks"):
                d[f"backbone.fpn.{kind}.{lvl}.1.weight"] = np.full((4,), fill + lvl)
                d[f"backbone.fpn.{kind}.{lvl}.1.bias"] = np.full((4,), fill + lvl)
        return d

    state = normed([40, 320], 1.0)
    out, fresh = match_fpn_levels(state, normed([24, 40, 320], 0.0))
    np.testing.assert_array_equal(out["backbone.fpn.inner_blocks.2.1.weight"],
                                  state["backbone.fpn.inner_blocks.1.1.weight"])
    np.testing.assert_array_equal(out["backbone.fpn.inner_blocks.1.0.weight"],
                                  state["backbone.fpn.inner_blocks.0.0.weight"])
    assert fresh and {k.split(".")[3] for k in fresh} == {"0"}
